"""Scene ``bank_shot``: Newton's ``diffsim_ball`` problem with exact CCD impulses (lifted events).

The problem of Newton 1.8's ``newton/examples/diffsim/example_diffsim_ball.py``: a particle
(1 kg) starts at (0, -0.5, 1) m; a static wall (a box centred at (0, 2, 1) m, half extents
(1, 0.25, 1) m) and a ground plane (z = 0); gravity 9.81 m/s^2 along -z; 36 frames of 1/60 s
with 8 substeps each. Its initial velocity must make it bounce off the floor and the wall so
that it ends at the target (0, -2, 1.5) m. Newton solves it with penalty contact (stiffness 1e4,
damping 10, friction gain 0) in float32 and plain gradient descent; here contacts are exact CCD
impulses (elastic, frictionless, as Newton's restitution 1 and zero friction gain) in float64.

Starts (``--start``):

* ``newton``: Newton's (0, 5, -5) m/s: floor, then wall, then it ends 3 m from the target.
* ``miss``: (3, 5, -5) m/s: floor, then past the wall's side (x = 1.35 m where the wall ends at
  x = 1 m); the distance's gradient alone leads to a direct throw that never touches the wall.
* ``seeded`` (with ``--seed S``): a miss drawn from the seed (:func:`seeded_start`): a
  sideways speed of 1.5-3.5 m/s to either side, 4-6 m/s towards the wall and 4-6 m/s down, kept
  when the path bounces off the floor and passes the wall without touching it.

Adam on the initial velocity, one rollout per iteration:

* **proposed**: while the rollout misses the wall, the loss is the lifted event (:mod:`sim.events`)
  of the particle and the wall's front triangle that the particle's path comes nearest, over
  frames ``EVENT_WINDOW`` (after the floor bounce): its root must lie in the window (eq.
  ``complexconjugateloss`` if it is complex) and its barycentric coordinates at the root's real
  part at the triangle's centroid. For a static wall the root is real; the miss lies outside the
  triangle, and the coordinates carry it in. Once the wall is hit, the loss is Newton's, the squared
  distance to the target, with the guarded steps of :class:`scenes.optim.GuardedAdam` (an
  iterate that leaves the wall or raises the loss is rejected).
* **baseline**: what a differentiable simulator without lifted events has: the squared distance
  from the start (the same loop, the unmollified ``-1/p'(t*)``).
* **cma**: CMA-ES (the ``cma`` package) on the same loss as the proposed method (its value only;
  a miss costs ``MISS_OFFSET`` more than any hit) with the same number of rollouts.

Success: the final position within ``TARGET_TOLERANCE`` (1 cm) of the target *and* bounces off
the floor and the wall (a bank shot; a direct throw, or one off the wall alone, does not count).
"The wall is hit" below means both bounces happen.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from scenes.optim import ITERS_HELP, central_difference_check, GuardedAdam, parse_methods, progress, reported_iterate, run_cma
from scenes.registry import int_at_least
from scenes.sim_common import RolloutSettings, add_rollout_arguments, rollout_settings

NAME = "bank_shot"
USES_SEED = "seed of the start drawn by --start seeded"
DESCRIPTION = "Newton's diffsim_ball: bounce off the floor and a wall onto a target (exact CCD, lifted events, CMA-ES)"
PRECISIONS = ("float64",)
SUPPORTS_STEPS = False

FRAMES = 36
DT = 1.0 / 60.0
SUBSTEPS = 8
PARTICLE_START = (0.0, -0.5, 1.0)  # [m]
WALL_CENTRE = (0.0, 2.0, 1.0)  # [m]
WALL_HALF_EXTENTS = (1.0, 0.25, 1.0)  # [m]
TARGET = (0.0, -2.0, 1.5)  # [m]
STARTS = {"newton": (0.0, 5.0, -5.0), "miss": (3.0, 5.0, -5.0)}  # [m/s]
TARGET_TOLERANCE = 0.01  # [m]
EVENT_WINDOW = (12, FRAMES)  # frames: from just after the floor bounce to the end
LEARNING_RATE = 0.1  # [m/s] Adam's step (and the hit phase's largest)
ADAM_BETAS = (0.9, 0.9)
GROWTH = 1.5
MISS_OFFSET = 100.0  # [m^2] CMA-ES: a miss of the wall costs this plus its event loss
CMA_SIGMA = 1.0  # [m/s] CMA-ES's initial step
METHODS = ("proposed", "baseline", "cma")


SEEDED_SIDEWAYS, SEEDED_FORWARD, SEEDED_DOWN = (1.5, 3.5), (4.0, 6.0), (4.0, 6.0)  # [m/s] ranges of seeded misses


def seeded_start(model, seed: int, settings: RolloutSettings | None = None) -> tuple[float, float, float]:
    """A start [m/s] that misses the wall, drawn from ``seed`` (see the module docstring): draws
    until the forward rollout (with ``settings``, as :func:`simulate`) bounces off the floor and
    never touches the wall."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        v = np.array([rng.choice((-1.0, 1.0)) * rng.uniform(*SEEDED_SIDEWAYS), rng.uniform(*SEEDED_FORWARD),
                      -rng.uniform(*SEEDED_DOWN)])
        hits = bounces(simulate(model, v, settings=settings)[1])
        if hits["floor"] > 0 and hits["wall"] == 0:
            return tuple(float(x) for x in v)
    raise RuntimeError(f"bank_shot: no missing start found for seed {seed}")


def build():
    """The model (static description) of the problem."""
    from sim.builder import ModelBuilder
    from sim.mesh_io import box_mesh

    b = ModelBuilder()  # gravity 9.81 m/s^2 along -z
    b.add_particle(PARTICLE_START, mass=1.0)
    b.add_static_mesh(*box_mesh(np.array(WALL_HALF_EXTENTS)), pos=WALL_CENTRE)
    b.add_ground_plane()
    b.set_contact(restitution=1.0, friction=0.0, thickness=0.0)
    return b.finalize()


def front_triangles(model) -> list[tuple[int, int, int]]:
    """The wall's two triangles facing the start (outward normal -y), as static vertex indices."""
    v = model.static_vertices.numpy()
    out = []
    for tri in model.static_faces.numpy().reshape(-1, 3):
        n = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
        if n[1] < -0.99 * np.linalg.norm(n):
            out.append(tuple(int(k) for k in tri))
    return out


def events_of(model):
    from sim.events import Event, particle, static_vertex

    return [Event("vertex_face", (particle(0),) + tuple(static_vertex(k) for k in tri), EVENT_WINDOW)
            for tri in front_triangles(model)]


def simulate(model, v, *, events=(), unmollified=False, grad=False, settings: RolloutSettings | None = None):
    """(initial velocity tensor (1, 3), rollout result) for ``v``: a (3,) array or a tensor;
    ``settings``: substeps, ``M`` and CCD knobs other than the scene's (``--substeps``,
    ``--max-derivative``, ``--ccd-*``)."""
    import torch

    from sim.rollout import rollout

    if isinstance(v, torch.Tensor):
        x = v
    else:
        x = torch.tensor(np.asarray(v, dtype=np.float64)[None], dtype=torch.float64, requires_grad=grad)
    substeps, kw = (settings or RolloutSettings()).rollout_arguments(SUBSTEPS, unmollified)
    return x, rollout(model, FRAMES, DT, substeps, particle_qd=x, events=list(events), **kw)


def bounces(res) -> dict[str, int]:
    """Counts of floor and wall bounces, from the velocity jumps of the trajectory: a jump along
    z below half the wall's height is the floor; any other jump is the wall (its faces)."""
    qd = res.particle_qd[:, 0].detach().numpy()
    q = res.particle_q[:, 0].detach().numpy()
    jumps = np.diff(qd, axis=0)
    # gravity changes the velocity by g dt every frame; a contact reverses a component
    size = np.linalg.norm(jumps - np.array([0.0, 0.0, -9.81 * DT]), axis=1)
    floor = wall = 0
    for k in np.flatnonzero(size > 1e-6):
        j = jumps[k]
        along_z = abs(j[2]) > 0.99 * np.linalg.norm(j)
        if along_z and min(q[k, 2], q[k + 1, 2]) < 0.5 * WALL_CENTRE[2]:
            floor += 1
        else:
            wall += 1
    return {"floor": floor, "wall": wall}


def banked(hits: dict[str, int]) -> bool:
    """A bank shot: the path bounced off the floor and the wall."""
    return hits["floor"] > 0 and hits["wall"] > 0


def distance(res) -> float:
    return float(np.linalg.norm(res.particle_q[-1, 0].detach().numpy() - np.asarray(TARGET)))


def distance_loss(res):
    import torch

    return ((res.particle_q[-1, 0] - torch.as_tensor(TARGET, dtype=torch.float64)) ** 2).sum()


def miss_loss(res):
    """The lifted event's loss of the front triangle the path comes nearest (see the module
    docstring): (loss, index of that triangle's event)."""
    import torch

    from sim.events import complex_conjugate_loss

    duration = (EVENT_WINDOW[1] - EVENT_WINDOW[0]) * DT
    best = None
    for e in range(res.event_roots.shape[0]):
        roots = res.event_roots[e] / duration  # in windows
        # the root nearest the window's middle (a static face: one finite real root)
        slot = int(torch.argmin((roots[:, 0].detach() - 0.5).abs() + roots[:, 1].detach().abs()))
        root, w = roots[slot], res.event_coords[e, slot]
        if float(root[1].detach()) != 0.0:
            partner = next(k for k in range(3) if k != slot and float(roots[k, 1].detach()) == -float(root[1].detach()))
            time_term = complex_conjugate_loss(root, roots[partner], (0.5, 0.0))
        else:
            time_term = torch.relu(-root[0]) ** 2 + torch.relu(root[0] - 1.0) ** 2
        outside = float(torch.relu(-w.detach()).sum())
        loss = time_term + ((w - 1.0 / 3.0) ** 2).sum()
        if best is None or outside < best[2]:
            best = (loss, e, outside)
    return best[0], best[1]


def optimise(model, start, iters: int, method: str = "proposed", callback=None,
             settings: RolloutSettings | None = None) -> dict[str, Any]:
    """Adam (``proposed``, ``baseline``) or CMA-ES (``cma``) from ``start`` [m/s] (see the module
    docstring). Returns the run's figures and its history (one entry per rollout)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "cma":
        return _optimise_cma(model, start, iters, settings, callback)
    import torch

    unmollified = method == "baseline"
    events = events_of(model) if method == "proposed" else []
    v = torch.tensor(np.asarray(start, dtype=np.float64)[None], requires_grad=True)
    opt = GuardedAdam(v, LEARNING_RATE, ADAM_BETAS, GROWTH)
    history = _history()
    reached = None
    t0 = time.perf_counter()
    for it in range(iters + 1):
        opt.zero_grad()
        _, res = simulate(model, v, events=events, unmollified=unmollified, settings=settings)
        hits = bounces(res)
        dist = distance(res)
        wall = banked(hits)
        if wall or method == "baseline":
            loss = distance_loss(res)
        elif not opt.guarded:
            loss, _ = miss_loss(res)
        else:
            loss = None  # left the wall: rejected
        # the baseline has one phase (the distance throughout), never guarded
        take = opt.judge(loss, wall and method == "proposed")
        history["loss"].append(float(loss.detach()) if loss is not None else float("nan"))
        history["distance"].append(dist)
        history["wall"].append(hits["wall"])
        history["floor"].append(hits["floor"])
        history["accepted"].append(bool(take))
        history["velocity"].append(v.detach().numpy()[0].copy())
        history["trajectory"].append(res.particle_q[:, 0].detach().numpy().copy())
        if wall and dist < TARGET_TOLERANCE:
            reached = it
            history["grad_norm"].append(0.0)
            break
        if it == iters:
            history["grad_norm"].append(0.0)
            break
        history["grad_norm"].append(opt.step(loss, wall and method == "proposed", take))
        if callback is not None:
            callback(it, history)
    last = reported_iterate(history["accepted"], reached, opt.guarded)
    return _result(history, last, reached, time.perf_counter() - t0)


def _history() -> dict[str, list]:
    return {"loss": [], "distance": [], "wall": [], "floor": [], "accepted": [], "velocity": [],
            "trajectory": [], "grad_norm": []}


def _result(history, last, reached, wall_time):
    return {
        "reached_target": reached is not None,
        "iterations_to_target": reached,
        "final_loss": history["loss"][last],
        "final_distance": history["distance"][last],
        "wall_bounces": history["wall"][last],
        "floor_bounces": history["floor"][last],
        "final_velocity": history["velocity"][last].tolist(),
        "rollouts": len(history["loss"]),
        "wall_time": wall_time,
        "history": history,
    }


def task_loss(model, v, settings: RolloutSettings | None = None) -> tuple[float, Any]:
    """The proposed method's loss as a plain value (CMA-ES): the squared distance when the wall
    is hit, ``MISS_OFFSET`` plus the event loss when it is missed. Returns (loss, rollout)."""
    _, res = simulate(model, v, events=events_of(model), settings=settings)
    if banked(bounces(res)):
        return float(distance_loss(res)), res
    return MISS_OFFSET + float(miss_loss(res)[0]), res


def _optimise_cma(model, start, iters: int, settings: RolloutSettings | None = None, callback=None) -> dict[str, Any]:
    history = _history()
    t0 = time.perf_counter()
    best = [np.inf, None]

    def evaluate(x):
        f, res = task_loss(model, x, settings)
        hits = bounces(res)
        dist = distance(res)
        history["loss"].append(f)
        history["distance"].append(dist)
        history["wall"].append(hits["wall"])
        history["floor"].append(hits["floor"])
        history["velocity"].append(x)
        history["trajectory"].append(res.particle_q[:, 0].detach().numpy().copy())
        history["grad_norm"].append(0.0)
        history["accepted"].append(bool(f < best[0]))
        if f < best[0]:
            best[:] = [f, len(history["loss"]) - 1]
        if callback is not None:
            callback(len(history["loss"]) - 1, history)
        return f, bool(banked(hits) and dist < TARGET_TOLERANCE)

    run_cma(start, CMA_SIGMA, iters + 1, evaluate)
    n = len(history["loss"])
    reached = n - 1 if banked({"wall": history["wall"][-1], "floor": history["floor"][-1]}) \
        and history["distance"][-1] < TARGET_TOLERANCE else None
    last = reached if reached is not None else best[1]
    return _result(history, last, reached, time.perf_counter() - t0)


def gradient_check(model, v, step: float = 1e-6, settings: RolloutSettings | None = None) -> dict[str, Any]:
    """The distance loss' gradient w.r.t. the initial velocity (rollout backward) against central
    finite differences of the same forward (step [m/s]; ``settings`` as :func:`simulate`)."""
    import torch

    x, res = simulate(model, v, grad=True, settings=settings)
    distance_loss(res).backward()

    def value(vv):
        with torch.no_grad():
            return distance_loss(simulate(model, vv, settings=settings)[1])

    return central_difference_check(x.grad.numpy()[0], value, v, step)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--iters", type=int_at_least(1), default=200,
                        help=ITERS_HELP + ", fewer once the target is reached (default %(default)s)")
    parser.add_argument("--start", choices=sorted(STARTS) + ["seeded"], default="newton",
                        help="initial velocity: Newton's (0, 5, -5) m/s, (3, 5, -5) m/s that misses the wall, or "
                             "'seeded': a miss drawn from --seed (default %(default)s)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help=f"comma-separated subset of {','.join(METHODS)} (default all)")
    add_rollout_arguments(parser, SUBSTEPS)


def _log_world(log: Any, model) -> None:
    import rerun as rr

    rec = log.stream
    rec.log("/world/wall", rr.Mesh3D(vertex_positions=model.static_vertices.numpy(),
                                     triangle_indices=model.static_faces.numpy().reshape(-1, 3)), static=True)
    rec.log("/world/floor", rr.Boxes3D(centers=[[0.0, 0.0, -0.005]], half_sizes=[[3.0, 4.0, 0.005]]), static=True)
    rec.log("/world/target", rr.Points3D([TARGET], radii=0.05, colors=[[255, 200, 0]]), static=True)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Optimises from ``--start`` with each method; logs the loss and distance curves
    (``/metrics/<loss|distance>/<method>``, timeline ``iteration``), every iterate's path
    (``/iterates/<method>/path``), the wall, the floor and the target."""
    import rerun as rr

    methods = parse_methods(args.methods, METHODS)
    settings = rollout_settings(args)
    model = build()
    _log_world(log, model)
    start = seeded_start(model, args.seed, settings) if args.start == "seeded" else STARTS[args.start]
    colors = {"proposed": [40, 160, 255], "baseline": [230, 80, 60], "cma": [120, 200, 90]}
    out = {}
    for method in methods:
        with progress(f"{NAME} {method}", args.iters + 1) as callback:
            result = optimise(model, start, args.iters, method, callback=callback, settings=settings)
        h = result.pop("history")
        frames = {"iteration": np.arange(len(h["loss"]))}
        log.log_scalars(f"/metrics/loss/{method}", np.asarray(h["loss"]), sequence=frames)
        log.log_scalars(f"/metrics/distance/{method}", np.asarray(h["distance"]), sequence=frames)
        for i, path in enumerate(h["trajectory"]):
            log.stream.set_time("iteration", sequence=i)
            log.stream.log(f"/iterates/{method}/path", rr.LineStrips3D([path], colors=[colors[method]]))
        out[method] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in result.items()}
    return {"scene": NAME, "start": args.start if args.start != "seeded" else f"seed {args.seed}", "start_velocity": list(start), "target": list(TARGET),
            "iters": args.iters, "substeps": settings.substeps, "max_derivative": settings.max_derivative,
            "ccd_options": settings.ccd_options, "methods": out}
