"""Scene ``billiards``: DiffTaichi's billiards, from a hit or from a miss.

The setup of taichi-dev/difftaichi ``examples/billiards.py``: 11 balls of radius 0.03 m and
equal mass (a cue ball and a rack of 4 rows, 10 balls) in the plane z = 0, without gravity,
friction or walls; restitution 0.8; 1023 steps of 0.003 s. The cue starts at (0.1, 0.5) m with
velocity (0.3, 0) m/s; the target is the rack's last ball (from (0.68, 0.617) m) and the goal is
(0.9, 0.75) m. The loss is the squared distance of the target's final position from the goal;
the cue's initial position and velocity (4 unknowns) are optimised. The rack uses DiffTaichi's
coordinates as they are: neighbours in a row touch (their distance is ``2 r`` to rounding, which
the builder accepts) and rest, so they exert nothing until something moves them.

Here the balls are sphere bodies (:meth:`sim.builder.ModelBuilder.add_sphere`): every pair's time
of impact is the smaller root of the quadratic ``|d + t dv|^2 = (2 r)^2``, from the project's
root solver with the mollified derivative, and the rollout's gradient is exact for its
trajectory (DiffTaichi's clamped linear estimate of the time of impact is not).

Starts (``--start``): ``default`` (DiffTaichi's), ``miss-above`` (velocity (0.3, 0.1) m/s: it
passes above the rack), ``miss-away`` (velocity (-0.3, 0) m/s), ``seeded`` (``--seed S``: a cue
position and velocity drawn at random whose straight path touches no ball, :func:`seeded_start`),
or any shot with ``--cue-pos X Y --cue-vel VX VY``.

Methods (``--methods``), at most ``--iters`` optimiser steps each (the start and every step's
shot are played: ``--iters`` + 1 rollouts), stopping once the target is within
``TARGET_TOLERANCE`` (5 mm) of the goal:

* **proposed**: until the shot is a hit, a lifted sphere event pulls the cue onto the ball that
  the chain to the goal needs first: :func:`scenes.rack.push_chain` follows the balls in the way
  of pushing the target straight at the goal back to one the cue can reach (on DiffTaichi's
  rack, the apex); :func:`lifted_event` lifts the cue and that ball over the cue's first straight path,
  and :func:`miss_loss` pulls the path's contact onto the striking point, where the contact
  normal sends the ball along the chain, at a time inside the run. That phase optimises the
  cue's speed and heading with Adam (:data:`MISS_LEARNING_RATE`, :func:`scenes.optim.to_polar`),
  its position fixed (a free one lets the cue park against the ball). A hit (:func:`good_hit`):
  the target moves and the cue's first contact sends the head within :data:`AIM_CONE` of the
  chain's direction. From the first hit the
  loss is the squared distance over all four unknowns, optimised with ``--optimizer``:
  ``adam``: the guarded Adam of :mod:`scenes.optim` (an iterate that is not a hit or does not
  lower the loss is rejected: back, half the step; :data:`HIT_LEARNING_RATE`). Where the
  descent steps from the best hit keep crossing a discontinuity into a worse branch (a later
  contact that switches on or off), the step keeps shrinking: once it is below
  :data:`STALL_STEP` of its largest, the best hit is played again :data:`STALL_SPEEDUP` times
  faster with the same aim, and a fresh hit phase starts there (at most
  :data:`STALL_RESTARTS` times; ``restarts`` in the result lists the rollouts that replay); ``gd``:
  DiffTaichi's plain gradient descent (learning rate 0.01), an iterate that is not a hit rejected
  the same way. Every method projects a cue inside a rack ball out of it
  (:func:`scenes.rack.outside_the_rack`).
* **baseline**: plain gradient descent (``--optimizer``) on the squared distance from the start,
  through the real contacts only: DiffTaichi's method. From a miss its gradient is exactly zero;
  a run stops at the first exactly zero gradient (``zero_gradient_at``), since every later
  iterate would be the same.
* **cma**: CMA-ES on the proposed method's loss values (a shot that is not a hit costs
  ``MISS_OFFSET`` more than any hit) with the same number of rollouts.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from scenes.optim import (ITERS_HELP, central_difference_check, from_polar, parse_methods, plot_loss_curves,
                          polar_gradient, progress, reported_iterate, run_cma, to_polar)
from scenes.rack import RADIUS, ROWS, outside_the_rack, push_chain, rack_positions
from scenes.registry import int_at_least

NAME = "billiards"
USES_SEED = "seed of the cue shot drawn by --start seeded"
DESCRIPTION = "DiffTaichi's billiards: move the last rack ball to a goal from any shot, misses included"
PRECISIONS = ("float64",)
SUPPORTS_STEPS = False

MASS = 1.0  # [kg]
RESTITUTION = 0.8
DT = 0.003  # [s]
STEPS = 1023
GOAL = (0.9, 0.75)  # [m]
STARTS = {"default": (0.1, 0.5, 0.3, 0.0), "miss-above": (0.1, 0.5, 0.3, 0.1), "miss-away": (0.1, 0.5, -0.3, 0.0)}
"""Cue position (x, y) [m] and velocity (vx, vy) [m/s] of the named starts."""
TARGET_TOLERANCE = 0.005  # [m]
LEARNING_RATE = 0.01
MISS_LEARNING_RATE = 0.03
"""Adam's step in the miss phase [m/s; the heading in units of :data:`HEADING_SCALE` rad]: a
miss may have to turn the shot around (``miss-away``)."""
MISS_OFFSET = 1.0  # [m^2] CMA-ES: a shot that leaves the target still costs this plus its event loss
CMA_SIGMA = 0.05  # CMA-ES's initial step [m, m/s]
METHODS = ("proposed", "baseline", "cma")
OPTIMIZERS = ("gd", "adam")
SEEDED_POSITION = ((0.05, 0.4), (0.1, 0.9))  # [m] ranges of a seeded cue position (x, y)
SEEDED_SPEED = (0.2, 0.5)  # [m/s]


def build(rows: int = ROWS, cue=STARTS["default"]):
    """The model: the cue (body 0) and the rack (bodies 1..); the target is the last body."""
    from sim.builder import ModelBuilder

    b = ModelBuilder(gravity=0.0)
    b.set_contact(restitution=RESTITUTION, friction=0.0, thickness=0.0)
    b.add_sphere(RADIUS, mass=MASS, pos=(cue[0], cue[1], 0.0), velocity=(cue[2], cue[3], 0.0))
    for x, y in rack_positions(rows):
        b.add_sphere(RADIUS, mass=MASS, pos=(x, y, 0.0))
    return b.finalize()


def target_of(model) -> int:
    return model.body_count - 1


def cue_path_gap(model, shot) -> float:
    """The smallest gap [m] between the cue's straight path over the whole run (no contact) and
    any other ball: positive when the shot touches nothing."""
    start = np.asarray(shot[:2], dtype=np.float64)
    travel = np.asarray(shot[2:], dtype=np.float64) * DT * STEPS
    centres = model.body_q.numpy()[1:, :2]
    d0 = start[None] - centres
    denom = float(travel @ travel)
    s = np.clip(-(d0 @ travel) / denom, 0.0, 1.0) if denom > 0.0 else np.zeros(len(centres))
    return float(np.min(np.linalg.norm(d0 + s[:, None] * travel[None], axis=1)) - 2 * RADIUS)


def seeded_start(model, seed: int) -> tuple[float, float, float, float]:
    """A shot drawn from ``seed`` whose straight path touches no ball: a cue position in
    :data:`SEEDED_POSITION`, a speed in :data:`SEEDED_SPEED` and any direction."""
    rng = np.random.default_rng(seed)
    for _ in range(1000):
        x, y = rng.uniform(*SEEDED_POSITION[0]), rng.uniform(*SEEDED_POSITION[1])
        speed, angle = rng.uniform(*SEEDED_SPEED), rng.uniform(-np.pi, np.pi)
        shot = (x, y, speed * np.cos(angle), speed * np.sin(angle))
        if cue_path_gap(model, shot) > 0.0:
            return tuple(float(c) for c in shot)
    raise RuntimeError(f"billiards: no missing shot found for seed {seed}")


def simulate(model, shot, events=(), grad: bool = False):
    """(shot tensor (4,), rollout result) of ``shot``: a tensor (x, y, vx, vy) or a sequence."""
    import torch

    from sim.rollout import rollout

    z = shot if isinstance(shot, torch.Tensor) else torch.tensor(np.asarray(shot, dtype=np.float64), requires_grad=grad)
    poses = torch.from_numpy(model.body_q.numpy().copy())
    twists = torch.from_numpy(model.body_qd.numpy().copy())
    zero = torch.zeros(1, dtype=torch.float64)
    cue_pose = torch.cat([z[:2], zero, poses[0, 3:]])
    cue_twist = torch.cat([zero, zero, zero, z[2:], zero])
    body_q = torch.cat([cue_pose[None], poses[1:]])
    body_qd = torch.cat([cue_twist[None], twists[1:]])
    return z, rollout(model, STEPS, DT, 1, body_qd=body_qd, body_q=body_q, events=list(events))


def distance_loss(model, res):
    import torch

    return ((res.body_q[-1, target_of(model), :2] - torch.as_tensor(GOAL, dtype=torch.float64)) ** 2).sum()


def target_distance(model, res) -> float:
    return float(np.linalg.norm(res.body_q[-1, target_of(model), :2].detach().numpy() - np.asarray(GOAL)))


def moved(res) -> np.ndarray:
    """Which balls ever move (bool (B,)): a ball at rest that nothing hits keeps velocity 0."""
    return np.any(res.body_qd[:, :, 3:].detach().numpy() != 0.0, axis=(0, 2))


AIM_CONE = 45.0
"""[deg] A shot is a hit (the proposed method's second phase) when the target moves and the
cue's first contact sends the chain's head (:func:`scenes.rack.push_chain`) within this angle of the
chain's direction. DiffTaichi's own start, a straight shot at the apex, is 33 degrees off."""
CONTACT_WINDOW = (0.1, 0.9)
"""Where in the run (fractions of its duration) the miss loss wants the lifted contact: not at
its very start (a cue parked against the ball) nor after its end."""


def _chain_of(model):
    centres = model.body_q.numpy()[:, :2].copy()
    centres[0] = np.inf  # the cue is the striker, not in the way
    return push_chain(centres, target_of(model), GOAL)


def _first_change(res, ball: int) -> int | None:
    """The first step whose end velocity differs from its start's (a contact), or None."""
    qd = res.body_qd.detach().numpy()[:, ball, 3:5]
    changes = np.flatnonzero(np.any(qd[1:] != qd[:-1], axis=1))
    return int(changes[0]) if len(changes) else None


def good_hit(model, res) -> bool:
    """Whether a rollout is in the proposed method's hit region: the target moves, and the cue's
    first contact is with the chain's head, sent within :data:`AIM_CONE` of the chain's
    direction (a frictionless ball at rest leaves along the contact normal)."""
    if not moved(res)[target_of(model)]:
        return False
    head, direction = _chain_of(model)
    cue_change, qd = _first_change(res, 0), res.body_qd.detach().numpy()[:, head, 3:5]
    head_moves = np.flatnonzero(np.any(qd != 0.0, axis=1))
    if cue_change is None or not len(head_moves) or int(head_moves[0]) != cue_change + 1:
        return False
    v = qd[int(head_moves[0])]
    return bool(v @ direction > np.cos(np.radians(AIM_CONE)) * np.linalg.norm(v))


def lifted_event(model, res):
    """The sphere event the proposed method lifts while the shot is not a hit: the cue and the
    chain's head (:func:`scenes.rack.push_chain`), over the cue's first straight path (from the start to
    its first contact, or the whole run)."""
    from sim.events import SphereEvent

    head, _ = _chain_of(model)
    change = _first_change(res, 0)
    return SphereEvent(0, head, (0, STEPS if change is None else max(change, 1)))


def miss_loss(model, res, event, roots):
    """The lifted event's loss from its roots (2, 2) [s] (slots ``t-``, ``t+``; Re, Im):

    * aim: at ``tau = Re t-`` (clamped to :data:`CONTACT_WINDOW` and to the event's window) the
      offset ``d`` of the cue from the head, against the striking offset ``-2 r u`` (``u`` the
      chain's direction): ``|d / 2r + u|^2``. For a miss (a complex pair) ``tau`` is the closest
      approach and ``|d|^2 = (2 r)^2 + a Im^2``, so the loss pulls the path onto the ball and its
      contact normal onto ``u`` at once; it is 0 exactly for paths that enter the ball at the
      striking point. The clamp to the contact window matters where the closest approach comes
      at the cue's start (a ball abeam of it): the aim at the closest approach slopes away from
      the ball there, into ``tau < 0``, and traps the cue; a little later on the path it slopes
      towards the ball;
    * time: ``tau`` inside :data:`CONTACT_WINDOW` of the run (the squared excess, in run
      durations); for a ball behind the cue (``tau < 0``) also the squared distance back to the
      closest approach in ball diameters, which turns the cue around.
    """
    import torch

    (_, direction), (first, last), tau, duration = _chain_of(model), event.window, roots[0, 0], STEPS * DT
    low, high = (f * duration for f in CONTACT_WINDOW)
    time_loss = ((low - tau).clamp(min=0.0) ** 2 + (tau - high).clamp(min=0.0) ** 2) / duration ** 2
    q = res.body_q[:, :, :2]
    start = q[first, 0] - q[first, event.body_b]
    travel = q[last, 0] - q[last, event.body_b] - start
    offset = start + (tau.clamp(low, high) / ((last - first) * DT)).clamp(0.0, 1.0) * travel
    aim = ((offset / (2 * RADIUS) + torch.as_tensor(direction, dtype=torch.float64)) ** 2).sum()
    behind = (-tau).clamp(min=0.0) * travel.norm() / ((last - first) * DT * 2 * RADIUS)
    return aim + time_loss + behind ** 2


def evaluate(model, shot, method: str, grad: bool):
    """One rollout of ``shot`` with the method's loss: (shot tensor, result, loss tensor, good,
    lifted event or None). ``good``: the shot is in the method's hit region (the baseline's:
    the target moves; the others': :func:`good_hit`), where the loss is the squared distance.
    Elsewhere (not the baseline) it is the lifted event's (:func:`lifted_event`,
    :func:`miss_loss`): the quadratic's roots from the rollout's own trajectory
    (:func:`sim.events.sphere_event_roots`, what ``rollout(events=[SphereEvent(...)])``
    returns)."""
    from sim.events import sphere_event_roots

    z, res = simulate(model, shot, grad=grad)
    good = bool(moved(res)[target_of(model)]) if method == "baseline" else good_hit(model, res)
    if good or method == "baseline":
        return z, res, distance_loss(model, res), good, None
    event = lifted_event(model, res)
    roots = sphere_event_roots(model, [event], res.body_q, DT)[0]
    return z, res, miss_loss(model, res, event, roots), False, event


HEADING_SCALE = 3.0
"""Miss phase: the unit [rad] of the cue's heading among Adam's variables (up to
``MISS_LEARNING_RATE * HEADING_SCALE`` rad per step)."""
HIT_LEARNING_RATE = 0.03
"""The proposed method's hit phase with Adam: the guarded Adam's largest step
(:class:`scenes.optim.GuardedAdam`) [m, m/s]."""
HIT_GROWTH = 1.5  # the hit phase's step growth after an accepted iterate
STALL_STEP = 2.0 ** -12
"""The guarded hit phase is stalled once its step has shrunk below this fraction of
:data:`HIT_LEARNING_RATE` (each rejected iterate halves the step, each accepted one grows it by
:data:`HIT_GROWTH`)."""
STALL_SPEEDUP = 1.5
"""At a stall the best hit is played again this much faster, with the same aim."""
STALL_RESTARTS = 3  # at most this many faster replays per run


def optimise(model, start, iters: int, method: str = "proposed", optimizer: str = "gd",
             lr: float = LEARNING_RATE, callback=None) -> dict[str, Any]:
    """At most ``iters`` optimiser steps of ``method`` from ``start`` (x, y, vx, vy), so at most
    ``iters + 1`` rollouts (the start and each step's shot); see the module docstring. Returns
    the run's figures and its history (one entry per rollout)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")
    if method == "cma":
        return _optimise_cma(model, start, iters, callback)
    import torch

    from scenes.optim import GuardedAdam

    z = torch.tensor(np.asarray(start, dtype=np.float64), requires_grad=True)
    history = {"loss": [], "distance": [], "hit": [], "moved": [], "shot": [], "accepted": [], "seconds": [],
               "restarts": []}
    phase, opt, polar = None, None, None  # polar: the miss phase's variables (to_polar)
    guard = None  # proposed, Adam: the guarded hit phase
    accepted = None  # proposed, gradient descent: (shot, gradient) of the last iterate in the hit region
    rate = lr
    reached = stalled = None
    t_start = time.perf_counter()
    for it in range(iters + 1):
        t0 = time.perf_counter()
        _, res, loss, good, _event = evaluate(model, z, method, grad=True)
        distance = target_distance(model, res)
        history["loss"].append(float(loss.detach()))
        history["distance"].append(distance)
        history["hit"].append(good)
        history["moved"].append(bool(moved(res)[target_of(model)]))
        history["shot"].append(z.detach().numpy().copy())
        if history["moved"][-1] and distance < TARGET_TOLERANCE:
            reached = it
            history["loss"][-1] = float(distance_loss(model, res).detach())  # the task's loss, hit or not
        wanted = "hit" if (good or method == "baseline") else "miss"
        if method == "proposed" and optimizer == "adam" and guard is None and good:
            guard = GuardedAdam(z, HIT_LEARNING_RATE, (0.9, 0.999), HIT_GROWTH)
        if guard is not None:
            take = guard.judge(loss, good)
        else:
            take = not (method == "proposed" and accepted is not None and not good)
        history["accepted"].append(take)
        if reached is not None or it == iters:
            history["seconds"].append(time.perf_counter() - t0)
            break
        if guard is not None:
            guard.zero_grad()
            guard.step(loss, good, take)
            if not bool(torch.isfinite(z.grad).all()):
                raise FloatingPointError(f"billiards: the gradient at iteration {it} is not finite ({z.grad.tolist()})")
            if guard.lr < HIT_LEARNING_RATE * STALL_STEP and len(history["restarts"]) < STALL_RESTARTS:
                # the descent steps from the best hit keep crossing a discontinuity (a later
                # contact that switches on or off) into a worse branch: the same aim played
                # faster changes the later contacts and leaves the chain more time
                with torch.no_grad():
                    z.copy_(guard.accepted[0])
                    z[2:] *= STALL_SPEEDUP
                # a fresh hit phase from the faster shot, or (should it not be a hit) a fresh
                # miss phase from its velocity
                guard, phase = None, None
                history["restarts"].append(it + 1)
            _finish_step(z, None, history, t0, it, callback)
            continue
        if take:
            z.grad = None
            loss.backward()
            if not bool(torch.isfinite(z.grad).all()):
                raise FloatingPointError(f"billiards: the gradient at iteration {it} is not finite ({z.grad.tolist()})")
            fresh = wanted != phase or (wanted == "hit" and optimizer == "gd")  # no momentum to carry on
            if fresh and not bool(z.grad[2 if wanted == "miss" else 0:].abs().sum() > 0.0):
                # a zero gradient (a shot that moves nothing it should) without momentum:
                # every later iterate would be this one
                stalled = it
                history["seconds"].append(time.perf_counter() - t0)
                break
            if wanted != phase:
                # a new phase starts with a fresh optimiser (its moments mean nothing across losses)
                phase = wanted
                rate = MISS_LEARNING_RATE if phase == "miss" else lr
                if phase == "miss":
                    polar = torch.tensor(to_polar(z.detach().numpy()[2:], HEADING_SCALE), dtype=torch.float64)
                    opt = torch.optim.Adam([polar], lr=rate)
                else:
                    polar = None
                    opt = (torch.optim.Adam if optimizer == "adam" else torch.optim.SGD)([z], lr=rate)
            if polar is not None:
                polar.grad = polar_gradient(polar, z.grad[2:], HEADING_SCALE)
            if phase == "hit" and method == "proposed":
                if accepted is not None:
                    rate = min(rate * HIT_GROWTH, lr)  # an accepted step after a rejection grows back
                accepted = (z.detach().clone(), z.grad.detach().clone())
        else:
            rate *= 0.5  # the step left the hit region: back to the last hit, half the step
            with torch.no_grad():
                z.copy_(accepted[0])
            z.grad = accepted[1].clone()
        if polar is None:
            for group in opt.param_groups:
                group["lr"] = rate
        opt.step()
        _finish_step(z, polar, history, t0, it, callback)
    last = reported_iterate(history["accepted"], reached, any(history["accepted"]))
    if reached is None and history["restarts"]:
        # a fresh phase accepts its first iterate whatever its loss: report the best hit
        hits = [i for i, (taken, hit) in enumerate(zip(history["accepted"], history["hit"])) if taken and hit]
        last = min(hits, key=lambda i: history["loss"][i]) if hits else last
    result = _result(history, last, reached, time.perf_counter() - t_start)
    result["zero_gradient_at"] = stalled
    return result


def _finish_step(z, polar, history, t0: float, it: int, callback) -> None:
    """The new iterate from the miss phase's variables (when given), projected out of the rack;
    the iteration's time; the progress callback."""
    import torch

    with torch.no_grad():
        if polar is not None:
            z[2:] = from_polar(polar, HEADING_SCALE)
        z.copy_(torch.tensor(outside_the_rack(z.detach().numpy()), dtype=torch.float64))
    history["seconds"].append(time.perf_counter() - t0)
    if callback is not None:
        callback(it, history)


def _result(history, last: int, reached, wall_time: float) -> dict[str, Any]:
    seconds = history["seconds"]
    return {
        "reached_target": reached is not None,
        "iterations_to_target": reached,
        "final_loss": history["loss"][last],
        "target_distance": history["distance"][last],
        "target_moved": bool(history["moved"][last]),
        "final_shot": [float(c) for c in history["shot"][last]],
        "rollouts": len(history["loss"]),
        "wall_time": wall_time,
        "seconds_per_iteration": float(np.mean(seconds[1:] if len(seconds) > 1 else seconds)),
        "restarts": list(history["restarts"]),
        "history": history,
    }


def task_loss(model, shot) -> tuple[float, Any, bool]:
    """The proposed method's loss as a plain value (CMA-ES): the squared distance for a hit
    (:func:`good_hit`), ``MISS_OFFSET`` plus the lifted event's loss otherwise. (value, rollout,
    hit)."""
    _, res, loss, hit, _event = evaluate(model, shot, "cma", grad=False)
    value = float(loss.detach()) if hit else MISS_OFFSET + float(loss.detach())
    return value, res, hit


def _optimise_cma(model, start, iters: int, callback=None) -> dict[str, Any]:
    """CMA-ES on :func:`task_loss`, ``iters + 1`` rollouts at most (the gradient methods')."""
    history = {"loss": [], "distance": [], "hit": [], "moved": [], "shot": [], "accepted": [], "seconds": [],
               "restarts": []}
    best = [np.inf, 0]
    t_start = time.perf_counter()

    def evaluate_shot(x):
        t0 = time.perf_counter()
        x = np.asarray(outside_the_rack(x))  # a candidate inside a rack ball is played from outside it
        value, res, hit = task_loss(model, x)
        distance = target_distance(model, res)
        history["loss"].append(value)
        history["distance"].append(distance)
        history["hit"].append(hit)
        history["moved"].append(bool(moved(res)[target_of(model)]))
        history["shot"].append(np.asarray(x, dtype=np.float64))
        history["accepted"].append(bool(value < best[0]))
        history["seconds"].append(time.perf_counter() - t0)
        if value < best[0]:
            best[:] = [value, len(history["loss"]) - 1]
        if callback is not None:
            callback(len(history["loss"]) - 1, history)
        return value, bool(history["moved"][-1] and distance < TARGET_TOLERANCE)

    run_cma(start, CMA_SIGMA, iters + 1, evaluate_shot)
    n = len(history["loss"])
    reached = n - 1 if history["moved"][-1] and history["distance"][-1] < TARGET_TOLERANCE else None
    return _result(history, reached if reached is not None else best[1], reached, time.perf_counter() - t_start)


def gradient_check(model, shot, step: float = 1e-6) -> dict[str, Any]:
    """The distance loss' gradient w.r.t. the shot (rollout backward) against central finite
    differences of the same forward (``step`` in m and m/s)."""
    import torch

    z, res = simulate(model, shot, grad=True)
    distance_loss(model, res).backward()

    def value(s):
        with torch.no_grad():
            return distance_loss(model, simulate(model, s)[1])

    return central_difference_check(z.grad.numpy(), value, shot, step)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--iters", type=int_at_least(1), default=200,
                        help=ITERS_HELP + ", fewer once the target is reached (default %(default)s)")
    parser.add_argument("--start", choices=sorted(STARTS) + ["seeded"], default="default",
                        help="the cue's shot: DiffTaichi's, one that passes above the rack, one away from it, or "
                             "'seeded': a miss drawn from --seed (default %(default)s)")
    parser.add_argument("--cue-pos", type=float, nargs=2, metavar=("X", "Y"), default=None,
                        help="the cue's initial position [m] (with --cue-vel: any shot; overrides --start; default: "
                             "the --start shot's)")
    parser.add_argument("--cue-vel", type=float, nargs=2, metavar=("VX", "VY"), default=None,
                        help="the cue's initial velocity [m/s] (with --cue-pos; default: the --start shot's)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help=f"comma-separated subset of {','.join(METHODS)} (default all)")
    parser.add_argument("--plot", type=str, default=None, metavar="PATH.png",
                        help="also write the loss curves of the methods as a PNG (needs matplotlib; default: none)")
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default="gd",
                        help="the optimiser of the squared distance: DiffTaichi's plain gradient descent "
                             "(learning rate 0.01) or the guarded Adam (0.03) (default %(default)s)")


def check_arguments(args: argparse.Namespace) -> str | None:
    """A usage error for inconsistent options (None when they are fine)."""
    if (args.cue_pos is None) != (args.cue_vel is None):
        return "--cue-pos and --cue-vel go together"
    if args.cue_pos is not None:
        if not np.all(np.isfinite(list(args.cue_pos) + list(args.cue_vel))):
            return "--cue-pos and --cue-vel must be finite"
        if not np.any(np.asarray(args.cue_vel) != 0.0):
            return "--cue-vel must not be zero (a cue at rest moves nothing and has no gradient)"
        gaps = np.linalg.norm(rack_positions() - np.asarray(args.cue_pos)[None], axis=1) - 2 * RADIUS
        if gaps.min() < 0.0:
            return f"--cue-pos puts the cue inside rack ball {int(np.argmin(gaps)) + 1} (overlap {-gaps.min():.3g} m)"
    if args.plot is not None:
        import os

        if not args.plot.endswith(".png"):
            return f"--plot must name a .png file, got {args.plot!r}"
        if os.path.abspath(args.plot) == os.path.abspath(str(args.out)):
            return "--plot and --out must be different files"
    return None


def start_of(args: argparse.Namespace, model) -> tuple[tuple[float, ...], str]:
    """The shot (x, y, vx, vy) of the options and its name."""
    if args.cue_pos is not None:
        return tuple(float(c) for c in list(args.cue_pos) + list(args.cue_vel)), "given"
    if args.start == "seeded":
        return seeded_start(model, args.seed), f"seed {args.seed}"
    return STARTS[args.start], args.start


def log_shot(log: Any, model, res, method: str) -> None:
    """The best shot's balls as spheres over time (timeline ``step``), the goal and the target."""
    import rerun as rr

    rec = log.stream
    n = model.body_count
    colors = np.tile(np.array([[200, 30, 40]], dtype=np.uint8), (n, 1))
    colors[0] = (230, 230, 230)
    colors[-1] = (50, 70, 210)
    rec.log("/world/goal", rr.Points3D([[GOAL[0], GOAL[1], 0.0]], radii=RADIUS / 2, colors=[[0, 0, 0]]), static=True)
    q = res.body_q.detach().numpy()
    for step in range(0, q.shape[0], 8):
        rec.set_time("step", sequence=step)
        rec.log(f"/shots/{method}/balls", rr.Ellipsoids3D(centers=q[step, :, :3], half_sizes=np.full((n, 3), RADIUS),
                                                        colors=colors, fill_mode="solid"))
        rec.log(f"/shots/{method}/target", rr.Points3D([q[step, -1, :3]], radii=RADIUS * 1.2, colors=[[50, 70, 210]]))


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Optimises the shot with each method; logs each method's loss and target distance per
    rollout (``/metrics/<loss|distance>/<method>``, timeline ``iteration``) and its best shot."""
    problem = check_arguments(args)
    if problem is not None:
        raise ValueError(problem)
    methods = parse_methods(args.methods, METHODS)
    model = build()
    shot, name = start_of(args, model)
    out, curves = {}, {}
    for method in methods:
        with progress(f"{NAME} {method}", args.iters + 1) as callback:
            result = optimise(model, shot, args.iters, method, args.optimizer, callback=callback)
        h = result.pop("history")
        curves[method] = h["loss"]
        frames = {"iteration": np.arange(len(h["loss"]))}
        log.log_scalars(f"/metrics/loss/{method}", np.asarray(h["loss"]), sequence=frames)
        log.log_scalars(f"/metrics/distance/{method}", np.asarray(h["distance"]), sequence=frames)
        _, res = simulate(model, result["final_shot"])
        log_shot(log, model, res, method)
        out[method] = result
    if args.plot is not None:
        plot_loss_curves(curves, args.plot, f"billiards from '{name}' ({args.optimizer})",
                         "loss [m^2] (before a hit: the lifted event's loss)")
    return {"scene": NAME, "start": name, "shot": list(shot), "goal": list(GOAL), "iters": args.iters,
            "optimizer": args.optimizer, "methods": out}
