"""Batched continuous collision detection (narrow phase) over the kernels of :mod:`kernels.ccd`.

Argument order follows ipctk: vertex-face ``(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1,
t2_t1)`` and edge-edge ``(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1)``; each
argument is an (N, 3) array of positions [m] (a single (3,) point is accepted as N = 1). The
motion over the step is linear, ``x(t) = x_t0 + t (x_t1 - x_t0)`` with ``t`` in ``[0, 1]``.

:func:`narrow_phase`, :func:`point_triangle_ccd` and :func:`edge_edge_ccd` take
``precision="float32"`` (the same narrow phase and root solver generated in float32 by
:mod:`kernels.variants`; positions are rounded to float32 before the kernel, times returned as
float64), ``tolerance_scale`` (a multiplier on the error bounds of the cubic's coefficients and of
the distances that decide a hit; default 1) and the root solver's knobs ``max_iterations`` /
``tolerance`` (see :func:`collision.roots.solve_cubic`). The defaults run the original kernels.

Example:
    >>> import numpy as np
    >>> from collision.ccd import point_triangle_ccd
    >>> tri = [np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])]
    >>> hit, toi = point_triangle_ccd(np.array([[0.2, 0.2, 1.0]]), *tri, np.array([[0.2, 0.2, -1.0]]), *tri)
    >>> bool(hit[0]), float(toi[0])
    (True, 0.5)
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.buffers import RecordedLaunches, host, read_only, upload, zero
from collision.roots import DEFAULT_MAX_DERIVATIVE, DERIVATIVES, cubic_roots
from core.device import init_warp
from kernels import ccd as _k
from kernels import variants as _variants
from kernels.decide import pair_proximity_kernel

__all__ = ["CandidateNarrowPhase", "MeshCCDResult", "edge_edge_ccd", "edge_edge_roots", "mesh_ccd", "point_triangle_ccd", "point_triangle_roots"]

_DEVICE = "cpu"
_VF_NAMES = ("p_t0", "t0_t0", "t1_t0", "t2_t0", "p_t1", "t0_t1", "t1_t1", "t2_t1")
_EE_NAMES = ("ea0_t0", "ea1_t0", "eb0_t0", "eb1_t0", "ea0_t1", "ea1_t1", "eb0_t1", "eb1_t1")


def _stack(args, names) -> np.ndarray:
    """(N, 8, 3) float64 queries from eight (N, 3) arrays, with clear errors."""
    if len(args) != 8:
        raise TypeError(f"expected 8 position arrays ({', '.join(names)}), got {len(args)}")
    arrays = []
    n = None
    for name, a in zip(names, args):
        arr = np.asarray(a, dtype=np.float64) if not isinstance(a, np.ndarray) else a
        if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
            raise ValueError(f"{name}: expected real positions, got dtype {arr.dtype}")
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{name}: expected shape (N, 3), got {np.shape(a)}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f"{name}: has {arr.shape[0]} rows, but {names[0]} has {n}")
        bad = ~np.isfinite(arr)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(f"{name}: positions must be finite; {name}[{r}, {c}]={float(arr[r, c])!r} ({int(bad.sum())} bad entries)")
        arrays.append(arr)
    return np.ascontiguousarray(np.stack(arrays, axis=1))


_VARIANTS: dict = {}


def _ccd_kernels(precision, tolerance_scale, max_iterations, tolerance):
    """:mod:`kernels.ccd` for the defaults, else its generated variant (cached here)."""
    if precision == "float64" and tolerance_scale == 1.0 and max_iterations is None and tolerance is None:
        return _k
    key = (precision, tolerance_scale, max_iterations, tolerance,
           type(tolerance_scale), type(max_iterations), type(tolerance))  # True != 1 here
    mod = _VARIANTS.get(key)
    if mod is None:
        init_warp()
        mod = _variants.kernel_variant(precision, max_iterations=max_iterations, tolerance=tolerance,
                                       tolerance_scale=tolerance_scale).ccd
        _VARIANTS[key] = mod
    return mod


def _is_float32(k) -> bool:
    """Whether the narrow-phase kernels ``k`` (:func:`_ccd_kernels`) are a float32 variant."""
    return k is not _k and k.mat83d._wp_scalar_type_ is wp.float32


def _as_float32(values, name: str) -> np.ndarray:
    """``values`` (an array, contiguous, or a scalar) rounded to float32; a ValueError naming
    ``name`` if any overflows."""
    with np.errstate(over="ignore"):
        rounded = np.asarray(values, dtype=np.float32)
    if rounded.ndim:
        rounded = np.ascontiguousarray(rounded)
    if not np.isfinite(rounded).all():
        raise ValueError(f"{name} overflows float32 (precision='float32')")
    return rounded


def narrow_phase(kind: int, queries: np.ndarray, thickness: float = 0.0, *, precision: str = "float64",
                 tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Batched narrow phase on stacked queries.

    Args:
        kind: 0 vertex-face, 1 edge-edge.
        queries: (N, 8, 3) float64: the four points at the start (rows 0-3, ipctk's order) and at
            the end (rows 4-7) of the step.
        thickness: minimum separation [m] (>= 0).
        precision: ``"float64"`` or ``"float32"`` (queries and thickness rounded to float32, the
            whole narrow phase and its root solver computed in float32).
        tolerance_scale: multiplier (> 0) of the coefficient and distance error bounds
            (``COEFFICIENT_ERROR_FACTOR``, ``DISTANCE_ERROR_FACTOR``): below 1 tighter (fewer
            false positives, false negatives possible), above 1 looser.
        max_iterations, tolerance: the root solver's Newton-bisection cap and relative step
            tolerance (None: 256 and 2 ulp of the precision).

    Returns:
        (hit: bool (N,), toi: float64 (N,) fraction of the step, inf where no hit, source: int32
        (N,) where the time came from: 0 start, 1-3 cubic root slot, 4 collinear, 5 advancement,
        -1 none).

    Raises:
        ValueError: a bad thickness or knob (named), or (float32) positions that overflow float32.
    """
    k = _ccd_kernels(precision, tolerance_scale, max_iterations, tolerance)
    t = float(thickness)
    if not np.isfinite(t) or t < 0.0:
        raise ValueError(f"thickness must be finite and >= 0, got {thickness!r}")
    init_warp()
    n = queries.shape[0]
    hit = np.zeros(n, dtype=np.int32)
    toi = np.full(n, np.inf)
    source = np.full(n, -1, dtype=np.int32)
    scalar, real = wp.float64, np.float64
    if _is_float32(k):
        scalar, real = wp.float32, np.float32
        queries = _as_float32(queries, "queries")
        _as_float32(t, "thickness")
        toi = np.full(n, np.inf, dtype=np.float32)
    if n:
        wp.launch(
            k.ccd_kernel,
            dim=n,
            inputs=[kind, wp.array(queries, dtype=k.mat83d, device=_DEVICE, copy=False), scalar(t)],
            outputs=[
                wp.array(hit, dtype=wp.int32, device=_DEVICE, copy=False),
                wp.array(toi, dtype=scalar, device=_DEVICE, copy=False),
                wp.array(source, dtype=wp.int32, device=_DEVICE, copy=False),
            ],
            device=_DEVICE,
        )
        wp.synchronize_device(_DEVICE)
    if real is np.float32:
        toi = toi.astype(np.float64)
    return hit.astype(bool), toi, source

# no hit (shared, read only): _collect's (kind, pair, order), CandidateNarrowPhase.ccd's (kind,
# pair, time, source, vertices)
_NONE = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64))
_NO_CCD_HITS = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64), np.zeros(0),
                         np.zeros(0, dtype=np.int64), np.zeros((0, 4), dtype=np.int64))
ONES3 = read_only(np.ones(3))[0]
"""Row sums of (N, 3) arrays as a product ``a @ ONES3`` (``einsum`` parses its subscripts on every call)."""


def _same_bytes(a, b: np.ndarray) -> bool:
    """Whether ``a`` holds exactly the float64 values of ``b`` (bit for bit: the same input)."""
    a = np.asarray(a, dtype=np.float64)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


class CandidateNarrowPhase:
    """The narrow phase (and the proximity test) of a mesh's broad-phase candidate pairs, run
    where the broad phase left them (:meth:`collision.broad_phase.BroadPhase.query_device`): one
    kernel launch over both pair kinds reads the pairs and the positions on the device and
    appends only the hits (with their kind), so the per-pair arrays never cross to the host. The results equal
    :func:`narrow_phase` on the same pairs, in the sorted order of
    :meth:`~collision.broad_phase.BroadPhase.query`.

    A collision response that runs several rounds per step can share one broad-phase query
    between them: :meth:`cover` queries the swept boxes from the start positions to the
    predicted end positions (optionally continued further along each vertex's motion, so that
    later substeps of steady motion stay inside), widened by a margin ``m``; a later
    :meth:`near` with ``max_distance = d <= m`` (every position within ``(m - d) / 2``, per coordinate, of the box of its
    vertex's covered motion) or :meth:`ccd` with thickness ``t`` (start and end positions
    within ``(m - t) / 2`` of those boxes; ``COVER_SAFETY`` instead of 1/2 in both) reuses those
    candidates, which then hold every pair the query of its own would have found (a
    primitive's swept box grows by at most how far its vertices' ends lie outside their covered
    boxes, and a pair's two boxes by twice that), as long as no other query
    of the broad phase has refilled its buffers since. Anything else queries afresh (and drops
    the cover). The hits are the same either way.

    Args:
        broad_phase: the :class:`collision.broad_phase.BroadPhase` of the mesh (its ``faces``
            and ``edges`` number the pairs; its device is used).
        precision, tolerance_scale, max_iterations, tolerance: the narrow phase's knobs, as
            :func:`narrow_phase`'s (defaults: the float64 kernels as written). A non-default
            setting runs a generated variant (:mod:`kernels.variants`, forward-only): these
            decide contacts, off any tape. With ``"float32"`` the positions of each :meth:`ccd`
            are rounded to float32 on the host and the whole narrow phase and its root solver
            run in float32; :meth:`near` (the proximity test) stays float64.
    """

    COVER_SAFETY = 0.45
    """An end position may move this fraction of ``m - t`` (not the full half) from the covered
    one: room for the rounding of the boxes' float64 arithmetic (the broad phase pads its
    float32 boxes for its own rounding only)."""

    def __init__(self, broad_phase, *, precision: str = "float64", tolerance_scale: float = 1.0,
                 max_iterations=None, tolerance=None) -> None:
        init_warp()
        self.settings = _variants.check_settings(precision, max_iterations, tolerance, tolerance_scale)
        self._kernels = _ccd_kernels(precision, tolerance_scale, max_iterations, tolerance)
        if self._kernels is not _k:
            # a generated variant compiles here, not at the first contact of a run (which would
            # put seconds of compilation into a timed step)
            wp.load_module(self._kernels.pair_ccd_kernel.module, device=broad_phase.device)
        self._float32 = _is_float32(self._kernels)
        self._real = wp.float32 if self._float32 else wp.float64
        self.broad_phase = broad_phase
        dev = self.device = broad_phase.device
        self._faces = wp.array(np.ascontiguousarray(broad_phase.faces, dtype=np.int32).reshape(-1, 3),
                               dtype=wp.vec3i, device=dev)
        self._edges = wp.array(np.ascontiguousarray(broad_phase.edges, dtype=np.int32).reshape(-1, 2),
                               dtype=wp.vec2i, device=dev)
        self._counter = wp.zeros(1, dtype=wp.int32, device=dev)
        self._pairs = wp.empty(0, dtype=wp.vec2i, device=dev)
        self._kind = wp.empty(0, dtype=wp.int32, device=dev)
        self._time = wp.empty(0, dtype=self._real, device=dev)
        self._source = wp.empty(0, dtype=wp.int32, device=dev)
        self._offset = wp.empty(0, dtype=wp.vec3d, device=dev)
        self._weights = wp.empty(0, dtype=wp.vec4d, device=dev)
        self._vertices = wp.empty(0, dtype=wp.vec4i, device=dev)
        n = broad_phase.num_vertices
        self._x0 = wp.empty(n, dtype=wp.vec3d, device=dev)
        self._x1 = wp.empty(n, dtype=wp.vec3d, device=dev)
        if self._float32:  # the float32 narrow phase's rounded positions
            self._x0_32 = wp.empty(n, dtype=wp.vec3f, device=dev)
            self._x1_32 = wp.empty(n, dtype=wp.vec3f, device=dev)
        self._cover = None  # (buffers, box lo, box hi, margin, broad-phase query count, scratch) of the last cover()
        # the pairs that a CCD from near()'s positions can hit (see near's motion_radius), per kind
        self._reach_pairs = [wp.empty(0, dtype=wp.vec2i, device=dev) for _ in range(2)]
        self._reach_counter = wp.zeros(2, dtype=wp.int32, device=dev)
        self._radius = wp.empty(n, dtype=wp.float64, device=dev)
        self._no_radius = wp.empty(0, dtype=wp.float64, device=dev)
        self._reach = None  # (cover, positions, radii, buffers) of the last near() with motion radii
        self._x0_holds_reach = False  # whether the start buffer still holds those positions
        self._launches = RecordedLaunches(dev)  # replayed launches: no per-call argument packing
        self.queries = 0  # broad-phase queries run (for benchmarks)
        self.reuses = 0  # calls answered from a cover
        self.kept_covers = 0  # cover() calls that kept the current cover (its slack)
        self.reach_calls = 0  # ccd() calls that tested only the pairs near() kept for them
        self.tested = 0  # candidate pairs that ccd() tested (for benchmarks)

    def cover(self, x0, x1, margin: float, slack: float = 0.0, ahead: float = 0.0, ahead_limit: float = 0.0) -> None:
        """One broad-phase query of the motion ``x0 -> x1`` ((V, 3) float64) widened by
        ``margin`` [m] (>= 0), kept for the calls that it covers (see the class docstring).

        ``slack`` [m] (>= 0, below ``COVER_SAFETY margin``): keep the current cover instead when
        it has this margin, its buffers are still the broad phase's and both ends of every
        vertex's new motion lie within ``slack`` (per coordinate) of the box of its covered
        motion (:attr:`kept_covers` counts these). Resting contact moves far less than a margin
        per substep, so one query then serves many substeps; the calls it answers still check
        their own motion against the covered one, so the hits are the same as with a fresh
        cover.

        ``ahead`` (>= 0) and ``ahead_limit`` [m] (>= 0; both > 0 to act): the fresh query covers
        each vertex's motion continued past ``x1`` by ``ahead`` times itself, at most
        ``ahead_limit`` per coordinate, so that the next substeps of steady motion stay inside
        the kept cover."""
        x0 = np.asarray(x0, dtype=np.float64)
        x1 = np.asarray(x1, dtype=np.float64)
        c = self._cover
        if slack > 0.0 and c is not None and c[3] == float(margin) and c[4] == self.broad_phase.query_count \
                and c[1].shape == x0.shape == x1.shape and self._outside(x0, x1, c) <= slack:
            self.kept_covers += 1
            return
        if ahead > 0.0 and ahead_limit > 0.0:  # the query covers the motion continued past x1
            x1 = x1 + np.clip(float(ahead) * (x1 - x0), -float(ahead_limit), float(ahead_limit))
        buffers = self.broad_phase.query_device(x0, x1, float(margin))
        self.queries += 1
        # the covered motion's vertex boxes (and scratch for _outside)
        self._cover = (buffers, np.minimum(x0, x1), np.maximum(x0, x1), float(margin), self.broad_phase.query_count,
                       np.empty((3,) + x0.shape))

    def covered_candidates(self) -> int:
        """Candidate pairs of the current cover (0 without one)."""
        c = self._cover
        return 0 if c is None else c[0][1] + c[0][3]

    @staticmethod
    def _outside(x0, x1, cover) -> float:
        """How far (largest coordinate) the ends ``x0``, ``x1`` of the vertices' motion lie
        outside the boxes of their covered motion (0 inside; exact: a covered end gives 0)."""
        lo, hi, scratch = cover[1], cover[2], cover[5]
        if not len(x0):
            return 0.0
        if x1 is x0:
            low = high = x0
        else:
            # lo - min(x0, x1) is max(lo - x0, lo - x1) exactly (rounding is monotone); NaN stays
            low, high = np.minimum(x0, x1, out=scratch[0]), np.maximum(x0, x1, out=scratch[1])
        out = 0.0
        for gap in (np.subtract(lo, low, out=scratch[2]).max(), np.subtract(high, hi, out=scratch[2]).max()):
            if not gap <= out:  # NaN is never covered: the fresh query refuses it
                out = float(gap) if gap == gap else np.inf
        return out

    def _candidates(self, x0, x1, inflation: float, end_moves: bool):
        """Candidate buffers and the device positions (start, end) for the motion ``x0 -> x1``
        and the inflation: from the cover when it holds them, else a fresh query."""
        c = self._cover
        # a pair within `inflation` at the new motion is within inflation + 2 x (how far an end
        # lies outside its vertex's covered box) at the covered one (a primitive's swept box is
        # its vertices' boxes' hull, so it grows by at most that on each side); and nobody else
        # may have refilled the broad phase's buffers
        if c is not None and inflation <= c[3] and c[4] == self.broad_phase.query_count \
                and np.shape(x0) == c[1].shape and np.shape(x1) == c[1].shape:
            if self._outside(x0, x1 if end_moves else x0, c) <= self.COVER_SAFETY * (c[3] - inflation):
                self.reuses += 1
                self._x0_holds_reach = False
                return c[0], upload(self._x0, x0), upload(self._x1, x1) if end_moves else self._x1
        self._cover = None  # the fresh query overwrites the broad phase's buffers
        self.queries += 1
        buffers = self.broad_phase.query_device(x0, x1, inflation)
        xa, xb = self.broad_phase.positions
        return buffers, xa, xb

    def _reserve(self, n: int) -> None:
        if self._pairs.shape[0] < n:
            n = max(n, 2 * self._pairs.shape[0], 64)
            dev = self.device
            self._pairs = wp.empty(n, dtype=wp.vec2i, device=dev)
            self._kind = wp.empty(n, dtype=wp.int32, device=dev)
            self._time = wp.empty(n, dtype=self._real, device=dev)
            self._source = wp.empty(n, dtype=wp.int32, device=dev)
            self._offset = wp.empty(n, dtype=wp.vec3d, device=dev)
            self._weights = wp.empty(n, dtype=wp.vec4d, device=dev)
            self._vertices = wp.empty(n, dtype=wp.vec4i, device=dev)

    def _run(self, buffers, launch) -> int:
        """Runs ``launch(vf, n_vf, ee, n_ee)`` once for both kinds' candidates (it appends the
        hits and their kinds to the output buffers through the counter) and returns the number
        of hits (unsorted, on the device: :attr:`hits`)."""
        vf, n_vf, ee, n_ee = buffers
        self._reserve(n_vf + n_ee)
        zero(self._counter)
        if n_vf + n_ee:
            launch(vf, n_vf, ee, n_ee)
        return int(host(self._counter)[0])

    def _sorted(self, total: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(kind (K,), pair (K, 2) int64, row order (K,)) of the ``total`` hits of the last call,
        sorted by kind, then lexicographically by pair (the order of ``BroadPhase.query``)."""
        if total == 0:
            return _NONE
        kind = host(self._kind)[:total].astype(np.int64)
        pair = host(self._pairs)[:total].astype(np.int64)
        order = np.lexsort((pair[:, 1], pair[:, 0], kind))
        return kind[order], pair[order], order

    @property
    def hits(self) -> dict:
        """The device buffers of the last :meth:`ccd_count` / :meth:`near_count` hits, in the
        kernel's order (first ``count`` rows): ``kind``, ``pairs``, ``vertices``, and ``time``
        (of the precision's float type) and ``source`` (CCD), or ``offset`` and ``weights``
        (proximity)."""
        return {"kind": self._kind, "pairs": self._pairs, "vertices": self._vertices, "time": self._time,
                "source": self._source, "offset": self._offset, "weights": self._weights}

    def ccd(self, x0, x1, thickness: float = 0.0):
        """Hits of the vertices moving linearly from ``x0`` to ``x1`` ((V, 3) float64), on the
        host (:meth:`ccd_count` leaves them on the device).

        After :meth:`near` at ``x0`` with motion radii, a zero-thickness call whose every vertex
        moves at most its radius tests only the pairs that near kept for it (same hits).

        Returns:
            (kind (K,) int64: 0 vertex-face, 1 edge-edge; pair (K, 2) int64 ``[vertex, face]`` /
            ``[edge_a, edge_b]``; time of impact (K,) as a fraction of the step; source (K,)
            int64, as :func:`narrow_phase`'s; vertices (K, 4) int64: the pairs' vertex indices,
            vertex-face ``(p, a, b, c)`` / edge-edge ``(a0, a1, b0, b1)``), hits only.
        """
        kind, pair, order = self._sorted(self.ccd_count(x0, x1, thickness))
        n = len(kind)
        if n == 0:
            return _NO_CCD_HITS
        toi = host(self._time)[:n][order].astype(np.float64)
        return (kind, pair, toi, host(self._source)[:n][order].astype(np.int64),
                host(self._vertices)[:n][order].astype(np.int64))

    def ccd_count(self, x0, x1, thickness: float = 0.0) -> int:
        """:meth:`ccd`'s hits left on the device (:attr:`hits`, the kernel's order); returns
        their number."""
        t = float(thickness)
        if not np.isfinite(t) or t < 0.0:
            raise ValueError(f"thickness must be finite and >= 0, got {thickness!r}")
        r = self._reach
        c = self._cover
        # from the positions of the last near() with motion radii, in the cover it used
        from_near = r is not None and t == 0.0 and c is r[0] and c[4] == self.broad_phase.query_count \
            and np.shape(x1) == c[1].shape and _same_bytes(x0, r[1])
        if from_near and self._x0_holds_reach and self._outside(x1, x1, c) <= self.COVER_SAFETY * c[3]:
            # the start was covered there with less room and is on the device already: only the
            # end is checked and uploaded (_candidates' cover test otherwise)
            self.reuses += 1
            buffers, xa, xb = c[0], self._x0, upload(self._x1, x1)
        else:
            buffers, xa, xb = self._candidates(x0, x1, t, end_moves=True)  # pairs within t are candidates
        if from_near and self._cover is r[0] and buffers is r[0][0]:
            step = np.subtract(x1, x0)
            if (np.square(step) @ ONES3 <= r[2]).all():
                buffers = r[3]
                self.reach_calls += 1
        self.tested += buffers[1] + buffers[3]
        if self._float32:
            xa, xb = upload(self._x0_32, _as_float32(x0, "x0")), upload(self._x1_32, _as_float32(x1, "x1"))
            t = float(_as_float32(t, "thickness"))

        def launch(vf, n_vf, ee, n_ee):
            self._launches.launch("ccd", self._kernels.pair_ccd_kernel, n_vf + n_ee,
                                  [n_vf, vf, ee, xa, xb, self._faces, self._edges, t,
                                   self._counter, self._pairs, self._kind, self._time, self._source,
                                   self._vertices])

        return self._run(buffers, launch)

    def near(self, x, max_distance: float, motion_radius=None):
        """Pairs of primitives at most ``max_distance`` [m] apart at positions ``x`` ((V, 3)).

        ``motion_radius`` ((V,) [m], optional): also keep, for later :meth:`ccd` calls from ``x``
        at thickness 0 in which every vertex moves at most its radius, the candidates they can
        hit (:func:`kernels.decide.pair_proximity_kernel`), so that those calls test only them.
        A collision response's rounds move the vertices about as predicted; most candidates of
        resting contact lie farther apart than that. Default narrow phase only (a variant's
        tolerances may reach further) and only when the cover answers this call.

        Returns:
            (kind (K,), pair (K, 2), offset (K, 3): closest point of the first primitive minus
            the second's, weights (K, 4): the closest points' signed weights, side A positive,
            side B negative (:func:`kernels.contact_geometry.pair_weights`), vertices (K, 4) int64: the
            pairs' vertex indices, vertex-face ``(p, a, b, c)`` / edge-edge ``(a0, a1, b0,
            b1)``). Without a pair the arrays are shared read-only empties.
        """
        kind, pair, order = self._sorted(self.near_count(x, max_distance, motion_radius))
        n = len(kind)
        return (kind, pair, host(self._offset)[:n][order], host(self._weights)[:n][order],
                host(self._vertices)[:n][order].astype(np.int64))

    def near_count(self, x, max_distance: float, motion_radius=None) -> int:
        """:meth:`near`'s pairs left on the device (:attr:`hits`, the kernel's order); returns
        their number."""
        self._reach = None
        max_distance = float(max_distance)
        if not (np.isfinite(max_distance) and max_distance >= 0.0):
            raise ValueError(f"max_distance: expected a finite distance >= 0, got {max_distance!r}")
        if motion_radius is not None:
            motion_radius = np.asarray(motion_radius, dtype=np.float64)
            if motion_radius.shape != (self._radius.shape[0],):
                raise ValueError(f"motion_radius: expected shape ({self._radius.shape[0]},), got {motion_radius.shape}")
            # NaN fails the first comparison, inf the second
            if len(motion_radius) and not (motion_radius.min() >= 0.0 and np.isfinite(motion_radius.max())):
                raise ValueError("motion_radius: radii must be finite and >= 0")
        buffers, xa, _ = self._candidates(x, x, max_distance, end_moves=False)
        radius = self._no_radius
        if motion_radius is not None and self._kernels is _k and self._cover is not None \
                and buffers is self._cover[0]:
            radius = upload(self._radius, motion_radius)
            zero(self._reach_counter)
            for kind in (0, 1):
                n = buffers[2 * kind + 1]
                if self._reach_pairs[kind].shape[0] < n:
                    self._reach_pairs[kind] = wp.empty(max(n, 2 * self._reach_pairs[kind].shape[0], 64),
                                                       dtype=wp.vec2i, device=self.device)

        def launch(vf, n_vf, ee, n_ee):
            self._launches.launch("near", pair_proximity_kernel, n_vf + n_ee,
                                  [n_vf, vf, ee, xa, self._faces, self._edges, max_distance,
                                   self._counter, self._pairs, self._kind, self._offset, self._weights,
                                   self._vertices, radius, self._reach_counter, self._reach_pairs[0], self._reach_pairs[1]])

        total = self._run(buffers, launch)
        if radius is not self._no_radius:
            self._x0_holds_reach = True  # the cover path of _candidates uploaded x there
            counts = host(self._reach_counter)
            self._reach = (self._cover, np.array(x, dtype=np.float64), np.square(motion_radius),
                           (self._reach_pairs[0], int(counts[0]), self._reach_pairs[1], int(counts[1])))
        return total


def point_triangle_ccd(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1, thickness: float = 0.0, *,
                       precision: str = "float64", tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Does the vertex hit the triangle during the step, and when first?

    Args:
        p_t0, t0_t0, t1_t0, t2_t0: vertex and triangle corners at the start [m], each (N, 3).
        p_t1, t0_t1, t1_t1, t2_t1: the same at the end of the step [m].
        thickness: minimum separation [m] (>= 0); contact when the distance reaches it.
        precision, tolerance_scale, max_iterations, tolerance: see :func:`narrow_phase`
            (defaults: the float64 kernels as written).

    Returns:
        (hit: bool (N,), toi: float64 (N,) earliest time of impact in [0, 1], ``inf`` where no hit).

    Raises:
        ValueError: wrong shapes, mismatched lengths, non-finite positions, a bad thickness or
            knob (named).
    """
    queries = _stack((p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1), _VF_NAMES)
    hit, toi, _ = narrow_phase(0, queries, thickness, precision=precision, tolerance_scale=tolerance_scale,
                               max_iterations=max_iterations, tolerance=tolerance)
    return hit, toi


def edge_edge_ccd(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, thickness: float = 0.0, *,
                  precision: str = "float64", tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Do the two edges hit during the step, and when first?

    Args:
        ea0_t0, ea1_t0, eb0_t0, eb1_t0: endpoints of edges a and b at the start [m], each (N, 3).
        ea0_t1, ea1_t1, eb0_t1, eb1_t1: the same at the end of the step [m].
        thickness: minimum separation [m] (>= 0).
        precision, tolerance_scale, max_iterations, tolerance: see :func:`narrow_phase`.

    Returns:
        (hit: bool (N,), toi: float64 (N,) in [0, 1], ``inf`` where no hit).
    """
    queries = _stack((ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1), _EE_NAMES)
    hit, toi, _ = narrow_phase(1, queries, thickness, precision=precision, tolerance_scale=tolerance_scale,
                               max_iterations=max_iterations, tolerance=tolerance)
    return hit, toi


def _roots(kind: int, queries: np.ndarray, max_derivative: float):
    init_warp()
    hit, toi, source = narrow_phase(kind, queries, 0.0)
    n = queries.shape[0]
    roots = np.zeros((n, 6))
    out_toi = np.zeros(n)
    if n:
        wp.launch(
            _k.ccd_time_of_impact_kernel,
            dim=n,
            inputs=[
                wp.array(queries, dtype=_k.mat83d, device=_DEVICE, copy=False),
                wp.array(source, dtype=wp.int32, device=_DEVICE, copy=False),
                wp.array(np.where(hit, toi, np.inf), dtype=wp.float64, device=_DEVICE),
                wp.float64(max_derivative),
            ],
            outputs=[
                wp.array(out_toi, dtype=wp.float64, device=_DEVICE, copy=False),
                wp.array(roots, dtype=_k.vec6d, device=_DEVICE, copy=False),
            ],
            device=_DEVICE,
        )
        wp.synchronize_device(_DEVICE)
    return roots.reshape(n, 6).view(np.complex128)


def point_triangle_roots(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1, max_derivative: float = DEFAULT_MAX_DERIVATIVE):
    """All three (complex) roots of each query's coplanarity cubic, slots (t-, tM, t+).

    The "lifted" event: when the vertex misses, the roots it would need are complex, and an
    optimiser can aim at them (their derivatives come from :mod:`kernels.roots`).
    """
    queries = _stack((p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1), _VF_NAMES)
    return _roots(0, queries, max_derivative)


def edge_edge_roots(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, max_derivative: float = DEFAULT_MAX_DERIVATIVE):
    """All three (complex) roots of each edge-edge query's coplanarity cubic."""
    queries = _stack((ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1), _EE_NAMES)
    return _roots(1, queries, max_derivative)


def _taped_query_function(kernel, out_dtype, out_shape):
    """A torch.autograd.Function over Warp ``kernel(queries (N, 8, 3), *scalars) -> out (N,)``:
    forward runs it under a ``wp.Tape``, backward replays the tape (the kernels' custom adjoints,
    e.g. the mollified root derivative). ``out_shape``: the torch shape of one output row."""
    import torch

    class Function(torch.autograd.Function):
        @staticmethod
        def forward(ctx, queries, *scalars):
            init_warp()
            n = queries.shape[0]
            q = wp.array(queries.detach().cpu().numpy().reshape(n, 8, 3), dtype=_k.mat83d, device=_DEVICE,
                         requires_grad=True)
            out = wp.zeros(n, dtype=out_dtype, device=_DEVICE, requires_grad=True)
            tape = wp.Tape()
            with tape:
                wp.launch(kernel, dim=n, inputs=[q, *(wp.float64(x) for x in scalars)], outputs=[out],
                          device=_DEVICE)
            ctx.tape, ctx.q, ctx.out, ctx.device = tape, q, out, queries.device
            return torch.from_numpy(out.numpy().reshape((n, *out_shape)).copy()).to(queries.device)

        @staticmethod
        def backward(ctx, grad):
            n = ctx.q.shape[0]
            ctx.out.grad.assign(wp.array(grad.detach().cpu().numpy().reshape(n, -1).astype(np.float64),
                                         dtype=out_dtype, device=_DEVICE))
            ctx.tape.backward()
            result = torch.from_numpy(ctx.q.grad.numpy().reshape(n, 8, 3).copy()).to(ctx.device)
            ctx.tape.zero()
            return (result, *([None] * (len(ctx.needs_input_grad) - 1)))

    return Function


class _CoplanarityRoots:
    """The torch functions of the coplanarity cubic (built lazily: torch stays optional for the
    numpy API): its three roots with the kernels' mollified adjoint, and its unit-scaled
    coefficients (for a root derivative chosen outside the kernels)."""

    function = None
    coefficients_function = None

    @classmethod
    def get(cls):
        if cls.function is None:
            cls.function = _taped_query_function(_k.coplanarity_roots_kernel, _k.vec6d, (3, 2))
        return cls.function

    @classmethod
    def get_coefficients(cls):
        if cls.coefficients_function is None:
            cls.coefficients_function = _taped_query_function(_k.coplanarity_coefficients_kernel, wp.vec4d, (4,))
        return cls.coefficients_function


def coplanarity_roots(x_start, x_end, max_derivative: float = DEFAULT_MAX_DERIVATIVE, derivative: str = "mollified"):
    """Torch: the lifted events of vertex-face or edge-edge pairs moving linearly over a step.

    The roots (real or complex) of the coplanarity cubic of the four points' straight paths
    ``x(s) = x_start + s (x_end - x_start)``, ``s`` the fraction of the step: a hit is a real root
    in [0, 1] with the point inside the triangle (edges overlapping); a miss has the wanted root
    complex or outside. Backward is the mollified implicit derivative (:mod:`kernels.roots`,
    bounded by ``max_derivative`` for the cubic scaled to a largest coefficient of 1), so a loss
    on a complex root has a finite gradient that pulls it onto the real axis.

    Args:
        x_start, x_end: torch float64 (N, 4, 3) [m]: vertex, triangle corners (vertex-face) or
            the two edges' endpoints (edge-edge), at the start and the end of the step.
        max_derivative: the robust-division bound ``M`` (> 0).
        derivative: "mollified" (the kernels' robust division) or "orthogonal" (real roots: the
            exact derivative with only its part along the merging direction clamped to ``M``,
            eq. ``orthogonal_clamping_real_side``; :func:`collision.roots.orthogonal_clamped_jacobian`).

    Returns:
        torch float64 (N, 3, 2): slots (t-, tM, t+) of design.md, (Re, Im), in fractions of the step.

    Raises:
        ValueError: not float64 tensors of matching (N, 4, 3) shape, or non-finite positions.
    """
    import torch

    for name, x in (("x_start", x_start), ("x_end", x_end)):
        if not isinstance(x, torch.Tensor) or x.dtype != torch.float64:
            raise ValueError(f"{name} must be a float64 torch tensor of shape (N, 4, 3)")
        if x.ndim != 3 or tuple(x.shape[1:]) != (4, 3):
            raise ValueError(f"{name} must have shape (N, 4, 3), got {tuple(x.shape)}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} must be finite (it holds NaN or inf)")
    if x_start.shape != x_end.shape:
        raise ValueError(f"x_start and x_end must have the same shape, got {tuple(x_start.shape)} and {tuple(x_end.shape)}")
    if not float(max_derivative) > 0.0:
        raise ValueError(f"max_derivative must be positive, got {max_derivative!r}")
    if derivative not in DERIVATIVES:
        raise ValueError(f"derivative must be one of {DERIVATIVES}, got {derivative!r}")
    queries = torch.cat([x_start, x_end], dim=1)
    if queries.shape[0] == 0:
        return torch.zeros((0, 3, 2), dtype=torch.float64, device=queries.device)
    if derivative == "orthogonal":
        coefficients = _CoplanarityRoots.get_coefficients().apply(queries)
        return cubic_roots(coefficients, float(_k.CCD_T_MAX), float(max_derivative), derivative="orthogonal")
    return _CoplanarityRoots.get().apply(queries, float(max_derivative))


# ---------------------------------------------------------------------------------------------
# meshes: broad phase + narrow phase
# ---------------------------------------------------------------------------------------------


class MeshCCDResult:
    """Contacts of one step of triangle meshes (all arrays are numpy).

    Attributes:
        vf: (K, 2) int64 candidate [vertex, face] pairs from the broad phase.
        vf_hit, vf_toi: (K,) their narrow-phase results (toi ``inf`` where no hit).
        ee: (L, 2) int64 candidate [edge_a, edge_b] pairs (indices into ``edges``).
        ee_hit, ee_toi: (L,) their results.
        edges: (E, 2) the edge list the ``ee`` indices refer to.
        time_of_impact: earliest time of impact over all pairs in [0, 1] (``inf`` if none).
    """

    def __init__(self, vf, vf_hit, vf_toi, ee, ee_hit, ee_toi, edges):
        self.vf, self.vf_hit, self.vf_toi = vf, vf_hit, vf_toi
        self.ee, self.ee_hit, self.ee_toi = ee, ee_hit, ee_toi
        self.edges = edges
        tois = np.concatenate([vf_toi[vf_hit], ee_toi[ee_hit]])
        self.time_of_impact = float(tois.min()) if tois.size else float("inf")

    @property
    def num_contacts(self) -> int:
        return int(self.vf_hit.sum() + self.ee_hit.sum())

    def __repr__(self) -> str:
        return (
            f"MeshCCDResult(vf candidates={len(self.vf)}, ee candidates={len(self.ee)}, "
            f"contacts={self.num_contacts}, time_of_impact={self.time_of_impact})"
        )


def mesh_ccd(x0, x1, faces, edges=None, *, thickness: float = 0.0, broad_phase=None, **broad_phase_options) -> MeshCCDResult:
    """Continuous collision detection of triangle meshes over one step.

    Swept-box broad phase (:mod:`collision.broad_phase`, adjacency excluded, body rules via
    ``groups``/``self_collision``/``static``) followed by the batched narrow phase on every
    candidate vertex-face and edge-edge pair.

    Args:
        x0, x1: (V, 3) vertex positions [m] at the start and end of the step.
        faces: (F, 3) triangle vertex indices.
        edges: (E, 2) edge vertex indices; derived from ``faces`` when None.
        thickness: minimum separation [m] (>= 0), also the broad phase's inflation.
        broad_phase: optional :class:`collision.broad_phase.BroadPhase` built for this topology
            (reused between steps); otherwise :func:`collision.broad_phase.candidate_pairs` runs.
        **broad_phase_options: ``groups``, ``self_collision``, ``static`` for candidate_pairs.

    Returns:
        :class:`MeshCCDResult` with per-pair hits and times and the earliest time of impact.
    """
    from collision.broad_phase import candidate_pairs, mesh_edges

    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    x1 = np.ascontiguousarray(x1, dtype=np.float64)
    faces_arr = np.asarray(faces)
    edge_arr = mesh_edges(faces_arr) if edges is None else np.asarray(edges)
    if broad_phase is not None:
        vf, ee = broad_phase.query(x0, x1, thickness)
    else:
        vf, ee = candidate_pairs(x0, x1, faces_arr, edge_arr, inflation=thickness, **broad_phase_options)
    # gather (N, 8, 3) queries: rows 0-3 at t0, rows 4-7 at t1
    vf_idx = np.column_stack([vf[:, 0], faces_arr[vf[:, 1]]]) if len(vf) else np.zeros((0, 4), dtype=np.int64)
    ee_idx = np.column_stack([edge_arr[ee[:, 0]], edge_arr[ee[:, 1]]]) if len(ee) else np.zeros((0, 4), dtype=np.int64)
    vf_q = np.ascontiguousarray(np.concatenate([x0[vf_idx], x1[vf_idx]], axis=1))
    ee_q = np.ascontiguousarray(np.concatenate([x0[ee_idx], x1[ee_idx]], axis=1))
    vf_hit, vf_toi, _ = narrow_phase(0, vf_q, thickness)
    ee_hit, ee_toi, _ = narrow_phase(1, ee_q, thickness)
    return MeshCCDResult(vf, vf_hit, vf_toi, ee, ee_hit, ee_toi, edge_arr)
