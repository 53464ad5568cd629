"""Quaternion helpers on the host (numpy), quaternions in (x, y, z, w) order, batched over
leading dimensions. One implementation for the builder, the collision response, the penetration
checker and the scenes' energy bookkeeping."""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a b (..., 4)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        -1,
    )


def _cross(a, b):
    # by index arrays, so numpy arrays and torch tensors (autograd) both work
    i, j = [1, 2, 0], [2, 0, 1]
    return a[..., i] * b[..., j] - a[..., j] * b[..., i]


def quat_rotate(q, v):
    """``v`` (..., 3) rotated by the quaternions ``q`` (..., 4) (x, y, z, w), normalised here;
    numpy arrays or torch tensors (differentiable)."""
    q = q / (q * q).sum(-1)[..., None] ** 0.5
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def quat_turn(q: np.ndarray, omega: np.ndarray, duration: np.ndarray) -> np.ndarray:
    """Quaternions ``q`` (..., 4) turned by world angular velocities ``omega`` [rad/s] (..., 3) for
    ``duration`` [s] (...,): the exact rotation, renormalised."""
    speed = np.linalg.norm(omega, axis=-1, keepdims=True)
    axis = np.divide(omega, speed, out=np.zeros_like(omega), where=speed > 0)
    angle = speed[..., 0] * duration
    dq = np.concatenate([axis * np.sin(angle / 2)[..., None], np.cos(angle / 2)[..., None]], -1)
    out = quat_multiply(dq, q)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)
