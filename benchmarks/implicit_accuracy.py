"""Accuracy of the implicit (backward-Euler) cloth integrator against a converged explicit reference.

    python benchmarks/implicit_accuracy.py [--cells 16] [--quick] [--out benchmarks/results/implicit_accuracy]

Two measurements on one cloth (a square of ``size`` = 0.8 m, ``cells x cells`` cells, areal density
0.2 kg/m^2, springs stretch 20 / shear 10 / bend 1 N/m as in ``scenes/cloth_drop.py``, but spring
damping 0.1 N s/m instead of 0.01 so that the hanging cloth comes to rest within seconds; gravity
-9.81 m/s^2 along z), each pinned along one whole edge (every particle of that edge is kinematic):

* **static sag** (:func:`sag`): the cloth hangs in the x-z plane from its pinned top edge at
  z = 1 m, released flat, unstretched and at rest, so gravity pulls along its plane. The *sag*
  is the drop [m] of the bottom-centre particle (the mean of the two middle ones for an odd cell
  count) below its unstretched position after ``sag_time`` seconds (by then its speed is below
  ~1e-4 m/s; the table reports the residual max particle speed). Static equilibrium does not
  depend on the integrator, so this shows whether each integrator settles onto it; it is also
  checked against an independent static solve (:func:`static_sag`, Newton on the springs' force
  balance in numpy). The *peak sag* is the largest drop of the same point during the run (the
  first stretch overshoot after release), a transient that does depend on the integrator.
* **swing** (:func:`swing`): the same cloth starts horizontal (x-y plane at the pins' height,
  the pinned edge along y at x = 0, the cloth towards +x) at rest and swings down like a
  pendulum, past the vertical to the other side and back. With ``X(t)`` the x of the centre of
  mass of the free particles (the hinge is at x = 0): ``t_quarter`` [s] is the first time
  ``X`` crosses 0 (the quarter swing: the centre of mass passes under the hinge), ``t_half``
  [s] is the time from there to the next, upward, crossing of 0 (half a period of the
  pendulum-like swing: from under the hinge out to the far side and back), and ``amplitude`` [m]
  is ``-min X`` between the two crossings (how far the cloth swings past the hinge; backward
  Euler's numerical damping shows here first). Crossings and the minimum come from cubic Hermite
  interpolation of the per-frame centre-of-mass position and velocity, so they are not
  quantised to frames.

Each is run with frames of 1/60 s split into ``substeps`` equal substeps: the explicit integrator
(semi-implicit Euler, ``make_integrator(model, "semi_implicit")``) at 1, 2, 4, ... substeps
("diverged" when positions or velocities blow up: non-finite, |x| > 100 m or |v| > 1000 m/s; a sag
run whose cloth still moves faster than 1e-2 m/s at the end is "not at rest", values kept) and
the implicit one (``make_integrator(model, "implicit", max_strain_step=None)``, one
Baraff-Witkin Newton step per substep, CG to a relative residual of 1e-8; "solve failed" if CG
hits its cap) at 1, 2, 4, ... The implicit integrator's strain-driven halving of substeps is off
here, so each row is exactly its substeps (no contacts: the contact passes never act).
The reference is the explicit integrator at ``reference_substeps``; its convergence is shown by
the relative difference of every measure between ``reference_substeps`` and half of it (first-
order method: that difference estimates the reference's own error). Relative errors are
``(value - reference) / |reference|``. Wall time is the stepping only (kernels loaded by a warm-up
before), on the machine and load it ran on; CG iterations are the implicit integrator's
``total_iterations``.

A third, tiny check with a closed form (:func:`spring_oscillator`): one particle hanging from a
pinned one by one damped spring, released at rest length, whose static extension is ``m g / k``
and whose first maximum of extension comes at ``pi / omega_d``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

import warp as wp

from core.device import init_warp
from sim.builder import ModelBuilder
from sim.integrators.implicit import SolveError
from sim.integrators import make_integrator
from sim.model import Model

FRAME_DT = 1.0 / 60.0
"""Frame length [s]; every run advances whole frames of ``substeps`` equal substeps."""

DIVERGED_POSITION = 100.0
"""|x| [m] beyond which a run of a 0.8 m cloth hanging 1 m above the origin counts as diverged."""
DIVERGED_SPEED = 1000.0
"""|v| [m/s] beyond which a run counts as diverged (the swing peaks near 2 m/s)."""

REST_SPEED = 1.0e-2
"""Largest particle speed [m/s] at the end of a sag run for the cloth to count as at rest; above
it the row's status is "not at rest" (e.g. the explicit integrator just inside its stable limit,
where the stiffest mode rings on undamped instead of decaying)."""

CG_TOLERANCE = 1.0e-8
"""The implicit integrator's CG relative residual (its default): well below every error reported."""

# Hanging cloth: rotation taking the builder's local grid (i cell, j cell, 0) to (i cell, 0, -j cell),
# so row j = 0 is the top edge and the cloth hangs down in the x-z plane.
_HANG_ROT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class ClothParams:
    """The cloth of both measurements.

    Attributes:
        cells: Cells per side (>= 2).
        size: Side length [m].
        density: Areal density [kg/m^2].
        stretch: Stretch spring stiffness [N/m].
        shear: Shear spring stiffness [N/m].
        bend: Bending spring stiffness [N/m].
        damping: Damping of every spring along its axis [N s/m] (10x cloth_drop's, so that the
            hanging cloth settles within a few seconds; the same for every run).
        gravity: Gravitational acceleration along -z [m/s^2] (> 0).
        height: z of the pinned edge [m].
    """

    cells: int = 16
    size: float = 0.8
    density: float = 0.2
    stretch: float = 20.0
    shear: float = 10.0
    bend: float = 1.0
    damping: float = 0.1
    gravity: float = 9.81
    height: float = 1.0


@dataclass(frozen=True)
class Config:
    """What is run: the cloth, durations and substep ladders.

    Attributes:
        params: The cloth.
        sag_time: Simulated time of each sag run [s].
        swing_time: Simulated time of each swing run [s] (must cover the return crossing, ~1.3 s).
        explicit_substeps: Substeps per frame of the explicit rows.
        implicit_substeps: Substeps per frame of the implicit rows.
        reference_substeps: Substeps per frame of the explicit reference (its half is run too).
        spring_explicit_substeps: Substeps per frame of the explicit closed-form spring rows.
        spring_implicit_substeps: Substeps per frame of the implicit closed-form spring rows.
    """

    params: ClothParams
    sag_time: float
    swing_time: float
    explicit_substeps: tuple[int, ...]
    implicit_substeps: tuple[int, ...]
    reference_substeps: int
    spring_explicit_substeps: tuple[int, ...] = (4, 16, 64)
    spring_implicit_substeps: tuple[int, ...] = (1, 4, 16, 64)


def default_config(cells: int = 16, quick: bool = False) -> Config:
    """The benchmark's configuration: full (default) or ``quick`` (a 6 x 6 cloth, shorter runs and
    fewer substeps, for the smoke test; ``cells`` is ignored then).

    The explicit ladder stops at a quarter of the reference (the reference and its half are the
    convergence check); the full implicit ladder goes to 32 substeps.
    """
    if quick:
        return Config(ClothParams(cells=6), sag_time=3.0, swing_time=1.5, explicit_substeps=(1, 2, 4, 8, 16, 32),
                      implicit_substeps=(1, 2, 4, 8), reference_substeps=128, spring_implicit_substeps=(1, 4, 16))
    return Config(ClothParams(cells=int(cells)), sag_time=4.0, swing_time=1.6,
                  explicit_substeps=(1, 2, 4, 8, 16, 32, 64, 128, 256), implicit_substeps=(1, 2, 4, 8, 16, 32),
                  reference_substeps=1024)


# --------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------


def _add_cloth(b: ModelBuilder, p: ClothParams, pos, rot, pinned) -> None:
    cell = p.size / p.cells
    b.add_cloth_grid(pos, rot, p.cells, p.cells, cell, cell, density=p.density, stretch_stiffness=p.stretch,
                     shear_stiffness=p.shear, bend_stiffness=p.bend, damping=p.damping, pinned=pinned)


def build_hanging(p: ClothParams) -> Model:
    """The cloth hanging in the x-z plane (y = 0 exactly) from its pinned top edge at ``p.height``.

    Particle ``(i, j)`` (index ``j (cells + 1) + i``) starts at ``(i cell, 0, height - j cell)``,
    unstretched and at rest; row ``j = 0`` is pinned.
    """
    b = ModelBuilder()
    b.set_gravity(-p.gravity)
    _add_cloth(b, p, (0.0, 0.0, p.height), _HANG_ROT, list(range(p.cells + 1)))
    model = b.finalize("cpu")
    # the rotation goes through a quaternion and leaves ~1e-16 m in y; zero it so that the motion
    # stays exactly in the x-z plane (all forces then have y = 0) and cannot buckle out of it
    q = model.particle_q.numpy().copy()
    q[:, 1] = 0.0
    model.particle_q.assign(q)
    return model


def build_swing(p: ClothParams) -> Model:
    """The cloth horizontal at ``p.height`` (x-y plane, ``x, y`` in ``[0, size]``), pinned along its
    edge ``x = 0`` (particles ``i = 0``), at rest."""
    b = ModelBuilder()
    b.set_gravity(-p.gravity)
    _add_cloth(b, p, (0.0, 0.0, p.height), None, [j * (p.cells + 1) for j in range(p.cells + 1)])
    return b.finalize("cpu")


def bottom_centre(p: ClothParams) -> list[int]:
    """Indices of the hanging cloth's bottom-centre particle (the two middle ones for odd ``cells``)."""
    row = p.cells * (p.cells + 1)
    return sorted({row + p.cells // 2, row + (p.cells + 1) // 2})


# --------------------------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------------------------

_warm: set = set()
# fixed substeps: the strain-driven halving would change what a row's substeps mean
_IMPLICIT_OPTIONS = {"tolerance": CG_TOLERANCE, "max_strain_step": None}


def _warm_up(model: Model, kind: str) -> None:
    """One step of ``kind`` on a scratch state, so kernel loading (or compiling) is not timed."""
    if kind in _warm:
        return
    integ = make_integrator(model, kind, **(_IMPLICIT_OPTIONS if kind == "implicit" else {}))
    integ.step(model.state(), model.state(), FRAME_DT, 1)
    _warm.add(kind)


def simulate(model: Model, kind: str, substeps: int, frames: int, probe: Callable[[np.ndarray, np.ndarray], np.ndarray],
             max_iterations: int = 2000) -> dict:
    """Runs ``frames`` frames of ``FRAME_DT`` in ``substeps`` substeps each and probes every frame.

    Args:
        model: The scene.
        kind: ``"semi_implicit"`` or ``"implicit"``.
        substeps: Substeps per frame (>= 1).
        frames: Frames to run.
        probe: ``probe(q, qd) -> array`` of what to record from positions [m] and velocities [m/s]
            (P, 3) numpy.
        max_iterations: The implicit integrator's CG cap.

    Returns:
        ``{"status": "ok" | "diverged" | "solve failed", "t": (F + 1,) frame times [s],
        "samples": (F + 1, ...) probes (frame 0 = the start), "max_speed": the largest particle
        speed at the end [m/s], "wall_s": stepping time [s], "cg_iterations": implicit only}``.
        After a divergence or a failed solve the arrays stop at the last good frame.
    """
    _warm_up(model, kind)
    options = {**_IMPLICIT_OPTIONS, "max_iterations": max_iterations} if kind == "implicit" else {}
    integ = make_integrator(model, kind, **options)
    s0, s1 = model.state(), model.state()
    samples = [probe(s0.particle_q.numpy(), s0.particle_qd.numpy())]
    status, wall, speed = "ok", 0.0, 0.0
    for _ in range(frames):
        t0 = time.perf_counter()
        try:
            integ.step(s0, s1, FRAME_DT, substeps)
        except SolveError:
            status = "solve failed"
            break
        except ValueError as e:  # the implicit step refuses a non-finite right-hand side
            if "finite" not in str(e):
                raise
            status = "diverged"
            break
        finally:
            wall += time.perf_counter() - t0
        q, qd = s1.particle_q.numpy(), s1.particle_qd.numpy()
        speed = float(np.sqrt(np.max(np.sum(qd * qd, axis=1)))) if np.all(np.isfinite(qd)) else np.inf
        if not (np.all(np.isfinite(q)) and np.max(np.abs(q)) < DIVERGED_POSITION and speed < DIVERGED_SPEED):
            status = "diverged"
            break
        samples.append(probe(q, qd))
        s0, s1 = s1, s0
    out = {"status": status, "t": FRAME_DT * np.arange(len(samples)), "samples": np.array(samples),
           "max_speed": speed, "wall_s": wall}
    if kind == "implicit":
        out["cg_iterations"] = int(integ.total_iterations)
    return out


# --------------------------------------------------------------------------------------------
# cubic Hermite interpolation of a sampled trajectory (value and derivative at every frame)
# --------------------------------------------------------------------------------------------


def _hermite(x0: float, x1: float, v0: float, v1: float, h: float) -> np.ndarray:
    """Power-basis coefficients (s^3, s^2, s, 1) of the cubic Hermite interpolant on s in [0, 1]."""
    return np.array([2.0 * (x0 - x1) + h * (v0 + v1), 3.0 * (x1 - x0) - h * (2.0 * v0 + v1), h * v0, x0])


def _real_roots_in_unit(c: np.ndarray) -> np.ndarray:
    r = np.roots(c)
    r = r[np.abs(r.imag) <= 1e-9 * max(1.0, np.max(np.abs(r)))].real if len(r) else np.zeros(0)
    return np.sort(r[(r >= -1e-12) & (r <= 1.0 + 1e-12)].clip(0.0, 1.0))


def crossing(t: np.ndarray, x: np.ndarray, v: np.ndarray, start: int = 0, direction: int = -1) -> tuple[float, int]:
    """First time at or after frame ``start`` where ``x`` crosses 0 downwards (``direction`` -1) or
    upwards (+1), from the Hermite interpolant of samples ``x`` [m] and derivatives ``v`` [m/s] at
    times ``t`` [s]. Returns ``(time [s], frame index after the crossing)``, or ``(nan, -1)``."""
    for k in range(start, len(x) - 1):
        if (direction < 0 and x[k] > 0.0 >= x[k + 1]) or (direction > 0 and x[k] < 0.0 <= x[k + 1]):
            h = t[k + 1] - t[k]
            roots = _real_roots_in_unit(_hermite(x[k], x[k + 1], v[k], v[k + 1], h))
            # the interpolant changes sign on [0, 1]: an odd number of roots; take the first
            s = roots[0] if len(roots) else x[k] / (x[k] - x[k + 1])
            return float(t[k] + s * h), k + 1
    return float("nan"), -1


def extremum(t: np.ndarray, x: np.ndarray, v: np.ndarray, lo: int, hi: int, sign: int = 1) -> tuple[float, float]:
    """Largest (``sign`` +1) or smallest (-1) value of the Hermite interpolant over frames
    ``[lo, hi]``: ``(value, time [s])``."""
    best_val, best_t = -np.inf, float("nan")
    for k in range(lo, hi):
        h = t[k + 1] - t[k]
        c = sign * _hermite(x[k], x[k + 1], v[k], v[k + 1], h)
        cand = np.concatenate([[0.0, 1.0], _real_roots_in_unit(np.polyder(c))])
        vals = np.polyval(c, cand)
        i = int(np.argmax(vals))
        if vals[i] > best_val:
            best_val, best_t = float(vals[i]), float(t[k] + cand[i] * h)
    return sign * best_val, best_t


# --------------------------------------------------------------------------------------------
# the measurements
# --------------------------------------------------------------------------------------------


def _frames(duration: float) -> int:
    return round(duration / FRAME_DT)


def sag(params: ClothParams, integrator: str, substeps: int, duration: float = 4.0) -> dict:
    """Static and peak sag of the hanging cloth (see the module docstring).

    Args:
        params: The cloth.
        integrator: ``"semi_implicit"`` or ``"implicit"``.
        substeps: Substeps per 1/60 s frame.
        duration: Simulated time [s]; the static sag is taken at its end.

    Returns:
        ``{"integrator", "substeps", "status", "sag": static sag [m], "peak_sag": largest drop
        [m], "t_peak": its time [s], "residual_speed": largest particle speed at the end [m/s],
        "wall_s", "cg_iterations" (implicit)}``; status "ok", "not at rest" (residual speed above
        :data:`REST_SPEED`; the values are kept), "diverged" or "solve failed" (values None).
    """
    model = build_hanging(params)
    idx = bottom_centre(params)
    z_rest = float(np.mean(model.particle_q.numpy()[idx, 2]))

    def probe(q, qd):
        # drop below the rest position and its rate [m, m/s]
        return np.array([z_rest - np.mean(q[idx, 2]), -np.mean(qd[idx, 2])])

    run = simulate(model, integrator, substeps, _frames(duration), probe)
    out = {"integrator": integrator, "substeps": substeps, "status": run["status"], "sag": None, "peak_sag": None,
           "t_peak": None, "residual_speed": None, "wall_s": run["wall_s"], "cg_iterations": run.get("cg_iterations")}
    if run["status"] == "ok":
        t, s = run["t"], run["samples"]
        k = int(np.argmax(s[:, 0]))
        peak, t_peak = extremum(t, s[:, 0], s[:, 1], max(k - 1, 0), min(k + 1, len(t) - 1), sign=1)
        out.update(sag=float(s[-1, 0]), peak_sag=peak, t_peak=t_peak, residual_speed=run["max_speed"])
        if run["max_speed"] > REST_SPEED:
            out["status"] = "not at rest"
    return out


def swing(params: ClothParams, integrator: str, substeps: int, duration: float = 1.6) -> dict:
    """Quarter swing, half period and amplitude of the cloth released horizontal (see the module
    docstring).

    Args:
        params: The cloth.
        integrator: ``"semi_implicit"`` or ``"implicit"``.
        substeps: Substeps per 1/60 s frame.
        duration: Simulated time [s] (must cover the return crossing).

    Returns:
        ``{"integrator", "substeps", "status", "t_quarter" [s], "t_half" [s], "amplitude" [m],
        "wall_s", "cg_iterations" (implicit)}``; a value is None when it was not reached or the
        status is not "ok".
    """
    model = build_swing(params)
    mass = model.particle_mass.numpy()
    w = mass / mass.sum()  # pinned particles have mass 0: the free particles' centre of mass

    def probe(q, qd):
        return np.array([w @ q[:, 0], w @ qd[:, 0]])  # hinge at x = 0

    run = simulate(model, integrator, substeps, _frames(duration), probe)
    out = {"integrator": integrator, "substeps": substeps, "status": run["status"], "t_quarter": None,
           "t_half": None, "amplitude": None, "wall_s": run["wall_s"], "cg_iterations": run.get("cg_iterations")}
    if run["status"] == "ok":
        t, x, v = run["t"], run["samples"][:, 0], run["samples"][:, 1]
        t_down, k_down = crossing(t, x, v, 0, -1)
        if k_down > 0:
            out["t_quarter"] = t_down
            t_up, k_up = crossing(t, x, v, k_down - 1, +1)
            if k_up > 0:
                out["t_half"] = t_up - t_down
                out["amplitude"] = -extremum(t, x, v, k_down - 1, k_up, sign=-1)[0]
    return out


def static_sag(params: ClothParams, tol: float = 1e-12, max_iterations: int = 50) -> dict:
    """The hanging cloth's static sag from the springs' force balance, independent of both
    integrators: Newton's method in numpy on ``sum_springs f(x) + m g = 0`` over the free
    particles' in-plane (x, z) coordinates, from the unstretched cloth, with the springs' exact
    tangent stiffness ``k (u u^T + (1 - L0 / l)(I - u u^T))`` and a backtracking line search.

    Args:
        params: The cloth.
        tol: Stop when the largest force residual is below ``tol`` times the largest particle
            weight.
        max_iterations: Newton iterations at most.

    Returns:
        ``{"sag": [m], "iterations", "residual": largest |force| [N] left}``.
    """
    model = build_hanging(params)
    x = model.particle_q.numpy().astype(np.float64).copy()
    mass = model.particle_mass.numpy()
    springs = model.spring_indices.numpy().reshape(-1, 2)
    rest, ke = model.spring_rest_length.numpy(), model.spring_stiffness.numpy()
    g = np.asarray(model.gravity, dtype=np.float64)
    n = len(x)
    free = mass > 0.0
    axes = (0, 2)  # the cloth stays in the x-z plane
    dofs = (3 * np.flatnonzero(free)[:, None] + np.array(axes)[None, :]).reshape(-1)
    i, j = springs[:, 0], springs[:, 1]

    def forces(x):
        d = x[i] - x[j]
        length = np.linalg.norm(d, axis=1)
        t = ke * (length - rest)
        f = mass[:, None] * g
        np.add.at(f, i, -(t / length)[:, None] * d)
        np.add.at(f, j, (t / length)[:, None] * d)
        f[~free] = 0.0
        return f

    def jacobian(x):
        d = x[i] - x[j]
        length = np.linalg.norm(d, axis=1)
        u = d / length[:, None]
        uu = u[:, :, None] * u[:, None, :]
        blk = ke[:, None, None] * (uu + (1.0 - rest / length)[:, None, None] * (np.eye(3) - uu))
        jac = np.zeros((3 * n, 3 * n))
        ax = np.arange(3)
        # df_i/dx_i = df_j/dx_j = -K, df_i/dx_j = df_j/dx_i = +K
        for a, c, sign in ((i, i, -1.0), (j, j, -1.0), (i, j, 1.0), (j, i, 1.0)):
            np.add.at(jac, (3 * a[:, None, None] + ax[None, :, None], 3 * c[:, None, None] + ax[None, None, :]),
                      sign * blk)
        return jac[np.ix_(dofs, dofs)]

    scale = float(np.max(mass) * np.linalg.norm(g))
    f = forces(x)
    it = 0
    for it in range(1, max_iterations + 1):
        r = f.reshape(-1)[dofs]
        dx = np.linalg.solve(jacobian(x), -r)
        norm0, step = np.max(np.abs(r)), 1.0
        while True:  # backtracking: accept the first step that lowers the largest residual
            x_try = x.copy()
            x_try.reshape(-1)[dofs] += step * dx
            f_try = forces(x_try)
            if np.max(np.abs(f_try)) < norm0 or step < 1e-6:
                break
            step *= 0.5
        x, f = x_try, f_try
        if np.max(np.abs(f)) <= tol * scale:
            break
    idx = bottom_centre(params)
    q0 = model.particle_q.numpy()
    return {"sag": float(np.mean(q0[idx, 2]) - np.mean(x[idx, 2])), "iterations": it,
            "residual": float(np.max(np.abs(f)))}


def spring_oscillator(integrator: str, substeps: int, duration: float = 1.0, mass: float = 0.1,
                      stiffness: float = 20.0, damping: float = 0.1, rest: float = 0.5,
                      gravity: float = 9.81) -> dict:
    """One particle of ``mass`` [kg] hanging from a pinned one by one spring (``stiffness`` [N/m],
    ``damping`` [N s/m], ``rest`` length [m]), released at rest at the rest length: closed form.

    The spring stays vertical, so the extension ``e`` obeys ``m e'' + c e' + k e = m g`` exactly:
    ``e(t) = e_s (1 - exp(-zeta w t)(cos(w_d t) + zeta w / w_d sin(w_d t)))`` with ``e_s = m g / k``,
    ``w = sqrt(k / m)``, ``zeta = c / (2 sqrt(k m))`` (< 1: under-damped, else ``ValueError``),
    ``w_d = w sqrt(1 - zeta^2)``: the first maximum is at ``pi / w_d`` with
    ``e_s (1 + exp(-zeta w pi / w_d))``.

    Returns:
        ``{"status", "t_peak" [s], "peak" [m], "final" [m] (extension at ``duration``),
        "exact_t_peak", "exact_peak", "exact_final" (``e(duration)``), "exact_static" (m g / k)
        [s, m]}``; measured values None unless status is "ok".
    """
    zeta = damping / (2.0 * np.sqrt(stiffness * mass))
    if not 0.0 <= zeta < 1.0:
        raise ValueError(f"the closed form here is the under-damped one: damping must be < {2 * np.sqrt(stiffness * mass):g}")
    b = ModelBuilder()
    b.set_gravity(-gravity)
    b.add_particle((0.0, 0.0, 1.0), pinned=True)
    b.add_particle((0.0, 0.0, 1.0 - rest), mass=mass)
    base = b.finalize("cpu")
    # the builder adds springs only with cloth; attach the one spring to the finalized arrays
    model = dataclasses.replace(
        base, spring_count=1, spring_indices=wp.array(np.array([[0, 1]], dtype=np.int32), dtype=wp.int32),
        spring_rest_length=wp.array([rest], dtype=wp.float64), spring_stiffness=wp.array([stiffness], dtype=wp.float64),
        spring_damping=wp.array([damping], dtype=wp.float64))

    def probe(q, qd):
        return np.array([(1.0 - rest) - q[1, 2], -qd[1, 2]])  # extension and its rate

    run = simulate(model, integrator, substeps, _frames(duration), probe)
    w = np.sqrt(stiffness / mass)
    wd = w * np.sqrt(1.0 - zeta * zeta)
    e_s = mass * gravity / stiffness
    t_end = _frames(duration) * FRAME_DT
    e_end = e_s * (1.0 - np.exp(-zeta * w * t_end) * (np.cos(wd * t_end) + zeta * w / wd * np.sin(wd * t_end)))
    out = {"status": run["status"], "t_peak": None, "peak": None, "final": None, "exact_t_peak": float(np.pi / wd),
           "exact_peak": float(e_s * (1.0 + np.exp(-zeta * w * np.pi / wd))), "exact_final": float(e_end),
           "exact_static": float(e_s)}
    if run["status"] == "ok":
        t, s = run["t"], run["samples"]
        k = int(np.argmax(s[: _frames(1.5 * np.pi / wd), 0]))  # the first maximum (before the next one)
        out["peak"], out["t_peak"] = extremum(t, s[:, 0], s[:, 1], max(k - 1, 0), min(k + 1, len(t) - 1), sign=1)
        out["final"] = float(s[-1, 0])
    return out


# --------------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------------

SAG_MEASURES = ("sag", "peak_sag")
SWING_MEASURES = ("t_quarter", "t_half", "amplitude")


def _rel(value, ref) -> float | None:
    if value is None or ref is None or not np.isfinite(value):
        return None
    return float((value - ref) / abs(ref))


def _with_errors(rows: list[dict], ref: dict, measures: tuple[str, ...]) -> list[dict]:
    for r in rows:
        for m in measures:
            r[f"{m}_rel_err"] = _rel(r[m], ref[m])
    return rows


def _convergence(ref: dict, half: dict, measures: tuple[str, ...]) -> dict:
    """Relative difference of each measure between the reference and half its substeps."""
    return {m: _rel(half[m], ref[m]) for m in measures}


def accuracy_tables(cells: int = 16, quick: bool = False, config: Config | None = None,
                    log: Callable[[str], None] | None = None) -> dict:
    """Runs both measurements over the substep ladders and returns every number.

    Args:
        cells: Cells per side of the full configuration.
        quick: The tiny configuration (:func:`default_config`).
        config: Overrides ``cells`` and ``quick``.
        log: Called with a line per run (progress), e.g. ``print``.

    Returns:
        ``{"config", "sag": {"reference", "reference_half", "convergence", "static_solve",
        "static_solve_rel_err", "rows"}, "swing": {"reference", "reference_half", "convergence",
        "rows"}, "spring": closed-form rows, "wall_s"}``; every row carries its measures, their
        ``*_rel_err`` against the reference (None where not available), ``wall_s`` and
        ``cg_iterations``.
    """
    cfg = config or default_config(cells, quick)
    p = cfg.params
    init_warp()
    say = log or (lambda s: None)
    t_start = time.perf_counter()
    result: dict = {"config": {**dataclasses.asdict(cfg), "frame_dt": FRAME_DT, "cg_tolerance": CG_TOLERANCE}}

    for name, fn, duration, measures in (("sag", sag, cfg.sag_time, SAG_MEASURES),
                                         ("swing", swing, cfg.swing_time, SWING_MEASURES)):
        ref = fn(p, "semi_implicit", cfg.reference_substeps, duration)
        half = fn(p, "semi_implicit", cfg.reference_substeps // 2, duration)
        if ref["status"] != "ok" or half["status"] != "ok":  # not at rest included: no reference then
            raise RuntimeError(f"{name}: the explicit reference did not run ({ref['status']}, {half['status']})")
        say(f"{name}: reference explicit x{cfg.reference_substeps} {_fmt_measures(ref, measures)} "
            f"({ref['wall_s']:.1f} s)")
        rows = []
        for kind, ladder in (("semi_implicit", cfg.explicit_substeps), ("implicit", cfg.implicit_substeps)):
            for n in ladder:
                r = fn(p, kind, n, duration)
                rows.append(r)
                say(f"{name}: {kind} x{n} {r['status']} {_fmt_measures(r, measures)} ({r['wall_s']:.1f} s)")
        _with_errors(rows, ref, measures)
        entry = {"reference": ref, "reference_half": half, "convergence": _convergence(ref, half, measures),
                 "rows": rows}
        if name == "sag":
            solve = static_sag(p)
            entry["static_solve"] = solve
            entry["static_solve_rel_err"] = _rel(ref["sag"], solve["sag"])
            for r in rows:
                r["sag_static_rel_err"] = _rel(r["sag"], solve["sag"])
        result[name] = entry

    spring_rows = []
    for kind, ladder in (("semi_implicit", cfg.spring_explicit_substeps), ("implicit", cfg.spring_implicit_substeps)):
        for n in ladder:
            r = spring_oscillator(kind, n)
            spring_rows.append({"integrator": kind, "substeps": n, **r,
                                "t_peak_rel_err": _rel(r["t_peak"], r["exact_t_peak"]),
                                "peak_rel_err": _rel(r["peak"], r["exact_peak"]),
                                "final_rel_err": _rel(r["final"], r["exact_final"])})
    result["spring"] = spring_rows
    result["wall_s"] = time.perf_counter() - t_start
    return result


def _fmt_measures(r: dict, measures: tuple[str, ...]) -> str:
    return " ".join(f"{m}={r[m]:.6g}" if r[m] is not None else f"{m}=-" for m in measures)


def _f(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def _label(kind: str) -> str:
    return "explicit" if kind == "semi_implicit" else "implicit"


def markdown(result: dict) -> str:
    """The tables of :func:`accuracy_tables` as markdown."""
    cfg = result["config"]
    p = cfg["params"]
    lines = [(f"# Implicit vs explicit accuracy: {p['cells']}x{p['cells']} cloth, {p['size']} m, "
             f"density {p['density']} kg/m^2, springs {p['stretch']}/{p['shear']}/{p['bend']} N/m, "
             f"damping {p['damping']} N s/m, frames of 1/60 s"), ""]

    s = result["sag"]
    ref, conv = s["reference"], s["convergence"]
    lines += [f"## Static sag (top edge pinned, {cfg['sag_time']} s) and peak sag of the bottom-centre particle", "",
              (f"Reference: explicit at {cfg['reference_substeps']} substeps: sag {ref['sag']:.9g} m, peak sag "
              f"{ref['peak_sag']:.9g} m at {ref['t_peak']:.4f} s, residual speed {ref['residual_speed']:.2e} m/s. "
              f"Converged: relative difference to {cfg['reference_substeps'] // 2} substeps "
              f"{_f(conv['sag'], '.1e')} (sag), {_f(conv['peak_sag'], '.1e')} (peak sag). "
              f"Independent static solve (Newton, numpy): sag {s['static_solve']['sag']:.9g} m, reference's "
              f"relative difference {_f(s['static_solve_rel_err'], '.1e')}."), "",
              ("| integrator | substeps | status | sag [m] | rel. error | rel. error vs static solve | peak sag [m] | "
              "rel. error | residual speed [m/s] | wall [s] | CG iterations |"),
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in s["rows"]:
        lines.append(f"| {_label(r['integrator'])} | {r['substeps']} | {r['status']} | {_f(r['sag'], '.7f')} | "
                     f"{_f(r['sag_rel_err'], '.1e')} | {_f(r['sag_static_rel_err'], '.1e')} | {_f(r['peak_sag'], '.7f')} | {_f(r['peak_sag_rel_err'], '.1e')} | "
                     f"{_f(r['residual_speed'], '.1e')} | {r['wall_s']:.2f} | {_f(r['cg_iterations'], 'd')} |")

    w = result["swing"]
    ref, conv = w["reference"], w["convergence"]
    lines += ["", f"## Swing (edge-pinned cloth released horizontal, {cfg['swing_time']} s)", "",
              (f"Reference: explicit at {cfg['reference_substeps']} substeps: t_quarter {ref['t_quarter']:.6f} s, "
              f"t_half {ref['t_half']:.6f} s, amplitude {ref['amplitude']:.6f} m. Converged: relative difference to "
              f"{cfg['reference_substeps'] // 2} substeps {_f(conv['t_quarter'], '.1e')} (t_quarter), "
              f"{_f(conv['t_half'], '.1e')} (t_half), {_f(conv['amplitude'], '.1e')} (amplitude)."), "",
              ("| integrator | substeps | status | t_quarter [s] | rel. error | t_half [s] | rel. error | "
              "amplitude [m] | rel. error | wall [s] | CG iterations |"),
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in w["rows"]:
        lines.append(f"| {_label(r['integrator'])} | {r['substeps']} | {r['status']} | {_f(r['t_quarter'], '.6f')} | "
                     f"{_f(r['t_quarter_rel_err'], '.1e')} | {_f(r['t_half'], '.6f')} | {_f(r['t_half_rel_err'], '.1e')} | "
                     f"{_f(r['amplitude'], '.6f')} | {_f(r['amplitude_rel_err'], '.1e')} | {r['wall_s']:.2f} | "
                     f"{_f(r['cg_iterations'], 'd')} |")

    sp = result["spring"]
    if sp:
        lines += ["", "## Closed form: one particle on one damped spring (m 0.1 kg, k 20 N/m, c 0.1 N s/m), 1 s", "",
                  (f"Exact: first peak at {sp[0]['exact_t_peak']:.6f} s, extension {sp[0]['exact_peak']:.6f} m; "
                  f"extension at 1 s {sp[0]['exact_final']:.6f} m."), "",
                  ("| integrator | substeps | status | t_peak rel. error | peak rel. error | extension at 1 s rel. error "
                  "(vs e(1 s)) |"),
                  "|---|---|---|---|---|---|"]
        for r in sp:
            lines.append(f"| {_label(r['integrator'])} | {r['substeps']} | {r['status']} | "
                         f"{_f(r['t_peak_rel_err'], '.1e')} | {_f(r['peak_rel_err'], '.1e')} | "
                         f"{_f(r['final_rel_err'], '.1e')} |")
    lines += ["", f"Total run time {result['wall_s']:.0f} s."]
    return "\n".join(lines) + "\n"


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", type=int, default=16, help="cells per side of the cloth (default 16)")
    ap.add_argument("--quick", action="store_true", help="tiny configuration (6x6 cloth, short runs): a smoke test")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "implicit_accuracy"),
                    help="output path without extension: writes <out>.md and <out>.json")
    args = ap.parse_args(argv)
    if args.cells < 2:
        ap.error("--cells must be >= 2")
    result = accuracy_tables(args.cells, args.quick, log=lambda s: print(s, file=sys.stderr, flush=True))
    md = markdown(result)
    print(md)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out + ".md", "w") as fh:
        fh.write(md)
    with open(args.out + ".json", "w") as fh:
        json.dump(_jsonable(result), fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
