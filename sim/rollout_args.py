"""Validation of :func:`sim.rollout.rollout`'s arguments: each check raises a ``ValueError`` that
names the argument, before anything runs."""

from __future__ import annotations

import math

import numpy as np
import torch

from sim.events import check_events
from sim.model import Model
from sim.validation import sphere_overlap


def check_tensor(value, shape: tuple, name: str, unit: str = "") -> torch.Tensor | None:
    """None, or a finite float64 torch tensor of ``shape`` (``unit`` names its unit in messages)."""
    if value is None:
        return None
    text = "(" + ", ".join(str(n) for n in shape) + ("," if len(shape) == 1 else "") + ")"
    unit = f" [{unit}]" if unit else ""
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be a torch tensor of shape {text}{unit}, got {type(value).__name__}")
    if value.dtype != torch.float64:
        raise ValueError(f"{name} must be float64, got {value.dtype}")
    if tuple(value.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {text}, got {tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must be finite (it holds NaN or inf)")
    return value


def check_parameter(value, count: int, name: str, unit: str) -> torch.Tensor | None:
    """A per-particle or per-spring parameter: None, or a finite, non-negative float64 torch
    tensor of shape (count,)."""
    value = check_tensor(value, (count,), name, unit)
    if value is not None and bool((value < 0.0).any()):
        raise ValueError(f"{name} must be >= 0 [{unit}], got a negative value")
    return value


def check_parameters(model: Model, particle_mass, spring_stiffness):
    mass = check_parameter(particle_mass, model.particle_count, "particle_mass", "kg")
    if mass is not None and model.particle_count:
        pinned = model.particle_mass.numpy() == 0.0
        zero = mass.detach().cpu().numpy() == 0.0
        if np.any(pinned != zero):
            i = int(np.flatnonzero(pinned != zero)[0])
            raise ValueError(
                f"particle_mass must keep the model's pinned particles (mass 0) pinned and the others free "
                f"(mass > 0): particle {i} is {'pinned' if pinned[i] else 'free'} in the model")
    stiffness = check_parameter(spring_stiffness, model.spring_count, "spring_stiffness", "N/m")
    return mass, stiffness


def check_poses(value, model: Model) -> torch.Tensor | None:
    """Initial body poses: None, or finite float64 (B, 7) with unit quaternions (to 1e-9)."""
    value = check_tensor(value, (model.body_count, 7), "body_q")
    if value is not None and model.body_count:
        norms = value.detach()[:, 3:].norm(dim=1)
        if bool(((norms - 1.0).abs() > 1.0e-9).any()):
            b = int(((norms - 1.0).abs() > 1.0e-9).nonzero()[0, 0])
            raise ValueError(f"body_q[{b}, 3:] must be a unit quaternion (x, y, z, w), its norm is {float(norms[b])!r}")
        if model.sphere_count:
            bodies = model.sphere_body.numpy()
            problem = sphere_overlap(value.detach().cpu().numpy()[bodies, :3], model.sphere_radius.numpy(), bodies)
            if problem:
                raise ValueError(f"body_q: {problem}")
    return value


def check_args(model, steps, dt, substeps, particle_qd, body_qd, events, checkpoint_every, max_derivative):
    if not isinstance(model, Model):
        raise ValueError(f"model must be a sim.model.Model, got {type(model).__name__}")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
        raise ValueError(f"dt must be a positive finite number [s], got {dt!r}")
    dt_f = float(dt)
    if not math.isfinite(dt_f) or dt_f <= 0.0:
        raise ValueError(f"dt must be a positive finite number [s], got {dt!r}")
    if checkpoint_every is not None and (
        isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, (int, np.integer)) or checkpoint_every < 1
    ):
        raise ValueError(f"checkpoint_every must be None or an integer >= 1, got {checkpoint_every!r}")
    if isinstance(max_derivative, bool) or not isinstance(max_derivative, (int, float, np.integer, np.floating)) \
            or not float(max_derivative) > 0.0:
        raise ValueError(f"max_derivative must be a positive number, got {max_derivative!r}")
    events = check_events(model, events, int(steps))
    pqd = check_tensor(particle_qd, (model.particle_count, 3), "particle_qd")
    bqd = check_tensor(body_qd, (model.body_count, 6), "body_qd")
    return int(steps), dt_f, int(substeps), pqd, bqd, events
