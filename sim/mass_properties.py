"""Mass properties of homogeneous solids bounded by closed triangle meshes, and lumped cloth masses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VOLUME_RTOL = 1e-12
"""A closed mesh has zero volume when |V| is at most this times the cube of its bounding-box
diagonal (flat or fully self-cancelling meshes)."""


def lumped_masses(v: np.ndarray, t: np.ndarray, area2: np.ndarray, density: float) -> np.ndarray:
    """Each triangle's mass (density x area) split in thirds onto its corners [kg] (N,)."""
    m = np.zeros(len(v))
    share = density * 0.5 * area2 / 3.0
    for k in range(3):
        np.add.at(m, t[:, k], share)
    return m


# --------------------------------------------------------------------------------------------
# mass properties of closed triangle meshes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MassProperties:
    """Mass properties of a homogeneous solid bounded by a closed triangle mesh.

    Attributes:
        volume: [m^3] (positive for outward-oriented meshes).
        mass: density x volume [kg].
        com: centre of mass [m], (3,), in the mesh's frame.
        inertia: inertia tensor about the centre of mass, mesh axes [kg m^2], (3, 3).
        inertia_origin: inertia tensor about the mesh frame's origin [kg m^2], (3, 3)
            (= ``inertia + mass * (|c|^2 I - c c^T)``, parallel axis theorem).
    """

    volume: float
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    inertia_origin: np.ndarray


def mesh_mass_properties(vertices: np.ndarray, triangles: np.ndarray, density: float = 1.0) -> MassProperties:
    """Volume, mass, centre of mass and inertia of the solid enclosed by a closed mesh.

    Divergence theorem on signed tetrahedra ``(r, a, b, c)``, one per triangle, with apex ``r`` the
    vertex mean (subtracted first to limit cancellation): ``V_i = det(a, b, c) / 6`` and the second
    moment ``int x x^T dV = det/120 (a a^T + b b^T + c c^T + s s^T)``, ``s = a + b + c`` (e.g.
    Eberly, "Polyhedral Mass Properties (Revisited)"; Blow & Binstock, "How to find the inertia
    tensor (or other mass properties) of a 3D solid body represented by a triangle mesh").
    The mesh is not validated here; see :meth:`ModelBuilder.add_rigid_body` for that.

    Args:
        vertices: Positions [m], float (N, 3).
        triangles: Outward-oriented (counter-clockwise seen from outside) indices, int (T, 3).
        density: [kg/m^3].

    Returns:
        :class:`MassProperties`.

    Raises:
        ValueError: If the signed volume is exactly zero (NaN inputs also end here).
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    ref = v.mean(axis=0)
    p = v - ref
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    volume = det.sum() / 6.0
    s = a + b + c
    first = (det[:, None] * s).sum(axis=0) / 24.0  # int x dV about ref
    second = np.einsum("i,ij,ik->jk", det, a, a)
    second += np.einsum("i,ij,ik->jk", det, b, b)
    second += np.einsum("i,ij,ik->jk", det, c, c)
    second += np.einsum("i,ij,ik->jk", det, s, s)
    second /= 120.0  # int (x - ref)(x - ref)^T dV
    if not volume != 0.0:
        raise ValueError("vertices/triangles enclose zero volume (0 m^3): not a closed solid")
    mass = density * volume
    d = first / volume  # com - ref
    cov_com = density * second - mass * np.outer(d, d)
    cov_com = 0.5 * (cov_com + cov_com.T)
    com = ref + d
    inertia = np.trace(cov_com) * np.eye(3) - cov_com
    inertia_origin = inertia + mass * (np.dot(com, com) * np.eye(3) - np.outer(com, com))
    return MassProperties(float(volume), float(mass), com, inertia, inertia_origin)


def check_closed_oriented(t: np.ndarray, n: int, name: str) -> None:
    """Every directed edge once and its reverse present: closed, 2-manifold edges, consistent winding."""
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    key = e[:, 0] * n + e[:, 1]
    uniq, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        k = uniq[np.argmax(counts > 1)]
        raise ValueError(
            f"{name}: edge ({k // n}, {k % n}) is traversed in the same direction by "
            f"{counts.max()} triangles: the mesh is non-manifold or inconsistently oriented"
        )
    rev = e[:, 1] * n + e[:, 0]
    missing = ~np.isin(rev, uniq)
    if np.any(missing):
        i = np.argmax(missing)
        raise ValueError(
            f"{name}: the mesh is open ({int(missing.sum())} boundary edge(s), e.g. "
            f"({e[i, 0]}, {e[i, 1]})); a rigid body needs a closed, consistently oriented surface"
        )
