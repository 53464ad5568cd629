"""Edge-edge primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import point_segment_distance


@wp.func
def segment_segment_distance(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d) -> wp.float64:
    """Distance between closed segments p1q1 and p2q2 (zero-length and parallel included).

    The minimum of the four endpoint-to-segment distances and, when the interior closest points
    of the two supporting lines fall inside both segments, the line-line distance there.
    """
    d = point_segment_distance(p1, p2, q2)
    d = wp.min(d, point_segment_distance(q1, p2, q2))
    d = wp.min(d, point_segment_distance(p2, p1, q1))
    d = wp.min(d, point_segment_distance(q2, p1, q1))
    u = q1 - p1
    v = q2 - p2
    w = p1 - p2
    a = wp.dot(u, u)
    b = wp.dot(u, v)
    c = wp.dot(v, v)
    dd = wp.dot(u, w)
    e = wp.dot(v, w)
    den = a * c - b * b
    if den > wp.float64(1.0e-24) * a * c and a > wp.float64(0.0) and c > wp.float64(0.0):
        s = (b * e - c * dd) / den
        t = (a * e - b * dd) / den
        if s >= wp.float64(0.0) and s <= wp.float64(1.0) and t >= wp.float64(0.0) and t <= wp.float64(1.0):
            d = wp.min(d, wp.length(w + s * u - t * v))
    return d
