"""Continuous-collision broad phase for triangle meshes moving linearly over one time step.

:func:`candidate_pairs` returns every vertex-face and edge-edge pair whose swept boxes come within
``inflation`` of each other, minus adjacent pairs, as the input of the narrow phase
(:mod:`collision.ccd`). :class:`BroadPhase` is the same query with the topology validated once, for
a simulation whose meshes keep their connectivity from step to step.

Definitions:

* The swept box of a primitive (vertex, edge, face) is the axis-aligned box of its vertices at the
  start (``x0``) and end (``x1``) of the step; it holds the primitive at every time of the step.
* A pair is a candidate when the two swept boxes, the first widened by ``inflation`` on every side,
  overlap (closed intervals: touching boxes count). Equivalently the per-axis gap between the boxes
  is at most ``inflation``; pass the narrow phase's thickness, since two primitives closer than
  ``d`` always have boxes within ``d`` on every axis.
* Excluded: a vertex and a face containing it; an edge and itself or an edge sharing a vertex.
* Bodies: ``groups[v]`` is the body of vertex ``v`` (every face and edge lies in one body). Pairs
  within one body are kept only where ``self_collision`` allows it; a ``static`` body never collides
  with itself nor with another static body.

Algorithm: faces and edges are sorted by body once (a stable permutation, kept internally; the
inputs, ``BroadPhase.faces`` / ``edges`` and the returned indices stay in the caller's numbering).
Each body with faces (edges) gets its own Warp BVH over its slice of the body-sorted face (edge)
boxes, built only if some body may collide with it. Every vertex queries the face BVH of each body
``h`` the body rules allow for its own body ``g``; an edge of body ``g`` queries the edge BVH of body
``h`` only if ``g <= h`` and the rules allow ``(g, h)``, so each pair of bodies is searched once, and
within one body (self-collision) only edges after it in the caller's order are kept. The query
primitives of forbidden bodies return before traversing: a body without self-collision never walks
its own dense neighbourhood, and two static bodies never meet. The trees are rebuilt every
``rebuild_every`` queries and refitted (same topology, new boxes) in between.

Conservative float32 boxes (Warp's BVH is float32): each float64 box coordinate ``c`` of a box whose
largest magnitude on that axis is ``m`` becomes ``fl32(c -/+ (m * 2^-21 + 2^-126))`` (lower bounds
move down, upper bounds up; clamped to +-FLT_MAX first). Rounding to float32 moves a number by at
most ``2^-24 m`` (``2^-149`` below FLT_MIN = 2^-126), so the float32 box contains the float64 box and
no pair is ever dropped; the factor-8 margin also covers the float64 inflation arithmetic and a
narrow phase evaluating ``x0 + t (x1 - x0)``. The price is a few extra candidates whose boxes are
within ``~4.8e-7`` relative of touching. See :mod:`kernels.broad_phase`.

Example:
    >>> import numpy as np
    >>> from collision.broad_phase import candidate_pairs
    >>> faces = np.array([[0, 1, 2]])
    >>> x0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1.0]])
    >>> x1 = x0.copy()
    >>> x1[3, 2] = -1.0                                   # the free vertex falls through the face
    >>> vf, ee = candidate_pairs(x0, x1, faces)
    >>> vf.tolist(), ee.tolist()
    ([[3, 0]], [])
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.buffers import RecordedLaunches, grown_capacity, host, upload, zero
from core.device import init_warp
from kernels import broad_phase as _k

__all__ = ["PAD_ABS", "PAD_REL", "BroadPhase", "candidate_pairs", "mesh_edges"]

PAD_REL = 2.0**-21
"""Relative float32 pad of every box coordinate (times the box's largest magnitude on that axis)."""
PAD_ABS = 2.0**-126
"""Absolute float32 pad (FLT_MIN), for coordinates near zero."""

_DEFAULT_DEVICE = "cpu"
_INT32_MAX = np.iinfo(np.int32).max
_INITIAL_PAIRS_PER_PRIMITIVE = 8
"""Starting capacity of the pair buffers (per query primitive); they grow on overflow."""


# ----------------------------------------------------------------------------------------------
# validation


def _positions(x, name: str) -> np.ndarray:
    arr = np.asarray(x)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name}: expected a numeric (V, 3) array of positions, got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise ValueError(f"{name}: positions must be real, got complex dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (V, 3), got {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=1))
        shown = ", ".join(f"{name}[{r}]={arr[r].tolist()}" for r in rows[:5])
        more = f" (and {len(rows) - 5} more)" if len(rows) > 5 else ""
        raise ValueError(f"{name}: positions must be finite; non-finite vertices: {shown}{more}")
    return arr


def _indices(a, name: str, width: int, what: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.size == 0 and arr.ndim <= 2:
        if arr.ndim == 2 and arr.shape[1] != width:
            raise ValueError(f"{name}: expected shape (N, {width}), got {arr.shape}")
        return np.zeros((0, width), dtype=np.int32)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected integer vertex indices, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(f"{name}: expected shape (N, {width}), got {arr.shape}")
    if arr.shape[0] > _INT32_MAX:
        raise ValueError(f"{name}: {arr.shape[0]} {what}s exceed the int32 index range")
    neg = np.argwhere(arr < 0)
    if len(neg):
        r, c = neg[0]
        raise ValueError(f"{name}: negative vertex index {arr[r, c]} at {name}[{r}, {c}]")
    rep = np.flatnonzero(np.any(np.diff(np.sort(arr, axis=1), axis=1) == 0, axis=1))
    if len(rep):
        r = rep[0]
        raise ValueError(f"{name}: {what} {r} repeats a vertex index: {arr[r].tolist()}")
    return arr


def _check_range(arr: np.ndarray, name: str, num_vertices: int) -> None:
    if arr.size and arr.max() >= num_vertices:
        r, c = np.argwhere(arr >= num_vertices)[0]
        raise ValueError(
            f"{name}: vertex index {arr[r, c]} at {name}[{r}, {c}] is out of range for {num_vertices} vertices"
        )


def _body_flags(value, name: str, num_bodies: int, default: bool) -> np.ndarray:
    """Per-body 0/1 flags from a bool (every body) or a sequence with one flag per body id."""
    if value is None:
        return np.full(num_bodies, int(default), dtype=np.int32)
    arr = np.asarray(value)
    if arr.ndim == 0:
        if arr.dtype != bool and not (np.issubdtype(arr.dtype, np.integer) and int(arr) in (0, 1)):
            raise ValueError(f"{name}: expected a bool or one bool per body, got {value!r}")
        return np.full(num_bodies, int(bool(arr)), dtype=np.int32)
    if arr.ndim != 1 or (arr.size and not (arr.dtype == bool or np.issubdtype(arr.dtype, np.integer))):
        raise ValueError(f"{name}: expected a bool or a 1-D sequence of bools (one per body id), got {value!r}")
    if arr.shape[0] < num_bodies:
        raise ValueError(
            f"{name}: expected one flag per body id (groups has {num_bodies} bodies), got {arr.shape[0]}"
        )
    return np.ascontiguousarray(arr[:num_bodies] != 0, dtype=np.int32)


def mesh_edges(faces) -> np.ndarray:
    """Unique undirected edges of a triangle mesh.

    Args:
        faces: (F, 3) non-negative integer vertex indices.

    Returns:
        int64 (E, 2) array, each row ``(i, j)`` with ``i < j``, rows sorted lexicographically.

    Raises:
        ValueError: ``faces`` not an (F, 3) integer array, negative or repeated indices.
    """
    f = _indices(faces, "faces", 3, "face").astype(np.int64, copy=False)
    if len(f) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    # unique on one int64 key per edge (lo * n + hi sorts like the rows; much faster than axis=0)
    n = int(f.max()) + 1
    keys = np.unique(e[:, 0] * n + e[:, 1])
    return np.stack([keys // n, keys % n], axis=1)


# ----------------------------------------------------------------------------------------------
# query


class BroadPhase:
    """Broad phase over fixed mesh topology; call :meth:`query` once per step.

    Args:
        faces: (F, 3) integer vertex indices.
        edges: (E, 2) integer vertex indices; ``None`` derives :func:`mesh_edges` of ``faces``.
        num_vertices: number of vertices ``V`` (rows of the positions passed to :meth:`query`).
        groups: (V,) non-negative integer body id per vertex; ``None`` puts every vertex in body 0.
            Every face and every edge must lie within one body.
        self_collision: ``True`` (every body may collide with itself), ``False`` (no body may), or
            one bool per body id (``len >= max(groups) + 1``, indexed by body id).
        static: ``None`` (no static body) or one bool per body id: static bodies never move, never
            collide with themselves (whatever ``self_collision`` says) nor with other static bodies.
        device: Warp device for the BVHs and kernels (default ``"cpu"``).
        rebuild_every: :meth:`query` rebuilds the BVHs on every ``rebuild_every``-th call and
            refits them (same tree, new boxes) in between; see its ``rebuild`` argument.

    Raises:
        ValueError: naming the offending argument (shapes, dtypes, negative or out-of-range indices,
            repeated indices within a face or edge, faces/edges spanning two bodies, flag lengths).
    """

    def __init__(
        self,
        faces,
        edges=None,
        *,
        num_vertices: int,
        groups=None,
        self_collision=True,
        static=None,
        device=None,
        rebuild_every: int = 16,
    ):
        init_warp()
        nv = int(num_vertices)
        if nv < 0 or nv > _INT32_MAX:
            raise ValueError(f"num_vertices: expected 0 <= num_vertices <= {_INT32_MAX}, got {num_vertices}")
        self.num_vertices = nv
        self.device = wp.get_device(device if device is not None else _DEFAULT_DEVICE)

        f = _indices(faces, "faces", 3, "face")
        _check_range(f, "faces", nv)
        if edges is None:
            e = mesh_edges(f)
        else:
            e = _indices(edges, "edges", 2, "edge")
            _check_range(e, "edges", nv)
        self.faces = np.ascontiguousarray(f, dtype=np.int32)
        self.edges = np.ascontiguousarray(e, dtype=np.int32)

        if groups is None:
            g = np.zeros(nv, dtype=np.int32)
        else:
            g = np.asarray(groups)
            if g.ndim != 1 or g.shape[0] != nv:
                raise ValueError(f"groups: expected shape ({nv},) (one body id per vertex), got {g.shape}")
            if g.size and not np.issubdtype(g.dtype, np.integer):
                raise ValueError(f"groups: expected integer body ids, got dtype {g.dtype}")
            if g.size and g.min() < 0:
                i = int(np.argmin(g))
                raise ValueError(f"groups: body ids must be non-negative, got groups[{i}]={g[i]}")
            if g.size and g.max() > _INT32_MAX:
                raise ValueError(f"groups: body ids must fit in int32, got {g.max()}")
            g = np.ascontiguousarray(g, dtype=np.int32)
        num_bodies = int(g.max()) + 1 if g.size else 1
        face_body = g[self.faces[:, 0]] if len(self.faces) else np.zeros(0, dtype=np.int32)
        edge_body = g[self.edges[:, 0]] if len(self.edges) else np.zeros(0, dtype=np.int32)
        for arr, body, what in ((self.faces, face_body, "face"), (self.edges, edge_body, "edge")):
            if len(arr):
                span = np.flatnonzero(np.any(g[arr] != body[:, None], axis=1))
                if len(span):
                    r = span[0]
                    raise ValueError(
                        f"groups: {what} {r} {arr[r].tolist()} spans bodies {sorted(set(g[arr[r]].tolist()))}; "
                        f"every {what} must lie within one body"
                    )
        self.groups = g
        self.num_bodies = num_bodies
        static_flags = _body_flags(static, "static", num_bodies, default=False)
        self_flags = _body_flags(self_collision, "self_collision", num_bodies, default=True)
        self_flags = self_flags & (1 - static_flags)  # a static body never collides with itself

        dev = self.device
        # Body-sorted copies (stable): the primitives of one body are contiguous, each body with
        # faces (edges) gets its own BVH over its slice of the sorted boxes, and the *_index arrays
        # map a sorted position back to the caller's numbering.
        vertex_order = np.argsort(g, kind="stable").astype(np.int32)
        face_order = np.argsort(face_body, kind="stable").astype(np.int32)
        edge_order = np.argsort(edge_body, kind="stable").astype(np.int32)
        face_body_s = np.ascontiguousarray(face_body[face_order], dtype=np.int32)
        edge_body_s = np.ascontiguousarray(edge_body[edge_order], dtype=np.int32)
        self._vertex_order = wp.array(vertex_order, dtype=wp.int32, device=dev)
        self._vertex_body = wp.array(g, dtype=wp.int32, device=dev)
        self._faces = wp.array(np.ascontiguousarray(self.faces[face_order]), dtype=wp.vec3i, device=dev)
        self._face_index = wp.array(face_order, dtype=wp.int32, device=dev)
        self._edges = wp.array(np.ascontiguousarray(self.edges[edge_order]), dtype=wp.vec2i, device=dev)
        self._edge_index = wp.array(edge_order, dtype=wp.int32, device=dev)
        self._edge_body = wp.array(edge_body_s, dtype=wp.int32, device=dev)
        self._self_ok = wp.array(self_flags, dtype=wp.int32, device=dev)
        self._static = wp.array(static_flags, dtype=wp.int32, device=dev)

        def may_collide(bodies: np.ndarray, tree: int) -> np.ndarray:
            """The body rule of ``kernels.broad_phase.bodies_may_collide`` for many query bodies."""
            other = (bodies != tree) & ~((static_flags[bodies] != 0) & (static_flags[tree] != 0))
            return other | ((bodies == tree) & (self_flags[tree] != 0))

        def plans(tree_sorted_body: np.ndarray, query_sorted_body: np.ndarray, lower_only: bool):
            """One ``(tree_body, leaf_start, leaf_end, query_start, query_count)`` per body whose
            tree some query primitive may pair with; the queries are the sorted range from the
            first to the last allowed query body (forbidden bodies inside it return early)."""
            out = []
            q_bodies, q_start, q_count = np.unique(query_sorted_body, return_index=True, return_counts=True)
            t_bodies, t_start, t_count = np.unique(tree_sorted_body, return_index=True, return_counts=True)
            for h, ts, tc in zip(t_bodies.tolist(), t_start.tolist(), t_count.tolist()):
                ok = may_collide(q_bodies, h)
                if lower_only:
                    ok &= q_bodies <= h
                    if tc < 2:  # a lone edge has no partner in its own body
                        ok &= q_bodies != h
                idx = np.flatnonzero(ok)
                if len(idx):
                    first, last = int(idx[0]), int(idx[-1])
                    qs = int(q_start[first])
                    out.append((h, ts, ts + tc, qs, int(q_start[last] + q_count[last]) - qs))
            return out

        vertex_body_s = g[vertex_order] if nv else np.zeros(0, dtype=np.int32)
        self._vf_plans = plans(face_body_s, vertex_body_s, lower_only=False)
        self._ee_plans = plans(edge_body_s, edge_body_s, lower_only=True)

        nf, ne = len(self.faces), len(self.edges)
        self._v_lo = wp.empty(nv, dtype=wp.vec3, device=dev)
        self._v_hi = wp.empty(nv, dtype=wp.vec3, device=dev)
        # face / edge boxes in body-sorted order; every body's BVH reads its contiguous slice (a view)
        self._f_lo = wp.empty(nf, dtype=wp.vec3, device=dev)
        self._f_hi = wp.empty(nf, dtype=wp.vec3, device=dev)
        self._e_lo = wp.empty(ne, dtype=wp.vec3, device=dev)
        self._e_hi = wp.empty(ne, dtype=wp.vec3, device=dev)
        self._eq_lo = wp.empty(ne, dtype=wp.vec3, device=dev)
        self._eq_hi = wp.empty(ne, dtype=wp.vec3, device=dev)
        self._xa = wp.empty(nv, dtype=wp.vec3d, device=dev)  # positions, copied in by every query
        self._xb = wp.empty(nv, dtype=wp.vec3d, device=dev)
        self._counter = wp.zeros(1, dtype=wp.int32, device=dev)
        self._launches = RecordedLaunches(dev)  # replayed launches: no per-query argument packing
        # output buffers grow on overflow and are kept for the next query
        self._vf_buf = wp.empty(_INITIAL_PAIRS_PER_PRIMITIVE * nv + 64, dtype=wp.vec2i, device=dev)
        self._ee_buf = wp.empty(_INITIAL_PAIRS_PER_PRIMITIVE * ne + 64, dtype=wp.vec2i, device=dev)
        self._face_bvhs: list[wp.Bvh] | None = None  # one per entry of _vf_plans
        self._edge_bvhs: list[wp.Bvh] | None = None  # one per entry of _ee_plans
        self._queries_since_build = 0
        self.query_count = 0  # queries so far (a cover of the buffers checks it is still the last)
        self.rebuild_every = int(rebuild_every)
        if self.rebuild_every < 1:
            raise ValueError(f"rebuild_every: expected a positive integer, got {rebuild_every!r}")
        # nothing can collide when no body may touch itself and at most one body is not static
        allowed = self_flags.any() or (num_bodies > 1 and (static_flags == 0).any())
        self._any_allowed = bool(allowed)

    def query(self, x0, x1, inflation: float = 0.0, *, rebuild: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Candidate pairs for vertices moving linearly from ``x0`` to ``x1``.

        Args:
            x0, x1: (V, 3) finite positions at the start and end of the step (float64).
            inflation: non-negative distance added around every query box (the contact thickness).
            rebuild: ``True`` rebuilds the BVHs from scratch, ``False`` refits the existing trees to
                the new boxes (builds them if there are none yet), ``None`` (default) rebuilds on
                every ``rebuild_every``-th query and refits otherwise. The pairs are the same
                either way; a refitted tree is only slower to query as the meshes deform.

        Returns:
            ``(vf, ee)``: int64 ``(K, 2)`` rows ``[vertex, face]`` and int64 ``(L, 2)`` rows
            ``[edge_a, edge_b]`` with ``edge_a < edge_b`` (indices into ``faces`` / ``edges``),
            both sorted lexicographically.
        """
        vf_buf, n_vf, ee_buf, n_ee = self.query_device(x0, x1, inflation, rebuild=rebuild)
        return _sorted_pairs(vf_buf, n_vf), _sorted_pairs(ee_buf, n_ee)

    def query_device(self, x0, x1, inflation: float = 0.0, *, rebuild: bool | None = None):
        """:meth:`query` with the pairs left on the device, unsorted (for a narrow phase that reads
        them there: no per-pair array crosses to the host).

        Returns:
            ``(vf, n_vf, ee, n_ee)``: Warp ``vec2i`` buffers whose first ``n_vf`` / ``n_ee`` rows
            are the pairs of :meth:`query` (in the order the kernels emitted them; deterministic
            on the CPU). The buffers are reused by the next query. The positions stay in
            :attr:`positions` until then.
        """
        a = _positions(x0, "x0")
        b = _positions(x1, "x1")
        if a.shape != b.shape:
            raise ValueError(f"x1: shape {b.shape} does not match x0 shape {a.shape}")
        if a.shape[0] != self.num_vertices:
            raise ValueError(f"x0: expected {self.num_vertices} vertices (the mesh's), got {a.shape[0]}")
        try:
            infl = float(inflation)
        except (TypeError, ValueError):
            raise ValueError(f"inflation: expected a non-negative finite number, got {inflation!r}") from None
        if not np.isfinite(infl) or infl < 0.0:
            raise ValueError(f"inflation: expected a non-negative finite number, got {inflation!r}")

        nv, nf, ne = self.num_vertices, len(self.faces), len(self.edges)
        self.query_count += 1  # the buffers are refilled: earlier results are gone
        if nv == 0 or not self._any_allowed:
            return self._vf_buf, 0, self._ee_buf, 0
        if rebuild is None:
            rebuild = self._queries_since_build >= self.rebuild_every
        if rebuild or self._face_bvhs is None or self._edge_bvhs is None:
            rebuild = True
            self._queries_since_build = 0
        self._queries_since_build += 1

        xa, xb = upload(self._xa, a), upload(self._xb, b)

        n_vf = 0
        if self._vf_plans:
            self._launches.launch("v_box", _k.vertex_boxes_kernel, nv, [xa, xb, infl, self._v_lo, self._v_hi])
            self._launches.launch("f_box", _k.face_boxes_kernel, nf, [xa, xb, self._faces, self._f_lo, self._f_hi])
            self._face_bvhs = self._fit(self._face_bvhs, self._vf_plans, self._f_lo, self._f_hi, rebuild)
            shared = [self._vertex_order, self._v_lo, self._v_hi, self._vertex_body, self._faces, self._face_index]
            launches = [
                (("vf", i), _k.vertex_face_pairs_kernel, qn, [bvh.id, h, ls, qs, *shared])
                for i, (bvh, (h, ls, _le, qs, qn)) in enumerate(zip(self._face_bvhs, self._vf_plans))
            ]
            self._vf_buf, n_vf = self._pairs(launches, self._vf_buf)
        elif self._face_bvhs is None:
            self._face_bvhs = []
        n_ee = 0
        if self._ee_plans:
            outputs = [self._e_lo, self._e_hi, self._eq_lo, self._eq_hi]
            self._launches.launch("e_box", _k.edge_boxes_kernel, ne, [xa, xb, self._edges, infl, *outputs])
            self._edge_bvhs = self._fit(self._edge_bvhs, self._ee_plans, self._e_lo, self._e_hi, rebuild)
            shared = [self._eq_lo, self._eq_hi, self._edges, self._edge_index, self._edge_body]
            launches = [
                (("ee", i), _k.edge_edge_pairs_kernel, qn, [bvh.id, h, ls, qs, *shared])
                for i, (bvh, (h, ls, _le, qs, qn)) in enumerate(zip(self._edge_bvhs, self._ee_plans))
            ]
            self._ee_buf, n_ee = self._pairs(launches, self._ee_buf)
        elif self._edge_bvhs is None:
            self._edge_bvhs = []
        return self._vf_buf, n_vf, self._ee_buf, n_ee

    @property
    def positions(self) -> tuple[wp.array, wp.array]:
        """The float64 positions (``x0``, ``x1``) of the last query, on the device."""
        return self._xa, self._xb

    @staticmethod
    def _fit(bvhs: list | None, plans: list, lo: wp.array, hi: wp.array, rebuild: bool) -> list:
        """Per-body BVHs over the slices ``lo[s:e]``, ``hi[s:e]`` of the plans: built when none
        exist yet, rebuilt in place when ``rebuild``, else refitted (each tree keeps its slice views, which share
        memory with ``lo`` / ``hi``, so a refit reads the boxes just written)."""
        if bvhs is None:
            return [wp.Bvh(lo[s:e], hi[s:e]) for (_h, s, e, _qs, _qn) in plans]
        for bvh in bvhs:
            if rebuild:
                bvh.rebuild()  # in place: the stepping loop allocates nothing
            else:
                bvh.refit()
        return bvhs

    def _pairs(self, launches: list, buf: wp.array) -> tuple[wp.array, int]:
        """The launches ``(key, kernel, dim, inputs)`` into ``buf`` through one shared counter; on
        overflow grow it (:func:`core.buffers.grown_capacity`) and launch them all again.

        Returns the buffer to keep and the number of pairs in it.
        """
        dev = self.device
        tail = [self._self_ok, self._static, self._counter]
        for _attempt in range(2):
            zero(self._counter)
            for key, kernel, dim, inputs in launches:
                self._launches.launch(key, kernel, dim, [*inputs, *tail, buf])
            total = int(host(self._counter)[0])
            if total < 0:
                raise RuntimeError("broad phase: more than 2^31 candidate pairs; reduce inflation")
            if total <= buf.shape[0]:
                break
            buf = wp.empty(grown_capacity(total, buf.shape[0], 64), dtype=wp.vec2i, device=dev)
        return buf, total


def _sorted_pairs(buf: wp.array, count: int) -> np.ndarray:
    """The first ``count`` rows of a pair buffer, int64, sorted lexicographically (grouped by query
    primitive and tree on the CPU, any order on a GPU: sorted for a deterministic result)."""
    if count == 0:
        return np.zeros((0, 2), dtype=np.int64)
    out = host(buf)[:count].astype(np.int64)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def candidate_pairs(
    x0,
    x1,
    faces,
    edges=None,
    *,
    groups=None,
    inflation: float = 0.0,
    self_collision=True,
    static=None,
    device=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertex-face and edge-edge candidate pairs of meshes moving linearly from ``x0`` to ``x1``.

    Args:
        x0, x1: (V, 3) finite float64 vertex positions at the start and end of the step.
        faces: (F, 3) integer vertex indices.
        edges: (E, 2) integer vertex indices; ``None`` derives the unique edges of ``faces``
            (:func:`mesh_edges`), and ``ee`` then indexes ``mesh_edges(faces)``.
        groups: (V,) non-negative integer body id per vertex (``None``: one body, id 0).
        inflation: non-negative; pairs whose swept boxes are within this distance on every axis
            are candidates (pass the narrow phase's thickness).
        self_collision: ``True`` / ``False`` for every body, or one bool per body id.
        static: ``None`` or one bool per body id; static bodies never collide with themselves or
            with each other.
        device: Warp device (default ``"cpu"``).

    Returns:
        ``(vf, ee)``: int64 ``(K, 2)`` ``[vertex, face]`` and int64 ``(L, 2)`` ``[edge_a, edge_b]``
        (``edge_a < edge_b``), sorted lexicographically. Adjacent pairs (a vertex of the face, edges
        sharing a vertex) are excluded. No pair whose float64 swept boxes overlap is ever missing
        (the float32 BVH boxes are padded outwards, see the module docstring).

    Raises:
        ValueError: naming the argument, for wrong shapes or dtypes, mismatched ``x0``/``x1``,
            non-finite positions, negative, repeated or out-of-range indices, faces or edges that
            span two bodies, per-body flag arrays shorter than the number of bodies, negative
            or non-finite inflation.
    """
    a = _positions(x0, "x0")
    b = _positions(x1, "x1")
    if a.shape != b.shape:
        raise ValueError(f"x1: shape {b.shape} does not match x0 shape {a.shape}")
    bp = BroadPhase(
        faces,
        edges,
        num_vertices=a.shape[0],
        groups=groups,
        self_collision=self_collision,
        static=static,
        device=device,
    )
    return bp.query(a, b, inflation)
