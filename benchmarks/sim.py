"""Steps per second of the force + integration part of the stepper against Warp's CPU cloth peers.

    python benchmarks/sim.py [--dims 32 64] [--frames 20] [--substeps 16] [--repeats 3] [--scene-steps 300]

Three tables: the force + integration part against Warp's CPU cloth peers (below), the full
steps per second with collisions of each simulation scene (:func:`scene_table`), and the cost
against cloth size, explicit and implicit, with Newton's cloth solvers beside it
(:func:`size_table`; ``--sizes-only`` runs just that one).

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

Ours is :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator` in float64 on the same springs (gravity
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

from sim.contact.stage import StageObserver  # noqa: E402
from sim.integrators.semi_implicit import SemiImplicitIntegrator  # noqa: E402
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
    def __init__(self, model, requires_grad=False, capture=None):
        self.model = model
        self.integrator = SemiImplicitIntegrator(model, capture=capture)
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
    ap.add_argument("--sizes-only", action="store_true", help="only the cloth-size table (and Newton beside it)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64, 128],
                    help="cloth cells per side of the size table (default 16 32 64 128)")
    ap.add_argument("--size-steps", type=int, default=40, help="steps per run of the size table (default 40)")
    ap.add_argument("--newton-sizes", type=int, nargs="*", default=[16, 32, 64],
                    help="cells per side Newton runs at (default 16 32 64; none: no Newton)")
    ap.add_argument("--scene-steps", type=int, default=300,
                    help="steps per scene in the full-step table (default 300)")
    ap.add_argument("--alone-repeats", type=int, default=2,
                    help="runs per setting of the replayed response run alone (default 2; 0: none)")
    ap.add_argument("--alone", metavar="SCENE:graph|plain", default=None,
                    help="time the replayed response of one scene alone in this process (see replayed_alone)")
    args = ap.parse_args(argv)
    if args.alone:
        scene, mode = args.alone.split(":")
        print(f"{_alone_ms_per_step(scene, mode == 'graph', args.scene_steps):.3f}")
        return
    if args.scenes_only:
        scene_table(args.scene_steps, args.alone_repeats)
        return
    if args.sizes_only:
        size_table(args.sizes, args.size_steps, args.newton_sizes)
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
        runs = [
            ("ours SemiImplicitIntegrator", "float64", lambda: Ours(model)),
            ("ours, launch by launch (no graph)", "float64", lambda: Ours(model, capture=False)),
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
        "ours/peer = our (no-gradient) steps/s over the peer's. Ours replays each substep as one recorded "
        "graph (the default on the CPU); the launch-by-launch row runs the same kernels one launch at a time "
        "(same bits). All integrators are single-threaded "
        "except torch's default. Every run does the same number of frames, so max|x-x_np| compares "
        "the same time (the Warp peer uses g = -9.81, the others -9.8)."
    )

    print()
    scene_table(args.scene_steps, args.alone_repeats)
    print()
    size_table(args.sizes, args.size_steps, args.newton_sizes)


WARM_UP_STEPS = 40
"""Steps run before a scene is timed: long enough for the first contacts (cloth_drop lands at
step ~14), so that no kernel is compiled or loaded inside the timed loop."""


INTERLEAVE_STEPS = 10
"""Steps each run of the per-scene table takes in its turn (see :func:`scene_table`)."""


class _SceneRun:
    """One scene stepped with collision handling ``mode`` ("none", "pgs" or "replayed"), from
    the start, one step per :meth:`step` call, its time summed; ``capture``: the integrator's
    (its stages up to the collision stage replayed as a recorded graph, or launched one by one)."""

    def __init__(self, model, args, mode: str, capture: bool = True) -> None:
        from sim.contact.response import ImpulseCollisionHandler

        self.args = args
        self.integrator = SemiImplicitIntegrator(model, capture=capture)
        self.handler = None if mode == "none" else ImpulseCollisionHandler(model, differentiable=mode == "replayed")
        self.contacts = 0
        if self.handler is not None:
            self.integrator.collision_handler = _CountingHook(self.handler, self)
        self.states = (model.state(), model.state())
        self.seconds = 0.0
        self.timed_steps = 0
        self.steps_done = 0

    def step(self) -> None:
        """One step, timed except the run's first (its handler records its kernel launches and
        sizes its buffers then)."""
        s0, s1 = self.states
        t0 = time.perf_counter()
        self.integrator.step(s0, s1, self.args.dt, self.args.substeps)
        if self.steps_done:
            self.seconds += time.perf_counter() - t0
            self.timed_steps += 1
        self.steps_done += 1
        self.states = (s1, s0)


def scene_table(steps: int, alone_repeats: int = 2) -> None:
    """Full steps per second of each simulation scene at its defaults (dt 1/60 s, 8 substeps):
    forces + integration + plane contacts + the mesh collision handler (proximity, CCD rounds,
    impulses, impact zones), from the first frame on (so the free-fall phase and the contact phase
    both count), for both forms of the response: Gauss-Seidel impulses (``ImpulseCollisionHandler``)
    and the replayed exact solve (``differentiable=True``, no tape recording). The same model
    without the collision handler is timed as the reference, which shows what the collision
    handling costs.

    Each run is timed twice, with the integrator's stages up to the collision stage replayed as
    a recorded graph (the default; without a handler that is the whole substep) and launched one
    by one, and the two must end in the same bits.

    The runs advance in turns of :data:`INTERLEAVE_STEPS` steps (interleaved), each step
    timed on its own: a shared machine's speed drifts over seconds (whole runs one after the
    other varied by up to 2x here), and interleaving makes every run see the same drift, so the
    ratios hold; a turn of several steps keeps each run's caches warm after its first step."""
    from scenes import cloth_drop, cloth_rigid, rigid_toss
    from scenes.sim_common import build_model, default_args

    print(f"Full steps per second with collisions, per scene ({steps} steps of 1/60 s in 8 substeps, "
          f"from the start, the six runs interleaved in turns of {INTERLEAVE_STEPS} steps; one CPU thread):")
    head = (f"{'scene':12s} {'response':9s} {'particles':>9s} {'bodies':>6s} {'faces':>6s} | {'steps/s':>8s} "
            f"{'ms/step':>8s} {'no graph':>8s} {'same bits':>9s} | {'contacts/step':>13s} {'fail-safe':>9s} | "
            f"{'collision cost':>14s}")
    print(head)
    print("-" * len(head))
    modes = ("none", "pgs", "replayed")
    for module in (cloth_drop, rigid_toss, cloth_rigid):
        args = default_args()
        model = build_model(module.build, args)
        # warm-up until contacts: kernel compilation and loading happen at first use
        for mode in modes:
            warm = _SceneRun(model, args, mode)
            for _ in range(min(steps, WARM_UP_STEPS)):
                warm.step()
        runs = {(mode, capture): _SceneRun(model, args, mode, capture) for mode in modes for capture in (True, False)}
        for turn, start in enumerate(range(0, steps, INTERLEAVE_STEPS)):
            # the graph and no-graph runs of a response swap places every turn: a run's time
            # depends on which run went just before it (the caches it left)
            for mode in modes:
                for capture in ((True, False) if turn % 2 == 0 else (False, True)):
                    for _ in range(min(INTERLEAVE_STEPS, steps - start)):
                        runs[mode, capture].step()
        ref = runs["none", True].timed_steps / runs["none", True].seconds
        faces = int(model.tri_count) + (model.shape_faces.shape[0] if model.shape_faces is not None else 0) \
            + (model.static_faces.shape[0] if model.static_faces is not None else 0)
        for mode in modes:
            run, plain = runs[mode, True], runs[mode, False]
            sps = run.timed_steps / run.seconds
            same = all(np.array_equal(getattr(run.states[0], name).numpy(), getattr(plain.states[0], name).numpy())
                       for name in ("particle_q", "particle_qd", "body_q", "body_qd"))
            # collision cost: time of the collision handling per step over the force+integration step
            cost = "-" if mode == "none" else f"{(1.0 / sps - 1.0 / ref) * ref:13.1f}x"
            contacts = "-" if run.handler is None else f"{run.contacts / steps:.1f}"
            failsafe = "-" if run.handler is None else run.handler.failsafe_count
            print(f"{module.NAME:12s} {mode:9s} {model.particle_count:9d} {model.body_count:6d} {faces:6d} | "
                  f"{sps:8.1f} {1e3 / sps:8.2f} {1e3 * plain.seconds / plain.timed_steps:8.2f} "
                  f"{'yes' if same else 'NO':>9s} | {contacts:>13s} {failsafe:>9} | {cost:>14s}")
    print("-" * len(head))
    print("ms/step: the default, the integrator's stages up to the collision stage replayed as one recorded "
          "graph per substep (core.capture.Graphs; in the none rows, no collision handler, the whole substep); "
          "no graph: the same run launched one launch at a time; same bits: both runs end in identical "
          "states. contacts/step: contacts that received an impulse, summed over the substeps; fail-safe: "
          "substeps that needed rigid impact zones; collision cost: time spent in collision handling "
          "per step, in multiples of the step without it (forces + integration + plane contacts).")
    if alone_repeats:
        print()
        replayed_alone(steps, alone_repeats)


def _alone_ms_per_step(scene: str, capture: bool, steps: int) -> float:
    """ms per step of ``scene``'s replayed response, run alone in this process after a warm-up run
    (the first step not timed, as in :class:`_SceneRun`)."""
    import importlib

    from scenes.sim_common import build_model, default_args

    args = default_args()
    model = build_model(importlib.import_module(f"scenes.{scene}").build, args)
    warm = _SceneRun(model, args, "replayed", capture)
    for _ in range(min(steps, WARM_UP_STEPS)):
        warm.step()
    run = _SceneRun(model, args, "replayed", capture)
    for _ in range(steps):
        run.step()
    return 1e3 * run.seconds / run.timed_steps


def replayed_alone(steps: int, repeats: int = 2) -> None:
    """The replayed response's ms/step with and without the graph, each run alone in a fresh
    process (``repeats`` times, alternating): in the interleaved table above one run of a pair
    can take up to about twice the other's time, and alone they agree."""
    import subprocess

    print(f"The replayed response alone: each run in a fresh process, {steps} steps from the start, "
          f"{repeats} runs per setting alternating, ms/step:")
    head = f"{'scene':12s} | {'with the graph':>20s} | {'launched one by one':>20s}"
    print(f"{head}\n{'-' * len(head)}")
    for scene in ("cloth_drop", "rigid_toss", "cloth_rigid"):
        times = {"graph": [], "plain": []}
        for _ in range(repeats):
            for mode in times:
                out = subprocess.run([sys.executable, "-m", "benchmarks.sim", "--alone", f"{scene}:{mode}",
                                      "--scene-steps", str(steps)], cwd=os.path.dirname(HERE),
                                     capture_output=True, text=True, check=True).stdout
                times[mode].append(float(out.split()[-1]))
        cells = [", ".join(f"{t:.2f}" for t in times[mode]) for mode in ("graph", "plain")]
        print(f"{scene:12s} | {cells[0]:>20s} | {cells[1]:>20s}")
    print("-" * len(head))


def explicit_substeps_estimate(model, dt: float = FRAME_DT, safety: float = 1.0) -> int:
    """A first guess of the substeps per ``dt`` semi-implicit Euler of the model's springs needs
    (a heuristic: :func:`size_table` doubles it until the run does not diverge, and never tries
    fewer): the highest frequency taken as ``w^2 = max_i 4 sum_{springs at i} k / m_i`` (twice
    the Gershgorin bound of ``M^-1 K``, a margin for the springs' damping, which the bound
    ignores), the step below ``2 / w`` (times ``safety``), rounded up to a power of two."""
    idx = model.spring_indices.numpy().reshape(-1, 2)
    k = model.spring_stiffness.numpy()
    w_inv = model.particle_inv_mass.numpy()
    load = np.zeros(model.particle_count)
    np.add.at(load, idx[:, 0], k)
    np.add.at(load, idx[:, 1], k)
    omega = np.sqrt(4.0 * np.max(load * w_inv))
    need = dt / (safety * 2.0 / omega)
    return int(2 ** max(0, int(np.ceil(np.log2(max(need, 1.0))))))


class _CountingHook(StageObserver):
    """The collision handler, adding its calls' contacts to ``run.contacts``."""

    def __init__(self, handler, run) -> None:
        super().__init__(handler)
        self.run = run

    def __call__(self, state_in, state_pred, h):
        out = self.handler(state_in, state_pred, h)
        self.run.contacts += self.handler.last_contact_count
        return out


class _TimedHandler(StageObserver):
    """The collision handler, its wall time summed (so a run splits into force + integration and
    collision handling on the same states)."""

    def __init__(self, handler):
        super().__init__(handler)
        self.seconds = 0.0

    def __call__(self, state_in, state_pred, h):
        t0 = time.perf_counter()
        try:
            return self.handler(state_in, state_pred, h)
        finally:
            self.seconds += time.perf_counter() - t0


def _cloth_drop_run(cells: int, integrator: str, substeps: int, steps: int) -> dict:
    """``cloth_drop`` at ``cells`` per side for ``steps`` steps from the start: ms per step (the
    integrator's ``step``: in all, and without the collision handler's share, i.e. forces +
    integration + plane contacts), penetrations and the energy peak, or ``{"diverged": True}``.
    The collision response is Gauss-Seidel's (``differentiable=False``): not taped, as the
    peers' contacts are; the replayed response's dense solves grow with the cloth's resting
    contacts (at 32 cells and one implicit substep a single solve of the pile on the sphere has
    433 unknowns and passes the work limit, :class:`sim.contact.contacts.ContactLimitExceeded`)."""
    from sim.contact.response import ImpulseCollisionHandler
    from scenes import cloth_drop
    from scenes.sim_common import EnergyMeter, build_model, default_args
    from sim.integrators import make_integrator
    from sim.penetration import PenetrationChecker

    model = build_model(cloth_drop.build, default_args(cloth_res=cells))
    integ = make_integrator(model, integrator)
    timed = _TimedHandler(ImpulseCollisionHandler(model, differentiable=False))
    integ.collision_handler = timed
    checker = PenetrationChecker(model)
    energy = EnergyMeter(model)
    s0, s1 = model.state(), model.state()
    e0 = sum(energy(s0))
    e_max, pen, wall = e0, 0, 0.0
    for _ in range(steps):
        t0 = time.perf_counter()
        integ.step(s0, s1, FRAME_DT, substeps)
        wall += time.perf_counter() - t0
        s0, s1 = s1, s0
        e = sum(energy(s0))
        if not np.isfinite(e) or e > 100.0 * abs(e0):
            return {"diverged": True}
        e_max = max(e_max, e)
        pen += checker.check(s0).count
    return {"diverged": False, "ms": 1e3 * wall / steps, "force_ms": 1e3 * (wall - timed.seconds) / steps,
            "penetrations": pen, "energy_peak": e_max / e0,
            "refined": int(getattr(integ, "refinements", 0)), "cg": int(getattr(integ, "total_iterations", 0)),
            "particles": model.particle_count}


def _growth_exponent(particles, ms) -> float:
    """Least-squares slope of log(ms) against log(particles)."""
    if len(ms) < 2:
        return float("nan")
    return float(np.polyfit(np.log(particles), np.log(ms), 1)[0])


def size_table(cells_list=(16, 32, 64, 128), steps: int = 40, newton_cells=(16, 32, 64)) -> dict:
    """Cost against cloth size on ``cloth_drop`` (16 to 128 cells per side, the cloth's size,
    density and springs kept), ``steps`` steps of 1/60 s from the start (the fall, the hit on the
    sphere at step ~15 and the start of settling). Explicit runs at the substeps its stability
    needs (:func:`explicit_substeps_estimate`, doubled until it does not diverge), implicit at 1
    substep (it halves impact substeps itself: ``refined``). Each is timed for the force +
    integration part (the step's time less the collision handler's: forces, the implicit solves
    and contact passes, plane contacts) and the full step with collisions, on the same run. The growth exponent is the fitted slope of log(ms per step) against log(vertex
    count). Newton 1.8's semi-implicit, XPBD and VBD cloth on the same drop at ``newton_cells``
    (``benchmarks/newton_cloth.py``) are timed in the same run, ms per frame of 1/60 s."""
    print(f"Cost against cloth size: cloth_drop, {steps} steps of 1/60 s from the start, Gauss-Seidel collision "
          "response, one CPU thread")
    head = (f"{'cells':>5s} {'vertices':>8s} | {'integrator':10s} {'substeps':>8s} | {'force+int ms/step':>17s} "
            f"{'full ms/step':>12s} {'full steps/s':>12s} | {'penetrations':>12s} {'energy peak':>11s} "
            f"{'refined':>7s}")
    print(head)
    print("-" * len(head))
    # warm-up: a run that reaches contact (the sphere at step ~15) per integrator, so that every
    # kernel, the contact ones included, is compiled and loaded before anything is timed
    from scenes import cloth_drop as _scene
    from scenes.sim_common import build_model as _build, default_args as _defaults

    warm_cells = min(cells_list) if cells_list else 16
    warm_probe = _build(_scene.build, _defaults(cloth_res=warm_cells))
    for kind in ("semi_implicit", "implicit"):
        sub = explicit_substeps_estimate(warm_probe) if kind == "semi_implicit" else 1
        _cloth_drop_run(warm_cells, kind, sub, 20)
    rows = []
    for cells in cells_list:
        from scenes import cloth_drop
        from scenes.sim_common import build_model, default_args

        probe = build_model(cloth_drop.build, default_args(cloth_res=cells))
        for kind in ("semi_implicit", "implicit"):
            sub = explicit_substeps_estimate(probe) if kind == "semi_implicit" else 1
            while True:
                full = _cloth_drop_run(cells, kind, sub, steps)
                if not full["diverged"] or kind == "implicit" or sub >= 1024:
                    break
                sub *= 2
            if full["diverged"]:
                print(f"{cells:5d} {probe.particle_count:8d} | {kind:10s} {sub:8d} | diverged")
                continue
            row = {"cells": cells, "vertices": probe.particle_count, "integrator": kind, "substeps": sub, **full}
            rows.append(row)
            print(f"{cells:5d} {probe.particle_count:8d} | {kind:10s} {sub:8d} | {row['force_ms']:17.1f} "
                  f"{row['ms']:12.1f} {1e3 / row['ms']:12.2f} | {row['penetrations']:12d} "
                  f"{row['energy_peak']:11.2f} {row['refined']:7d}", flush=True)
    print("-" * len(head))
    for kind in ("semi_implicit", "implicit"):
        sel = [r for r in rows if r["integrator"] == kind]
        v = [r["vertices"] for r in sel]
        print(f"growth exponent (ms ~ vertices^p), {kind}: force+integration p = "
              f"{_growth_exponent(v, [r['force_ms'] for r in sel]):.2f}, full step p = "
              f"{_growth_exponent(v, [r['ms'] for r in sel]):.2f}")
    newton_rows = []
    if newton_cells:
        try:
            from benchmarks import newton_cloth
        except ImportError as exc:
            print(f"Newton not available ({exc}); pip install -e '.[bench]'")
            return {"rows": rows, "newton": newton_rows}
        print()
        print(f"Newton {__import__('newton').__version__} on the same drop (CPU, its examples' settings), ms per frame "
              f"of 1/60 s, next to ours (the full steps above):")
        head = (f"{'cells':>5s} | {'simulator':28s} {'substeps':>8s} | {'ms/frame':>9s} | "
                f"{'passes through the sphere':>25s}")
        print(head)
        print("-" * len(head))
        for cells in newton_cells:
            for r in (r for r in rows if r["cells"] == cells):
                print(f"{cells:5d} | {'tunnelsim ' + r['integrator']:28s} {r['substeps']:8d} | {r['ms']:9.1f} | "
                      f"{('yes' if r['penetrations'] else 'no'):>25s}")
            for solver in newton_cloth.SOLVERS:
                res = newton_cloth.run_newton_cloth(cells, solver, frames=steps)
                newton_rows.append(res)
                if res.get("error"):
                    print(f"{cells:5d} | {'newton ' + solver:28s} {'-':>8s} | {'error':>9s} | {res['error'][:40]}")
                    continue
                print(f"{cells:5d} | {'newton ' + solver:28s} {res['substeps']:8d} | {res['ms_per_frame']:9.1f} | "
                      f"{('yes' if res['passes_through_sphere'] else 'no'):>25s}", flush=True)
        print("-" * len(head))
        print("passes through: ours, any penetration found by the independent checker (sim/penetration.py) on any "
              "frame; Newton, a particle more than its 5 mm radius inside the sphere on any frame, the cloth ending "
              "below the sphere's top, or a blow-up (benchmarks/newton_cloth.py)")
    return {"rows": rows, "newton": newton_rows}


if __name__ == "__main__":
    main()
