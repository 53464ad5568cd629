"""Scene ``grazing``: gradients across a grazing contact, mollified and unmollified.

A particle (1 g, no gravity) passes a box (0.1 m half extents, 8 kg) spinning about z at
``w = 3 rad/s``, aimed so that it meets the face x = 0.1 (box frame) *tangentially*: when the
face normal points along x, a point at (0.1, Y) moving with ``v_x = -w Y`` has zero normal
relative velocity, and ``v_y > w X / 2`` makes its distance to the face plane a local minimum
there: a double root of the coplanarity cubic, where ``dt*/dp = -1/p'(t*)`` is unbounded.

The sweep aims the particle's initial ``v_x`` deeper than the threshold aim (found by bisection
between a hit and a miss) by a relative ``offset``; as the offset goes to zero the contact turns
grazing. For each aim it records the gradient of the final x w.r.t. the initial ``v_x`` through
:func:`sim.rollout.rollout` with the paper's mollified derivative (``M = 1000``) and with the
unmollified ``-1/p'(t*)``, next to the free-flight gradient ``T``. The recording logs both
curves against the sweep index (timeline ``aim``); the summary gives their largest magnitudes
as multiples of the free-flight gradient.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from scenes.registry import int_at_least

NAME = "grazing"
DESCRIPTION = "Gradient of a particle passing a spinning box across a grazing contact (mollified vs -1/p')"
PRECISIONS = ("float64",)
SUPPORTS_STEPS = False

SPIN = 3.0  # [rad/s] about z
MEET_TIME = 0.1  # [s] when the face normal points along +x
MEET_Y = 0.05  # [m] where the particle meets the face x = 0.1
SPEED_Y = 1.0  # [m/s]
STEPS, SUBSTEPS, DT = 12, 4, 1.0 / 60.0
DEFAULT_OFFSETS = (1e-1, 6.3e-2, 4e-2, 2.5e-2, 1.6e-2, 1e-2, 6.3e-3)


def build_model():
    """The particle and the spinning box (restitution 0.5, frictionless)."""
    from sim.builder import ModelBuilder
    from sim.mesh_io import box_mesh

    b = ModelBuilder()
    b.set_gravity(0.0)
    start = np.array([0.1, MEET_Y, 0.0]) - MEET_TIME * np.array([-SPIN * MEET_Y, SPEED_Y, 0.0])
    b.add_particle(tuple(start), mass=0.001)
    angle = -SPIN * MEET_TIME
    b.add_rigid_body(*box_mesh(0.1), density=1000.0, rot=(0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)),
                     angular_velocity=(0.0, 0.0, SPIN))
    b.set_contact(restitution=0.5, friction=0.0)
    return b.finalize()


def sweep(offsets=DEFAULT_OFFSETS, bisections: int = 50, max_derivative: float = 1000.0) -> dict[str, Any]:
    """Runs the sweep (see the module docstring).

    Returns:
        dict with ``free`` (free-flight gradient [s]), ``threshold`` (the grazing aim [m/s]),
        ``offsets``, ``mollified``, ``unmollified`` (gradients per offset, numpy) and
        ``contacts`` (contact substeps per offset).
    """
    import torch

    from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE, rollout

    model = build_model()

    def run(vx, max_derivative=1000.0, grad=False):
        v = torch.tensor([[vx, SPEED_Y, 0.0]], dtype=torch.float64, requires_grad=grad)
        res = rollout(model, STEPS, DT, SUBSTEPS, particle_qd=v, max_derivative=max_derivative)
        if not grad:
            return res.stats["contact_substeps"]
        res.particle_q[-1, 0, 0].backward()
        return float(v.grad[0, 0]), res.stats["contact_substeps"]

    aim = -SPIN * MEET_Y
    hit, miss = aim - 0.01, aim + 0.01
    if not run(hit) or run(miss):
        raise RuntimeError("grazing sweep: the bracketing aims do not hit and miss")
    for _ in range(bisections):
        mid = 0.5 * (hit + miss)
        if run(mid):
            hit = mid
        else:
            miss = mid
    free, _ = run(miss + 0.01, grad=True)
    mollified, unmollified, contacts = [], [], []
    for k in offsets:
        g, c = run(hit * (1.0 + k), max_derivative, grad=True)
        mollified.append(g)
        contacts.append(c)
        unmollified.append(run(hit * (1.0 + k), UNMOLLIFIED_MAX_DERIVATIVE, grad=True)[0])
    return {"free": free, "threshold": hit, "offsets": np.asarray(offsets, dtype=np.float64),
            "mollified": np.asarray(mollified), "unmollified": np.asarray(unmollified),
            "contacts": np.asarray(contacts)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--points", type=int_at_least(2), default=len(DEFAULT_OFFSETS),
                        help="aims in the sweep, log-spaced offsets 1e-1 .. 6.3e-3 (default %(default)s)")


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the sweep, logs ``/metrics/gradient/{mollified,unmollified,free_flight}`` per aim."""
    result = sweep(np.logspace(-1.0, -2.2, args.points))
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
        "threshold_vx": result["threshold"],
        "max_mollified_over_free": float(np.abs(result["mollified"]).max() / free),
        "max_unmollified_over_free": float(np.abs(result["unmollified"]).max() / free),
        "offsets": result["offsets"].tolist(),
        "mollified": result["mollified"].tolist(),
        "unmollified": result["unmollified"].tolist(),
    }
