"""Validation of the model builder's arguments: every check raises ValueError naming the argument."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from core.rotation import quat_from_matrix, quat_to_matrix

ROTATION_TOL = 1e-4
"""Accepted deviation of a rotation from unit norm / orthonormality before it is re-normalised.
Loose enough for hand-typed values such as ``(0, 0, 0.7071, 0.7071)`` (error 1e-5), tight enough to
reject a non-rotation (e.g. an axis-angle vector or a scaled matrix)."""


DEGENERATE_TRIANGLE_RTOL = 1e-12
"""A triangle is degenerate when twice its area is at most this times its longest edge squared
(height/longest-edge ratio below 1e-12, i.e. zero to within a few thousand ulps of float64)."""


Vec3Like = Sequence[float] | np.ndarray


Pinned = Sequence[int] | np.ndarray | Callable[[int, np.ndarray], bool]


# --------------------------------------------------------------------------------------------
# small validation helpers (all raise ValueError naming the argument)
# --------------------------------------------------------------------------------------------


def check_scalar(x, name: str, *, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(x, bool) or np.ndim(x) != 0:
        raise ValueError(f"{name} must be a real scalar, got {x!r}")
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real scalar, got {x!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    if positive and not v > 0.0:
        raise ValueError(f"{name} must be > 0, got {v}")
    if nonnegative and not v >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {v}")
    return v


def check_float_array(x, name: str, shape: tuple) -> np.ndarray:
    """float64 copy of ``x`` checked against ``shape`` (``None`` entries: any size) and finiteness."""
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real array of shape {shape_str(shape)}, got {x!r}") from None
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise ValueError(f"{name} must have shape {shape_str(shape)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def shape_str(shape: tuple) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def check_vec3(x, name: str) -> np.ndarray:
    return check_float_array(x, name, (3,))


def check_vertices(x, name: str, min_count: int = 3) -> np.ndarray:
    v = check_float_array(x, name, (None, 3))
    if len(v) < min_count:
        raise ValueError(f"{name} needs at least {min_count} vertices, got {len(v)}")
    return v


def check_triangles(t, n_vertices: int, name: str) -> np.ndarray:
    try:
        a = np.asarray(t)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an integer array of shape (T, 3)") from None
    if a.size == 0 and a.ndim <= 2:
        raise ValueError(f"{name} is empty: at least one triangle is needed")
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be an integer array of shape (T, 3), got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (T, 3), got {a.shape}")
    a = a.astype(np.int64)
    if a.min() < 0:
        raise ValueError(f"{name} contains negative indices (min {a.min()})")
    if a.max() >= n_vertices:
        raise ValueError(f"{name} index {a.max()} out of range for {n_vertices} vertices")
    return a


def check_nondegenerate(v: np.ndarray, t: np.ndarray, name: str) -> np.ndarray:
    """Twice the area of every triangle [m^2]; raises on zero-area triangles."""
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest2 = np.max(
        np.stack([np.sum((b - a) ** 2, 1), np.sum((c - b) ** 2, 1), np.sum((a - c) ** 2, 1)]), axis=0
    )
    bad = np.flatnonzero(area2 <= DEGENERATE_TRIANGLE_RTOL * longest2)
    if bad.size:
        raise ValueError(
            f"{name} has {bad.size} degenerate (zero-area) triangle(s), first: index {bad[0]} "
            f"= {t[bad[0]].tolist()}"
        )
    return area2


def compact_mesh(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drops vertices no triangle references (indices remapped, order kept)."""
    used = np.zeros(len(v), dtype=bool)
    used[t.reshape(-1)] = True
    if used.all():
        return v, t
    new = np.cumsum(used) - 1
    return v[used], new[t]


def check_rotation(rot, name: str = "rot") -> tuple[np.ndarray, np.ndarray]:
    """(matrix (3, 3), quaternion xyzw (4,)) of ``rot``: None (identity), a quaternion or a matrix."""
    if rot is None:
        return np.eye(3), np.array([0.0, 0.0, 0.0, 1.0])
    try:
        a = None if isinstance(rot, str) else np.asarray(rot, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape not in ((4,), (3, 3)):
        raise ValueError(
            f"{name} must be a quaternion (x, y, z, w) of shape (4,) or a 3x3 rotation matrix, "
            f"got shape {None if a is None else a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    if a.shape == (4,):
        n = np.linalg.norm(a)
        if abs(n - 1.0) > ROTATION_TOL:
            raise ValueError(f"{name} quaternion (x, y, z, w) must have unit norm, got norm {n:.6g}")
        q = a / n
        return quat_to_matrix(q), q
    err = np.max(np.abs(a.T @ a - np.eye(3)))
    if err > ROTATION_TOL or np.linalg.det(a) <= 0.0:
        raise ValueError(
            f"{name} matrix must be a rotation (orthonormal, det +1); |R^T R - I|_max = {err:.3g}, "
            f"det = {np.linalg.det(a):.6g}"
        )
    q = quat_from_matrix(a)
    return quat_to_matrix(q), q


def check_velocities(v, n: int, name: str) -> np.ndarray:
    """(n, 3) velocities from one shared (3,) vector or per-particle (n, 3) values."""
    try:
        shape = np.shape(v)
    except ValueError:
        raise ValueError(f"{name} must have shape (3,) or ({n}, 3)") from None
    if shape == (3,):
        return np.tile(check_vec3(v, name), (n, 1))
    if shape != (n, 3):
        raise ValueError(f"{name} must have shape (3,) or ({n}, 3), got {shape}")
    return check_float_array(v, name, (n, 3))


def pinned_mask(pinned, positions: np.ndarray, name: str = "pinned") -> np.ndarray:
    """Boolean (N,) mask from an index list, a boolean mask (N,) or ``pinned(i, x) -> bool``."""
    n = len(positions)
    if pinned is None:
        return np.zeros(n, dtype=bool)
    if callable(pinned):
        return np.array([bool(pinned(i, positions[i].copy())) for i in range(n)], dtype=bool)
    try:
        a = np.asarray(pinned)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 1-D list of particle indices, a boolean mask or a callable") from None
    if a.size == 0:
        return np.zeros(n, dtype=bool)
    if a.dtype == bool:
        if a.shape != (n,):
            raise ValueError(f"{name} as a boolean mask must have shape ({n},), got {a.shape}")
        return a.copy()
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be a 1-D list of particle indices, a boolean mask or a callable")
    if a.min() < 0 or a.max() >= n:
        raise ValueError(f"{name} index out of range [0, {n}): min {a.min()}, max {a.max()}")
    mask = np.zeros(n, dtype=bool)
    mask[a] = True
    return mask


SPHERE_TOUCH_RTOL = 1.0e-12
"""Spheres may overlap at the start by this fraction of the sum of their radii (rounding: rows
of touching balls computed in floating point overlap by ~1e-16 m)."""


def sphere_overlap(centres: np.ndarray, radii: np.ndarray, bodies) -> str | None:
    """A message naming the first two spheres (by body index) whose centres (N, 3) [m] and radii
    (N,) [m] overlap beyond :data:`SPHERE_TOUCH_RTOL` (touching is fine), or None."""
    reach = radii[:, None] + radii[None]
    gap = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - reach
    gap[np.diag_indices(len(radii))] = np.inf
    bad = np.argwhere(gap < -SPHERE_TOUCH_RTOL * reach)
    if not len(bad):
        return None
    i, j = bad[0]
    return f"spheres {int(bodies[i])} and {int(bodies[j])} overlap by {-gap[i, j]:.3g} m at the start (touching is fine)"
