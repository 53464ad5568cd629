"""Edge-edge primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import closest_segment_parameter


@wp.func
def segment_segment_closest(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d) -> wp.vec2d:
    """Parameters ``(s, t)`` of the closest points ``p1 + s (q1 - p1)`` and ``p2 + t (q2 - p2)``
    of two closed segments (zero-length and parallel included).

    The nearest of the four endpoint-to-segment pairs and, when the closest points of the two
    supporting lines fall inside both segments, the line-line pair there.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    u = q1 - p1
    v = q2 - p2
    w = p1 - p2
    t0 = closest_segment_parameter(p1, p2, q2)
    best = wp.vec2d(zero, t0)
    d = w - t0 * v
    t1 = closest_segment_parameter(q1, p2, q2)
    e1 = w + u - t1 * v
    if wp.dot(e1, e1) < wp.dot(d, d):
        best = wp.vec2d(one, t1)
        d = e1
    s0 = closest_segment_parameter(p2, p1, q1)
    e2 = w + s0 * u
    if wp.dot(e2, e2) < wp.dot(d, d):
        best = wp.vec2d(s0, zero)
        d = e2
    s1 = closest_segment_parameter(q2, p1, q1)
    e3 = w + s1 * u - v
    if wp.dot(e3, e3) < wp.dot(d, d):
        best = wp.vec2d(s1, one)
        d = e3
    a = wp.dot(u, u)
    b = wp.dot(u, v)
    c = wp.dot(v, v)
    dd = wp.dot(u, w)
    e = wp.dot(v, w)
    den = a * c - b * b
    if den > wp.float64(1.0e-24) * a * c and a > zero and c > zero:
        s = (b * e - c * dd) / den
        t = (a * e - b * dd) / den
        if s >= zero and s <= one and t >= zero and t <= one:
            e4 = w + s * u - t * v
            if wp.dot(e4, e4) < wp.dot(d, d):
                best = wp.vec2d(s, t)
    return best


@wp.func
def segment_segment_offset(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d) -> wp.vec3d:
    """Closest point of segment p1q1 minus closest point of segment p2q2
    (:func:`segment_segment_closest`)."""
    st = segment_segment_closest(p1, q1, p2, q2)
    return (p1 - p2) + st[0] * (q1 - p1) - st[1] * (q2 - p2)
