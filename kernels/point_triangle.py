"""Vertex-triangle primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import closest_segment_parameter


@wp.func
def point_triangle_closest(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec2d:
    """Parameters ``(v, w)`` of the closest point ``a + v (b - a) + w (c - a)`` of the closed
    triangle abc to p (any shape, degenerate included).

    Closest point by Voronoi regions (Ericson, Real-Time Collision Detection 5.1.5); a zero-area
    triangle falls back to the nearest of its three edges. The one closest-point definition of
    the project: the narrow phase's distances, the contact weights (barycentric ``(1 - v - w, v,
    w)``) and the penetration checker all use it. Differentiable inside each region.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    ab = b - a
    ac = c - a
    n = wp.cross(ab, ac)
    nn = wp.dot(n, n)
    scale = wp.max(wp.dot(ab, ab), wp.dot(ac, ac))
    if nn <= wp.float64(1.0e-30) * scale * scale or nn == zero:
        s_ab = closest_segment_parameter(p, a, b)
        s_bc = closest_segment_parameter(p, b, c)
        s_ac = closest_segment_parameter(p, a, c)
        best = wp.vec2d(s_ab, zero)
        d = p - (a + s_ab * ab)
        d_bc = p - (b + s_bc * (c - b))
        if wp.dot(d_bc, d_bc) < wp.dot(d, d):
            best = wp.vec2d(one - s_bc, s_bc)
            d = d_bc
        d_ac = p - (a + s_ac * ac)
        if wp.dot(d_ac, d_ac) < wp.dot(d, d):
            best = wp.vec2d(zero, s_ac)
        return best
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return wp.vec2d(zero, zero)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.vec2d(one, zero)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return wp.vec2d(d1 / (d1 - d3), zero)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.vec2d(zero, one)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return wp.vec2d(zero, d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec2d(one - w, w)
    # inside the face region: the projection on the plane
    denom = va + vb + vc
    return wp.vec2d(vb / denom, vc / denom)


@wp.func
def point_triangle_offset(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """p minus its closest point on the closed triangle abc (:func:`point_triangle_closest`).

    Returning the offset vector (not only its length) lets the caller bound its rounding per axis.
    """
    vw = point_triangle_closest(p, a, b, c)
    return p - (a + vw[0] * (b - a) + vw[1] * (c - a))
