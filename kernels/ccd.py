"""Narrow-phase continuous collision detection for vertex-triangle and edge-edge pairs.

A query holds eight points as the rows of a (8, 3) matrix: rows 0-3 at the start of the step,
rows 4-7 at its end, in ipctk's order (vertex-face: ``p, t0, t1, t2``; edge-edge:
``ea0, ea1, eb0, eb1``). Candidate contact times are

* ``t = 0`` (contact at the start),
* the roots of the coplanarity cubic (:func:`kernels.ccd_common.coplanarity_cubic`), real or
  complex with an imaginary part within the root's time uncertainty (a grazing contact is a
  double root, which rounding may turn into a complex pair), with real part in ``[0, 1]`` up to
  that uncertainty,
* when the four points stay coplanar for the whole step (cubic identically zero up to rounding):
  the times a vertex becomes collinear with an edge of the other primitive (sliding in-plane
  motion, collinear overlap),

and the query hits at the earliest candidate where the exact distance of the primitives is at
most ``thickness + tolerance``; the tolerance is the distance the primitives can move relative
to each other within the candidate's time uncertainty plus the rounding of the distance itself.

With ``thickness > 0`` the contact need not be coplanar: conservative advancement (steps of
``0.9 (distance - thickness) / relative speed bound``) is used instead.

The time of impact is differentiable: :func:`ccd_time_of_impact_kernel` recomputes it from the
positions through the cubic coefficients and :func:`kernels.roots.cubic_roots` (whose adjoint is
the paper's mollified implicit derivative), so a ``wp.Tape`` over it yields bounded gradients.
"""

import warp as wp

from kernels.ccd_common import (
    CCD_T_MAX,
    COEFFICIENT_ERROR_FACTOR,
    COPLANAR_RELATIVE,
    DISTANCE_ERROR_FACTOR,
    UNIT_ROUNDOFF,
    collinearity_quadratics,
    coplanarity_cubic,
    unit_scaled_cubic,
    lerp3,
    max_abs_vec3,
    root_time_uncertainty,
)
from kernels.edge_edge import segment_segment_offset
from kernels.point_triangle import point_triangle_offset
from kernels.roots import cubic_roots, cubic_solve, quadratic_solve, vec6d

mat83d = wp.types.matrix(shape=(8, 3), dtype=wp.float64)

VERTEX_FACE = wp.constant(0)
EDGE_EDGE = wp.constant(1)

# Where the reported time of impact came from (for the differentiable recomputation).
SOURCE_NONE = wp.constant(-1)
SOURCE_START = wp.constant(0)  # t = 0
SOURCE_CUBIC = wp.constant(1)  # 1 + slot of the coplanarity cubic (1, 2, 3)
SOURCE_COLLINEAR = wp.constant(4)  # a vertex-edge collinearity root (coplanar step)
SOURCE_ADVANCE = wp.constant(5)  # conservative advancement (thickness > 0)

# Conservative advancement: at most this many steps; if the distance is still above the
# thickness after them, the query is reported as a hit at the current time (conservative).
ADVANCE_MAX_STEPS = wp.constant(2000)


@wp.func
def row(m: mat83d, i: int) -> wp.vec3d:
    return wp.vec3d(m[i, 0], m[i, 1], m[i, 2])


@wp.func
def offset_at(kind: int, m: mat83d, t: wp.float64) -> wp.vec3d:
    """Offset between the closest points of the two primitives at time t."""
    y0 = lerp3(row(m, 0), row(m, 4), t)
    y1 = lerp3(row(m, 1), row(m, 5), t)
    y2 = lerp3(row(m, 2), row(m, 6), t)
    y3 = lerp3(row(m, 3), row(m, 7), t)
    if kind == VERTEX_FACE:
        return point_triangle_offset(y0, y1, y2, y3)
    return segment_segment_offset(y0, y1, y2, y3)


@wp.func
def distance_at(kind: int, m: mat83d, t: wp.float64) -> wp.float64:
    """Distance of the two primitives at time t."""
    return wp.length(offset_at(kind, m, t))


@wp.func
def axis_extents(m: mat83d) -> wp.vec3d:
    """Per axis: the largest component of the edge vectors from point 0 (start and end) and of
    their motions. Every term of the coplanarity cubic's coefficients is a product of one x, one
    y and one z component of these, which bounds the coefficients' size and rounding per axis
    (a step that is flat in x, say, has tiny x components and accurately known coefficients)."""
    ext = wp.vec3d()
    for k in range(1, 4):
        d = row(m, k) - row(m, 0)
        d1 = row(m, k + 4) - row(m, 4)
        e = d1 - d
        for c in range(3):
            ext[c] = wp.max(ext[c], wp.max(wp.abs(d[c]), wp.max(wp.abs(d1[c]), wp.abs(e[c]))))
    return ext


@wp.func
def relative_motion_bound(kind: int, m: mat83d) -> wp.float64:
    """Largest displacement over the step of a point of one primitive relative to a point of the
    other (the closest points are convex combinations of the vertices): bounds how fast their
    distance can change per unit of t."""
    # written out, not as loops over the pairs: a loop with a kind-dependent bound indexes the
    # matrix at run time, which made this the narrow phase's most expensive step (4x slower)
    d0 = row(m, 4) - row(m, 0)
    d1 = row(m, 5) - row(m, 1)
    d2 = row(m, 6) - row(m, 2)
    d3 = row(m, 7) - row(m, 3)
    if kind == EDGE_EDGE:
        return wp.max(wp.max(wp.length(d2 - d0), wp.length(d3 - d0)), wp.max(wp.length(d2 - d1), wp.length(d3 - d1)))
    return wp.max(wp.length(d1 - d0), wp.max(wp.length(d2 - d0), wp.length(d3 - d0)))


@wp.func
def relative_extent(m: mat83d) -> wp.float64:
    """Largest coordinate of the points relative to point 0, at the start or the end."""
    a = row(m, 0)
    b = row(m, 4)
    s = wp.max(max_abs_vec3(row(m, 1) - a), wp.max(max_abs_vec3(row(m, 2) - a), max_abs_vec3(row(m, 3) - a)))
    return wp.max(s, wp.max(max_abs_vec3(row(m, 5) - b), wp.max(max_abs_vec3(row(m, 6) - b), max_abs_vec3(row(m, 7) - b))))


# Rounding of :func:`farther_than`'s bound (below about 20 u extent where it answers: measured
# 10.5 u against exact arithmetic) plus that of the exact distance it stands in for, whose
# vertex-face form works in absolute coordinates (a few u (|x| + extent)), with margin; a
# constant, not DISTANCE_ERROR_FACTOR, so that the tolerance_scale knob cannot shrink it.
FILTER_ROUNDING_FACTOR = wp.constant(wp.float64(1024.0))


@wp.func
def filter_rounding(extent: wp.float64, y0: wp.vec3d) -> wp.float64:
    """What :func:`farther_than`'s threshold adds to an exact distance test of four points whose
    coordinates relative to ``y0`` are at most ``extent``: ``FILTER_ROUNDING_FACTOR u (extent +
    |y0|)`` (largest coordinates)."""
    return FILTER_ROUNDING_FACTOR * UNIT_ROUNDOFF * (extent + max_abs_vec3(y0))


@wp.func
def farther_than(kind: int, y0: wp.vec3d, y1: wp.vec3d, y2: wp.vec3d, y3: wp.vec3d, distance: wp.float64) -> bool:
    """A cheap sufficient test that two primitives (in a query's order, rows 0-3) are more than
    ``distance`` apart: the distance of the vertex from the face's plane, or of the edges'
    supporting lines from each other, is a lower bound of theirs.

    It only answers for a face, or a pair of edges, that is at least about 6 degrees from
    degenerate (parallel edges, a needle face), where the bound's rounding stays below about
    ``20 u`` times the points' extent; otherwise, and whenever the bound is not above
    ``distance``, it returns False and the caller computes the exact distance. A caller that
    must decide exactly as the exact distance would adds both roundings to ``distance``
    (:func:`filter_rounding`)."""
    u = wp.vec3d()
    v = wp.vec3d()
    w = wp.vec3d()
    if kind == VERTEX_FACE:
        u = y2 - y1
        v = y3 - y1
        w = y0 - y1
    else:
        u = y1 - y0
        v = y3 - y2
        w = y0 - y2
    n = wp.cross(u, v)
    nn = wp.dot(n, n)
    if nn >= wp.float64(0.01) * wp.dot(u, u) * wp.dot(v, v):
        s = wp.dot(w, n)
        return s * s > distance * distance * nn
    return False


@wp.func
def box_farther_than(kind: int, y0: wp.vec3d, y1: wp.vec3d, y2: wp.vec3d, y3: wp.vec3d, distance: wp.float64) -> bool:
    """A cheaper sufficient test than :func:`farther_than` (rows 0-3 in a query's order): the
    primitives' bounding boxes are more than ``distance`` apart along an axis, which bounds
    their distance from below (each primitive lies in its box). It rejects the pairs of a flat
    sheet that lie in one plane, which the plane test cannot. The gaps are differences of two
    coordinates (rounded by at most ``u`` of their size), so a caller adds the same rounding
    (:func:`filter_rounding`) as for the plane test."""
    lo_a = y0
    hi_a = y0
    lo_b = wp.min(y2, y3)
    hi_b = wp.max(y2, y3)
    if kind == VERTEX_FACE:
        lo_b = wp.min(lo_b, y1)
        hi_b = wp.max(hi_b, y1)
    else:
        lo_a = wp.min(y0, y1)
        hi_a = wp.max(y0, y1)
    gap = wp.max(lo_b - hi_a, lo_a - hi_b)
    return wp.max(gap[0], wp.max(gap[1], gap[2])) > distance


@wp.func
def collinear_pair(kind: int, combo: int) -> wp.vec3i:
    """(vertex, edge start, edge end) of the vertex-edge combination ``combo`` (-1 when unused)."""
    if kind == VERTEX_FACE:
        if combo == 0:
            return wp.vec3i(0, 1, 2)
        if combo == 1:
            return wp.vec3i(0, 2, 3)
        if combo == 2:
            return wp.vec3i(0, 3, 1)
        return wp.vec3i(-1, -1, -1)
    if combo == 0:
        return wp.vec3i(0, 2, 3)
    if combo == 1:
        return wp.vec3i(1, 2, 3)
    if combo == 2:
        return wp.vec3i(2, 0, 1)
    return wp.vec3i(3, 0, 1)


@wp.func
def advance(kind: int, m: mat83d, thickness: wp.float64, tolerance: wp.float64, speed: wp.float64) -> wp.float64:
    """Conservative advancement: the first t in [0, 1] with distance <= thickness + tolerance,
    or 2 if none. Each step is 0.9 of the time the primitives need to close the gap at the
    bound ``speed`` on their relative motion, so the contact is never stepped over."""
    t = wp.float64(0.0)
    result = wp.float64(2.0)
    steps = int(0)
    while steps < ADVANCE_MAX_STEPS:
        steps = steps + 1
        gap = distance_at(kind, m, t) - thickness
        if gap <= tolerance:
            result = t
            break
        if speed <= wp.float64(0.0):
            break
        if t >= wp.float64(1.0):
            break
        step = wp.float64(0.9) * gap / speed
        t = wp.min(t + step, wp.float64(1.0))
    if steps >= ADVANCE_MAX_STEPS and result > wp.float64(1.0):
        result = t  # not resolved within the step budget: report the contact conservatively
    return result


@wp.func
def candidate_contact(
    kind: int, m: mat83d, re: wp.float64, im: wp.float64, dt: wp.float64, tol_distance: wp.float64, speed: wp.float64
) -> wp.float64:
    """Time in [0, 1] of a contact at the candidate root ``re + i im`` with time uncertainty
    ``dt``, or 2 when it is no contact: the root must be real up to ``dt`` and inside [0, 1] up to
    ``dt``, and the primitives within the distance they can cover in ``dt + |im|`` (plus the
    distance computation's own rounding)."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if wp.abs(im) <= dt and re >= -dt and re <= one + dt:
        t = wp.clamp(re, zero, one)
        if distance_at(kind, m, t) <= tol_distance + speed * (dt + wp.abs(im)):
            return t
    return wp.float64(2.0)


@wp.func
def ccd_query(kind: int, m: mat83d, thickness: wp.float64) -> wp.vec3d:
    """Earliest contact of one query.

    Returns:
        vec3d(hit (1 or 0), time of impact (inf when no hit), source code (SOURCE_*, with the
        cubic slot added for SOURCE_CUBIC)).
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    inf = wp.float64(1.0e308) * wp.float64(10.0)
    speed = relative_motion_bound(kind, m)
    extent = relative_extent(m) + speed
    # rounding of a distance computed from coordinates of size `extent`
    tol_distance = DISTANCE_ERROR_FACTOR * UNIT_ROUNDOFF * extent
    best = inf
    source = wp.float64(-1.0)

    if thickness > zero:
        t_hit = advance(kind, m, thickness, tol_distance, speed)
        if t_hit <= one:
            return wp.vec3d(one, t_hit, wp.float64(5.0))
        return wp.vec3d(zero, inf, wp.float64(-1.0))

    # most candidates of a broad phase are farther apart than they move: a plane / line distance
    # rules them out before the exact distance. Its threshold is the exact test's below plus both
    # distances' rounding (FILTER_ROUNDING_FACTOR), so it rejects only pairs that test rejects too
    threshold = tol_distance + speed + filter_rounding(extent, row(m, 0))
    if box_farther_than(kind, row(m, 0), row(m, 1), row(m, 2), row(m, 3), threshold):
        return wp.vec3d(zero, inf, wp.float64(-1.0))
    if farther_than(kind, row(m, 0), row(m, 1), row(m, 2), row(m, 3), threshold):
        return wp.vec3d(zero, inf, wp.float64(-1.0))
    start_distance = distance_at(kind, m, zero)
    if start_distance <= tol_distance:
        return wp.vec3d(one, zero, zero)
    # the distance changes by at most `speed` over the step (relative_motion_bound): a pair
    # farther apart than that can never touch, so skip the cubic (most resting-contact candidates)
    if start_distance > tol_distance + speed:
        return wp.vec3d(zero, inf, wp.float64(-1.0))

    coefficients = coplanarity_cubic(
        row(m, 0), row(m, 1), row(m, 2), row(m, 3), row(m, 4), row(m, 5), row(m, 6), row(m, 7)
    )
    # each coefficient sums at most 18 terms, each a product of one x, one y and one z component
    ext = axis_extents(m)
    magnitude = wp.float64(18.0) * ext[0] * ext[1] * ext[2]
    coefficient_error = COEFFICIENT_ERROR_FACTOR * UNIT_ROUNDOFF * magnitude
    largest = wp.max(wp.max(wp.abs(coefficients[0]), wp.abs(coefficients[1])), wp.max(wp.abs(coefficients[2]), wp.abs(coefficients[3])))
    if largest > COPLANAR_RELATIVE * magnitude:
        roots = cubic_solve(coefficients, CCD_T_MAX)
        for slot in range(3):
            re = roots[slot + slot]
            im = roots[slot + slot + 1]
            dt = root_time_uncertainty(coefficients, re, coefficient_error)
            t = candidate_contact(kind, m, re, im, dt, tol_distance, speed)
            if t < best:
                best = t
                source = wp.float64(1.0) + wp.float64(slot)
    else:
        # coplanar for the whole step: first contact is a vertex meeting an edge
        for combo in range(4):
            trio = collinear_pair(kind, combo)
            if trio[0] >= 0:
                quads = collinearity_quadratics(
                    row(m, trio[0]), row(m, trio[1]), row(m, trio[2]),
                    row(m, trio[0] + 4), row(m, trio[1] + 4), row(m, trio[2] + 4),
                )
                n_significant = int(0)
                for comp in range(3):
                    qa = quads[comp, 0]
                    qb = quads[comp, 1]
                    qc = quads[comp, 2]
                    if wp.max(wp.abs(qa), wp.max(wp.abs(qb), wp.abs(qc))) > COPLANAR_RELATIVE * extent * extent:
                        n_significant = n_significant + 1
                        pair_roots, _sa = quadratic_solve(qa, qb, qc, CCD_T_MAX)
                        cubic_view = wp.vec4d(zero, qa, qb, qc)
                        err = COEFFICIENT_ERROR_FACTOR * UNIT_ROUNDOFF * wp.float64(4.0) * extent * extent
                        for r in range(2):
                            re = pair_roots[r + r]
                            im = pair_roots[r + r + 1]
                            dt = root_time_uncertainty(cubic_view, re, err)
                            t = candidate_contact(kind, m, re, im, dt, tol_distance, speed)
                            if t < best:
                                best = t
                                source = wp.float64(4.0)
                if n_significant == 0:
                    # vertex and edge stay collinear: the vertex enters the segment when it meets
                    # an endpoint, p(t) = e(t), linear in each coordinate
                    for end in range(2):
                        e_idx = trio[1 + end]
                        g0 = row(m, trio[0]) - row(m, e_idx)
                        g1 = (row(m, trio[0] + 4) - row(m, e_idx + 4)) - g0
                        for comp in range(3):
                            if wp.abs(g1[comp]) > COPLANAR_RELATIVE * extent:
                                t_lin = -g0[comp] / g1[comp]
                                dt_lin = DISTANCE_ERROR_FACTOR * UNIT_ROUNDOFF * extent / wp.abs(g1[comp])
                                t = candidate_contact(kind, m, t_lin, zero, dt_lin, tol_distance, speed)
                                if t < best:
                                    best = t
                                    source = wp.float64(4.0)
        if distance_at(kind, m, one) <= tol_distance and one < best:
            best = one
            source = wp.float64(4.0)
    if best <= one:
        return wp.vec3d(one, best, source)
    return wp.vec3d(zero, inf, wp.float64(-1.0))


@wp.kernel(enable_backward=False)
def ccd_kernel(
    kind: int,
    queries: wp.array(dtype=mat83d),
    thickness: wp.float64,
    hit: wp.array(dtype=wp.int32),
    time_of_impact: wp.array(dtype=wp.float64),
    source: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    r = ccd_query(kind, queries[i], thickness)
    hit[i] = wp.int32(r[0])
    time_of_impact[i] = r[1]
    source[i] = wp.int32(r[2])


@wp.func
def query_coefficients(m: mat83d) -> wp.vec4d:
    return coplanarity_cubic(row(m, 0), row(m, 1), row(m, 2), row(m, 3), row(m, 4), row(m, 5), row(m, 6), row(m, 7))


@wp.kernel
def ccd_time_of_impact_kernel(
    queries: wp.array(dtype=mat83d),
    source: wp.array(dtype=wp.int32),
    detected_time: wp.array(dtype=wp.float64),
    max_derivative: wp.float64,
    time_of_impact: wp.array(dtype=wp.float64),
    roots: wp.array(dtype=vec6d),
):
    """Differentiable recomputation of the time of impact and the three (lifted) roots.

    For a hit found at a root of the coplanarity cubic (source 1-3) the time of impact is that
    root's real part, recomputed from the positions through the cubic's coefficients and
    :func:`kernels.roots.cubic_roots`; its adjoint is the mollified implicit derivative, bounded
    by ``max_derivative``. Other sources (t = 0, collinearity in a coplanar step, conservative
    advancement) and misses pass ``detected_time`` through with no time derivative.
    ``roots`` holds all three roots for every query (the lifted event an optimiser can aim at).
    """
    i = wp.tid()
    r = cubic_roots(unit_scaled_cubic(query_coefficients(queries[i])), CCD_T_MAX, max_derivative)
    roots[i] = r
    s = source[i]
    if s >= 1 and s <= 3:
        time_of_impact[i] = wp.clamp(r[(s - 1) + (s - 1)], wp.float64(0.0), wp.float64(1.0))
    else:
        time_of_impact[i] = detected_time[i]


@wp.kernel
def coplanarity_roots_kernel(
    queries: wp.array(dtype=mat83d),
    max_derivative: wp.float64,
    roots: wp.array(dtype=vec6d),
):
    """The three roots (fractions of the step; real or complex) of each query's unit-scaled
    coplanarity cubic: the lifted event of a pair, whatever it hits. Differentiable under a
    tape (mollified implicit derivative bounded by ``max_derivative``)."""
    i = wp.tid()
    roots[i] = cubic_roots(unit_scaled_cubic(query_coefficients(queries[i])), CCD_T_MAX, max_derivative)


@wp.kernel
def coplanarity_coefficients_kernel(
    queries: wp.array(dtype=mat83d),
    coefficients: wp.array(dtype=wp.vec4d),
):
    """Each query's unit-scaled coplanarity cubic ``[q, a, b, c]`` (the one whose roots
    :func:`coplanarity_roots_kernel` solves), for a root derivative chosen outside the kernel
    (eq. ``orthogonal_clamping_real_side``). Differentiable under a tape."""
    i = wp.tid()
    coefficients[i] = unit_scaled_cubic(query_coefficients(queries[i]))


@wp.func
def pair_vertex_indices(
    kind: int,
    pair: wp.vec2i,
    faces: wp.array(dtype=wp.vec3i),
    edges: wp.array(dtype=wp.vec2i),
) -> wp.vec4i:
    """The four vertex indices, in the query's order, of a candidate pair of a mesh:
    ``[vertex, face]`` (kind 0: ``p, t0, t1, t2``) or ``[edge_a, edge_b]`` (kind 1:
    ``ea0, ea1, eb0, eb1``)."""
    if kind == VERTEX_FACE:
        f = faces[pair[1]]
        return wp.vec4i(pair[0], f[0], f[1], f[2])
    a = edges[pair[0]]
    b = edges[pair[1]]
    return wp.vec4i(a[0], a[1], b[0], b[1])


@wp.func
def pair_query(q: wp.vec4i, x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d)) -> mat83d:
    """The (8, 3) query of a candidate pair's vertices ``q`` (:func:`pair_vertex_indices`)
    moving from positions ``x0`` at the start to ``x1`` at the end."""
    m = mat83d()
    for k in range(4):
        m[k] = x0[q[k]]
        m[k + 4] = x1[q[k]]
    return m


@wp.kernel(enable_backward=False)
def pair_ccd_kernel(
    vf_count: int,
    vf_pairs: wp.array(dtype=wp.vec2i),
    ee_pairs: wp.array(dtype=wp.vec2i),
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    edges: wp.array(dtype=wp.vec2i),
    thickness: wp.float64,
    counter: wp.array(dtype=wp.int32),
    hit_pairs: wp.array(dtype=wp.vec2i),
    hit_kind: wp.array(dtype=wp.int32),
    hit_time: wp.array(dtype=wp.float64),
    hit_source: wp.array(dtype=wp.int32),
    hit_vertices: wp.array(dtype=wp.vec4i),
):
    """The narrow phase of :func:`ccd_kernel` straight on a broad phase's candidate pairs: the
    first ``vf_count`` threads take the vertex-face pairs, the rest the edge-edge ones (indices
    into ``faces`` / ``edges`` of the positions ``x0``, ``x1``), one launch for both kinds. The
    hits are appended through ``counter`` with their kind and vertex indices (the buffers hold at
    least as many rows as there are pairs), so no per-pair array leaves the device."""
    i = wp.tid()
    kind = int(VERTEX_FACE)
    pair = wp.vec2i()
    if i < vf_count:
        pair = vf_pairs[i]
    else:
        kind = int(EDGE_EDGE)
        pair = ee_pairs[i - vf_count]
    q = pair_vertex_indices(kind, pair, faces, edges)
    r = ccd_query(kind, pair_query(q, x0, x1), thickness)
    if r[0] != wp.float64(0.0):
        slot = wp.atomic_add(counter, 0, 1)
        hit_pairs[slot] = pair
        hit_kind[slot] = wp.int32(kind)
        hit_time[slot] = r[1]
        hit_source[slot] = wp.int32(r[2])
        hit_vertices[slot] = q
