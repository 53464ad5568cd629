"""Convergence on closed forms: each check's error against its exact answer as the substeps
double, and the fitted order.

    python benchmarks/convergence.py [--quick] [--out benchmarks/results/convergence]

Checks (the replayed response, dt 1/60 s, substeps 4, 8, 16, 32, 64; ``--quick``: 8, 16, 32):

* ``ballistic``: a particle thrown at (1, 0, 3) m/s under gravity, no contact: its position after
  0.5 s against ``x0 + v0 t + g t^2 / 2``; ``ballistic_exact`` with the integrator's exact
  ballistic update (``make_integrator(model, exact_gravity=True)``);
* ``bounce``: a particle dropped from 1 m onto a plane with restitution 0.7: its height at 1.5 s
  (after two bounces) against the piecewise parabola of the exact restitution law, impact times
  solved in closed form (``bounce_exact``: with the exact ballistic update);
* ``sliding``: a box sliding at 2 m/s on a plane with mu 0.3: its stopping distance against
  ``v^2 / (2 mu g)`` (:func:`benchmarks.physics.check_sliding_friction`);
* ``elastic_hit``: a particle (0.2 kg) at 1 m/s hitting a free box (zero gravity, e = 1,
  frictionless) off its centre: the particle's normal velocity after the hit against
  ``(m1 - m_e) / (m1 + m_e) v``, ``m_e = 1 / (1/M + (r x n)^T I^-1 (r x n))`` the box's effective
  mass at the contact point;
* ``free_rotation``: a box of half extents 0.1 x 0.2 x 0.3 spinning at (1, 5, 0.1) rad/s, zero
  gravity, 5 s: the relative energy drift and the error of the intermediate-axis flip interval
  against Euler's equations integrated by DOP853
  (:func:`benchmarks.physics.check_free_rotation`).

The order is the slope of log error against log substeps, fitted over the substeps whose error
is above rounding (1e-13 relative); "exact" where every error is at rounding. Writes
``<out>.md`` and ``<out>.json`` (``checks``: each with ``name``, ``quantity``, ``substeps``,
``errors``, ``order``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)  # before this folder: benchmarks/sim.py must not shadow the sim package

from benchmarks import physics, report  # noqa: E402

SUBSTEPS = (4, 8, 16, 32, 64)
SUBSTEPS_QUICK = (8, 16, 32)
ROUNDING = 1e-13
G = physics.GRAVITY


def ballistic(substeps: int, exact_gravity: bool = False) -> float:
    """Position error [m] of a particle thrown at (1, 0, 3) m/s after 0.5 s of free flight."""
    b = physics.scene_builder()
    v0 = np.array([1.0, 0.0, 3.0])
    b.add_particle((0.0, 0.0, 1.0), velocity=tuple(v0), mass=1.0)
    run = physics.Run(b, "replayed", substeps, exact_gravity=exact_gravity).run_for(0.5)
    t = run.t[-1]
    exact = np.array([0.0, 0.0, 1.0]) + v0 * t + 0.5 * np.array([0.0, 0.0, -G]) * t * t
    return float(np.linalg.norm(run.particle_q[-1, 0] - exact))


def _bounce_height(t: float, z0: float, e: float, contact: float) -> float:
    """Exact height at ``t`` [s] of a particle dropped from ``z0`` [m] onto a plane (contact at
    height ``contact``) with restitution ``e``: a parabola between impacts."""
    start, z, v = 0.0, z0, 0.0
    while True:
        # time to reach the contact height: z + v s - g s^2 / 2 = contact
        s = (v + math.sqrt(v * v + 2.0 * G * (z - contact))) / G
        if start + s >= t:
            s = t - start
            return z + v * s - 0.5 * G * s * s
        start += s
        v = e * (G * s - v)  # the impact speed g s - v, reflected and scaled
        z = contact


def ballistic_exact(substeps: int) -> float:
    """:func:`ballistic` with the integrator's exact ballistic update (``exact_gravity``)."""
    return ballistic(substeps, exact_gravity=True)


def bounce(substeps: int, restitution: float = 0.7, exact_gravity: bool = False) -> float:
    """Height error [m] at 1.5 s of a particle dropped from 1 m with restitution 0.7."""
    b = physics.scene_builder(restitution=restitution)
    b.add_particle((0.0, 0.0, 1.0), mass=1.0)
    b.add_ground_plane()
    run = physics.Run(b, "replayed", substeps, exact_gravity=exact_gravity).run_for(1.5)
    contact = run.integrator.plane_separation()
    return abs(float(run.particle_q[-1, 0, 2]) - _bounce_height(float(run.t[-1]), 1.0, restitution, contact))


def bounce_exact(substeps: int) -> float:
    """:func:`bounce` with the exact ballistic update."""
    return bounce(substeps, exact_gravity=True)


SLIDING_SPEEDS = (1.8, 1.9, 2.0, 2.1, 2.2)
"""Start speeds [m/s] of the sliding box. A slide to rest is exact but for its last substep,
whose error ``f^2 mu g h^2 / 2`` depends on the fraction ``f`` of the substep left when the box
stops; one speed alone can keep ``f h`` constant as ``h`` halves (2 m/s does from 4 to 32
substeps), several average it out."""


def sliding(substeps: int) -> float:
    """Mean relative error of the stopping distance of a box sliding at 1.8..2.2 m/s, mu 0.3."""
    return float(np.mean([physics.check_sliding_friction("replayed", substeps, speed=v)[0].error
                          for v in SLIDING_SPEEDS]))


def elastic_hit(substeps: int) -> float:
    """Relative error of the particle's normal velocity after an elastic hit on a free box."""
    b = physics.scene_builder(gravity=(0.0, 0.0, 0.0), restitution=1.0, friction=0.0)
    half = physics.BOX_HALF
    body = physics.add_box(b, half, (0.0, 0.0, 0.0))
    m1, v = 0.2, 1.0
    offset = np.array([0.05, 0.03])  # off the face's centre (y, z)
    start = (half + physics.THICKNESS + 0.03, offset[0], offset[1])
    b.add_particle(start, velocity=(-v, 0.0, 0.0), mass=m1)
    run = physics.Run(b, "replayed", substeps).run_for(0.1)
    model = run.model
    mass = float(model.body_mass.numpy()[body])
    inertia = model.body_inertia.numpy().reshape(-1, 3, 3)[body]
    n = np.array([1.0, 0.0, 0.0])
    r = np.array([half, offset[0], offset[1]])
    rn = np.cross(r, n)
    m_e = 1.0 / (1.0 / mass + rn @ np.linalg.solve(inertia, rn))
    # the particle arrives along -x at speed v and leaves along +x at (m_e - m1) / (m1 + m_e) v
    expected = (m_e - m1) / (m1 + m_e) * v
    measured = float(run.particle_qd[-1, 0, 0])
    return abs(measured - expected) / abs(expected)


STRIP = dict(cells=4, cell=0.1, density=1.0, stretch_stiffness=50.0, shear_stiffness=20.0, bend_stiffness=5.0,
             damping=0.02, seconds=0.5)
"""The swinging strip: 4 x 1 cells of 0.1 m, 1 kg/m^2, springs 50 / 20 / 5 N/m with damping
0.02 N s/m, horizontal at the start and pinned at one short edge, swinging down for 0.5 s
(no contact)."""


def _spring_ode(model):
    """The model's equations of motion (springs along their axes with damping, gravity, air
    drag, pinned particles at rest) as ``f(t, y)`` for ``y = (x, v)`` flattened, written here in numpy from
    the model's arrays: an implementation independent of the simulator's kernels."""
    idx = model.spring_indices.numpy().reshape(-1, 2)
    rest = model.spring_rest_length.numpy()
    k = model.spring_stiffness.numpy()
    d = model.spring_damping.numpy()
    inv_m = model.particle_inv_mass.numpy()
    drag = float(model.particle_drag)
    moving = (inv_m > 0.0)[:, None]
    g = np.asarray(model.gravity, dtype=np.float64)
    n = model.particle_count

    def f(_t, y):
        x, v = y[: 3 * n].reshape(n, 3), y[3 * n:].reshape(n, 3)
        dx = x[idx[:, 0]] - x[idx[:, 1]]
        length = np.linalg.norm(dx, axis=1)
        u = dx / length[:, None]
        tension = k * (length - rest) + d * np.einsum("ij,ij->i", u, v[idx[:, 0]] - v[idx[:, 1]])
        force = np.zeros((n, 3))
        np.add.at(force, idx[:, 0], -tension[:, None] * u)
        np.add.at(force, idx[:, 1], tension[:, None] * u)
        a = np.where(moving, force * inv_m[:, None] + g - drag * v, 0.0)
        return np.concatenate([np.where(moving, v, 0.0).ravel(), a.ravel()])

    return f


def strip(substeps: int) -> float:
    """Largest position error [m] after 0.5 s of the swinging strip (:data:`STRIP`) against a
    DOP853 integration (rtol 1e-12) of the same equations of motion (:func:`_spring_ode`)."""
    from scipy.integrate import solve_ivp

    cfg = STRIP
    n, cell = int(cfg["cells"]), float(cfg["cell"])
    b = physics.scene_builder(friction=0.0)
    material = {key: cfg[key] for key in ("density", "stretch_stiffness", "shear_stiffness", "bend_stiffness",
                                          "damping")}
    b.add_cloth_grid((0.0, 0.0, 1.0), None, n, 1, cell, cell, pinned=[0, n + 1], **material)
    run = physics.Run(b, "replayed", substeps).run_for(float(cfg["seconds"]))
    model = run.model
    y0 = np.concatenate([model.particle_q.numpy().ravel(), model.particle_qd.numpy().ravel()])
    ref = solve_ivp(_spring_ode(model), (0.0, float(run.t[-1])), y0, method="DOP853", rtol=1e-12, atol=1e-14)
    x_ref = ref.y[: 3 * model.particle_count, -1].reshape(-1, 3)
    return float(np.linalg.norm(run.particle_q[-1] - x_ref, axis=1).max())


def free_rotation_energy(substeps: int) -> float:
    """Largest relative energy drift of the torque-free box over 5 s."""
    rec = [r for r in physics.check_free_rotation("replayed", substeps) if "energy" in r.quantity]
    return float(rec[0].measured)


def free_rotation_flip(substeps: int) -> float:
    """Relative error of the intermediate-axis flip interval against DOP853."""
    rec = [r for r in physics.check_free_rotation("replayed", substeps) if "flip interval" in r.quantity]
    return float(rec[0].error)


CHECKS = {
    "ballistic": ("position error at 0.5 s [m]", ballistic, 1.0),
    "ballistic_exact": ("the same, exact ballistic update (exact_gravity=True)", ballistic_exact, 1.0),
    "bounce": ("height error at 1.5 s [m]", bounce, 1.0),
    "bounce_exact": ("the same, exact ballistic update", bounce_exact, 1.0),
    "sliding": ("stopping distance, mean relative error over 5 speeds", sliding, 1.0),
    "elastic_hit": ("particle's velocity after the hit, relative error", elastic_hit, 1.0),
    "strip": ("swinging cloth strip: largest position error at 0.5 s [m] (DOP853 reference)", strip, 1.0),
    "free_rotation_energy": ("largest relative energy drift over 5 s", free_rotation_energy, 1.0),
    "free_rotation_flip": ("flip interval, relative error", free_rotation_flip, 1.0),
}
"""name -> (quantity, function of the substeps returning the error, the error's scale: rounding
is ``ROUNDING`` times it)."""


def fitted_order(substeps, errors, scale: float = 1.0) -> float | None:
    """Slope of -log(error) against log(substeps) over the errors above rounding; ``inf`` when
    every error is at rounding; None with fewer than two errors above it."""
    pts = [(n, e) for n, e in zip(substeps, errors) if math.isfinite(e) and e > ROUNDING * scale]
    if not pts:
        return math.inf
    if len(pts) < 2:
        return None
    n, e = np.array(pts, dtype=np.float64).T
    return float(-np.polyfit(np.log(n), np.log(e), 1)[0])


def run(substeps=SUBSTEPS, only=None, progress=None) -> list[dict[str, Any]]:
    out = []
    for name, (quantity, function, scale) in CHECKS.items():
        if only and name not in only:
            continue
        errors = []
        for n in substeps:
            if progress:
                progress(f"{name}: {n} substeps")
            errors.append(float(function(n)))
        out.append({"name": name, "quantity": quantity, "substeps": list(substeps), "errors": errors,
                    "order": fitted_order(substeps, errors, scale)})
    return out


def main(argv=None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"substeps {SUBSTEPS_QUICK} only")
    parser.add_argument("--only", default=None, help=f"comma-separated checks of {', '.join(CHECKS)}")
    parser.add_argument("--out", default=os.path.join(report.RESULTS, "convergence"), help="output prefix")
    args = parser.parse_args(argv)
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    if only and any(s not in CHECKS for s in only):
        parser.error(f"--only: choose from {', '.join(CHECKS)}")
    import warp as wp

    wp.config.quiet = True
    substeps = SUBSTEPS_QUICK if args.quick else SUBSTEPS
    results = run(substeps, only, lambda text: print(f"[convergence] {text}", file=sys.stderr, flush=True))
    lines = ["Error against the closed form as the substeps double (replayed response, dt 1/60 s); order: "
             "slope of log error against log substeps over the errors above rounding ('exact': all at "
             "rounding).", ""]
    body = [[r["name"], r["quantity"], *r["errors"],
             "exact" if r["order"] == math.inf else ("n/a" if r["order"] is None else f"{r['order']:.2f}")]
            for r in results]
    lines += report.table(["check", "quantity", *[f"{n} sub" for n in substeps], "order"], body)
    report.write(args.out, "Convergence on closed forms", lines, {"checks": results})
    return results


if __name__ == "__main__":
    main()
