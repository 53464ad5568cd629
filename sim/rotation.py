"""Quaternion helpers on the host (numpy), quaternions in (x, y, z, w) order, batched over
leading dimensions. One implementation for the builder, the collision response, the penetration
checker and the scenes' energy bookkeeping."""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    # entries written into one array (not stacked): the collision response calls this several
    # times per substep on a few bodies, where numpy's per-call overhead is the whole cost
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a b (..., 4)."""
    a, b = np.asarray(a), np.asarray(b)
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        -1,
    )


def cross(a, b):
    """Cross products (..., 3) of ``a`` and ``b`` (..., 3), numpy arrays or torch tensors: the
    arithmetic of ``np.cross`` (the same bits), without its per-call overhead (tens of
    microseconds, the whole cost on the collision response's few rows)."""
    # by index arrays, so numpy arrays and torch tensors (autograd) both work
    i, j = [1, 2, 0], [2, 0, 1]
    return a[..., i] * b[..., j] - a[..., j] * b[..., i]


def quat_rotate(q, v):
    """``v`` (..., 3) rotated by the quaternions ``q`` (..., 4) (x, y, z, w), normalised here;
    numpy arrays or torch tensors (differentiable)."""
    q = q / (q * q).sum(-1)[..., None] ** 0.5
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def quat_turn(q: np.ndarray, omega: np.ndarray, duration: np.ndarray) -> np.ndarray:
    """Quaternions ``q`` (..., 4) turned by world angular velocities ``omega`` [rad/s] (..., 3) for
    ``duration`` [s] (...,): the exact rotation, renormalised."""
    speed = np.linalg.norm(omega, axis=-1, keepdims=True)
    axis = np.divide(omega, speed, out=np.zeros_like(omega), where=speed > 0)
    angle = speed[..., 0] * duration
    dq = np.concatenate([axis * np.sin(angle / 2)[..., None], np.cos(angle / 2)[..., None]], -1)
    out = quat_multiply(dq, q)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)
