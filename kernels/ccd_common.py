"""Shared pieces of the narrow-phase CCD kernels (Warp, float64).

Four points moving linearly over a step, ``x_i(t) = x_i0 + t (x_i1 - x_i0)`` with ``t in [0, 1]``,
are coplanar when the triple product of three edge vectors vanishes: a cubic in ``t`` (paper,
"Preliminaries"). Every first contact of a vertex with a triangle or of two edges happens at such
a root, or at ``t = 0``, or, when the four points stay coplanar for the whole step, at a time
when a vertex becomes collinear with an edge (a quadratic per coordinate). The narrow phase
checks the exact distance at each of these candidate times with a tolerance taken from an error
bound of the candidate time; see :func:`root_time_uncertainty`.
"""

import warp as wp


# float64 unit roundoff (2^-53)
UNIT_ROUNDOFF = wp.constant(wp.float64(1.1102230246251565e-16))
# Rounding in the coefficients: each is a sum of up to 9 triple products of differences of
# inputs (about 6 roundings deep); 64 u bounds it with margin for the Horner evaluation too.
COEFFICIENT_ERROR_FACTOR = wp.constant(wp.float64(64.0))
# Distance computations (closest points of point/triangle, segment/segment) round about 30
# times; 256 u of the coordinate magnitude bounds their error with margin.
DISTANCE_ERROR_FACTOR = wp.constant(wp.float64(256.0))
# A cubic whose coefficients are all below this fraction of its natural magnitude (S^3, with S
# the size of the relative motion) is treated as "coplanar for the whole step": rounding alone
# can produce coefficients of about 64 u S^3 = 7e-15 S^3, so 1e-12 leaves a margin.
COPLANAR_RELATIVE = wp.constant(wp.float64(1.0e-12))
# The solver's t_max for CCD cubics: roots beyond it are far outside [0, 1] anyway.
CCD_T_MAX = wp.constant(wp.float64(1.0e150))


@wp.func
def coplanarity_cubic(
    x1_0: wp.vec3d, x2_0: wp.vec3d, x3_0: wp.vec3d, x4_0: wp.vec3d,
    x1_1: wp.vec3d, x2_1: wp.vec3d, x3_1: wp.vec3d, x4_1: wp.vec3d,
) -> wp.vec4d:
    """Coefficients [q, a, b, c] of (x2 - x1) x (x3 - x1) . (x4 - x1) as a cubic in t.

    Edge vectors are differences of positions *at the same time* (start d_k, end d_k'), and the
    motion of each is e_k = d_k' - d_k: no large absolute coordinates enter the products, so a
    scene far from the origin loses nothing to cancellation.
    """
    d2 = x2_0 - x1_0
    d3 = x3_0 - x1_0
    d4 = x4_0 - x1_0
    e2 = (x2_1 - x1_1) - d2
    e3 = (x3_1 - x1_1) - d3
    e4 = (x4_1 - x1_1) - d4
    c = wp.dot(wp.cross(d2, d3), d4)
    b = wp.dot(wp.cross(e2, d3), d4) + wp.dot(wp.cross(d2, e3), d4) + wp.dot(wp.cross(d2, d3), e4)
    a = wp.dot(wp.cross(e2, e3), d4) + wp.dot(wp.cross(e2, d3), e4) + wp.dot(wp.cross(d2, e3), e4)
    q = wp.dot(wp.cross(e2, e3), e4)
    return wp.vec4d(q, a, b, c)


@wp.func
def unit_scaled_cubic(p: wp.vec4d) -> wp.vec4d:
    """``p / max|p_k|`` (``p`` itself when all are zero): the same roots with the largest
    coefficient of magnitude 1.

    The coplanarity cubic has units of volume, so its raw size depends on the scene's scale; the
    robust division bound ``M`` of the mollified derivative (the paper's eq. ``dpboundeddp``
    scales only coefficients *above* 1) would then clamp the derivative of perfectly transversal
    contacts of small primitives (a 2 cm particle step on a 20 cm face: ``|p'(t*)| = 6e-4 <
    1/M``). Scaling to unit size makes ``M`` a unit-free bound on ``1/|p'(t*)|`` relative to
    the cubic's own size, which is what "near-tangential" means.
    """
    m = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.max(wp.abs(p[2]), wp.abs(p[3])))
    if m > wp.float64(0.0):
        return p / m
    return p


@wp.func
def lerp3(x0: wp.vec3d, x1: wp.vec3d, t: wp.float64) -> wp.vec3d:
    return x0 + t * (x1 - x0)


@wp.func
def max_abs_vec3(v: wp.vec3d) -> wp.float64:
    return wp.max(wp.abs(v[0]), wp.max(wp.abs(v[1]), wp.abs(v[2])))


@wp.func
def cubic_derivative_values(p: wp.vec4d, t: wp.float64) -> wp.vec4d:
    """(f, f', f'', f''') of q t^3 + a t^2 + b t + c at t."""
    q = p[0]
    a = p[1]
    b = p[2]
    c = p[3]
    f = ((q * t + a) * t + b) * t + c
    d1 = (wp.float64(3.0) * q * t + wp.float64(2.0) * a) * t + b
    d2 = wp.float64(6.0) * q * t + wp.float64(2.0) * a
    d3 = wp.float64(6.0) * q
    return wp.vec4d(f, d1, d2, d3)


@wp.func
def root_time_uncertainty(p: wp.vec4d, t: wp.float64, coefficient_error: wp.float64) -> wp.float64:
    """How far the exact cubic's root may lie from a computed root ``t``, from rounding alone.

    The coefficients are known to within ``coefficient_error`` each, so f is known to within
    E = coefficient_error * sum |t|^k (plus the evaluation's rounding). A perturbation of size E
    moves a root by about min_k (k! E / |f^(k)(t)|)^(1/k), k = 1..3 (the Taylor expansion is exact
    for a cubic; the minimum over orders covers simple, double and triple roots alike). For a
    complex pair evaluated at its real part, an imaginary part below this radius means the exact
    cubic may have real roots there (a graze). Returns at most 1 (the whole step), never NaN.
    """
    at = wp.abs(t)
    powers = wp.float64(1.0) + at + at * at + at * at * at
    vals = cubic_derivative_values(p, t)
    mag = (wp.abs(p[0]) * at * at * at + wp.abs(p[1]) * at * at + wp.abs(p[2]) * at + wp.abs(p[3]))
    e = coefficient_error * powers + COEFFICIENT_ERROR_FACTOR * UNIT_ROUNDOFF * mag
    best = wp.float64(1.0)
    if wp.abs(vals[1]) > wp.float64(0.0):
        best = wp.min(best, e / wp.abs(vals[1]))
    if wp.abs(vals[2]) > wp.float64(0.0):
        best = wp.min(best, wp.sqrt(wp.float64(2.0) * e / wp.abs(vals[2])))
    if wp.abs(vals[3]) > wp.float64(0.0):
        best = wp.min(best, wp.pow(wp.float64(6.0) * e / wp.abs(vals[3]), wp.float64(1.0) / wp.float64(3.0)))
    return best


@wp.func
def closest_segment_parameter(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d) -> wp.float64:
    ab = b - a
    denom = wp.dot(ab, ab)
    if denom <= wp.float64(0.0):
        return wp.float64(0.0)
    s = wp.dot(p - a, ab) / denom
    return wp.clamp(s, wp.float64(0.0), wp.float64(1.0))


@wp.func
def within(offset: wp.vec3d, tolerance: wp.vec3d) -> bool:
    """|offset| <= tolerance on every axis (a box test, as conservative as its per-axis bounds)."""
    return wp.abs(offset[0]) <= tolerance[0] and wp.abs(offset[1]) <= tolerance[1] and wp.abs(offset[2]) <= tolerance[2]


@wp.func
def collinearity_quadratics(
    p0: wp.vec3d, a0: wp.vec3d, b0: wp.vec3d, p1: wp.vec3d, a1: wp.vec3d, b1: wp.vec3d
) -> wp.mat33d:
    """Rows k = 0..2: [t^2, t, 1] coefficients of component k of (a - p) x (b - p) over the step.

    p(t) lies on the line ab exactly when all three vanish; in a step where the four points stay
    coplanar, a vertex meets an edge only at a common root of these.
    """
    u0 = a0 - p0
    v0 = b0 - p0
    du = (a1 - p1) - u0
    dv = (b1 - p1) - v0
    c0 = wp.cross(u0, v0)
    c1 = wp.cross(du, v0) + wp.cross(u0, dv)
    c2 = wp.cross(du, dv)
    return wp.mat33d(c2[0], c1[0], c0[0], c2[1], c1[1], c0[1], c2[2], c1[2], c0[2])
