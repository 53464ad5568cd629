"""Scene ``grazing``: gradients across a grazing contact (a true double root), mollified and not.

Geometry (no gravity, times from the start of the rollout, ``t_m = 1/80 s``):

* a *flap*: one triangle of three free particles (no springs, about 0.94 kg each) whose corners
  are ``(-0.1, -0.05)``, ``(0.1, -0.05)`` and ``(0, 0.15)`` (x, y) [m] at ``t_m``. Each corner
  moves at constant velocity, vertically at ``K y`` with ``K = -4 1/s`` (so the flap's plane
  is ``z = K (t - t_m) y`` at every time: it tilts about the x axis, flat at ``t_m``), and the two
  lower corners at ``-/+ 0.5 m/s`` in x (the flap widens, so the coplanarity cubic has all four
  coefficients);
* a particle (1 g) with velocity ``(0, 2, v_z)`` [m/s] that, for the threshold aim
  ``v_z* = K y_m = -1/4 m/s``, is at ``(0, y_m = 1/16, 0)`` at ``t_m``: inside the flap.

Its height above the flap's plane is ``f(t) = z(t) - K (t - t_m) y(t)``, a quadratic with
``f(t_m) = 0``, ``f'(t_m) = v_z - K y_m = 0`` and ``f'' = -2 K v_y = 16 m/s^2 > 0``: the particle
touches the flap tangentially at ``t_m`` and leaves. All four points move linearly for the whole
rollout, so the coplanarity cubic of every substep (kernels/ccd_common.py, the same points'
straight paths from the substep's start to its end) is ``p(t) = D(t) f(t)`` with ``D`` twice the
flap's xy area (linear in t, never zero here): ``p(t_m) = p'(t_m) = 0``, ``p''(t_m) != 0``, a
true double root in the middle of the second of the two substeps of the one step
(``dt = 1/60 s``), with the coplanarity point strictly inside the face. Changing the aim by
``dv`` shifts ``f`` by ``dv t``: deeper aims (``v_z < v_z*``, relative offset
``(v_z - v_z*) / v_z* > 0``) give two roots and a hit at the first, ``t* = t_m -
sqrt(2 |dv| t_m / f'')`` to first order, shallower ones no real root near ``t_m`` and a miss. The
exact ``dt*/dv_z = -(dp/dv_z) / p'(t*)`` therefore grows like ``offset^(-1/2)``;
``tests/test_rollout.py`` checks the double root in exact rational arithmetic (sympy).

The output is the particle's final height ``z(T)`` (``T = 1/60 s``); restitution 0.5, no
friction, and a tiny contact thickness (1e-9 m, the separation kept by the proximity pass, so
that neither proximity contacts nor the separation speed interfere near the tangency). The
post-impact velocity depends on ``t*`` through the normal relative velocity at ``t*``
(``v_n(t*) ~ f'(t*)``, ``dv_n / dt* ~ f''``), so ``dz(T)/dv_z`` carries ``(T - t*) (1 + e) f''
dt*/dv_z``: with the unmollified ``-1/p'(t*)`` (``sim.rollout.UNMOLLIFIED_MAX_DERIVATIVE``) it
blows up like ``offset^(-1/2)``; the paper's mollified derivative bounds ``|dt*/dp|`` of the
unit-scaled cubic by ``M``, so the gradient levels off at about ``2 M (1 + e) (t_m / h) (T - t_m)
/ T`` times the free-flight gradient ``T`` (1.1e3 for ``M = 1000``, ``h = dt / 2``: a unit change
of the scaled cubic is a change of ``f`` by ``f'' h^2 / 2 = 0.56 mm``, which the aim makes in
0.56 mm / ``t_m`` = 0.044 m/s).

:func:`sweep` records, per offset, the gradient of ``z(T)`` w.r.t. the initial ``v_z`` through
:func:`sim.rollout.rollout` with the mollified derivative (``M = 1000`` unless told) and the
unmollified one, optionally central finite differences of the forward and other ``M``; and a few
miss-side aims (no contact: the free-flight gradient). The recording logs both curves against
the sweep index (timeline ``aim``); the summary gives their largest magnitudes as multiples of
the free-flight gradient.
"""

from __future__ import annotations

import argparse
from fractions import Fraction
from typing import Any

import numpy as np

from scenes import interrupts
from scenes.registry import int_at_least

NAME = "grazing"
DESCRIPTION = "Gradient of a particle grazing a tilting flap (a double root): mollified vs -1/p'"
PRECISIONS = ("float64",)
SUPPORTS_STEPS = False

# the geometry, exact (tests rebuild it in rational arithmetic)
TILT_RATE = Fraction(-4)  # K [1/s]: the flap's plane is z = K (t - t_m) y
FLAP = ((Fraction(-1, 10), Fraction(-1, 20)), (Fraction(1, 10), Fraction(-1, 20)), (Fraction(0), Fraction(3, 20)))
"""(x, y) [m] of the flap's corners at ``t_m`` (z = 0 then)."""
WIDEN = (Fraction(-1, 2), Fraction(1, 2), Fraction(0))  # x velocities of the corners [m/s]
SPEED_Y = Fraction(2)  # [m/s]
MEET_Y = Fraction(1, 16)  # [m]: y of the tangency point
STEPS, SUBSTEPS = 1, 2
DT = Fraction(1, 60)
MEET_TIME = (Fraction(1) + Fraction(1, 2)) * DT / SUBSTEPS  # t_m = 1/80 s: the middle of the second substep
THRESHOLD_VZ = TILT_RATE * MEET_Y  # v_z* = -1/4 m/s: the grazing aim
RESTITUTION = 0.5
THICKNESS = 1e-9  # [m]
FLAP_DENSITY = 150.0  # [kg/m^2]
PARTICLE_MASS = 0.001  # [kg]
PARTICLE = 3  # the particle's index (the flap's corners are 0, 1, 2)

DEFAULT_OFFSETS = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)  # hits
MISS_OFFSETS = (1e-1, 1e-6, 1e-11)  # aims shallower than v_z* by these (misses)


def initial_state(vz=THRESHOLD_VZ) -> tuple[list, list]:
    """Positions and velocities at ``t = 0`` of the flap's corners (0-2) and the particle (3),
    as lists of ``[x, y, z]`` in exact arithmetic when ``vz`` is (Fraction or int; a float gives
    floats). The particle starts where the grazing path does whatever ``vz`` (its initial
    velocity is ``(0, v_y, vz)``). Each point moves on ``position + t velocity`` for the whole
    rollout when no contact happens."""
    tm = MEET_TIME
    pos, vel = [], []
    for (x, y), u in zip(FLAP, WIDEN):
        pos.append([x - u * tm, y, -TILT_RATE * tm * y])
        vel.append([u, Fraction(0), TILT_RATE * y])
    pos.append([Fraction(0), MEET_Y - SPEED_Y * tm, -THRESHOLD_VZ * tm])
    vel.append([Fraction(0), SPEED_Y, vz])
    return pos, vel


def build_model():
    """The flap and the particle (restitution 0.5, frictionless, thickness 1e-9 m)."""
    from sim.builder import ModelBuilder

    pos, vel = initial_state()
    pos = np.array(pos, dtype=np.float64)
    vel = np.array(vel, dtype=np.float64)
    b = ModelBuilder()
    b.set_gravity(0.0)
    b.add_cloth_mesh(pos[:3], np.array([[0, 1, 2]]), density=FLAP_DENSITY, stretch_stiffness=0.0,
                     bend_stiffness=0.0, damping=0.0, velocity=vel[:3])
    b.add_particle(tuple(pos[3]), velocity=tuple(vel[3]), mass=PARTICLE_MASS)
    b.enable_self_collision()
    b.set_contact(restitution=RESTITUTION, friction=0.0, thickness=THICKNESS)
    return b.finalize()


def final_height(model, vz: float, max_derivative: float = 1000.0, grad: bool = False):
    """``z(T)`` of the particle for the initial ``v_z = vz`` (``grad``: its derivative w.r.t.
    ``vz`` instead, through :func:`sim.rollout.rollout` with ``max_derivative``), and the
    rollout's ``stats``."""
    import torch

    from sim.rollout import rollout

    v = torch.tensor(model.particle_qd.numpy(), dtype=torch.float64)
    v[PARTICLE, 2] = vz
    if grad:
        v.requires_grad_()
    res = rollout(model, STEPS, float(DT), SUBSTEPS, particle_qd=v, max_derivative=max_derivative)
    if not grad:
        return float(res.particle_q[-1, PARTICLE, 2]), res.stats
    res.particle_q[-1, PARTICLE, 2].backward()
    return float(v.grad[PARTICLE, 2]), res.stats


def aim(offset: float) -> float:
    """The initial ``v_z`` at relative ``offset`` from the grazing aim (> 0 deeper: a hit)."""
    return float(THRESHOLD_VZ) * (1.0 + offset)


def predicted_plateau(max_derivative: float) -> float:
    """First-order size of the mollified gradient near the tangency, in free-flight units:
    ``2 M (1 + e) (t_m / h) (T - t_m) / T`` (the contact's share; see the module docstring)."""
    h = float(DT) / SUBSTEPS
    t_end, tm = STEPS * float(DT), float(MEET_TIME)
    return 2.0 * max_derivative * (1.0 + RESTITUTION) * (tm / h) * (t_end - tm) / t_end


def sweep(offsets=DEFAULT_OFFSETS, max_derivative: float = 1000.0, *, other_max_derivatives=(),
          fd_steps=(), miss_offsets=MISS_OFFSETS) -> dict[str, Any]:
    """Runs the sweep (see the module docstring).

    Args:
        offsets: relative aim offsets (> 0, hits).
        max_derivative: ``M`` of the mollified gradient.
        other_max_derivatives: more values of ``M`` to record (``by_max_derivative``).
        fd_steps: relative steps ``s`` (of the offset: the aim moves by ``s * offset * |v_z*|``)
            of central finite differences of the forward to record (``fd``, one row per step).
        miss_offsets: offsets on the miss side (aims shallower by these).

    Returns:
        dict with ``free`` (free-flight gradient [s]), ``threshold`` (``v_z*`` [m/s]),
        ``offsets``, ``mollified``, ``unmollified`` (gradients per offset, numpy),
        ``contacts`` (contact substeps per offset), ``failsafe`` (fail-safe substeps per offset),
        ``by_max_derivative`` ({M: gradients}), ``fd`` ((len(fd_steps), n)), ``miss_offsets``,
        ``miss_gradients``, ``miss_contacts``.
    """
    from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE

    model = build_model()
    offsets = np.asarray(offsets, dtype=np.float64)
    free, _ = final_height(model, aim(-0.5), max_derivative, grad=True)
    mollified, unmollified, contacts, failsafe = [], [], [], []
    by_m = {float(m): [] for m in other_max_derivatives}
    fd = np.zeros((len(fd_steps), len(offsets)))
    for i, k in enumerate(offsets):
        interrupts.raise_pending()
        vz = aim(k)
        g, stats = final_height(model, vz, max_derivative, grad=True)
        mollified.append(g)
        contacts.append(stats["contact_substeps"])
        failsafe.append(stats["failsafe_substeps"])
        unmollified.append(final_height(model, vz, UNMOLLIFIED_MAX_DERIVATIVE, grad=True)[0])
        for m, grads in by_m.items():
            grads.append(final_height(model, vz, m, grad=True)[0])
        for j, s in enumerate(fd_steps):
            step = s * k * abs(float(THRESHOLD_VZ))
            fd[j, i] = (final_height(model, vz + step)[0] - final_height(model, vz - step)[0]) / (2.0 * step)
    miss_g, miss_c = [], []
    for k in miss_offsets:
        g, stats = final_height(model, aim(-k), max_derivative, grad=True)
        miss_g.append(g)
        miss_c.append(stats["contact_substeps"])
    return {"free": free, "threshold": float(THRESHOLD_VZ), "offsets": offsets,
            "mollified": np.asarray(mollified), "unmollified": np.asarray(unmollified),
            "contacts": np.asarray(contacts), "failsafe": np.asarray(failsafe),
            "by_max_derivative": {m: np.asarray(v) for m, v in by_m.items()}, "fd": fd,
            "miss_offsets": np.asarray(miss_offsets, dtype=np.float64), "miss_gradients": np.asarray(miss_g),
            "miss_contacts": np.asarray(miss_c)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--points", type=int_at_least(2), default=len(DEFAULT_OFFSETS),
                        help="aims in the sweep, log-spaced offsets 1e-1 .. 1e-11 (default %(default)s)")


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the sweep, logs ``/metrics/gradient/{mollified,unmollified,free_flight}`` per aim."""
    result = sweep(np.logspace(-1.0, -11.0, args.points))
    n = len(result["offsets"])
    frames = {"aim": np.arange(n)}
    log.log_scalars("/metrics/gradient/mollified", result["mollified"], sequence=frames)
    log.log_scalars("/metrics/gradient/unmollified", result["unmollified"], sequence=frames)
    log.log_scalars("/metrics/gradient/free_flight", np.full(n, result["free"]), sequence=frames)
    log.log_scalars("/metrics/aim_offset", result["offsets"], sequence=frames)
    free = abs(result["free"])
    return {
        "scene": NAME,
        "free_flight_gradient": result["free"],
        "threshold_vz": result["threshold"],
        "max_mollified_over_free": float(np.abs(result["mollified"]).max() / free),
        "max_unmollified_over_free": float(np.abs(result["unmollified"]).max() / free),
        "offsets": result["offsets"].tolist(),
        "mollified": result["mollified"].tolist(),
        "unmollified": result["unmollified"].tolist(),
        "contacts": result["contacts"].tolist(),
        "miss_gradients": result["miss_gradients"].tolist(),
    }
