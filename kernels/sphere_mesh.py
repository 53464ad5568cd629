"""Sphere-vs-static-triangle primitive pair (Warp, float64): when and where a moving sphere
first touches a triangle's face, one of its edges or one of its corners.

A sphere of radius ``reach`` (its radius plus the separation) whose centre moves on
``x(t) = x0 + t v`` touches the closed triangle abc when the centre enters the triangle grown by
``reach``: the union of the face's slab (a linear time of impact, valid where the contact point
lies inside the triangle), the edges' cylinders (the quadratic of the centre's distance from the
edge's line, valid within the edge) and the corners' spheres (the quadratic of the distance from
the corner, the paper's sphere case). The earliest entry over the seven features is the
triangle's contact. Features are numbered 0 (face), 1-3 (edges ab, bc, ca) and 4-6 (corners a,
b, c).

:func:`feature_entry_time` decides (off the tape); :func:`feature_contact` replays the chosen
feature's time of impact and contact normal on the tape (the edges and corners are
:mod:`kernels.point_ball` pairs: quadratics with the mollified derivative).
"""

import warp as wp

from kernels.point_ball import entry_time, impact_time

f64 = wp.float64


@wp.func
def corner(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, k: int) -> wp.vec3d:
    if k == 0:
        return a
    if k == 1:
        return b
    return c


@wp.func
def face_normal_towards(x0: wp.vec3d, v: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """The triangle's unit normal on the side the centre starts (against ``v`` when it starts
    in the plane)."""
    n = wp.normalize(wp.cross(b - a, c - a))
    side = wp.dot(n, x0 - a)
    if side < f64(0.0) or (side == f64(0.0) and wp.dot(n, v) > f64(0.0)):
        n = -n
    return n


@wp.func
def feature_entry_time(x0: wp.vec3d, v: wp.vec3d, reach: wp.float64, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d,
                       feature: int, h: wp.float64, t_max: wp.float64) -> wp.float64:
    """The time [s] in ``[0, h]`` at which the centre first comes within ``reach`` of the
    triangle's ``feature`` (module docstring), moving closer, with the contact inside that
    feature; -1 when it does not."""
    if feature == 0:
        n = face_normal_towards(x0, v, a, b, c)
        vn = wp.dot(n, v)
        if vn >= f64(0.0):
            return f64(-1.0)
        t = wp.max((reach - wp.dot(n, x0 - a)) / vn, f64(0.0))
        if t > h:
            return f64(-1.0)
        # the contact point on the face must lie inside the triangle
        p = x0 + t * v - reach * n - a
        e1 = b - a
        e2 = c - a
        d11 = wp.dot(e1, e1)
        d12 = wp.dot(e1, e2)
        d22 = wp.dot(e2, e2)
        det = d11 * d22 - d12 * d12
        s1 = (d22 * wp.dot(p, e1) - d12 * wp.dot(p, e2)) / det
        s2 = (d11 * wp.dot(p, e2) - d12 * wp.dot(p, e1)) / det
        if s1 < f64(0.0) or s2 < f64(0.0) or s1 + s2 > f64(1.0):
            return f64(-1.0)
        return t
    if feature <= 3:
        q0 = corner(a, b, c, feature - 1)
        q1 = corner(a, b, c, feature % 3)
        length = wp.length(q1 - q0)
        u = (q1 - q0) / length
        w = x0 - q0
        t = entry_time(w - wp.dot(w, u) * u, v - wp.dot(v, u) * u, reach, h, t_max, f64(0.0))
        if t < f64(0.0):
            return t
        s = wp.dot(w + t * v, u)
        if s < f64(0.0) or s > length:
            return f64(-1.0)
        return t
    return entry_time(x0 - corner(a, b, c, feature - 4), v, reach, h, t_max, f64(0.0))


@wp.func
def feature_contact(x0: wp.vec3d, v: wp.vec3d, reach: wp.float64, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d,
                    feature: int, h: wp.float64, t_max: wp.float64, max_derivative: wp.float64) -> wp.vec4d:
    """The chosen feature's time of impact [s] (clamped to ``[0, h]``) and unit contact normal
    (from the triangle to the centre), ``(t*, n)``; differentiable on the tape."""
    zero = f64(0.0)
    if feature == 0:
        n = face_normal_towards(x0, v, a, b, c)
        t = wp.clamp((reach - wp.dot(n, x0 - a)) / wp.dot(n, v), zero, h)
        return wp.vec4d(t, n[0], n[1], n[2])
    w = x0 - corner(a, b, c, feature - 4)
    dv = v
    if feature <= 3:
        q0 = corner(a, b, c, feature - 1)
        u = wp.normalize(corner(a, b, c, feature % 3) - q0)
        w0 = x0 - q0
        w = w0 - wp.dot(w0, u) * u
        dv = v - wp.dot(v, u) * u
    t = impact_time(w, dv, reach, h, t_max, max_derivative)
    n = wp.normalize(w + t * dv)
    return wp.vec4d(t, n[0], n[1], n[2])
