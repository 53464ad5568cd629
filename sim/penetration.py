"""Independent geometric interpenetration checker for tests and scene summaries.

Nothing here reads the simulator's own contact flags: the check looks only at the geometry of a
:class:`sim.model.Model` posed by a :class:`sim.model.State` (float64 throughout).

What counts as one penetration (``tol`` is :data:`DEFAULT_TOL` unless given):

1. **plane**: a cloth particle or a rigid-body surface vertex more than ``tol`` below a ground
   plane (``dot(n, x) < offset - tol``); depth ``offset - dot(n, x)``. One per (vertex, plane).
   Static meshes are not tested against planes (scenery may legitimately sit in the ground).
2. **inside**: a vertex strictly inside another *solid*, i.e. at distance more than ``tol`` from
   its surface and with generalised winding number above 1/2; depth = distance to that surface.
   Solids are the rigid bodies (posed by ``body_q``) and the closed, consistently and outward
   oriented connected components of the static meshes (open or inward-oriented static components
   are not solids; they still take part in 3.). Tested vertices: cloth particles, rigid-body
   vertices of other bodies, and static vertices against rigid bodies (never static in static).
   One per (vertex, solid).
3. **crossing**: a pair of triangles of two different surfaces (cloth/rigid, cloth/static,
   rigid/rigid, rigid/static; not cloth/cloth) that cross transversally: an edge of one has its
   end points more than ``tol`` on opposite sides of the other's plane and meets that plane more
   than ``tol`` inside the other triangle (in-plane distance to each of its edges). Depth 0. Only
   pairs none of whose vertices is already counted inside the other triangle's solid are counted
   (those penetrations already have a depth).

``count`` is the sum of the three; ``max_depth`` the largest depth (0 when there is none, or when
only crossings were found). Touching is never a penetration: a vertex exactly on a plane or a
face, cloth lying flat on a face or draped over a box edge, surfaces separated by any positive gap.
The crossing test misses (measure-zero) configurations where every crossing point lies within
``tol`` of a triangle edge.

Speed: the winding number (and, where it exceeds 1/2, the distance to the surface) is a float64
Warp kernel on the CPU, one thread per (vertex, solid) query for the vertices inside the solid's
bounding box, brute force over the solid's triangles. Candidate triangle pairs come from the
project's broad phase (:func:`collision.broad_phase.candidate_pairs`): every triangle of the query side becomes one
pseudo-vertex swept from its box's min corner (``x0``) to its max corner (``x1``), so the
vertex-face candidates of that call are exactly the overlapping triangle boxes (conservative
float32 boxes, nothing is dropped), and the crossing tests are vectorised numpy. A 64 x 64 cloth
(4225 particles) draped on a 642-vertex sphere takes ~0.12 s per check on one CPU core (the first
call compiles the kernel, ~5 s, cached by Warp afterwards).

Global numbering used in :class:`PenetrationReport`: vertices are ``[particles (P), rigid shape
vertices (Vs), static vertices (Vg)]`` and faces ``[cloth triangles (T), rigid shape faces (Fs),
static faces (Fg)]``, in the model's order.

Example:
    >>> count, depth = penetrations(model, state)  # doctest: +SKIP
    >>> checker = PenetrationChecker(model)         # topology analysed once  # doctest: +SKIP
    >>> report = checker.check(state); report.count, report.max_depth  # doctest: +SKIP
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from kernels import penetration as _k
from sim.model import Model, State
from core.buffers import rows

__all__ = [
    "DEFAULT_TOL",
    "PenetrationChecker",
    "PenetrationReport",
    "Solid",
    "penetrations",
    "state_positions",
    "vertex_components",
]

DEFAULT_TOL = 1e-10
"""Default tolerance [m]: penetrations no deeper than this are treated as contact. Far above the
float64 rounding of positions of scenes a few metres across (~1e-15 m) and far below any contact
thickness a scene uses (>= 1e-5 m), so a resting contact computed with rounding is not flagged."""

# --------------------------------------------------------------------------------------------
# vectorised geometry
# --------------------------------------------------------------------------------------------


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _segments_cross_triangles(p, q, u, v, w, tol: float) -> np.ndarray:
    """Segment ``p-q`` crosses triangle ``u-v-w`` transversally with margin ``tol`` ((K,) bool)."""
    n = np.cross(v - u, w - u)
    ln = np.sqrt(_dot(n, n))
    ok = ln > 0.0
    n = n / np.where(ok, ln, 1.0)[:, None]
    dp = _dot(p - u, n)
    dq = _dot(q - u, n)
    strict = ok & (((dp > tol) & (dq < -tol)) | ((dp < -tol) & (dq > tol)))
    t = np.divide(dp, dp - dq, out=np.zeros_like(dp), where=strict)
    x = p + t[:, None] * (q - p)
    for s0, s1 in ((u, v), (v, w), (w, u)):
        e = s1 - s0
        le = np.sqrt(_dot(e, e))
        strict &= _dot(np.cross(e, x - s0), n) > tol * le
    return strict


def _triangles_cross(ta: np.ndarray, tb: np.ndarray, tol: float) -> np.ndarray:
    """(K,) bool: triangles ``ta[k]`` and ``tb[k]`` ((K, 3, 3) corners) cross (see module doc)."""
    hit = np.zeros(len(ta), dtype=bool)
    for s, t in ((ta, tb), (tb, ta)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            todo = ~hit
            if not todo.any():
                break
            idx = np.flatnonzero(todo)
            hit[idx] = _segments_cross_triangles(
                s[idx, i], s[idx, j], t[idx, 0], t[idx, 1], t[idx, 2], tol
            )
    return hit


def vertex_components(faces: np.ndarray, n: int) -> np.ndarray:
    """Connected-component label of each of ``n`` vertices of a triangle mesh.

    Args:
        faces: (F, 3) integer vertex indices.
        n: Number of vertices (vertices no face uses are components of their own).

    Returns:
        (n,) int64 labels ``0..C-1``, numbered in order of each component's lowest vertex.
    """
    label = np.arange(n)
    if len(faces) == 0:
        return label
    while True:
        low = label[faces].min(axis=1)
        new = label.copy()
        for k in range(3):
            np.minimum.at(new, faces[:, k], low)
        while True:  # pointer jumping
            nxt = new[new]
            if np.array_equal(nxt, new):
                break
            new = nxt
        if np.array_equal(new, label):
            break
        label = new
    _, dense = np.unique(label, return_inverse=True)
    return dense.reshape(-1)


def _closed_oriented(faces: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse appears too (closed, consistent winding)."""
    if len(faces) == 0:
        return False
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    n = int(e.max()) + 1
    key = e[:, 0] * n + e[:, 1]
    uniq, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        return False
    return bool(np.all(np.isin(e[:, 1] * n + e[:, 0], uniq)))


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    v = vertices - vertices.mean(axis=0)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(_dot(a, np.cross(b, c)).sum() / 6.0)


# --------------------------------------------------------------------------------------------
# The winding-number / distance kernel lives in kernels/penetration.py (one thread per (point,
# solid) query, brute force over the solid's faces)
# --------------------------------------------------------------------------------------------


def _winding_and_distance(
    x: np.ndarray, query_point: np.ndarray, query_solid: np.ndarray, faces: np.ndarray, face_start: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Runs :func:`_k.winding_distance_kernel` on the CPU; returns (winding, distance) numpy."""
    from core.device import init_warp

    init_warp()
    n = len(query_point)
    dev = "cpu"
    xa = wp.array(np.ascontiguousarray(x), dtype=wp.vec3d, device=dev)
    qp = wp.array(query_point.astype(np.int32), dtype=wp.int32, device=dev)
    qs = wp.array(query_solid.astype(np.int32), dtype=wp.int32, device=dev)
    fa = wp.array(np.ascontiguousarray(faces, dtype=np.int32), dtype=wp.vec3i, device=dev)
    fs = wp.array(face_start.astype(np.int32), dtype=wp.int32, device=dev)
    w = wp.empty(n, dtype=wp.float64, device=dev)
    d = wp.empty(n, dtype=wp.float64, device=dev)
    wp.launch(_k.winding_distance_kernel, dim=n, inputs=[xa, qp, qs, fa, fs], outputs=[w, d], device=dev)
    return w.numpy(), d.numpy()



def state_positions(state: State | Mapping) -> tuple[np.ndarray, np.ndarray]:
    """``(particle_q (P, 3), body_q (B, 7))`` float64 numpy from a State or a mapping of arrays.

    Args:
        state: A :class:`sim.model.State` (Warp arrays, any device) or a mapping with keys
            ``"particle_q"`` and ``"body_q"`` (e.g. ``State.numpy()``; missing keys are empty).
    """
    if isinstance(state, Mapping):
        return rows(state.get("particle_q"), (3,)), rows(state.get("body_q"), (7,))
    return rows(state.particle_q, (3,)), rows(state.body_q, (7,))


# --------------------------------------------------------------------------------------------
# checker
# --------------------------------------------------------------------------------------------


@dataclass
class PenetrationReport:
    """Result of :meth:`PenetrationChecker.check` (indices: see the module docstring).

    Attributes:
        count: total number of penetrations (plane + inside + crossing).
        max_depth: largest depth [m] (0 if none or only crossings).
        plane_vertices, plane_ids, plane_depths: (K,) global vertex, plane index, depth.
        inside_vertices, inside_solids, inside_depths: (L,) global vertex, solid index (into
            :attr:`PenetrationChecker.solids`), depth.
        crossing_faces: (M, 2) global face pairs counted as crossings (depth 0).
    """

    count: int = 0
    max_depth: float = 0.0
    plane_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    plane_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    plane_depths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    inside_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    inside_solids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    inside_depths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    crossing_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))

    @property
    def plane_count(self) -> int:
        return len(self.plane_vertices)

    @property
    def inside_count(self) -> int:
        return len(self.inside_vertices)

    @property
    def crossing_count(self) -> int:
        return len(self.crossing_faces)

    def summary(self) -> dict:
        """JSON-friendly figures: count, max_depth and the per-kind counts."""
        return {
            "count": int(self.count),
            "max_depth": float(self.max_depth),
            "plane": self.plane_count,
            "inside": self.inside_count,
            "crossing": self.crossing_count,
        }


@dataclass(frozen=True)
class Solid:
    """A closed, outward-oriented surface used for the inside test.

    Attributes:
        group: surface id (0 cloth, 1 + b rigid body b, 1 + B + c static component c).
        kind: ``"rigid"`` or ``"static"``.
        index: body index or static component index.
        vertices: global vertex ids of the surface, (n,) int64.
        faces: its triangles as indices into ``vertices``, (F, 3) int64.
    """

    group: int
    kind: str
    index: int
    vertices: np.ndarray
    faces: np.ndarray


class PenetrationChecker:
    """Analyses a model's topology once; :meth:`check` then poses and tests one State.

    Args:
        model: The :class:`sim.model.Model` (any device; arrays are copied to numpy once).
        tol: Margin [m] (>= 0), see the module docstring.
    """

    def __init__(self, model: Model, tol: float = DEFAULT_TOL) -> None:
        tol = float(tol)
        if not (np.isfinite(tol) and tol >= 0.0):
            raise ValueError(f"tol must be finite and >= 0, got {tol}")
        self.tol = tol
        mesh = self.mesh = model.collision_mesh
        self.particle_count = P = mesh.particle_count
        self.shape_vertices = mesh.shape_local
        self.shape_body = mesh.shape_body
        self.static_vertices = mesh.static_vertices
        fo = mesh.face_offsets
        self.tris = mesh.faces[fo[0]:fo[1]]
        self.static_faces = mesh.faces[fo[2]:fo[3]] - mesh.static_offset
        self.planes = rows(model.planes, (4,)) if model.plane_count else np.zeros((0, 4))
        self.body_count = B = mesh.body_count
        Vg = len(self.static_vertices)
        self.vertex_offsets = (0, P, mesh.static_offset, mesh.vertex_count)
        self.face_offsets = fo

        static_comp = vertex_components(self.static_faces, Vg)
        C = int(static_comp.max()) + 1 if Vg else 0
        self.static_component_count = C
        self.static_vertex_component = static_comp
        # surface id per global vertex and per global face
        self.vertex_group = np.concatenate(
            [np.zeros(P, np.int64), 1 + self.shape_body, 1 + B + static_comp]
        )
        self.faces = mesh.faces
        self.face_group = self.vertex_group[self.faces[:, 0]] if len(self.faces) else np.zeros(0, np.int64)
        self.group_count = 1 + B + C
        self.group_static = np.zeros(self.group_count, dtype=bool)
        self.group_static[1 + B :] = True

        solids: list[Solid] = []
        for b in range(B):
            solids.append(self._solid(1 + b, "rigid", b, self.shape_vertices))
        for c in range(C):
            solids.append(self._solid(1 + B + c, "static", c, self.static_vertices))
        self.solids = [s for s in solids if s is not None]
        # all solids' faces (global vertex ids) concatenated, for the kernel
        faces = [s.vertices[s.faces] for s in self.solids]
        self._solid_faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        self._solid_face_start = np.concatenate([[0], np.cumsum([len(f) for f in faces])]).astype(np.int64)

    def _solid(self, group: int, kind: str, index: int, local_vertices: np.ndarray) -> Solid | None:
        fmask = self.face_group == group
        faces_g = self.faces[fmask]
        if len(faces_g) == 0:
            return None
        verts = np.unique(faces_g)
        local = np.searchsorted(verts, faces_g)
        if not _closed_oriented(local):
            return None
        offset = self.vertex_offsets[1] if kind == "rigid" else self.vertex_offsets[2]
        if _signed_volume(local_vertices[verts - offset], local) <= 0.0:
            return None
        return Solid(group, kind, index, verts, local)

    # ---------------------------------------------------------------------------- posing
    def positions(self, state: State | Mapping) -> np.ndarray:
        """World positions of all global vertices (N, 3) for ``state``."""
        pq, bq = state_positions(state)
        if len(pq) != self.particle_count:
            raise ValueError(f"state has {len(pq)} particles, the model {self.particle_count}")
        if len(bq) != self.body_count:
            raise ValueError(f"state has {len(bq)} bodies, the model {self.body_count}")
        return self.mesh.positions(pq, bq)

    # ---------------------------------------------------------------------------- checks
    def check(self, state: State | Mapping) -> PenetrationReport:
        """All penetrations of ``state`` (see the module docstring)."""
        x = self.positions(state)
        if not np.all(np.isfinite(x)):
            raise ValueError("state positions contain NaN or inf")
        tol = self.tol
        rep = PenetrationReport()

        # 1. planes: particles and rigid vertices
        dyn = self.vertex_offsets[2]
        if len(self.planes) and dyn:
            depth = self.planes[None, :, 3] - x[:dyn] @ self.planes[:, :3].T  # (N, K)
            vi, pi = np.nonzero(depth > tol)
            rep.plane_vertices, rep.plane_ids = vi.astype(np.int64), pi.astype(np.int64)
            rep.plane_depths = depth[vi, pi]

        # 2. vertices inside solids: AABB filter, then winding number and distance (Warp)
        qp, qs = [], []
        for si, s in enumerate(self.solids):
            sv = x[s.vertices]
            lo, hi = sv.min(axis=0), sv.max(axis=0)
            cand = self.vertex_group != s.group
            if s.kind == "static":
                cand &= ~self.group_static[self.vertex_group]
            cand &= np.all((x >= lo) & (x <= hi), axis=1)
            idx = np.flatnonzero(cand)
            qp.append(idx)
            qs.append(np.full(len(idx), si, dtype=np.int64))
        if qp and sum(len(a) for a in qp):
            qp_a, qs_a = np.concatenate(qp), np.concatenate(qs)
            w, d = _winding_and_distance(x, qp_a, qs_a, self._solid_faces, self._solid_face_start)
            keep = (w > 0.5) & (d > tol)
            rep.inside_vertices, rep.inside_solids, rep.inside_depths = qp_a[keep], qs_a[keep], d[keep]

        # 3. crossing triangle pairs
        pairs = self._candidate_face_pairs(x)
        if len(pairs):
            fa, fb = self.faces[pairs[:, 0]], self.faces[pairs[:, 1]]
            hit = _triangles_cross(x[fa], x[fb], tol)
            pairs, fa, fb = pairs[hit], fa[hit], fb[hit]
            if len(pairs) and len(rep.inside_vertices):
                # drop pairs with a vertex already counted inside the other triangle's solid
                G = self.group_count
                sol_group = np.array([s.group for s in self.solids], dtype=np.int64)
                inside_key = rep.inside_vertices * G + sol_group[rep.inside_solids]
                ga, gb = self.face_group[pairs[:, 0]], self.face_group[pairs[:, 1]]
                dup = np.isin(fa * G + gb[:, None], inside_key).any(axis=1)
                dup |= np.isin(fb * G + ga[:, None], inside_key).any(axis=1)
                pairs = pairs[~dup]
            rep.crossing_faces = pairs

        depths = np.concatenate([rep.plane_depths, rep.inside_depths])
        rep.max_depth = float(depths.max()) if len(depths) else 0.0
        rep.count = rep.plane_count + rep.inside_count + rep.crossing_count
        return rep

    def _candidate_face_pairs(self, x: np.ndarray) -> np.ndarray:
        """(K, 2) global face pairs of different, allowed surfaces whose boxes overlap.

        Query side: cloth and rigid faces, each a pseudo-vertex swept over its box; target side:
        rigid and static faces (real vertices, ``x0 = x1``). Each unordered pair appears once,
        ordered as (lower face id, higher face id).
        """
        from collision.broad_phase import candidate_pairs

        T, Fs_end = self.face_offsets[1], self.face_offsets[2]
        nf = len(self.faces)
        if nf == T or Fs_end == 0:
            return np.zeros((0, 2), dtype=np.int64)  # no targets (rigid/static) or no queries
        P = self.vertex_offsets[1]
        target_vertices = x[P:]  # rigid + static vertices
        target_faces = self.faces[T:] - P
        corners = x[self.faces[:Fs_end]]  # (Q, 3, 3) query triangles
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        nt = len(target_vertices)
        x0 = np.concatenate([target_vertices, lo])
        x1 = np.concatenate([target_vertices, hi])
        groups = np.concatenate([self.vertex_group[P:], self.face_group[:Fs_end]])
        vf, _ = candidate_pairs(
            x0,
            x1,
            target_faces,
            np.zeros((0, 2), dtype=np.int64),
            groups=groups,
            self_collision=False,
            static=self.group_static,
        )
        q = vf[:, 0] - nt
        keep = q >= 0  # pseudo-vertices only
        a, b = q[keep], vf[keep, 1] + T
        pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
        if len(pairs):
            pairs = np.unique(pairs, axis=0)
        return pairs.astype(np.int64)


def penetrations(model: Model, state: State | Mapping, tol: float = DEFAULT_TOL) -> tuple[int, float]:
    """``(count, max_depth [m])`` of the interpenetrations of ``state`` (see the module docstring).

    Builds a :class:`PenetrationChecker` each call; keep one to check many states of one model.

    Args:
        model: The model.
        state: A :class:`sim.model.State` or a mapping with ``particle_q`` / ``body_q`` arrays.
        tol: Margin [m] below which penetrations count as contact.
    """
    rep = PenetrationChecker(model, tol).check(state)
    return rep.count, rep.max_depth


class InitialPenetrationWarning(UserWarning):
    """A model whose rigid bodies start interpenetrating something (:func:`warn_initial_penetrations`)."""


def warn_initial_penetrations(model: Model, stacklevel: int = 3) -> int:
    """Warns (:class:`InitialPenetrationWarning`) when the model's initial state has rigid-body
    penetrations: a body's vertex inside another body, a static solid or below a ground plane,
    or crossing surfaces (:class:`PenetrationChecker`). Contacts only keep apart what starts
    apart, so such a start is almost always a placement mistake. Models without rigid bodies are
    not checked (the builder refuses overlapping spheres itself). Returns the count."""
    import warnings

    if "rigid" not in model.components:
        return 0
    report = PenetrationChecker(model).check(model.state())
    if report.count:
        warnings.warn(f"the model's initial state has {report.count} interpenetrations of rigid bodies "
                      f"({report.summary()}): contacts cannot separate bodies that start inside each other "
                      f"or inside a static mesh; move them apart", InitialPenetrationWarning, stacklevel=stacklevel)
    return int(report.count)

