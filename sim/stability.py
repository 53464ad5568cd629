"""Stability limits and divergence checks: fail fast, with a clear message, where a setting
cannot be accurate.

* :func:`explicit_substep_limit` estimates the longest stable substep of the explicit
  (semi-implicit Euler) springs from their stiffness and the particle masses. A substep more
  than :data:`REFUSAL_FACTOR` times longer diverges for certain: the scenes refuse such a
  setting before the run (:func:`check_explicit_substep`).
* :class:`DivergenceGuard` checks every substep, on the device, whether a position or velocity
  is not finite or a position left a ball of :data:`BOUNDS_FACTOR` times the scene's reach (its
  initial bounding box plus the ballistic reach of its initial speeds and gravity over the
  run). The integrator reads its flag once per substep.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from kernels.integrate import outside_bounds_kernel

REFUSAL_FACTOR = 3.0
"""A substep longer than this many times :func:`explicit_substep_limit` is refused. The limit
is a Gershgorin bound (it is at most the true stability limit: 1.79 ms against 2.36 ms for the
linearised springs of ``cloth_drop``), so only settings far past the true limit are refused;
those near it are caught by the :class:`DivergenceGuard` while they run."""

BOUNDS_FACTOR = 10.0
"""A position farther than this many times the scene's reach from the centre of its initial
bounding box counts as divergence (:class:`DivergenceGuard`)."""


class SimulationDiverged(RuntimeError):
    """The simulation blew up (non-finite values, positions far outside the scene's reach, or
    kinetic energy no physics of the scene can reach), or a setting was refused because it
    certainly would."""


def explicit_substep_limit(model) -> float:
    """Estimated stability limit [s] of the explicit springs' substep: ``2 / sqrt(lambda)``,
    with ``lambda`` Gershgorin's bound on the largest eigenvalue of ``M^-1 K`` for the springs'
    Laplacian (per free particle: ``k`` of each of its springs, twice when the other end is free
    too, over its mass). Springs are taken as aligned, so the estimate is at most the true
    limit of the linearised springs at rest. ``inf`` without springs on free particles."""
    if not model.spring_count or not model.particle_count:
        return math.inf
    idx = model.spring_indices.numpy().reshape(-1, 2)
    k = np.abs(model.spring_stiffness.numpy())
    inv_mass = model.particle_inv_mass.numpy()
    free = inv_mass > 0
    # a row of the springs' Laplacian: k on the diagonal, k off it when the other end is free
    row = np.zeros(model.particle_count)
    np.add.at(row, idx[:, 0], k * (1.0 + free[idx[:, 1]]))
    np.add.at(row, idx[:, 1], k * (1.0 + free[idx[:, 0]]))
    lam = float(np.max(row * inv_mass))
    return 2.0 / math.sqrt(lam) if lam > 0 else math.inf


def check_explicit_substep(model, substep: float) -> str | None:
    """None when ``substep`` [s] may be stable for the explicit springs of ``model``; else a
    sentence saying why it cannot be (the substep against :func:`explicit_substep_limit`)."""
    limit = explicit_substep_limit(model)
    if substep > REFUSAL_FACTOR * limit:
        return (f"substeps of {substep:.3g} s are {substep / limit:.3g}x the explicit springs' stability limit "
                f"of about {limit:.3g} s (2 / sqrt(k / m)); they diverge within a few substeps")
    return None


class DivergenceGuard:
    """Per-substep divergence check of a model's states (one launch and one flag read).

    Args:
        model: the model whose states are checked.
        state: its initial state (the bounds are set from it).
        duration: the simulated time the run covers [s] (the ballistic reach).
    """

    def __init__(self, model, state, duration: float):
        self.model = model
        P, B = int(model.particle_count), int(model.body_count)
        pts = [state.particle_q.numpy().reshape(-1, 3)[:P]] if P else []
        speeds = [np.linalg.norm(state.particle_qd.numpy().reshape(-1, 3)[:P], axis=1)] if P else []
        if B:
            bq = state.body_q.numpy().reshape(-1, 7)[:B]
            bqd = state.body_qd.numpy().reshape(-1, 6)[:B]
            pts.append(bq[:, :3])
            # a body point's speed: the centre's plus the turn's at the body's size (at most 10 m)
            speeds.append(np.linalg.norm(bqd[:, 3:], axis=1) + 10.0 * np.linalg.norm(bqd[:, :3], axis=1))
        x = np.concatenate(pts) if pts else np.zeros((1, 3))
        lo, hi = x.min(0), x.max(0)
        speed = float(np.max(np.concatenate(speeds))) if speeds else 0.0
        g = float(np.linalg.norm(np.asarray(model.gravity, dtype=np.float64)))
        T = float(duration)
        reach = 0.5 * float(np.linalg.norm(hi - lo)) + speed * T + 0.5 * g * T * T + float(model.thickness)
        self.center = 0.5 * (lo + hi)
        self.radius = BOUNDS_FACTOR * reach if reach > 0 else math.inf
        self.count = P + B
        self._flag = wp.zeros(1, dtype=wp.int32, device=model.device)
        self._host = self._flag.numpy() if self._flag.device.is_cpu else None

    def exceeded(self, state) -> bool:
        """Whether ``state`` has a non-finite value or a position outside the bounds."""
        if not self.count:
            return False
        m = self.model
        self._flag.zero_()
        wp.launch(outside_bounds_kernel, dim=self.count, inputs=[
            state.particle_q, state.particle_qd, state.body_q, state.body_qd, int(m.particle_count),
            wp.vec3d(*self.center), wp.float64(self.radius if math.isfinite(self.radius) else 1e300), self._flag],
            device=m.device, record_tape=False)
        flag = self._host if self._host is not None else self._flag.numpy()
        return bool(flag[0])

    def message(self) -> str:
        """What diverged."""
        return (f"the simulation diverged: a position or velocity became non-finite or a position left "
                f"{BOUNDS_FACTOR:g}x the scene's reach ({self.radius:.3g} m from its centre)")
