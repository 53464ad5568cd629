"""Scene ``tunnel``: make a miss into a hit at a target time and velocity (lifted events).

A particle (10 g, no gravity) and a rigid tetrahedron (0.3 m, 27 kg, spinning and drifting).
``--seed`` draws the tetrahedron's pose and motion, a face of it, a point on that face and a
hit time: an aimed initial velocity ``v*`` that really hits that face there is found with the
simulator itself, and its rollout gives the **targets**: the hit time ``t_target`` and the
particle's velocity after the bounce ``v_target`` (so the targets are reachable exactly). The
start ``v0`` misses the tetrahedron altogether, and the *wanted* root (followed from ``v*`` to
``v0`` with :class:`sim.events.BranchTracker`) is complex there.

Adam on the initial velocity then minimises, per iteration:

* while the rollout misses: the lifted event of the face and the particle over the step that
  holds ``t_target`` (:mod:`sim.events`): eq. ``loss`` on the tracked root (target
  ``(t_target - window start, 0)``), the partner's real part (eq. ``complexconjugateloss``) while
  the root is complex, and a hinge on the barycentric coordinates at the root's real part
  (inside the face with a margin);
* once it hits: the squared errors of the hit time (from the replayed contact through the
  trajectory) and of the final velocity.

The **baseline** is what a differentiable simulator without lifted roots has: the same loop with
the unmollified ``-1/p'(t*)`` and event terms only when the root is real (a complex root has no
value there, so the miss gives it nothing to follow).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from scenes.registry import int_at_least

NAME = "tunnel"
DESCRIPTION = "Optimise a particle's initial velocity from a miss to a hit of a spinning tetrahedron (lifted events)"
PRECISIONS = ("float64",)
SUPPORTS_STEPS = False

STEPS, DT = 40, 1.0 / 40.0  # 1 s, one substep per step
TIME_TOLERANCE = 1e-6  # [s] |t_hit - t_target| for success (the figure)
VELOCITY_TOLERANCE = 1e-3  # relative error of the final velocity for success
PARTICLE_MASS = 0.01  # [kg]
EDGE = 0.3  # [m] tetrahedron size (vertices at +-EDGE/2 on alternating cube corners)
EVENT_STEPS = 6  # the event's window: the steps before the one of the target hit (free flight
# for every velocity near the target, so its roots extrapolate to the hit)
INSIDE_MARGIN = 0.15
HIT_SLACK = 0.05  # once hitting, the linearised event's coordinates may be this far outside
INSIDE_WEIGHT = 1.0  # a linear hinge: a constant pull towards the inside however close the edge  # barycentric margin the miss loss asks for
LEARNING_RATE = 0.05  # [m/s] Adam step while missing
HIT_DECAY = 0.98  # per iteration once hitting: the step shrinks geometrically ...
MIN_LEARNING_RATE = 1e-8  # ... down to this [m/s] (the time tolerance needs ~1e-6 m/s)


def tetrahedron(size: float = EDGE):
    """A regular tetrahedron (closed, outward-oriented): vertices (4, 3) [m], faces (4, 3)."""
    s = size / 2.0
    v = np.array([[s, s, s], [s, -s, -s], [-s, s, -s], [-s, -s, s]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], dtype=np.int64)
    # orient outwards
    for k, (a, b, c) in enumerate(f):
        if np.dot(np.cross(v[b] - v[a], v[c] - v[a]), v[a] + v[b] + v[c]) < 0:
            f[k] = (a, c, b)
    return v, f


@dataclass
class Problem:
    seed: int
    model: Any
    face: tuple  # the designated face's three body-vertex indices
    v_star: np.ndarray  # an initial velocity that hits
    v0: np.ndarray  # the start (a miss)
    t_target: float
    v_target: np.ndarray
    window: tuple
    tracked_slot: int  # the wanted root's slot at v0


def _rollout(problem_or_model, v, *, events=(), unmollified=False, grad=False):
    """(initial velocity tensor, rollout result); ``v`` a (3,) array, or a (1, 3) tensor used as is."""
    import torch

    from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE, rollout

    model = problem_or_model.model if isinstance(problem_or_model, Problem) else problem_or_model
    if isinstance(v, torch.Tensor):
        x = v
    else:
        x = torch.tensor(np.asarray(v, dtype=np.float64)[None], dtype=torch.float64, requires_grad=grad)
    kw = {"max_derivative": UNMOLLIFIED_MAX_DERIVATIVE} if unmollified else {}
    return x, rollout(model, STEPS, DT, 1, particle_qd=x, events=events, **kw)


def hit_time(res):
    """First time [s] the particle's velocity changes (a contact) and the step it happens in,
    from the trajectory: in that step ``x1 = x0 + t* v- + (h - t*) v+`` (time-of-impact
    integration), solved for ``t*`` in least squares (differentiable); (None, None) for no hit."""
    qd = res.particle_qd[:, 0].detach().numpy()
    jumps = np.flatnonzero(np.linalg.norm(np.diff(qd, axis=0), axis=1) > 1e-12)
    if len(jumps) == 0:
        return None, None
    k = int(jumps[0])
    x0, x1 = res.particle_q[k, 0], res.particle_q[k + 1, 0]
    vm, vp = res.particle_qd[k, 0], res.particle_qd[k + 1, 0]
    d = vm - vp
    t_star = ((x1 - x0 - DT * vp) * d).sum() / (d * d).sum()
    return k * DT + t_star, k


def _event(problem_face, window):
    from sim.events import Event, body_vertex, particle

    return Event("vertex_face", (particle(0),) + tuple(body_vertex(0, int(k)) for k in problem_face), window)


def make_problem(seed: int) -> Problem:
    """Draws a problem (see the module docstring); retries inside the seed's stream until the
    aimed velocity hits the designated face once and the start misses with a complex root."""
    from sim.builder import ModelBuilder
    from sim.events import BranchTracker, event_positions

    rng = np.random.default_rng(seed)
    verts, faces = tetrahedron()
    for _ in range(200):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, np.pi)
        rot = (*(axis * np.sin(angle / 2)), np.cos(angle / 2))
        omega = rng.normal(size=3)
        omega *= rng.uniform(0.5, 1.5) / np.linalg.norm(omega)
        drift = rng.normal(size=3) * 0.05
        b = ModelBuilder(gravity=0.0)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        start = -0.8 * direction
        b.add_particle(tuple(start), mass=PARTICLE_MASS)
        b.add_rigid_body(verts, faces, density=1000.0, rot=rot, angular_velocity=tuple(omega), velocity=tuple(drift))
        b.set_contact(restitution=0.8, friction=0.0, thickness=0.0)
        model = b.finalize()
        face_index = int(rng.integers(0, 4))
        face = tuple(int(k) for k in model.shape_faces.numpy().reshape(-1, 3)[face_index])
        t_aim = rng.uniform(0.4, 0.6)
        bary = rng.dirichlet([4.0, 4.0, 4.0])
        # aim at the face point at t_aim: the body's pose there from a body-only rollout
        _, free = _rollout(model, np.zeros(3))
        k = int(t_aim / DT)
        frac = t_aim / DT - k
        ev = _event(face, (k, k + 1))
        xa, xb = event_positions(model, [ev], free.particle_q, free.body_q)
        corners = (xa[0, 1:] + frac * (xb[0, 1:] - xa[0, 1:])).numpy()
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        point = bary @ corners
        v_star = (point - start) / t_aim
        if np.dot(v_star, normal) >= -0.2 * np.linalg.norm(v_star) * np.linalg.norm(normal):
            continue  # the face looks away from the particle or is hit too obliquely
        _, res = _rollout(model, v_star)
        t_hit, k_hit = hit_time(res)
        if t_hit is None or res.stats["contact_substeps"] != 1 or res.stats["failsafe_substeps"]:
            continue
        t_target = float(t_hit)
        v_target = res.particle_qd[-1, 0].detach().numpy().copy()
        window = (max(0, k_hit - EVENT_STEPS), k_hit)
        event = _event(face, window)
        # the wanted root: at v* the real one at t_target (the window ends before the hit, so
        # the event sees free flight there as for any miss)
        roots_star = _rollout(model, v_star, events=[event])[1].event_roots[0].detach().numpy()
        tau = t_target - window[0] * DT
        wanted = int(np.argmin(np.abs(roots_star[:, 0] - tau) + np.abs(roots_star[:, 1])))
        # start: a miss, reached from v* by a growing sideways push
        side = np.cross(v_star, rng.normal(size=3))
        side *= np.linalg.norm(v_star) / np.linalg.norm(side)
        for push in (0.3, 0.45, 0.6, 0.8):
            v0 = v_star + push * side
            if _rollout(model, v0)[1].stats["contact_substeps"]:
                continue
            # follow the wanted root from v* to v0
            tracker = BranchTracker(wanted)
            tracker.update(roots_star)
            for s in np.linspace(0.0, 1.0, 41)[1:]:
                r = _rollout(model, v_star + s * push * side, events=[event])[1].event_roots[0].detach().numpy()
                tracker.update(r)
            if r[tracker.slot, 1] != 0.0:
                return Problem(seed, model, face, v_star, v0, t_target, v_target, window, tracker.slot)
    raise RuntimeError(f"tunnel: no problem found for seed {seed}")


def optimise(problem: Problem, iters: int, method: str = "proposed", callback=None) -> dict[str, Any]:
    """Adam on the initial velocity (see the module docstring). ``method``: "proposed" or
    "baseline". Returns the figures of the run and its history."""
    import torch

    from sim.events import BranchTracker, complex_conjugate_loss, root_loss

    if method not in ("proposed", "baseline"):
        raise ValueError(f"method must be 'proposed' or 'baseline', got {method!r}")
    unmollified = method == "baseline"
    v = torch.tensor(problem.v0[None], dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([v], lr=LEARNING_RATE)
    tracker = BranchTracker(problem.tracked_slot)
    event = _event(problem.face, problem.window)
    tau = problem.t_target - problem.window[0] * DT
    v_target = torch.tensor(problem.v_target, dtype=torch.float64)
    v_scale = float(np.linalg.norm(problem.v_target))
    history = {"loss": [], "hit": [], "time_error": [], "velocity_error": [], "grad_norm": [], "velocity": []}
    reached = None
    t0 = time.perf_counter()
    for it in range(iters + 1):
        opt.zero_grad()
        _, res = _rollout(problem, v, events=[event], unmollified=unmollified)
        t_hit, _ = hit_time(res)
        v_final = res.particle_qd[-1, 0]
        if t_hit is not None:
            time_error = float(t_hit.detach()) - problem.t_target
            velocity_error = float(torch.linalg.norm(v_final - v_target)) / v_scale
            loss = ((t_hit - problem.t_target) / DT) ** 2 + ((v_final - v_target) ** 2).sum() / v_scale**2
            # keep the hit on the designated face (the event's coordinates at the root nearest the target)
            roots = res.event_roots[0].detach() / DT
            slot = int(torch.argmin((roots[:, 0] - tau / DT).abs() + roots[:, 1].abs()))
            loss = loss + INSIDE_WEIGHT * torch.relu(-HIT_SLACK - res.event_coords[0, slot]).sum()
        else:
            time_error, velocity_error = float("nan"), float("nan")
            roots = res.event_roots[0] / DT
            slot = tracker.update(roots)
            root = roots[slot]
            is_complex = bool(root[1].detach() != 0.0)
            loss = torch.zeros((), dtype=torch.float64)
            if not unmollified or not is_complex:
                loss = root_loss(root, (tau / DT, 0.0))
                if is_complex and not unmollified:
                    partner = next(k for k in range(3) if k != slot and float(roots[k, 1].detach()) == -float(root[1].detach()))
                    loss = complex_conjugate_loss(root, roots[partner], (tau / DT, 0.0))
            w = res.event_coords[0, slot]
            if not unmollified or not is_complex:
                # (the baseline has no position for a complex root either)
                loss = loss + INSIDE_WEIGHT * torch.relu(INSIDE_MARGIN - w).sum()
            history.setdefault("root", []).append(root.detach().numpy().copy())
            history.setdefault("coords", []).append(w.detach().numpy().copy())
        history["loss"].append(float(loss.detach()))
        history["hit"].append(t_hit is not None)
        history["time_error"].append(time_error)
        history["velocity_error"].append(velocity_error)
        history["velocity"].append(v.detach().numpy()[0].copy())
        if t_hit is not None and abs(time_error) < TIME_TOLERANCE and velocity_error < VELOCITY_TOLERANCE:
            reached = it
            history["grad_norm"].append(0.0)
            break
        if it == iters or not loss.requires_grad:
            history["grad_norm"].append(0.0)
            if not loss.requires_grad:
                continue
            break
        loss.backward()
        history["grad_norm"].append(float(torch.linalg.norm(v.grad)))
        opt.step()
        for group in opt.param_groups:
            group["lr"] = max(group["lr"] * HIT_DECAY, MIN_LEARNING_RATE) if t_hit is not None else LEARNING_RATE
        if callback is not None:
            callback(it, history)
    return {
        "reached_target": reached is not None,
        "iterations_to_target": reached,
        "final_loss": history["loss"][-1],
        "time_error": history["time_error"][-1],
        "velocity_error": history["velocity_error"][-1],
        "hit": history["hit"][-1],
        "wall_time": time.perf_counter() - t0,
        "history": history,
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--iters", type=int_at_least(1), default=200,
                        help="Adam iterations per method (default %(default)s)")


def _figures(run: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in run.items() if k != "history"}


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Draws the problem of ``--seed``, optimises it with the proposed method and the baseline,
    logs both loss curves (``/metrics/loss/<method>``, timeline ``iteration``), the hit flags and
    the initial velocity of every iterate (``/metrics/velocity/<method>/<axis>``)."""
    problem = make_problem(args.seed)
    methods = {}
    for method in ("proposed", "baseline"):
        result = optimise(problem, args.iters, method)
        h = result["history"]
        frames = {"iteration": np.arange(len(h["loss"]))}
        log.log_scalars(f"/metrics/loss/{method}", np.asarray(h["loss"]), sequence=frames)
        log.log_scalars(f"/metrics/hit/{method}", np.asarray(h["hit"], dtype=np.float64), sequence=frames)
        vel = np.asarray(h["velocity"])
        for axis, name in enumerate("xyz"):
            log.log_scalars(f"/metrics/velocity/{method}/{name}", vel[:, axis], sequence=frames)
        figures = _figures(result)
        figures["left_the_miss"] = bool(any(h["hit"]))
        figures["first_hit_iteration"] = int(np.argmax(h["hit"])) if any(h["hit"]) else None
        methods[method] = figures
    return {
        "scene": NAME,
        "seed": args.seed,
        "iters": args.iters,
        "t_target": problem.t_target,
        "v_target": problem.v_target.tolist(),
        "start_velocity": problem.v0.tolist(),
        "methods": methods,
    }
