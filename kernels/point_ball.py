"""A point moving on a straight line against a ball (Warp, float64): the paper's quadratic case.

The point ``w + t v`` (relative to the ball's centre) is within ``reach`` of the centre when
``|w + t v|^2 - reach^2 = 0``: a quadratic in ``t`` whose smaller root is the time of impact and
whose complex pair is a miss. Two spheres (``w`` the difference of their centres, ``reach`` the
sum of their radii), a sphere's centre against a triangle's corner, and against an edge's line
(the components across the edge) are this pair. :func:`entry_time` decides (off the tape);
:func:`impact_time` replays the time of impact on the tape, through
:func:`kernels.roots.quadratic_roots`, whose adjoint is the mollified implicit derivative.
"""

import warp as wp

from kernels.roots import quadratic_roots, quadratic_solve

f64 = wp.float64


@wp.func
def distance_quadratic(w: wp.vec3d, v: wp.vec3d, reach: wp.float64) -> wp.vec3d:
    """Coefficients ``(a, b, c)`` of ``|w + t v|^2 - reach^2`` [m^2] in ``t`` [s], the constant
    term factored, ``(|w| - reach)(|w| + reach)`` (exact to rounding near touching)."""
    dist = wp.length(w)
    return wp.vec3d(wp.dot(v, v), f64(2.0) * wp.dot(w, v), (dist - reach) * (dist + reach))


@wp.func
def entry_time(w: wp.vec3d, v: wp.vec3d, reach: wp.float64, h: wp.float64, t_max: wp.float64,
               slack: wp.float64) -> wp.float64:
    """When ``w + t v`` first comes within ``reach`` of the origin, moving closer (its speed
    towards the origin above ``slack`` [m/s]), within ``[0, h]`` (0 when it starts within); -1
    when it does not."""
    if wp.dot(w, v) >= -slack * wp.length(w):
        return f64(-1.0)
    if wp.length(w) <= reach:
        return f64(0.0)
    p = distance_quadratic(w, v, reach)
    roots, _sa = quadratic_solve(p[0], p[1], p[2], t_max)
    if roots[1] == f64(0.0) and roots[0] <= h:
        return roots[0]
    return f64(-1.0)


@wp.func
def impact_time(w: wp.vec3d, v: wp.vec3d, reach: wp.float64, h: wp.float64, t_max: wp.float64,
                max_derivative: wp.float64) -> wp.float64:
    """The time of impact [s] in ``[0, h]`` of a contact :func:`entry_time` decided: the
    quadratic's smaller root, clamped (0 when the point starts within ``reach``);
    differentiable on the tape."""
    if wp.length(w) <= reach:
        return f64(0.0)
    roots = quadratic_roots(distance_quadratic(w, v, reach), t_max, max_derivative)
    return wp.clamp(roots[0], f64(0.0), h)
