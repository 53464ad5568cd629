"""Vertex-triangle primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import nearer, point_segment_offset


@wp.func
def point_triangle_offset(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """p minus its closest point on the closed triangle abc (any shape, degenerate included).

    Closest point by Voronoi regions (Ericson, Real-Time Collision Detection 5.1.5); a zero-area
    triangle falls back to the nearest of its three edges. Returning the offset vector (not only
    its length) lets the caller bound its rounding per axis.
    """
    zero = wp.float64(0.0)
    ab = b - a
    ac = c - a
    n = wp.cross(ab, ac)
    nn = wp.dot(n, n)
    scale = wp.max(wp.dot(ab, ab), wp.dot(ac, ac))
    if nn <= wp.float64(1.0e-30) * scale * scale or nn == zero:
        d = point_segment_offset(p, a, b)
        d = nearer(d, point_segment_offset(p, b, c))
        d = nearer(d, point_segment_offset(p, a, c))
        return d
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return ap
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return bp
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        v = d1 / (d1 - d3)
        return p - (a + v * ab)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return cp
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        w = d2 / (d2 - d6)
        return p - (a + w * ac)
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return p - (b + w * (c - b))
    # inside the face region: p minus its projection on the plane, (ap . n) n / |n|^2
    denom = va + vb + vc
    v = vb / denom
    w = vc / denom
    return p - (a + v * ab + w * ac)
