"""Steps per second of the force + integration part of the stepper against Warp's CPU cloth peers.

    python benchmarks/sim.py [--dims 32 64] [--frames 20] [--substeps 16] [--repeats 3] [--scene-steps 300]

Two tables: the force + integration part against Warp's CPU cloth peers (below), and the full
steps per second with collisions of each simulation scene (:func:`scene_table`).

The scene is Warp's own cloth benchmark (``warp/examples/benchmarks/benchmark_cloth.py``): a
``dim x dim`` grid, spacing 0.1 m, particle mass 0.1 kg, two pinned corners, structural + shear +
bend springs (k = 1000 N/m, damping 10 N s/m), frames of 1/60 s in 16 substeps. Its ``Cloth``
class is taken from that file (the file itself imports ``pxr`` and runs on import, so only the
class definition is executed here), and the peers are the shipped integrators instantiated on
the same grid in the same process:

* ``benchmark_cloth_numpy.NpIntegrator`` (float32 numpy),
* ``benchmark_cloth_pytorch.TrIntegrator(cloth, "cpu")`` (float32 torch, default thread count
  and one thread),
* ``benchmark_cloth_warp.WpIntegrator(cloth, "cpu")`` (float32 Warp, in place, no tape support).

Ours is :class:`sim.integrator.SemiImplicitIntegrator` in float64 on the same springs (gravity
-9.8 m/s^2 along y like the numpy/torch peers), timed twice: without gradients (two scratch
States reused) and tape-ready (``requires_grad`` States: fresh arrays per substep, what a
``wp.Tape`` needs; the tape itself is not recorded). A step is one force evaluation + one
integration (one substep); the figure is substeps per second, best of ``--repeats`` blocks of
``--frames`` frames after a warm-up frame (kernel compile/load). The last column checks that
the cloths agree: max |x_ours - x_numpy| after the timed frames (float32 vs float64).
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_WARNING if hasattr(wp, "LOG_WARNING") else wp.config.log_level
wp.config.quiet = True
wp.init()

from sim.integrator import SemiImplicitIntegrator  # noqa: E402
from sim.model import Model  # noqa: E402

PEER_DIR = os.path.join(os.path.dirname(wp.__file__), "examples", "benchmarks")
sys.path.insert(0, PEER_DIR)

FRAME_DT = 1.0 / 60.0
GRAVITY = np.array([0.0, -9.8, 0.0])  # the numpy / torch peers' value


def load_cloth_class():
    """The ``Cloth`` class of Warp's benchmark_cloth.py, without running that script."""
    path = os.path.join(PEER_DIR, "benchmark_cloth.py")
    with open(path) as fh:
        tree = ast.parse(fh.read(), filename=path)
    cls = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Cloth"]
    if not cls:
        raise SystemExit(f"no class Cloth in {path}")
    namespace = {"np": np}
    exec(compile(ast.Module(body=cls, type_ignores=[]), path, "exec"), namespace)
    return namespace["Cloth"]


def import_peers():
    import benchmark_cloth_numpy
    import benchmark_cloth_pytorch

    # benchmark_cloth_warp.py calls wp.clear_kernel_cache() at import, which would delete our
    # compiled kernels too; make it a no-op while importing.
    clear = wp.clear_kernel_cache
    wp.clear_kernel_cache = lambda *a, **k: None
    try:
        import benchmark_cloth_warp
    finally:
        wp.clear_kernel_cache = clear
    return benchmark_cloth_numpy, benchmark_cloth_pytorch, benchmark_cloth_warp


def make_cloth(Cloth, dim):
    return Cloth(
        lower=(0.0, 0.0, 0.0),
        dx=dim,
        dy=dim,
        radius=0.1,
        stretch_stiffness=1000.0,
        bend_stiffness=1000.0,
        shear_stiffness=1000.0,
        mass=0.1,
        fix_corners=True,
    )


def model_from_cloth(cloth) -> Model:
    """Our float64 Model on exactly the peer cloth's particles and springs."""
    inv = cloth.inv_masses.astype(np.float64)
    mass = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), 0.0)
    s = cloth.num_springs
    x = cloth.positions.astype(np.float64)
    idx = cloth.spring_indices.reshape(s, 2)
    return Model(
        device="cpu",
        components=frozenset({"cloth"}),
        gravity=GRAVITY.copy(),
        particle_count=cloth.num_particles,
        particle_q=wp.array(x, dtype=wp.vec3d),
        particle_qd=wp.array(cloth.velocities.astype(np.float64), dtype=wp.vec3d),
        particle_mass=wp.array(mass, dtype=wp.float64),
        particle_inv_mass=wp.array(inv, dtype=wp.float64),
        spring_count=s,
        spring_indices=wp.array(idx, dtype=wp.int32),
        # rest lengths recomputed in float64 (the peer stores them rounded to float32)
        spring_rest_length=wp.array(np.linalg.norm(x[idx[:, 0]] - x[idx[:, 1]], axis=1), dtype=wp.float64),
        spring_stiffness=wp.array(cloth.spring_stiffness.astype(np.float64), dtype=wp.float64),
        spring_damping=wp.array(cloth.spring_damping.astype(np.float64), dtype=wp.float64),
        tri_count=cloth.num_tris,
        tri_indices=wp.array(np.asarray(cloth.triangles, dtype=np.int32).reshape(-1, 3), dtype=wp.int32),
    )


class Ours:
    def __init__(self, model, requires_grad=False):
        self.model = model
        self.integrator = SemiImplicitIntegrator(model)
        self.requires_grad = requires_grad
        self.s0 = model.state(requires_grad=requires_grad)
        self.s1 = model.state(requires_grad=requires_grad)

    def simulate(self, dt, substeps):
        if self.requires_grad:
            # a rollout under a tape keeps every State; here each frame gets a fresh output
            s1 = self.model.state(requires_grad=True)
            self.integrator.step(self.s0, s1, dt, substeps)
            self.s0 = s1
        else:
            self.integrator.step(self.s0, self.s1, dt, substeps)
            self.s0, self.s1 = self.s1, self.s0
        return self.s0.particle_q.numpy()


def time_frames(integrator, frames, substeps, repeats):
    """Best substeps/s over ``repeats`` blocks of ``frames`` frames (after one warm-up frame)."""
    integrator.simulate(FRAME_DT, substeps)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(frames):
            integrator.simulate(FRAME_DT, substeps)
        best = min(best, time.perf_counter() - t0)
    return frames * substeps / best


def positions(integrator):
    if isinstance(integrator, Ours):
        return integrator.s0.particle_q.numpy().astype(np.float64)
    if hasattr(integrator, "positions") and hasattr(integrator.positions, "numpy"):
        p = integrator.positions
        return (p.cpu().numpy() if hasattr(p, "cpu") else p.numpy()).astype(np.float64)
    return integrator.cloth.positions.astype(np.float64)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dims", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--substeps", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes-only", action="store_true", help="only the per-scene table with collisions")
    ap.add_argument("--scene-steps", type=int, default=300,
                    help="steps per scene in the full-step table (default 300)")
    args = ap.parse_args(argv)
    if args.scenes_only:
        scene_table(args.scene_steps)
        return

    import torch

    Cloth = load_cloth_class()
    np_peer, torch_peer, wp_peer = import_peers()
    threads = torch.get_num_threads()

    print(
        f"Force + integration, substeps/s (best of {args.repeats} x {args.frames} frames of "
        f"{args.substeps} substeps, dt = 1/60 s); Warp {wp.__version__} CPU, torch {torch.__version__} "
        f"({threads} threads), numpy {np.__version__}"
    )
    head = f"{'grid':>7s} {'springs':>7s} | {'integrator':34s} {'dtype':7s} | {'steps/s':>10s} {'ours/peer':>9s} | {'max|x-x_np|':>11s}"
    print(head)
    print("-" * len(head))
    for dim in args.dims:
        probe = make_cloth(Cloth, dim)
        model = model_from_cloth(probe)
        rows = []
        runs = [
            ("ours SemiImplicitIntegrator", "float64", lambda: Ours(model)),
            ("ours, tape-ready (requires_grad)", "float64", lambda: Ours(model, requires_grad=True)),
            ("numpy NpIntegrator", "float32", lambda: np_peer.NpIntegrator(make_cloth(Cloth, dim))),
            (f"torch TrIntegrator cpu ({threads} thr)", "float32", lambda: torch_peer.TrIntegrator(make_cloth(Cloth, dim), "cpu")),
            ("torch TrIntegrator cpu (1 thr)", "float32", "torch1"),
            ("warp WpIntegrator cpu", "float32", lambda: wp_peer.WpIntegrator(make_cloth(Cloth, dim), "cpu")),
        ]
        results = {}
        finals = {}
        for name, dtype, make in runs:
            if make == "torch1":
                torch.set_num_threads(1)
                try:
                    integ = torch_peer.TrIntegrator(make_cloth(Cloth, dim), "cpu")
                    sps = time_frames(integ, args.frames, args.substeps, args.repeats)
                finally:
                    torch.set_num_threads(threads)
            else:
                integ = make()
                sps = time_frames(integ, args.frames, args.substeps, args.repeats)
            results[name] = (dtype, sps)
            finals[name] = positions(integ)
        ours = results["ours SemiImplicitIntegrator"][1]
        ref = finals["numpy NpIntegrator"]
        for name, (dtype, sps) in results.items():
            ratio = "" if name.startswith("ours") else f"{ours / sps:9.2f}"
            dev = np.max(np.abs(finals[name] - ref))
            print(
                f"{dim:>3d}x{dim:<3d} {probe.num_springs:7d} | {name:34s} {dtype:7s} | {sps:10.0f} {ratio:>9s} | {dev:11.2e}"
            )
        print("-" * len(head))
    print(
        "ours/peer = our (no-gradient) steps/s over the peer's. All integrators are single-threaded "
        "except torch's default. Every run does the same number of frames, so max|x-x_np| compares "
        "the same time (the Warp peer uses g = -9.81, the others -9.8)."
    )

    print()
    scene_table(args.scene_steps)


def scene_table(steps: int) -> None:
    """Full steps per second of each simulation scene at its defaults (dt 1/60 s, 8 substeps):
    forces + integration + plane contacts + the mesh collision handler (proximity, CCD rounds,
    impulses, impact zones), from the first frame on (so the free-fall phase and the contact phase
    both count), for both forms of the response: Gauss-Seidel impulses (``ImpulseCollisionHandler``)
    and the replayed exact solve (``differentiable=True``, no tape recording). The same model
    without the collision handler is timed as the reference, which shows what the collision
    handling costs."""
    from scenes import cloth_drop, cloth_rigid, rigid_toss
    from scenes.sim_common import build_model, default_args
    from collision.response import ImpulseCollisionHandler

    print(f"Full steps per second with collisions, per scene ({steps} steps of 1/60 s in 8 substeps, "
          "from the start; one CPU thread):")
    head = (f"{'scene':12s} {'response':9s} {'particles':>9s} {'bodies':>6s} {'faces':>6s} | {'steps/s':>8s} "
            f"{'ms/step':>8s} {'contacts/step':>13s} {'fail-safe':>9s} | {'no-collision steps/s':>20s} "
            f"{'collision cost':>14s}")
    print(head)
    print("-" * len(head))
    for module in (cloth_drop, rigid_toss, cloth_rigid):
        args = default_args()
        model = build_model(module.build, args)
        rates = {}
        for mode in ("none", "pgs", "replayed"):
            integrator = SemiImplicitIntegrator(model)
            handler = None if mode == "none" else ImpulseCollisionHandler(model, differentiable=mode == "replayed")
            contacts = [0]
            if handler is not None:
                def hook(s_in, s_pred, h, handler=handler, contacts=contacts):
                    out = handler(s_in, s_pred, h)
                    contacts[0] += len(handler.last_times)
                    return out
                integrator.collision_handler = hook
            s0, s1 = model.state(), model.state()
            integrator.step(s0, s1, args.dt, args.substeps)  # warm-up: kernel load
            s0, s1 = model.state(), model.state()
            contacts[0] = 0
            t0 = time.perf_counter()
            for _ in range(steps):
                integrator.step(s0, s1, args.dt, args.substeps)
                s0, s1 = s1, s0
            rates[mode] = (steps / (time.perf_counter() - t0), contacts[0] / steps,
                           handler.failsafe_count if handler else 0)
        ref = rates["none"][0]
        faces = int(model.tri_count) + (model.shape_faces.shape[0] if model.shape_faces is not None else 0) \
            + (model.static_faces.shape[0] if model.static_faces is not None else 0)
        for mode in ("pgs", "replayed"):
            sps, cps, fs = rates[mode]
            # collision cost: time of the collision handling per step over the force+integration step
            cost = (1.0 / sps - 1.0 / ref) * ref
            print(f"{module.NAME:12s} {mode:9s} {model.particle_count:9d} {model.body_count:6d} {faces:6d} | "
                  f"{sps:8.1f} {1e3 / sps:8.1f} {cps:13.1f} {fs:9d} | {ref:20.1f} {cost:13.1f}x")
    print("-" * len(head))
    print("contacts/step: contacts that received an impulse, summed over the substeps; fail-safe: "
          "substeps that needed rigid impact zones; collision cost: time spent in collision handling "
          "per step, in multiples of the step without it (forces + integration + plane contacts).")


if __name__ == "__main__":
    main()
