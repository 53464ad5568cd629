"""Warp kernels of the independent penetration checker (:mod:`sim.penetration`)."""

import warp as wp

from kernels.point_triangle import point_triangle_offset


@wp.kernel(enable_backward=False)
def winding_distance_kernel(
    x: wp.array(dtype=wp.vec3d),
    query_point: wp.array(dtype=wp.int32),
    query_solid: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec3i),
    solid_face_start: wp.array(dtype=wp.int32),
    winding: wp.array(dtype=wp.float64),
    distance: wp.array(dtype=wp.float64),
):
    """Winding number of point ``x[query_point[i]]`` w.r.t. solid ``query_solid[i]`` (faces
    ``solid_face_start[s] .. solid_face_start[s + 1]``, global vertex ids) and, where it exceeds
    1/2, the distance to the solid's surface (else +inf)."""
    i = wp.tid()
    p = x[query_point[i]]
    s = query_solid[i]
    f0 = solid_face_start[s]
    f1 = solid_face_start[s + 1]
    total = wp.float64(0.0)
    for f in range(f0, f1):
        t = faces[f]
        a = x[t[0]] - p
        b = x[t[1]] - p
        c = x[t[2]] - p
        la = wp.length(a)
        lb = wp.length(b)
        lc = wp.length(c)
        det = wp.dot(a, wp.cross(b, c))
        den = la * lb * lc + wp.dot(a, b) * lc + wp.dot(b, c) * la + wp.dot(c, a) * lb
        total += wp.atan2(det, den)
    w = total / wp.float64(2.0 * 3.141592653589793)
    winding[i] = w
    best = wp.float64(1.0e300)
    if w > wp.float64(0.5):
        for f in range(f0, f1):
            t = faces[f]
            q = point_triangle_offset(p, x[t[0]], x[t[1]], x[t[2]])
            best = wp.min(best, wp.length(q))
    distance[i] = best
