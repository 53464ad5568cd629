"""Vertex-triangle primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import point_segment_distance


@wp.func
def point_triangle_distance(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """Euclidean distance from p to the closed triangle abc (any shape, degenerate included).

    Closest point by Voronoi regions (Ericson, Real-Time Collision Detection 5.1.5); a zero-area
    triangle falls back to the nearest of its three edges.
    """
    zero = wp.float64(0.0)
    ab = b - a
    ac = c - a
    n = wp.cross(ab, ac)
    nn = wp.dot(n, n)
    scale = wp.max(wp.dot(ab, ab), wp.dot(ac, ac))
    if nn <= wp.float64(1.0e-30) * scale * scale or nn == zero:
        d = point_segment_distance(p, a, b)
        d = wp.min(d, point_segment_distance(p, b, c))
        d = wp.min(d, point_segment_distance(p, a, c))
        return d
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return wp.length(ap)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.length(bp)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        v = d1 / (d1 - d3)
        return wp.length(p - (a + v * ab))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.length(cp)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        w = d2 / (d2 - d6)
        return wp.length(p - (a + w * ac))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.length(p - (b + w * (c - b)))
    # inside the face region: distance to the plane
    return wp.abs(wp.dot(ap, n)) / wp.sqrt(nn)
