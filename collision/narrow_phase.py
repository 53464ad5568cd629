"""The narrow phase on the broad phase's device buffers (:class:`CandidateNarrowPhase`): CCD and
proximity of a mesh's candidate pairs without a per-pair host array, with one broad-phase query
kept while the motion stays inside its cover."""

from __future__ import annotations

import numpy as np
import warp as wp

from collision.ccd import ONES3, as_float32, ccd_kernels, is_float32
from core.buffers import RecordedLaunches, grown_capacity, host, read_only, upload, zero
from core.device import init_warp
from kernels import ccd as _k
from kernels.broad_phase import cover_check_kernel, reach_radius_kernel
from kernels import variants as _variants
from kernels.decide import pair_proximity_kernel

def _same_bytes(a, b: np.ndarray) -> bool:
    """Whether ``a`` holds exactly the float64 values of ``b`` (bit for bit: the same input)."""
    a = np.asarray(a, dtype=np.float64)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def _distance(max_distance) -> float:
    """``max_distance`` [m] as a float, checked finite and >= 0 (a ValueError naming it)."""
    value = float(max_distance)
    if not (np.isfinite(value) and value >= 0.0):
        raise ValueError(f"max_distance: expected a finite distance >= 0, got {max_distance!r}")
    return value


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
        counter: a one-element int32 device array (a view into a caller's counts, so that
            they cross to the host together) that counts the hits; default its own.
        reach_counter: likewise a two-element int32 device array that counts the pairs
            :meth:`near` keeps for the CCD calls that follow (vertex-face, edge-edge).
    """

    COVER_SAFETY = 0.45
    """An end position may move this fraction of ``m - t`` (not the full half) from the covered
    one: room for the rounding of the boxes' float64 arithmetic (the broad phase pads its
    float32 boxes for its own rounding only)."""

    def __init__(self, broad_phase, *, precision: str = "float64", tolerance_scale: float = 1.0,
                 max_iterations=None, tolerance=None, counter: wp.array | None = None,
                 reach_counter: wp.array | None = None) -> None:
        init_warp()
        self.settings = _variants.check_settings(precision, max_iterations, tolerance, tolerance_scale)
        self._kernels = ccd_kernels(precision, tolerance_scale, max_iterations, tolerance)
        if self._kernels is not _k:
            # a generated variant compiles here, not at the first contact of a run (which would
            # put seconds of compilation into a timed step)
            wp.load_module(self._kernels.pair_ccd_kernel.module, device=broad_phase.device)
        self._float32 = is_float32(self._kernels)
        self._real = wp.float32 if self._float32 else wp.float64
        self.broad_phase = broad_phase
        dev = self.device = broad_phase.device
        self._faces = wp.array(np.ascontiguousarray(broad_phase.faces, dtype=np.int32).reshape(-1, 3),
                               dtype=wp.vec3i, device=dev)
        self._edges = wp.array(np.ascontiguousarray(broad_phase.edges, dtype=np.int32).reshape(-1, 2),
                               dtype=wp.vec2i, device=dev)
        self._counter = wp.zeros(1, dtype=wp.int32, device=dev) if counter is None else counter
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
        self._reach_counter = wp.zeros(2, dtype=wp.int32, device=dev) if reach_counter is None else reach_counter
        self._reach_x = wp.empty(n, dtype=wp.vec3d, device=dev)  # near_count_covered's positions
        self._radius = wp.empty(n, dtype=wp.float64, device=dev)
        # the cover's boxes of the covered motion on the device (ccd_count_device's test)
        self._cover_lo = wp.empty(n, dtype=wp.vec3d, device=dev)
        self._cover_hi = wp.empty(n, dtype=wp.vec3d, device=dev)
        self._no_radius = wp.empty(0, dtype=wp.float64, device=dev)
        self._reach = None  # the _Reach of the last near() / near_count_covered() with motion radii
        self._start_gap = 0.0  # how far the last cover()'s start positions may lie outside its boxes [m]
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
        if self._keepable(margin, slack) and c[1].shape == x0.shape == x1.shape and self._outside(x0, x1, c) <= slack:
            self.keep_cover(slack)
            return
        self.query_cover(x0, x1, margin, ahead, ahead_limit)

    def _keepable(self, margin: float, slack: float) -> bool:
        """Whether :meth:`cover` may keep the current cover for a motion within ``slack`` of its
        boxes (its margin is ``margin`` and no other query has refilled the broad phase's buffers)."""
        c = self._cover
        return slack > 0.0 and c is not None and c[3] == float(margin) and c[4] == self.broad_phase.query_count

    def keep_cover(self, slack: float) -> None:
        """Keeps the current cover for a motion whose ends lie within ``slack`` [m] of its boxes
        (:meth:`cover`'s test held, on the host or on the device)."""
        self.kept_covers += 1
        self._start_gap = float(slack)

    def assume_kept(self, slack: float) -> None:
        """Uses the current cover for a motion assumed within ``slack`` [m] of its boxes, its
        device test not read yet (the caller then keeps it, :meth:`keep_cover`, or queries
        afresh, :meth:`query_cover`, and calls :meth:`discard_pass` for the pass it ran on it)."""
        self._start_gap = float(slack)

    def discard_pass(self) -> None:
        """A :meth:`near_count_covered` pass ran on a cover that failed its test: not a reuse."""
        self.reuses -= 1

    def cover_test_device(self, x0, x1, margin: float, slack: float, outside: wp.array) -> bool:
        """:meth:`cover`'s test of the kept cover for the device positions ``x0``, ``x1`` (vec3d
        arrays of at least V rows), on the device: ``outside`` (a one-element int32 device array)
        counts the vertices with an end farther than ``slack`` outside the box of its covered
        motion (:func:`kernels.broad_phase.cover_check_kernel`, the host test's comparisons).
        While it stays 0 the caller keeps the cover (:meth:`keep_cover`), else it queries afresh
        (:meth:`query_cover`). Returns False, launching nothing, when no cover can be kept
        (:meth:`cover` would query afresh without a test)."""
        if not self._keepable(margin, slack):
            return False
        c = self._cover
        n = len(c[1])
        if x0.shape[0] < n or x1.shape[0] < n:
            raise ValueError(f"x0, x1: expected at least {n} rows (the mesh's vertices), got {x0.shape[0]}, {x1.shape[0]}")
        zero(outside)
        self._launches.launch("cover_keep", cover_check_kernel, n, [
            x0, x1, self._cover_lo, self._cover_hi, float(slack), self._no_radius, 0, outside, outside])
        return True

    def query_cover(self, x0, x1, margin: float, ahead: float = 0.0, ahead_limit: float = 0.0) -> None:
        """:meth:`cover`'s fresh broad-phase query of the motion ``x0 -> x1`` ((V, 3) float64 on the host)."""
        x0 = np.asarray(x0, dtype=np.float64)
        x1 = np.asarray(x1, dtype=np.float64)
        if ahead > 0.0 and ahead_limit > 0.0:  # the query covers the motion continued past x1
            x1 = x1 + np.clip(float(ahead) * (x1 - x0), -float(ahead_limit), float(ahead_limit))
        buffers = self.broad_phase.query_device(x0, x1, float(margin))
        self.queries += 1
        # the covered motion's vertex boxes (and scratch for _outside), on the device too
        lo, hi = np.minimum(x0, x1), np.maximum(x0, x1)
        upload(self._cover_lo, lo)
        upload(self._cover_hi, hi)
        self._cover = (buffers, lo, hi, float(margin), self.broad_phase.query_count, np.empty((3,) + x0.shape))
        self._start_gap = 0.0

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

    def reserve(self, n: int) -> None:
        """Room for the hits of ``n`` candidates in the output buffers."""
        if self._pairs.shape[0] < n:
            n = grown_capacity(n, self._pairs.shape[0], 64)
            dev = self.device
            self._pairs = wp.empty(n, dtype=wp.vec2i, device=dev)
            self._kind = wp.empty(n, dtype=wp.int32, device=dev)
            self._time = wp.empty(n, dtype=self._real, device=dev)
            self._source = wp.empty(n, dtype=wp.int32, device=dev)
            self._offset = wp.empty(n, dtype=wp.vec3d, device=dev)
            self._weights = wp.empty(n, dtype=wp.vec4d, device=dev)
            self._vertices = wp.empty(n, dtype=wp.vec4i, device=dev)

    def _run(self, buffers, launch, read: bool = True) -> int:
        """Runs ``launch(vf, n_vf, ee, n_ee)`` once for both kinds' candidates (it appends the
        hits and their kinds to the output buffers through the counter) and returns the number
        of hits (unsorted, on the device: :attr:`hits`), or with ``read=False`` the number of
        candidates tested, a bound on it (the count stays in the device counter)."""
        vf, n_vf, ee, n_ee = buffers
        self.reserve(n_vf + n_ee)
        zero(self._counter)
        if n_vf + n_ee:
            launch(vf, n_vf, ee, n_ee)
        return int(host(self._counter)[0]) if read else n_vf + n_ee

    def _sorted(self, total: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(kind (K,), pair (K, 2) int64, row order (K,)) of the ``total`` hits of the last call,
        sorted by kind, then lexicographically by pair (the order of ``BroadPhase.query``)."""
        if total == 0:
            return NO_PAIRS
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
            return NO_CCD_HITS
        toi = host(self._time)[:n][order].astype(np.float64)
        return (kind, pair, toi, host(self._source)[:n][order].astype(np.int64),
                host(self._vertices)[:n][order].astype(np.int64))

    def ccd_count(self, x0, x1, thickness: float = 0.0, read: bool = True) -> int:
        """:meth:`ccd`'s hits left on the device (:attr:`hits`, the kernel's order); returns
        their number, or with ``read=False`` a bound on it without reading the device (the
        number is in the counter)."""
        t = float(thickness)
        if not np.isfinite(t) or t < 0.0:
            raise ValueError(f"thickness must be finite and >= 0, got {thickness!r}")
        r = self._reach
        c = self._cover
        # from the positions of the last near() with motion radii, in the cover it used
        from_near = r is not None and t == 0.0 and c is r.cover and c[4] == self.broad_phase.query_count \
            and np.shape(x1) == c[1].shape and _same_bytes(x0, r.positions())
        if from_near and self._x0_holds_reach and self._outside(x1, x1, c) <= self.COVER_SAFETY * c[3]:
            # the start was covered there with less room and is on the device already: only the
            # end is checked and uploaded (_candidates' cover test otherwise)
            self.reuses += 1
            buffers, xa, xb = c[0], self._x0, upload(self._x1, x1)
        else:
            buffers, xa, xb = self._candidates(x0, x1, t, end_moves=True)  # pairs within t are candidates
        if from_near and self._cover is r.cover and buffers is r.cover[0]:
            step = np.subtract(x1, x0)
            if (np.square(step) @ ONES3 <= r.radius_squared()).all():
                buffers = r.buffers()
                self.reach_calls += 1
        self.tested += buffers[1] + buffers[3]
        if self._float32:
            xa, xb = upload(self._x0_32, as_float32(x0, "x0")), upload(self._x1_32, as_float32(x1, "x1"))
            t = float(as_float32(t, "thickness"))

        def launch(vf, n_vf, ee, n_ee):
            self._launches.launch("ccd", self._kernels.pair_ccd_kernel, n_vf + n_ee,
                                  [n_vf, vf, ee, xa, xb, self._faces, self._edges, t,
                                   self._counter, self._pairs, self._kind, self._time, self._source,
                                   self._vertices])

        return self._run(buffers, launch, read)

    def ccd_count_device(self, x0, x1, same_start: bool, uncovered: wp.array, beyond_reach: wp.array) -> int | None:
        """:meth:`ccd_count` at zero thickness of the device positions ``x0``, ``x1`` (vec3d
        arrays of at least V rows) with the cover's test on the device: the cover's candidates
        (with ``same_start``, ``x0`` holding the positions of the last :meth:`near` with motion
        radii, the pairs it kept) are tested without the host reading a position, and
        :func:`kernels.broad_phase.cover_check_kernel` counts into ``uncovered`` the vertices whose
        motion leaves the cover's room and into ``beyond_reach`` those that moved farther than
        their radius (one-element int32 device arrays). While both stay 0 the hits are
        :meth:`ccd_count`'s; otherwise they may lack some, and the caller runs :meth:`ccd_count`
        instead. Returns the number of candidates tested (a bound on the hits, which are counted
        in the counter), or None when no cover serves (no cover, another query since, or the
        float32 narrow phase, which rounds the positions on the host)."""
        chosen = self._device_candidates(same_start)
        if chosen is None:
            return None
        buffers, use_reach = chosen
        c = self._cover
        n = len(c[1])
        if x0.shape[0] < n or x1.shape[0] < n:
            raise ValueError(f"x0, x1: expected at least {n} rows (the mesh's vertices), got {x0.shape[0]}, {x1.shape[0]}")
        zero(uncovered)
        zero(beyond_reach)
        self._launches.launch("cover_check", cover_check_kernel, n, [
            x0, x1, self._cover_lo, self._cover_hi, self.COVER_SAFETY * c[3], self._radius, int(use_reach),
            uncovered, beyond_reach])
        self.reuses += 1
        self.reach_calls += use_reach
        self.tested += buffers[1] + buffers[3]

        def launch(vf, n_vf, ee, n_ee):
            self._launches.launch("ccd", self._kernels.pair_ccd_kernel, n_vf + n_ee,
                                  [n_vf, vf, ee, x0, x1, self._faces, self._edges, 0.0,
                                   self._counter, self._pairs, self._kind, self._time, self._source,
                                   self._vertices])

        return self._run(buffers, launch, read=False)

    def device_bound(self, same_start: bool) -> int | None:
        """The candidates :meth:`ccd_count_device` would test (a bound on its hits), or None when
        no cover serves."""
        chosen = self._device_candidates(same_start)
        return None if chosen is None else chosen[0][1] + chosen[0][3]

    def _device_candidates(self, same_start: bool):
        """(candidate buffers, whether they are :meth:`near`'s kept pairs) of
        :meth:`ccd_count_device`, or None when no cover serves."""
        c = self._cover
        if self._float32 or c is None or c[4] != self.broad_phase.query_count:
            return None
        r = self._reach
        use_reach = bool(same_start) and r is not None and r.cover is c
        return (r.buffers() if use_reach else c[0]), use_reach

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

    def near_count(self, x, max_distance: float, motion_radius=None, read: bool = True) -> int:
        """:meth:`near`'s pairs left on the device (:attr:`hits`, the kernel's order); returns
        their number, or with ``read=False`` a bound on it (the number is in the counter)."""
        self._reach = None
        max_distance = _distance(max_distance)
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
            self._reserve_reach(buffers)

        total = self._run(buffers, self._near_launch(xa, max_distance, radius), read)
        if radius is not self._no_radius:
            self._x0_holds_reach = True  # the cover path of _candidates uploaded x there
            self._reach = _Reach(self, np.array(x, dtype=np.float64), np.square(motion_radius))
        return total

    def near_count_covered(self, x, max_distance: float, x1=None, reach_slack: float = 0.0,
                           unbounded: wp.array | None = None, read: bool = True) -> int:
        """:meth:`near_count` at the device positions ``x`` (a vec3d array of at least V rows)
        that the last :meth:`cover` started from, without the host reading a position: the
        cover's test of those positions (how far they may lie outside its boxes is known from
        :meth:`cover`'s decision) is settled on the host. With ``x1`` (the end positions the
        cover's motion went to, same rows) the motion radii are the step lengths plus
        ``reach_slack`` [m] (:func:`kernels.broad_phase.reach_radius_kernel`: the host's values),
        and ``unbounded`` (a one-element int32 device array) counts the radii that are not
        finite: the caller then drops the kept pairs (:meth:`drop_reach`), as :meth:`near_count`
        keeps none for them. Returns as :meth:`near_count`."""
        max_distance = _distance(max_distance)
        c = self._cover
        if c is None or c[4] != self.broad_phase.query_count:
            raise RuntimeError("near_count_covered needs the cover of its positions' motion (cover() first)")
        # the positions lie within _start_gap of the covered boxes; the test of near_count's
        # cover path (_candidates) allows COVER_SAFETY (m - d)
        if not (max_distance <= c[3] and self._start_gap <= self.COVER_SAFETY * (c[3] - max_distance)):
            raise RuntimeError(f"near_count_covered: positions up to {self._start_gap} m outside the cover, which "
                               f"serves distances up to {max_distance} m only within "
                               f"{self.COVER_SAFETY * (c[3] - max_distance)} m")
        n = len(c[1])
        if x.shape[0] < n or (x1 is not None and x1.shape[0] < n):
            raise ValueError(f"x, x1: expected at least {n} rows (the mesh's vertices)")
        if x1 is not None and unbounded is None:
            raise ValueError("unbounded: a one-element int32 device array is needed with x1")
        self._reach = None
        self.reuses += 1
        self._x0_holds_reach = False
        buffers = c[0]
        radius = self._no_radius
        if unbounded is not None:
            zero(unbounded)
        if x1 is not None and self._kernels is _k:
            radius = self._radius
            self._launches.launch("reach_radius", reach_radius_kernel, n, [x, x1, float(reach_slack), radius, unbounded])
            wp.copy(self._x0, x, count=n)
            wp.copy(self._reach_x, x, count=n)
            self._reserve_reach(buffers)

        total = self._run(buffers, self._near_launch(x, max_distance, radius), read)
        if radius is not self._no_radius:
            self._x0_holds_reach = True
            self._reach = _Reach(self, None, None)
        return total

    def _near_launch(self, x, max_distance: float, radius):
        """The proximity kernel's launch over candidate buffers (:meth:`_run`'s ``launch``) at the
        device positions ``x``, keeping the pairs the motion radii ``radius`` reach (none when empty)."""
        def launch(vf, n_vf, ee, n_ee):
            self._launches.launch("near", pair_proximity_kernel, n_vf + n_ee,
                                  [n_vf, vf, ee, x, self._faces, self._edges, max_distance,
                                   self._counter, self._pairs, self._kind, self._offset, self._weights,
                                   self._vertices, radius, self._reach_counter, self._reach_pairs[0], self._reach_pairs[1]])
        return launch

    def drop_reach(self) -> None:
        """Forgets the pairs the last near() kept for the CCD calls (its radii were not finite)."""
        self._reach = None
        self._x0_holds_reach = False

    def note_reach_counts(self, counts) -> None:
        """The kept pairs' counts (vertex-face, edge-edge) as the caller read them with its own
        counts (the reach counter is a view into them): no second read."""
        if self._reach is not None:
            self._reach.counts = (int(counts[0]), int(counts[1]))

    def _reserve_reach(self, buffers) -> None:
        """Room in the kept pairs' buffers for every candidate of ``buffers``, per kind."""
        zero(self._reach_counter)
        for kind in (0, 1):
            n = buffers[2 * kind + 1]
            if self._reach_pairs[kind].shape[0] < n:
                self._reach_pairs[kind] = wp.empty(grown_capacity(n, self._reach_pairs[kind].shape[0], 64),
                                                   dtype=wp.vec2i, device=self.device)


class _Reach:
    """The pairs that the last :meth:`CandidateNarrowPhase.near` with motion radii kept for the
    CCD calls from its positions, with its cover, and those positions and radii, on the host when
    given, else read from the device when first asked for (the kept pairs' counts too, unless the
    caller noted them)."""

    def __init__(self, narrow: CandidateNarrowPhase, positions, radius_squared) -> None:
        self.narrow, self.cover = narrow, narrow._cover
        self._positions, self._radius_squared = positions, radius_squared
        self.counts = None

    def positions(self) -> np.ndarray:
        if self._positions is None:
            self._positions = np.array(host(self.narrow._reach_x)[:len(self.cover[1])], dtype=np.float64)
        return self._positions

    def radius_squared(self) -> np.ndarray:
        if self._radius_squared is None:
            self._radius_squared = np.square(host(self.narrow._radius)[:len(self.cover[1])])
        return self._radius_squared

    def buffers(self) -> tuple:
        if self.counts is None:
            counts = host(self.narrow._reach_counter)
            self.counts = (int(counts[0]), int(counts[1]))
        pairs = self.narrow._reach_pairs
        return pairs[0], self.counts[0], pairs[1], self.counts[1]


# no hit (shared, read only): _collect's (kind, pair, order), CandidateNarrowPhase.ccd's (kind,
# pair, time, source, vertices)
NO_PAIRS = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64))


NO_CCD_HITS = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64), np.zeros(0),
                         np.zeros(0, dtype=np.int64), np.zeros((0, 4), dtype=np.int64))
