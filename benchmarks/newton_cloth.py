"""Newton 1.8's cloth solvers (semi-implicit, XPBD, VBD), headless on the CPU, on our ``cloth_drop`` scene.

The scene is :mod:`scenes.cloth_drop`'s, rebuilt with Newton's own builder: a square cloth 0.8 m per side
(``add_cloth_grid``, ``cells`` x ``cells`` cells, (cells + 1)^2 particles of equal mass, 0.128 kg in all =
0.2 kg/m^2), flat and at rest, centred at (0.1, 0, 0.7); z up, gravity -9.81 m/s^2; a static sphere (radius
0.2 m, centre (0, 0, 0.2)), a static box (half extent 0.1 m, centre (0.35, 0, 0.1)), both ``body=-1``, and the
ground plane z = 0. Friction 0.3 (shape materials and ``model.soft_contact_mu``), restitution 0. Frames of
1/60 s. Our sphere is an icosphere mesh, Newton's an analytic sphere.

Solver settings: Newton's ``examples/cloth/example_cloth_hanging.py`` (the example that runs the same cloth
with ``semi_implicit``, ``xpbd`` and ``vbd``), unless noted:

* substeps per frame: semi-implicit 32, XPBD 10, VBD 10; iterations: XPBD 10, VBD 10 (the example's;
  ``substeps=`` overrides the substeps);
* elements: FEM triangles + dihedral bending edges for semi-implicit and VBD, springs on the triangle edges
  (``add_springs=True``) + dihedral bending for XPBD; ``builder.color(include_bending=True)`` for VBD;
* ``SolverSemiImplicit(model)``, ``SolverXPBD(model, iterations=10)``, ``SolverVBD(model, iterations=10,
  particle_enable_self_contact=True, particle_self_contact_margin=0.02, particle_self_contact_gap=0.01)``;
* collisions: ``pipeline = newton.CollisionPipeline(model)`` (default ``soft_contact_gap`` 0.01 m),
  ``contacts = pipeline.contacts()``, and every substep ``state_0.clear_forces()``,
  ``pipeline.collide(state_0, contacts)``, ``solver.step(state_0, state_1, control, contacts, dt)``, swap;
* the frame's substeps are recorded once with ``wp.ScopedCapture`` and replayed with ``wp.capture_launch``, as
  the example does (on the CPU Warp 1.19 records the launches and replays them; checked bit-identical to running
  them over 60 frames at 16 cells, and 1.4x (semi-implicit), 3.4x (XPBD), 1.6x (VBD) faster there). Skipped
  for an odd ``substeps`` (the state swap would not close a cycle) or ``capture=False``;
* contact stiffness: ``model.soft_contact_ke = 1e2`` N/m for all three, shape ``ke = 1e2`` for semi-implicit
  (the example's ground), Newton's default shape material (ke 2.5e3, kd 1e2) for XPBD and VBD;
  ``model.soft_contact_kd``: VBD 1e2 (the example's; VBD is implicit), XPBD 1 (unused by XPBD).

Not the example's, with the reason:

* cloth material: the example's (tri_ke 1e3 or spring_ke 1e3, bending edge_ke 10, damping 10 / 1 / 100) is
  for 0.1 kg particles on 0.1 m cells (10 kg/m^2). Used as they are on our 0.2 kg/m^2 cloth (0.03-0.4 g
  particles), semi-implicit blows up in free fall (explicit damping 10), XPBD at contact (Jacobi projection of
  springs much stiffer than m/dt^2), and VBD's cloth is so stiff (bending 10) that it lands on the sphere as a
  plate and slides off it within the second. So the cloth has *our*
  scene's material: stretch 20 N/m (``tri_ke = tri_ka = 20`` N/m, or ``spring_ke = 20`` N/m on every triangle
  edge, which with one diagonal per cell stands for our two 10 N/m shear springs), damping 0.01 (``tri_kd`` /
  ``spring_kd``), and a nearly free bending ``edge_ke = 1e-3`` (Newton's ``example_cloth_twist.py`` value for
  its 0.2 kg/m^2 cloth; our distance-2 bending springs resist bending only to second order about the flat
  state), ``edge_kd = 0``;
* semi-implicit contact damping: the example's (``soft_contact_kd`` 1, ground kd 50) is explicit and
  ``kd dt / m >> 1`` for our particles, which blows up; 0.01 N s/m (our spring damping) for shapes and soft
  contacts. Its particle-particle contact (on by default through ``model.particle_grid``; Newton's default
  ke 1e3, kd 1e2) blows up for the same reason when the hanging cloth folds: ``model.particle_ke = 1e2``,
  ``model.particle_kd = 0.01``;
* particle radius (the collision thickness): 5 mm (the example's 0.05 m is half its 0.1 m cells; Newton's
  ``example_cloth_style3d.py`` uses 5 mm, our scene a 1 mm thickness); friction 0.3 (the example: 1).

What happens (60 frames, CPU; see the table printed by the CLI):

* 16 cells: all three hold the cloth on the sphere; the particle nearest the sphere's axis rests at
  z = 0.40 + the 5 mm radius. XPBD's cloth does not settle (max speed ~3 m/s after 1 s, a flap up to 0.49 m).
  VBD's deepest point, 4.9 mm inside the sphere (just under the 5 mm threshold), is a one-substep kick of a
  hanging-edge particle (6.5 m/s for one substep) that goes away with ``vbd_self_contact=False``: the cloth
  then stays 2.4 mm outside the sphere, and VBD runs twice as fast.
* 32 cells: semi-implicit and VBD hold it; XPBD blows up at contact. This is the solver, not the set-up:
  Newton's XPBD projects the springs Jacobi-style (deltas summed, not averaged), which diverges once
  ``spring_ke dt^2 / m`` is not small: 0.028 in the example, 0.13 / 0.47 / 1.9 here at 16 / 32 / 64 cells
  (spring_kd 0 blows up too). With 20 substeps it stays bounded at 32 cells but throws the cloth off the
  sphere (ends below the top).
* 64 cells: all three fail with the example's settings. XPBD blows up (as above). Semi-implicit blows up in
  free fall within 3 frames: its FEM damping is explicit, and ``tri_kd dt / m`` is too large for 0.03 g
  particles at 32 substeps (``tri_kd`` 0.005 blows up too, 0 does not). VBD's self-contact (the example's
  2 cm margin + 1 cm gap, made for 10 cm cells, against our 1.25 cm cells) makes it ~18x slower (14.5 s a
  frame) and pushes particles 31 mm into the sphere; without self-contact VBD holds the cloth (0.8 s a frame).
  Shrinking the margin to the example's ratio to the cell size (2.5 mm + 1.25 mm) is no fix either: VBD's
  divide-and-truncate bound then caps each particle's motion at ~1.6 mm a substep, and the cloth falls at
  < 1 m/s.

Measured: ``ms_per_frame`` is the mean wall time of a frame (all its substeps, collision detection included)
over frames 2..``frames``; frame 1 is a warm-up that loads the compiled kernels and is not timed; model
building, graph recording and the checks (a copy of the positions to numpy after each frame) are not timed.

"Passes through the sphere": on any frame some particle is more than the particle radius (5 mm) inside
the sphere (``|x - c| - r < -0.005`` m), or the cloth ends below the sphere's top: its highest particle at the
end is below z = 0.35 m (resting on the sphere it is at 0.405 m), or the run blew up (positions non-finite, or
a particle outside |x|, |y| <= 2 m, -0.5 <= z <= 2 m: Newton clamps speeds at 1e5 m/s, so blow-ups stay finite).
``min_sphere_distance`` is min over frames (after each frame, the initial state included) and particles of
``|x - c| - r``.

Run: ``python benchmarks/newton_cloth.py [--cells 16 32 64] [--solvers semi_implicit xpbd vbd] [--frames 60]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from typing import Any

import numpy as np
import warp as wp

wp.config.quiet = True  # older Warp; 1.19 filters its messages with log_level
if hasattr(wp, "LOG_WARNING"):
    wp.config.log_level = wp.LOG_WARNING

SOLVERS = ("semi_implicit", "xpbd", "vbd")

FPS = 60
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
# the drop of scenes/cloth_drop.py (its geometry and material, not copies)
from scenes.cloth_drop import (
    BOX_CENTRE,
    BOX_HALF,
    CLOTH_CENTRE_XY,
    CLOTH_HEIGHT,
    CLOTH_SIZE,
    DENSITY,
    FRICTION,
    RESTITUTION,
    SPHERE_CENTRE,
    SPHERE_RADIUS,
)

GRAVITY = -9.81
PARTICLE_RADIUS = 5.0e-3
"""Particle radius = collision thickness [m]; also the pass-through depth."""
REST_TOP_MIN_Z = 0.35
"""The cloth's highest particle must end above this height [m] (sphere top 0.4 m)."""
SCENE_BOUNDS_XY = 2.0
SCENE_BOUNDS_Z = (-0.5, 2.0)
"""A particle outside |x|, |y| <= 2 m, -0.5 m <= z <= 2 m on any frame: the simulation blew up (Newton's
solvers clamp particle speeds at ``particle_max_velocity`` = 1e5 m/s, so a blow-up can stay finite)."""

MATERIAL_FEM = {"tri_ke": 20.0, "tri_ka": 20.0, "tri_kd": 0.01, "edge_ke": 1.0e-3, "edge_kd": 0.0}
MATERIAL_SPRINGS = {"add_springs": True, "spring_ke": 20.0, "spring_kd": 0.01, "edge_ke": 1.0e-3, "edge_kd": 0.0}

SETTINGS: dict[str, dict[str, Any]] = {
    "semi_implicit": {
        "substeps": 32, "iterations": None, "cloth": MATERIAL_FEM,
        "shape_ke": 1.0e2, "shape_kd": 0.01, "soft_contact_ke": 1.0e2, "soft_contact_kd": 0.01,
        "particle_ke": 1.0e2, "particle_kd": 0.01,
    },
    "xpbd": {
        "substeps": 10, "iterations": 10, "cloth": MATERIAL_SPRINGS,
        "shape_ke": None, "shape_kd": None, "soft_contact_ke": 1.0e2, "soft_contact_kd": 1.0,
    },
    "vbd": {
        "substeps": 10, "iterations": 10, "cloth": MATERIAL_FEM,
        "shape_ke": None, "shape_kd": None, "soft_contact_ke": 1.0e2, "soft_contact_kd": 1.0e2,
        "self_contact_margin": 0.02, "self_contact_gap": 0.01,
    },
}
"""Per solver: substeps, iterations, cloth material (``add_cloth_grid`` keywords), contact parameters
(``shape_ke/kd`` None: Newton's default shape material). See the module docstring for their sources."""


class NewtonClothDrop:
    """The scene, solver, states and collision pipeline; :meth:`frame` advances one frame."""

    def __init__(self, cells: int, solver: str, substeps: int, device: str = "cpu", capture: bool = True,
                 vbd_self_contact: bool = True):
        import newton

        cfg = SETTINGS[solver]
        self.device = device
        self.substeps = substeps
        self.sim_dt = 1.0 / FPS / substeps
        self.iterations = cfg["iterations"]
        with wp.ScopedDevice(device):
            builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, GRAVITY))
            shape_cfg = builder.default_shape_cfg.copy()
            shape_cfg.mu = FRICTION
            shape_cfg.restitution = RESTITUTION
            if cfg["shape_ke"] is not None:
                shape_cfg.ke = cfg["shape_ke"]
                shape_cfg.kd = cfg["shape_kd"]
            builder.add_ground_plane(cfg=shape_cfg)
            builder.add_shape_sphere(-1, xform=wp.transform(wp.vec3(*SPHERE_CENTRE), wp.quat_identity()),
                                     radius=SPHERE_RADIUS, cfg=shape_cfg)
            builder.add_shape_box(-1, xform=wp.transform(wp.vec3(*BOX_CENTRE), wp.quat_identity()),
                                  hx=BOX_HALF, hy=BOX_HALF, hz=BOX_HALF, cfg=shape_cfg)
            cell = CLOTH_SIZE / cells
            corner = (CLOTH_CENTRE_XY[0] - CLOTH_SIZE / 2, CLOTH_CENTRE_XY[1] - CLOTH_SIZE / 2, CLOTH_HEIGHT)
            builder.add_cloth_grid(
                pos=wp.vec3(*corner), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                dim_x=cells, dim_y=cells, cell_x=cell, cell_y=cell,
                mass=DENSITY * CLOTH_SIZE**2 / (cells + 1) ** 2,
                particle_radius=PARTICLE_RADIUS, **cfg["cloth"],
            )
            if solver == "vbd":
                builder.color(include_bending=True)
            self.model = builder.finalize()
            self.model.soft_contact_ke = cfg["soft_contact_ke"]
            self.model.soft_contact_kd = cfg["soft_contact_kd"]
            self.model.soft_contact_mu = FRICTION
            self.model.soft_contact_restitution = RESTITUTION
            if "particle_ke" in cfg:
                self.model.particle_ke = cfg["particle_ke"]
                self.model.particle_kd = cfg["particle_kd"]
            if solver == "semi_implicit":
                self.solver = newton.solvers.SolverSemiImplicit(self.model)
            elif solver == "xpbd":
                self.solver = newton.solvers.SolverXPBD(self.model, iterations=self.iterations)
            else:
                self.solver = newton.solvers.SolverVBD(
                    self.model, iterations=self.iterations, particle_enable_self_contact=vbd_self_contact,
                    particle_self_contact_margin=cfg["self_contact_margin"],
                    particle_self_contact_gap=cfg["self_contact_gap"],
                )
            self.state_0 = self.model.state()
            self.state_1 = self.model.state()
            self.control = self.model.control()
            self.collision_pipeline = newton.CollisionPipeline(self.model)
            self.contacts = self.collision_pipeline.contacts()
        self.graph = None
        if capture and substeps % 2 == 0:
            with wp.ScopedCapture(device=device) as cap:
                self.simulate()
            self.graph = cap.graph

    def simulate(self) -> None:
        for _ in range(self.substeps):
            self.state_0.clear_forces()
            self.collision_pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.sim_dt)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def frame(self) -> None:
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            with wp.ScopedDevice(self.device):
                self.simulate()

    def positions(self) -> np.ndarray:
        return self.state_0.particle_q.numpy().astype(np.float64)


def run_newton_cloth(cells: int, solver: str, frames: int = 60, substeps: int | None = None,
                     device: str = "cpu", *, capture: bool = True, vbd_self_contact: bool = True) -> dict[str, Any]:
    """Drops the cloth for ``frames`` frames with Newton's ``solver``; returns timing and the sphere checks.

    Args:
        cells: Cloth cells per side.
        solver: One of :data:`SOLVERS`.
        frames: Frames of 1/60 s (>= 2); the first is an untimed warm-up.
        substeps: Substeps per frame (None: the example's, see :data:`SETTINGS`).
        device: Warp device.
        capture: Record the frame with ``wp.ScopedCapture`` and replay it, as Newton's example does.
        vbd_self_contact: VBD's ``particle_enable_self_contact`` (the example's: True).

    Returns:
        ``solver``, ``cells``, ``particles``, ``frames``, ``substeps``, ``iterations``, ``ms_per_frame``,
        ``passes_through_sphere``, ``min_sphere_distance`` [m], ``max_penetration_depth`` [m] (deepest a
        particle got inside the sphere, 0 if none), ``finite``, plus the parts of the verdict
        (``penetrates_sphere``, ``ends_below_sphere_top``, ``blew_up``), ``final_max_z`` [m], ``final_top_z``
        (end height of the particle nearest the sphere's vertical axis) [m], ``final_min_sphere_distance`` [m],
        ``final_max_speed`` [m/s], ``min_z`` [m] (lowest particle over all frames), ``particle_radius`` [m],
        ``graph_captured``, ``vbd_self_contact``, ``device``.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if frames < 2:
        raise ValueError(f"frames must be >= 2 (the first is a warm-up), got {frames}")
    wp.init()
    substeps = int(SETTINGS[solver]["substeps"] if substeps is None else substeps)
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    sim = NewtonClothDrop(cells, solver, substeps, device, capture, vbd_self_contact)
    centre = np.asarray(SPHERE_CENTRE, dtype=np.float64)

    def sphere_distance(q: np.ndarray) -> float:
        return float(np.min(np.linalg.norm(q - centre, axis=1) - SPHERE_RADIUS))

    q = sim.positions()
    min_dist = sphere_distance(q)
    min_z = float(np.min(q[:, 2]))
    finite = True
    blew_up = False
    times = []
    for i in range(frames):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sim.frame()
        wp.synchronize_device(device)
        if i > 0:
            times.append(time.perf_counter() - t0)
        q = sim.positions()
        if not np.all(np.isfinite(q)):
            finite = False
            break
        outside_z = (q[:, 2] < SCENE_BOUNDS_Z[0]) | (q[:, 2] > SCENE_BOUNDS_Z[1])
        if np.any(np.abs(q[:, :2]) > SCENE_BOUNDS_XY) or np.any(outside_z):
            blew_up = True
        min_dist = min(min_dist, sphere_distance(q))
        min_z = min(min_z, float(np.min(q[:, 2])))
    nearest_axis = int(np.argmin(np.linalg.norm(q[:, :2] - centre[:2], axis=1)))
    penetrates = min_dist < -PARTICLE_RADIUS
    below_top = bool(finite and np.max(q[:, 2]) < REST_TOP_MIN_Z)
    return {
        "solver": solver,
        "cells": cells,
        "particles": int(sim.model.particle_count),
        "frames": frames,
        "substeps": substeps,
        "iterations": sim.iterations,
        "ms_per_frame": 1e3 * float(np.mean(times)) if times else math.nan,
        "passes_through_sphere": bool(penetrates or below_top or blew_up or not finite),
        "min_sphere_distance": min_dist,
        "max_penetration_depth": max(0.0, -min_dist),
        "finite": finite,
        "penetrates_sphere": bool(penetrates),
        "blew_up": bool(blew_up),
        "ends_below_sphere_top": below_top,
        "final_max_z": float(np.max(q[:, 2])) if finite else math.nan,
        "final_top_z": float(q[nearest_axis, 2]) if finite else math.nan,
        "final_min_sphere_distance": sphere_distance(q) if finite else math.nan,
        "final_max_speed": float(np.max(np.linalg.norm(sim.state_0.particle_qd.numpy(), axis=1)))
        if finite else math.nan,
        "min_z": min_z,
        "particle_radius": PARTICLE_RADIUS,
        "graph_captured": sim.graph is not None,
        "vbd_self_contact": bool(vbd_self_contact) if solver == "vbd" else None,
        "device": str(device),
    }


def _row(r: dict[str, Any]) -> str:
    if "error" in r:
        return (f"| {r['solver']} | {r['cells']} | {(r['cells'] + 1) ** 2} | {r.get('substeps', '')} | "
                f"error: {r['error']} | | |")
    if r["passes_through_sphere"]:
        why = [w for w, on in (("non-finite", not r["finite"]), ("blew up", r["blew_up"]),
                               ("inside > 5 mm", r["penetrates_sphere"]),
                               ("ends below top", r["ends_below_sphere_top"])) if on]
        verdict = "yes (" + ", ".join(why) + ")"
    else:
        verdict = "no"
    name = r["solver"] + (" (no self-contact)" if r.get("vbd_self_contact") is False else "")
    return (f"| {name} | {r['cells']} | {r['particles']} | {r['substeps']} | {r['ms_per_frame']:.1f} | "
            f"{1e3 * r['min_sphere_distance']:.2f} | {verdict} |")


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[16, 32, 64], help="cloth cells per side")
    parser.add_argument("--solvers", nargs="+", choices=SOLVERS, default=list(SOLVERS))
    parser.add_argument("--frames", type=int, default=60, help="frames of 1/60 s, the first a warm-up")
    parser.add_argument("--substeps", type=int, default=None, help="override the example's substeps")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--vbd-no-self-contact", action="store_true",
                        help="VBD without particle self-contact (the example has it on)")
    args = parser.parse_args(argv)
    print("| solver | cells | particles | substeps | ms per frame | min distance to sphere [mm] | passes through |")
    print("|---|---|---|---|---|---|---|")
    results = []
    for cells in args.cells:
        for solver in args.solvers:
            try:
                r = run_newton_cloth(cells, solver, args.frames, args.substeps, args.device,
                                     vbd_self_contact=not args.vbd_no_self_contact)
            except Exception as e:  # noqa: BLE001 - one solver's failure must not lose the table
                r = {"solver": solver, "cells": cells, "frames": args.frames,
                     "substeps": args.substeps or SETTINGS[solver]["substeps"], "error": f"{type(e).__name__}: {e}"}
            results.append(r)
            print(_row(r), flush=True)
    return results


if __name__ == "__main__":
    main()
