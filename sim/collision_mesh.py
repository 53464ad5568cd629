"""The collidable surface of a model, built once: :class:`CollisionMesh`.

One numbering of every vertex that can touch something, shared by the collision response
(:mod:`sim.contact.response`), the penetration checker (:mod:`sim.penetration`) and the recorder
(:mod:`sim.recorder`), after ipc-toolkit's ``CollisionMesh``:

* vertices ``[0, P)``: the particles (cloth and loose particles, in the model's order);
* ``[P, P + S)``: the rigid bodies' surface vertices (body frame in :attr:`CollisionMesh.local`);
* ``[P + S, P + S + G)``: the static meshes' vertices (world frame in ``local``).

Each vertex has a type (:data:`VERTEX_PARTICLE`, :data:`VERTEX_BODY`, :data:`VERTEX_STATIC`, the
constants of :mod:`kernels.pose`) and an owner (particle index, body index, or 0), and
:meth:`CollisionMesh.positions` / :meth:`CollisionMesh.pose` put them in the world for a state,
on the host or with the Warp kernel :func:`kernels.pose.pose_vertices_kernel` on the model's
device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from collision.broad_phase import mesh_edges
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, VERTEX_STATIC, pose_vertices_kernel
from core.rotation import quat_to_matrix
from core.buffers import rows




FLAT_EDGE_COSINE = 1.0 - 1e-12
"""Two faces sharing an edge are coplanar when the cosine between their unit normals is at
least this (a dihedral angle below ~1.4e-6 rad: the float64 rounding of a box's split face,
with room to spare, and far below any modelled crease)."""


def flat_edges(edges: np.ndarray, faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which ``edges`` (E, 2) lie between exactly two ``faces`` (F, 3) that are coplanar and face
    the same way (vertex positions ``vertices`` (V, 3)), such as a box face's diagonal.

    Such an edge is no collision feature: whatever touches it touches the faces' plane inside
    the flat region first or at the same time, which the vertex-face pairs of that region and
    the edge-edge pairs of its border edges report, with the plane's normal. The edge's own
    edge-edge pairs would report the same touch with the normal of the two edges' cross
    product, which is sideways for an edge lying in the plane (a box dropped flat onto another
    box's face then turns about the vertical).

    Returns:
        bool (E,) mask, and (E, 2) int64: the third vertices of each edge's two faces (-1 for an
        edge without exactly two), with which a point beyond a flat edge can be tested against
        the neighbouring face (a box face's diagonal leads to the face's other half, not to the
        whole plane beyond it).
    """
    flat = np.zeros(len(edges), dtype=bool)
    opposites = np.full((len(edges), 2), -1, dtype=np.int64)
    if not len(edges) or not len(faces):
        return flat, opposites
    f = np.asarray(faces, dtype=np.int64)
    y = vertices[f]
    normal = np.cross(y[:, 1] - y[:, 0], y[:, 2] - y[:, 0])
    length = np.linalg.norm(normal, axis=1)
    ok = length > 0.0
    normal[ok] /= length[ok, None]
    # each face's three edges as (lo, hi) keys, matched to the edge rows
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    third = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])  # the vertex opposite each face edge
    e.sort(axis=1)
    n = int(max(edges.max(), f.max())) + 1
    row = np.searchsorted(edges[:, 0] * n + edges[:, 1], e[:, 0] * n + e[:, 1])
    face = np.tile(np.arange(len(f)), 3)
    count = np.bincount(row, minlength=len(edges))
    order = np.argsort(row, kind="stable")
    two = np.flatnonzero(count == 2)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    fa, fb = face[order[start[two]]], face[order[start[two] + 1]]
    cos = np.einsum("ij,ij->i", normal[fa], normal[fb])
    flat[two] = ok[fa] & ok[fb] & (cos >= FLAT_EDGE_COSINE)
    opposites[two, 0] = third[order[start[two]]]
    opposites[two, 1] = third[order[start[two] + 1]]
    return flat, opposites


@dataclass
class CollisionMesh:
    """Vertices, faces and edges of everything in a model that can collide (see the module
    docstring for the numbering). Build it with :meth:`from_model`.

    Attributes:
        particle_count: P, particles (all of the model's).
        body_count: B, rigid bodies.
        shape_offset: first rigid surface vertex (= P).
        static_offset: first static vertex (= P + S).
        vertex_count: V = P + S + G.
        faces: (F, 3) int64 vertex indices: cloth triangles, then the bodies' faces, then the
            static faces.
        face_offsets: (0, T, T + Fs, F): where the cloth, body and static faces start and end.
        edges: (E, 2) int64 unique edges of ``faces`` (:func:`collision.broad_phase.mesh_edges`).
        feature_edges: (E', 2) int64, the rows of ``edges`` that are collision features: every
            cloth edge, and the rigid and static edges except those between two coplanar faces
            (:func:`flat_edges`), which add nothing the faces do not hold and whose edge-edge
            normals point sideways.
        flat_edges: (E - E', 2) int64, the other rows of ``edges``: edges inside a flat region
            of a rigid or static surface (vertex-face contacts whose closest point lies on one
            take the face's normal, :func:`kernels.contact_geometry.contact_geometry_kernel`).
        flat_opposites: (E - E', 2) int64, the third vertices of the two faces of each flat edge
            (:func:`flat_edges`).
        vertex_type: (V,) int64, ``VERTEX_*``.
        vertex_owner: (V,) int64: particle index, body index, or 0 for static vertices.
        local: (V, 3) float64: body-frame positions [m] of rigid vertices, world positions of
            static ones, zeros for particles.
        device: the model's Warp device.
    """

    particle_count: int
    body_count: int
    shape_offset: int
    static_offset: int
    vertex_count: int
    faces: np.ndarray
    face_offsets: tuple
    edges: np.ndarray
    feature_edges: np.ndarray
    flat_edges: np.ndarray
    flat_opposites: np.ndarray
    vertex_type: np.ndarray
    vertex_owner: np.ndarray
    local: np.ndarray
    device: object

    @classmethod
    def from_model(cls, model) -> "CollisionMesh":
        """The collidable surface of a finalised :class:`sim.model.Model` (arrays copied to the
        host once)."""
        P, B = int(model.particle_count), int(model.body_count)
        tris = rows(model.tri_indices, (3,), np.int64) if model.tri_count else np.zeros((0, 3), np.int64)
        shape_vertices = rows(model.shape_vertices, (3,))
        shape_body = rows(model.shape_vertex_body, (), np.int64)
        shape_faces = rows(model.shape_faces, (3,), np.int64)
        static_vertices = rows(model.static_vertices, (3,))
        static_faces = rows(model.static_faces, (3,), np.int64)
        S, G = len(shape_vertices), len(static_vertices)
        faces = np.concatenate([tris, shape_faces + P, static_faces + P + S]).astype(np.int64)
        T, Fs = len(tris), len(shape_faces)
        edges = mesh_edges(faces) if len(faces) else np.zeros((0, 2), dtype=np.int64)
        local = np.concatenate([np.zeros((P, 3)), shape_vertices, static_vertices]).reshape(-1, 3)
        # rigid and static faces keep their shape; cloth faces bend, so all their edges stay
        flat, opposites = flat_edges(edges, faces[T:], local)
        return cls(
            particle_count=P,
            body_count=B,
            shape_offset=P,
            static_offset=P + S,
            vertex_count=P + S + G,
            faces=faces,
            face_offsets=(0, T, T + Fs, len(faces)),
            edges=edges,
            feature_edges=edges[~flat],
            flat_edges=edges[flat],
            flat_opposites=opposites[flat],
            vertex_type=np.concatenate([np.full(P, VERTEX_PARTICLE), np.full(S, VERTEX_BODY),
                                        np.full(G, VERTEX_STATIC)]).astype(np.int64),
            vertex_owner=np.concatenate([np.arange(P), shape_body, np.zeros(G)]).astype(np.int64),
            local=local,
            device=model.device,
        )

    @property
    def shape_count(self) -> int:
        """S: rigid surface vertices."""
        return self.static_offset - self.shape_offset

    @property
    def shape_body(self) -> np.ndarray:
        """(S,) the body of each rigid surface vertex."""
        return self.vertex_owner[self.shape_offset:self.static_offset]

    @property
    def shape_local(self) -> np.ndarray:
        """(S, 3) body-frame positions [m] of the rigid surface vertices."""
        return self.local[self.shape_offset:self.static_offset]

    @property
    def static_vertices(self) -> np.ndarray:
        """(G, 3) world positions [m] of the static vertices."""
        return self.local[self.static_offset:]

    def levers(self, rotations: np.ndarray) -> np.ndarray:
        """(S, 3) offsets [m] of the rigid surface vertices from their body's centre of mass, in
        the world frame, for the bodies' rotation matrices (B, 3, 3)."""
        return np.einsum("nij,nj->ni", rotations[self.shape_body], self.shape_local)

    def positions(self, particle_q: np.ndarray, body_q: np.ndarray) -> np.ndarray:
        """World positions (V, 3) [m] for particle positions (P, 3) and body poses (B, 7)
        (centre of mass, quaternion x y z w), on the host.

        Raises:
            ValueError: naming the argument whose length does not match the model.
        """
        particle_q = np.asarray(particle_q, dtype=np.float64).reshape(-1, 3)
        body_q = np.asarray(body_q, dtype=np.float64).reshape(-1, 7)
        if len(particle_q) != self.particle_count:
            raise ValueError(f"particle_q: the state has {len(particle_q)} particles, the model {self.particle_count}")
        if len(body_q) != self.body_count:
            raise ValueError(f"body_q: the state has {len(body_q)} bodies, the model {self.body_count}")
        x = np.empty((self.vertex_count, 3))
        x[:self.shape_offset] = particle_q
        if self.shape_count:
            levers = self.levers(quat_to_matrix(body_q[:, 3:7]))
            np.add(body_q[self.shape_body, :3], levers, out=x[self.shape_offset:self.static_offset])
        x[self.static_offset:] = self.static_vertices
        return x

    def pose(self, particle_q: wp.array, body_q: wp.array, x: wp.array, lever: wp.array) -> None:
        """World positions ``x`` (V,) and lever arms from the owning body's centre of mass
        ``lever`` (V,) (zero for particles and static vertices), vec3d arrays on the model's
        device, by :func:`kernels.pose.pose_vertices_kernel` (differentiable under a tape)."""
        if not self.vertex_count:
            return
        if not hasattr(self, "_type_w"):
            d = self.device
            self._type_w = wp.array(self.vertex_type.astype(np.int32), dtype=wp.int32, device=d)
            self._owner_w = wp.array(self.vertex_owner.astype(np.int32), dtype=wp.int32, device=d)
            self._local_w = wp.array(self.local, dtype=wp.vec3d, device=d)
        wp.launch(pose_vertices_kernel, dim=self.vertex_count, device=self.device,
                  inputs=[particle_q, body_q, self._type_w, self._owner_w, self._local_w], outputs=[x, lever])
