"""Edge-edge primitive pair for the narrow phase (Warp, float64)."""

import warp as wp

from kernels.ccd_common import nearer, point_segment_offset


@wp.func
def segment_segment_offset(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d) -> wp.vec3d:
    """Closest point of segment p1q1 minus closest point of segment p2q2 (closed segments;
    zero-length and parallel included).

    The nearest of the four endpoint-to-segment offsets and, when the closest points of the two
    supporting lines fall inside both segments, the line-line offset there.
    """
    d = point_segment_offset(p1, p2, q2)
    d = nearer(d, point_segment_offset(q1, p2, q2))
    d = nearer(d, -point_segment_offset(p2, p1, q1))
    d = nearer(d, -point_segment_offset(q2, p1, q1))
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
            d = nearer(d, w + s * u - t * v)
    return d
