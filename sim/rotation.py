"""Quaternion helpers on the host (numpy), quaternions in (x, y, z, w) order, batched over
leading dimensions. One implementation for the builder, the collision response, the penetration
checker and the scenes' energy bookkeeping."""

from __future__ import annotations

import numpy as np


# quat_to_matrix: row-major entry k is 1 - 2 (p + SIGN[k] r) where DIAGONAL[k], else 2 (p + SIGN[k] r),
# for the products p = q[FIRST[0][k]] q[FIRST[1][k]] and r = q[SECOND[0][k]] q[SECOND[1][k]]
# (x, y, z, w = 0, 1, 2, 3): the textbook formula's arithmetic, entry by entry
_ROT_FIRST = (np.array([1, 0, 0, 0, 0, 1, 0, 1, 0]), np.array([1, 1, 2, 1, 0, 2, 2, 2, 0]))
_ROT_SECOND = (np.array([2, 2, 1, 2, 2, 0, 1, 0, 1]), np.array([2, 3, 3, 3, 2, 3, 3, 3, 1]))
_ROT_SIGN = np.array([1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
_ROT_DIAGONAL = np.array([True, False, False, False, True, False, False, False, True])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    # all nine entries in a few whole-array operations (not one per entry): the collision
    # response calls this several times per substep on a few bodies, where numpy's per-call
    # overhead is the whole cost. Same arithmetic per entry as 1 - 2 (y y + z z), 2 (x y - z w), ...
    q = np.asarray(q, dtype=np.float64)
    first = q[..., _ROT_FIRST[0]] * q[..., _ROT_FIRST[1]]
    second = q[..., _ROT_SECOND[0]] * q[..., _ROT_SECOND[1]]
    twice = 2 * (first + _ROT_SIGN * second)
    return np.where(_ROT_DIAGONAL, 1 - twice, twice).reshape(q.shape[:-1] + (3, 3))


def cross(a, b):
    """Cross products (..., 3) of ``a`` and ``b`` (..., 3), numpy arrays or torch tensors: the
    arithmetic of ``np.cross`` (the same bits), without its per-call overhead (tens of
    microseconds, the whole cost on the collision response's few rows)."""
    # by index arrays, so numpy arrays and torch tensors (autograd) both work
    i, j = [1, 2, 0], [2, 0, 1]
    return a[..., i] * b[..., j] - a[..., j] * b[..., i]


def row_norms(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """Euclidean norms over the last axis of ``x`` (..., 3): ``np.linalg.norm(x, axis=-1)``'s
    arithmetic (the square root of the summed squares, the same bits) without its per-call
    overhead."""
    return np.sqrt((x * x).sum(-1, keepdims=keepdims))


def quat_rotate(q, v):
    """``v`` (..., 3) rotated by the quaternions ``q`` (..., 4) (x, y, z, w), normalised here;
    numpy arrays or torch tensors (differentiable)."""
    q = q / (q * q).sum(-1)[..., None] ** 0.5
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)
