"""Continuous-collision broad phase: swept boxes and BVH pair queries (Warp kernels only).

Every primitive (vertex, edge, face) moves linearly over the step, so its swept volume lies in the
box of its vertices at ``t0`` and ``t1``. Positions are float64; Warp's BVH stores float32 boxes, so
every float64 box coordinate is widened outwards before it is rounded (see :func:`lower32` /
:func:`upper32` for the padding rule and why it is conservative).

There is one BVH per body (over that body's faces or edges, stored in body-sorted order); the pair
kernels query one body's tree per launch and map tree leaves back to the caller's numbering through
an int32 index array. A query primitive whose body may not collide with the tree's body returns
before the traversal.

Pairs are written in one pass into a fixed-capacity buffer through an atomic counter: the counter
keeps counting past the capacity, so after the launch it holds the exact number of pairs; when it
exceeds the capacity the caller grows the buffer to that size and launches again (the writes beyond
the capacity were dropped, never out of bounds). The launches for the trees of all bodies share one
counter and buffer. Rows come out grouped by tree and query primitive on the CPU (serial launches)
and in any order on a GPU; the Python API sorts them.

Body rules (per-body int32 flags, indexed by body id):

* ``self_ok[b] != 0``: primitives of body ``b`` may collide with each other (the Python API already
  clears it for static bodies: a static body never collides with itself);
* ``is_static[b] != 0``: body ``b`` never moves; two primitives of static bodies never collide.
"""

import warp as wp

f64 = wp.float64

PAD_REL = wp.constant(wp.float64(2.0**-21))
"""Relative pad: 4 float32 ulps (float32 eps = 2^-23) of the box's largest coordinate magnitude.

Rounding a float64 to the nearest float32 moves it by at most 2^-24 of its magnitude, so 2^-21 leaves
a factor 8 for the float64 arithmetic of the inflation and for the narrow phase evaluating
``x0 + t (x1 - x0)``, whose float64 result may leave ``[min(x0, x1), max(x0, x1)]`` by an ulp."""

PAD_ABS = wp.constant(wp.float64(2.0**-126))
"""Absolute pad: the smallest normal float32 (FLT_MIN). Below it float32 spacing is absolute
(2^-149) and a flush-to-zero build maps subnormals to 0; a pad of FLT_MIN keeps the rounded lower
bound <= the true one (and the upper >= it) in both cases."""

FLT_MAX64 = wp.constant(wp.float64(3.4028234663852886e38))
"""Largest finite float32, exact in float64. Box coordinates are clamped to +-FLT_MAX before rounding
so no bound becomes inf (clamping is monotone, so no overlapping pair is lost)."""


@wp.func
def lower32(lo: f64, mag: f64) -> wp.float32:
    """Float32 lower bound <= ``lo``: ``lo - (mag * PAD_REL + PAD_ABS)`` clamped to +-FLT_MAX, rounded."""
    y = lo - (mag * PAD_REL + PAD_ABS)
    y = wp.min(wp.max(y, -FLT_MAX64), FLT_MAX64)
    return wp.float32(y)


@wp.func
def upper32(hi: f64, mag: f64) -> wp.float32:
    """Float32 upper bound >= ``hi``: ``hi + (mag * PAD_REL + PAD_ABS)`` clamped to +-FLT_MAX, rounded."""
    y = hi + (mag * PAD_REL + PAD_ABS)
    y = wp.min(wp.max(y, -FLT_MAX64), FLT_MAX64)
    return wp.float32(y)


@wp.func
def store_box(
    lo: wp.vec3d,
    hi: wp.vec3d,
    inflation: f64,
    i: int,
    out_lo: wp.array(dtype=wp.vec3),
    out_hi: wp.array(dtype=wp.vec3),
):
    """Write the float64 box ``[lo - inflation, hi + inflation]`` as a conservative float32 box."""
    a = lo - wp.vec3d(inflation, inflation, inflation)
    b = hi + wp.vec3d(inflation, inflation, inflation)
    m0 = wp.max(wp.abs(a[0]), wp.abs(b[0]))
    m1 = wp.max(wp.abs(a[1]), wp.abs(b[1]))
    m2 = wp.max(wp.abs(a[2]), wp.abs(b[2]))
    out_lo[i] = wp.vec3(lower32(a[0], m0), lower32(a[1], m1), lower32(a[2], m2))
    out_hi[i] = wp.vec3(upper32(b[0], m0), upper32(b[1], m1), upper32(b[2], m2))


@wp.kernel(enable_backward=False)
def vertex_boxes_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    inflation: f64,
    out_lo: wp.array(dtype=wp.vec3),
    out_hi: wp.array(dtype=wp.vec3),
):
    """Swept box of each vertex, inflated by ``inflation`` (these are query boxes)."""
    i = wp.tid()
    a = x0[i]
    b = x1[i]
    store_box(wp.min(a, b), wp.max(a, b), inflation, i, out_lo, out_hi)


@wp.kernel(enable_backward=False)
def edge_boxes_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    edges: wp.array(dtype=wp.vec2i),
    inflation: f64,
    tree_lo: wp.array(dtype=wp.vec3),
    tree_hi: wp.array(dtype=wp.vec3),
    query_lo: wp.array(dtype=wp.vec3),
    query_hi: wp.array(dtype=wp.vec3),
):
    """Swept box of each edge: once as stored in the BVH (no inflation), once inflated for queries."""
    i = wp.tid()
    e = edges[i]
    lo = wp.min(wp.min(x0[e[0]], x1[e[0]]), wp.min(x0[e[1]], x1[e[1]]))
    hi = wp.max(wp.max(x0[e[0]], x1[e[0]]), wp.max(x0[e[1]], x1[e[1]]))
    store_box(lo, hi, f64(0.0), i, tree_lo, tree_hi)
    store_box(lo, hi, inflation, i, query_lo, query_hi)


@wp.kernel(enable_backward=False)
def face_boxes_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    out_lo: wp.array(dtype=wp.vec3),
    out_hi: wp.array(dtype=wp.vec3),
):
    """Swept box of each face (stored in the BVH, not inflated: the vertex query box carries it)."""
    i = wp.tid()
    f = faces[i]
    lo = wp.min(wp.min(wp.min(x0[f[0]], x1[f[0]]), wp.min(x0[f[1]], x1[f[1]])), wp.min(x0[f[2]], x1[f[2]]))
    hi = wp.max(wp.max(wp.max(x0[f[0]], x1[f[0]]), wp.max(x0[f[1]], x1[f[1]])), wp.max(x0[f[2]], x1[f[2]]))
    store_box(lo, hi, f64(0.0), i, out_lo, out_hi)


@wp.func
def bodies_may_collide(
    ba: int, bb: int, self_ok: wp.array(dtype=wp.int32), is_static: wp.array(dtype=wp.int32)
) -> bool:
    """Body rule: same body needs its self-collision flag; two static bodies never collide."""
    if ba == bb:
        return self_ok[ba] != 0
    return is_static[ba] == 0 or is_static[bb] == 0


@wp.func
def emit(counter: wp.array(dtype=wp.int32), pairs: wp.array(dtype=wp.vec2i), i: int, j: int):
    """Append ``(i, j)`` if the buffer has room; the counter counts every pair regardless."""
    slot = wp.atomic_add(counter, 0, 1)
    if slot >= 0 and slot < pairs.shape[0]:  # slot < 0 only if the int32 counter wrapped
        pairs[slot] = wp.vec2i(i, j)


@wp.kernel(enable_backward=False)
def vertex_face_pairs_kernel(
    bvh: wp.uint64,
    tree_body: int,
    leaf_start: int,
    query_start: int,
    vertex_order: wp.array(dtype=wp.int32),
    query_lo: wp.array(dtype=wp.vec3),
    query_hi: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec3i),
    face_index: wp.array(dtype=wp.int32),
    self_ok: wp.array(dtype=wp.int32),
    is_static: wp.array(dtype=wp.int32),
    counter: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
):
    """Vertices against the face BVH of one body (``tree_body``), appended to ``pairs`` via ``counter``.

    Thread ``t`` handles vertex ``v = vertex_order[query_start + t]`` (``vertex_order``: vertices
    sorted by body; ``query_lo`` / ``query_hi`` / ``vertex_body`` indexed by ``v``). It returns before
    the traversal when the body rules forbid ``(vertex_body[v], tree_body)``. Leaf ``j`` of the tree is
    face ``leaf_start + j`` of the body-sorted ``faces``; ``face_index`` maps a sorted face back to the
    caller's numbering, which is what is written: rows ``(v, original face)``, minus faces that
    contain ``v``."""
    v = int(vertex_order[query_start + wp.tid()])
    if not bodies_may_collide(int(vertex_body[v]), tree_body, self_ok, is_static):
        return
    query = wp.bvh_query_aabb(bvh, query_lo[v], query_hi[v])
    j = int(0)
    while wp.bvh_query_next(query, j):
        f = leaf_start + j
        tri = faces[f]
        if tri[0] == v or tri[1] == v or tri[2] == v:
            continue
        emit(counter, pairs, v, int(face_index[f]))


@wp.kernel(enable_backward=False)
def edge_edge_pairs_kernel(
    bvh: wp.uint64,
    tree_body: int,
    leaf_start: int,
    query_start: int,
    query_lo: wp.array(dtype=wp.vec3),
    query_hi: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    edge_index: wp.array(dtype=wp.int32),
    edge_body: wp.array(dtype=wp.int32),
    self_ok: wp.array(dtype=wp.int32),
    is_static: wp.array(dtype=wp.int32),
    counter: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
):
    """Edges against the edge BVH of one body (``tree_body``), appended as above.

    Every array is in body-sorted edge order; ``edge_index`` maps it back to the caller's numbering.
    Thread ``t`` handles sorted edge ``a = query_start + t`` of body ``ba``; it returns before the
    traversal unless ``ba <= tree_body`` and the body rules allow ``(ba, tree_body)``, so a pair of
    two bodies is searched once, from the lower body. Leaf ``j`` is sorted edge ``b = leaf_start + j``;
    within one body only ``b > a`` is kept (the sort is stable, so this is ``original b > original a``).
    Edges sharing a vertex with ``a`` are skipped; rows are ``(min, max)`` of the original indices."""
    a = query_start + wp.tid()
    ba = int(edge_body[a])
    if ba > tree_body or not bodies_may_collide(ba, tree_body, self_ok, is_static):
        return
    ea = edges[a]
    query = wp.bvh_query_aabb(bvh, query_lo[a], query_hi[a])
    j = int(0)
    while wp.bvh_query_next(query, j):
        b = leaf_start + j
        if b <= a:  # same body: each pair once; other body (b > a always): never taken
            continue
        eb = edges[b]
        if ea[0] == eb[0] or ea[0] == eb[1] or ea[1] == eb[0] or ea[1] == eb[1]:
            continue
        ia = int(edge_index[a])
        ib = int(edge_index[b])
        emit(counter, pairs, wp.min(ia, ib), wp.max(ia, ib))


@wp.kernel(enable_backward=False)
def cover_check_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    covered_lo: wp.array(dtype=wp.vec3d),
    covered_hi: wp.array(dtype=wp.vec3d),
    room: f64,
    reach_radius: wp.array(dtype=f64),
    use_reach: int,
    uncovered: wp.array(dtype=wp.int32),
    beyond_reach: wp.array(dtype=wp.int32),
):
    """The broad-phase cover's test of vertex ``tid``'s straight motion ``x0 -> x1`` on the
    device: ``uncovered[0]`` counts the vertices with an end farther than ``room`` (per
    coordinate) outside the box ``covered_lo .. covered_hi`` of its covered motion (a NaN end
    counts), and with ``use_reach`` ``beyond_reach[0]`` those whose step is longer than
    ``reach_radius`` (:meth:`collision.narrow_phase.CandidateNarrowPhase.ccd_count_device`).
    The comparisons are the host test's (``lo - x <= room``, ``x - hi <= room``)."""
    i = wp.tid()
    a = x0[i]
    b = x1[i]
    lo = covered_lo[i]
    hi = covered_hi[i]
    inside = bool(True)
    for k in range(3):
        if not (lo[k] - a[k] <= room and a[k] - hi[k] <= room and lo[k] - b[k] <= room and b[k] - hi[k] <= room):
            inside = False
    if not inside:
        wp.atomic_add(uncovered, 0, 1)
    if use_reach != 0:
        step = b - a
        r = reach_radius[i]
        if not (wp.dot(step, step) <= r * r):
            wp.atomic_add(beyond_reach, 0, 1)


@wp.kernel(enable_backward=False)
def reach_radius_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    slack: f64,
    radius: wp.array(dtype=f64),
    unbounded: wp.array(dtype=wp.int32),
):
    """Vertex ``tid``'s motion radius [m] for the proximity pass's kept pairs
    (:meth:`collision.narrow_phase.CandidateNarrowPhase.near_count_covered`): the length of its
    step ``x0 -> x1`` plus ``slack``; ``unbounded[0]`` counts the radii that are not finite (a
    step past 1e154 m, or NaN), after which the caller drops the kept pairs. The squares are
    summed in the host's order, ``(x^2 + y^2) + z^2`` (``np.square(step) @ ONES3``), in separate
    statements: on the CPU, which fuses no multiply-add here, the radii are the host's bits."""
    i = wp.tid()
    step = x1[i] - x0[i]
    sx = step[0] * step[0]
    sy = step[1] * step[1]
    sz = step[2] * step[2]
    r = wp.sqrt((sx + sy) + sz) + slack
    radius[i] = r
    if not wp.isfinite(r):
        wp.atomic_add(unbounded, 0, 1)
