"""Robust all-roots solvers for quadratics and cubics, with the paper's mollified derivatives.

Everything here is Warp float64 code. The solvers return *every* root, real and complex, for every
coefficient pattern (leading coefficients zero, all zero, repeated and triple roots, roots beyond
``t_max``), and the derivative of each root comes from the implicit equations of the paper
(Johnson & Fedkiw), never from the iterations:

* quadratic: eq. ``ourapproachderivctilde`` with the clamped signs of Remark ``clampingderiv``;
* cubic: eqs. ``ourapproachderivcubicorigreal`` (real roots), ``handle_by_factoring`` (q = 0),
  ``ourapproachderivcubicsecondcase`` (3 q tR + a = 0), ``ourapproachderivcubicrealmul`` and
  ``ourapproachderivcubicimagmul`` (general complex roots), with the signs of Remarks
  ``cubicclampingderivs`` / ``othercubicclampingderivs``, chained through the coefficient
  normalisation of eq. ``dpboundeddp``.

Every scalar multiplier is evaluated by *robust division*: the largest entry of its vector is
factored out (numerator magnitude ``N``), and ``N / D`` is replaced by ``M`` (``max_derivative``)
whenever ``N >= D * M`` or the denominator has the wrong (clamped) sign.

The solver is exposed to other kernels as :func:`quadratic_roots` and :func:`cubic_roots`
(``@wp.func``), whose adjoints are registered with ``@wp.func_grad``: any kernel that calls them
under a ``wp.Tape`` receives the mollified derivatives.

Root slots (design.md, "Root slot conventions"):

* quadratic ``vec4d(t-.re, t-.im, t+.re, t+.im)``; ``t+ = (-b + sqrt(b^2 - 4ac)) / 2a``;
* cubic ``vec6d(t-.re, t-.im, tM.re, tM.im, t+.re, t+.im)``; three real roots ascending; one real
  root sits in ``t+`` when it lies right of the complex pair's real part (equivalently the reduced
  ``c^ <= 0``) and in ``t-`` otherwise; the larger-labelled slot of the pair takes ``+Im``.
"""

import warp as wp

f64 = wp.float64

vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat43d = wp.types.matrix(shape=(4, 3), dtype=wp.float64)
"""Quadratic Jacobian: rows (t-.re, t-.im, t+.re, t+.im), columns (a, b, c)."""
mat64d = wp.types.matrix(shape=(6, 4), dtype=wp.float64)
"""Cubic Jacobian: rows (t-.re, t-.im, tM.re, tM.im, t+.re, t+.im), columns (q, a, b, c)."""
mat24d = wp.types.matrix(shape=(2, 4), dtype=wp.float64)
"""d(Re, Im)/d(q, a, b, c) of one cubic root."""

DEFAULT_T_MAX = 1.0e150
"""Largest root magnitude returned (the paper's value); escaping roots are clamped to it."""
DEFAULT_MAX_DERIVATIVE = 1000.0
"""``M`` of the robust division (the paper's value)."""

# Safeguarded Newton-bisection on a bracket inside [-1, 1]: bisection alone needs at most
# ~11 steps to locate the binary exponent (geometric bisection) plus 53 for the mantissa; the
# Newton acceptance test below bisects at least every other step, so 256 is a generous cap.
NEWTON_MAX_ITERATIONS = wp.constant(256)
# Relative step below which a Newton iterate is accepted: 2 ulp of float64.
NEWTON_RELATIVE_TOLERANCE = wp.constant(wp.float64(4.440892098500626e-16))
# Largest max-|coefficient| solved without rescaling (2^100): cubic values on [-1, 1] stay far
# from overflow, and for maxima >= 0.5 rescaling could only push small terms towards underflow.
NO_RESCALE_MAX = wp.constant(wp.float64(1.2676506002282294e30))
# sqrt(3), used for the cancellation-free factorisations of 3 x^2 - y^2 (Remark splitupforcancelerror).
SQRT3 = wp.constant(wp.float64(1.7320508075688772))


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------


@wp.func
def sign_nonneg(x: wp.float64) -> wp.float64:
    """+1 for x >= 0 (including +0 and -0), -1 otherwise."""
    if x < wp.float64(0.0):
        return wp.float64(-1.0)
    return wp.float64(1.0)


@wp.func
def bounded_quotient(num: wp.float64, den: wp.float64, limit: wp.float64) -> wp.float64:
    """num / den with magnitude clamped to ``limit`` (the root solver's ``t_max`` division).

    ``den == 0`` gives ``sign(num) * limit`` (``num`` must then be non-zero) without dividing.
    """
    an = wp.abs(num)
    ad = wp.abs(den)
    if an == wp.float64(0.0):
        return wp.float64(0.0)
    s = sign_nonneg(num) * sign_nonneg(den)
    if ad == wp.float64(0.0):
        return s * limit
    if an < ad * limit:
        return num / den
    return s * limit


@wp.func
def robust_multiplier(
    num_mag: wp.float64, den: wp.float64, den_scale: wp.float64, required_sign: wp.float64, limit: wp.float64
) -> wp.float64:
    """Robust division of the paper (text after eq. ``ourapproachderivctilde``).

    Returns ``required_sign * min(num_mag / |den * den_scale|, limit)``. The denominator's sign is
    clamped: if ``den * required_sign <= 0`` it is treated as zero and the result is
    ``required_sign * limit``. ``den_scale > 0`` is a second factor of the denominator kept apart
    so that the product never under- or overflows before the comparison with ``limit``.

    Args:
        num_mag: magnitude factored out of the vector (>= 0, finite).
        den: signed denominator.
        den_scale: positive finite factor of the denominator's magnitude.
        required_sign: +1 or -1, the sign the denominator must have.
        limit: maximum magnitude ``M``.
    """
    d = den * required_sign
    if d <= wp.float64(0.0):
        return required_sign * limit
    # sequential division: an intermediate overflow means the quotient exceeds any sane limit
    r = num_mag / d
    r = r / den_scale
    if r < limit:
        return required_sign * r
    return required_sign * limit


@wp.func
def cubic_value(q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, x: wp.float64) -> wp.float64:
    return ((q * x + a) * x + b) * x + c


@wp.func
def bracket_split(lo: wp.float64, hi: wp.float64) -> wp.float64:
    """A point strictly inside (lo, hi) when one exists, else lo or hi.

    Zero when the bracket straddles it; the geometric mean when the ends differ by more than a
    factor 16 (so roots of tiny magnitude are reached in ~log2(exponent range) steps); the
    arithmetic midpoint otherwise.
    """
    zero = wp.float64(0.0)
    if lo < zero and hi > zero:
        return zero
    s = wp.float64(1.0)
    small = wp.abs(lo)
    big = wp.abs(hi)
    if hi <= zero:
        s = wp.float64(-1.0)
        small = wp.abs(hi)
        big = wp.abs(lo)
    if small == zero:
        if big > wp.float64(1.0e-280):
            return s * big * wp.float64(2.3283064365386963e-10)  # 2^-32
        return lo + wp.float64(0.5) * (hi - lo)
    if big > wp.float64(16.0) * small:
        return s * wp.sqrt(small) * wp.sqrt(big)
    return lo + wp.float64(0.5) * (hi - lo)


@wp.func
def newton_bisect_core(
    q: wp.float64,
    a: wp.float64,
    b: wp.float64,
    c: wp.float64,
    x_neg: wp.float64,
    f_neg: wp.float64,
    x_pos: wp.float64,
    f_pos: wp.float64,
    rescale_below: wp.float64,
) -> wp.vec4d:
    """Safeguarded Newton-bisection for a root of q x^3 + a x^2 + b x + c in a sign-change bracket.

    Starts at the secant (regula falsi) point of the bracket; a Newton step is taken only when it
    stays strictly inside the bracket and is at most 0.4 of the previous step (so a Newton
    sequence that merely halves x far from the root is replaced by the geometric split of
    :func:`bracket_split`); otherwise the bracket is split. Stops on an exact zero, a Newton step
    below 2 ulp, or a bracket of adjacent floats.

    Args:
        x_neg, f_neg: bracket end with cubic value < 0.
        x_pos, f_pos: bracket end with cubic value > 0 (either order).

        rescale_below: stop early, flagged, once the whole bracket is below this magnitude.

    Returns:
        vec4d(root (to about 2 ulp), 1 if stopped for rescaling else 0, x_neg, x_pos).
    """
    zero = wp.float64(0.0)
    rescale = wp.float64(0.0)
    lo = wp.min(x_neg, x_pos)
    hi = wp.max(x_neg, x_pos)
    x = x_neg - f_neg * ((x_pos - x_neg) / (f_pos - f_neg))
    if not (x > lo and x < hi):
        x = bracket_split(lo, hi)
    last_step = hi - lo
    result = x
    it = int(0)
    while it < NEWTON_MAX_ITERATIONS:
        it = it + 1
        if wp.max(wp.abs(x_neg), wp.abs(x_pos)) < rescale_below:
            rescale = wp.float64(1.0)
            break
        f = cubic_value(q, a, b, c, x)
        if f == zero:
            result = x
            break
        if f < zero:
            x_neg = x
            f_neg = f
        else:
            x_pos = x
            f_pos = f
        lo = wp.min(x_neg, x_pos)
        hi = wp.max(x_neg, x_pos)
        df = (wp.float64(3.0) * q * x + wp.float64(2.0) * a) * x + b
        x_new = x
        use_newton = bool(False)
        if df != zero:
            x_new = x - f / df
            if x_new > lo and x_new < hi:
                if wp.abs(x_new - x) <= wp.float64(0.4) * wp.abs(last_step):
                    use_newton = True
        if use_newton:
            step = x_new - x
            last_step = step
            x = x_new
            result = x
            if wp.abs(step) <= NEWTON_RELATIVE_TOLERANCE * wp.abs(x_new):
                break
        else:
            x_mid = bracket_split(lo, hi)
            if x_mid <= lo or x_mid >= hi:
                # adjacent floats: the end with the smaller residual
                if -f_neg < f_pos:
                    result = x_neg
                else:
                    result = x_pos
                break
            last_step = x_mid - x
            x = x_mid
            result = x
    return wp.vec4d(result, rescale, x_neg, x_pos)


# --------------------------------------------------------------------------------------------
# balancing for coefficients spread over more than ~2^960 (root-scale change t = 2^L u)
# --------------------------------------------------------------------------------------------

# Nonzero coefficients closer than this factor to the largest one survive a rescaling to ~1
# without entering the subnormal range (2^-960 leaves 62 binary orders of headroom).
BALANCE_SPREAD = wp.constant(wp.float64(1.0261652496336e-289))


@wp.func
def times_pow2(x: wp.float64, e: wp.float64) -> wp.float64:
    """x * 2^e for integer-valued e (|e| <= 3000) in three exact steps (no intermediate overflow
    when the result is representable: each step moves a third of the way)."""
    e1 = wp.floor(e / wp.float64(3.0))
    e2 = wp.floor((e - e1) / wp.float64(2.0))
    e3 = e - e1 - e2
    two = wp.float64(2.0)
    return ((x * wp.pow(two, e1)) * wp.pow(two, e2)) * wp.pow(two, e3)


@wp.func
def needs_balancing(p: wp.vec4d, m: wp.float64) -> bool:
    """True when some nonzero coefficient is below 2^-960 times the largest magnitude ``m``."""
    limit = m * BALANCE_SPREAD
    small = bool(False)
    for i in range(4):
        v = wp.abs(p[i])
        if v != wp.float64(0.0) and v < limit:
            small = True
    return small


@wp.func
def exponent_spread(p: wp.vec4d, e: wp.vec4d, root_exp: wp.float64) -> wp.vec2d:
    """(max, min) over nonzero p[k] of e[k] + (3 - k) * root_exp."""
    hi = wp.float64(-1.0e30)
    lo = wp.float64(1.0e30)
    for k in range(4):
        if p[k] != wp.float64(0.0):
            v = e[k] + wp.float64(3 - k) * root_exp
            hi = wp.max(hi, v)
            lo = wp.min(lo, v)
    return wp.vec2d(hi, lo)


@wp.func
def balance(p: wp.vec4d):
    """Root-scale exponent L and coefficients of the cubic in u = t / 2^L, rescaled to max ~1.

    Substituting t = 2^L u multiplies coefficient k (degree 3 - k) by 2^((3-k) L); L is chosen
    among the breakpoints of the Newton polygon (exponent differences of coefficient pairs over
    their degree gap) to minimise the spread of the resulting binary exponents, then everything
    is divided by a power of two so the largest magnitude is in [1, 2). All scalings are exact.

    Returns:
        (L, scaled coefficients vec4d).
    """
    e = wp.vec4d()
    for k in range(4):
        if p[k] != wp.float64(0.0):
            e[k] = wp.floor(wp.log2(wp.abs(p[k])))
    best_l = wp.float64(0.0)
    spread0 = exponent_spread(p, e, best_l)
    best_spread = spread0[0] - spread0[1]
    for i in range(4):
        for j in range(i + 1, 4):
            if p[i] != wp.float64(0.0) and p[j] != wp.float64(0.0):
                cand = wp.round((e[j] - e[i]) / wp.float64(j - i))
                sp = exponent_spread(p, e, cand)
                if sp[0] - sp[1] < best_spread:
                    best_spread = sp[0] - sp[1]
                    best_l = cand
    top = exponent_spread(p, e, best_l)[0]
    scaled = wp.vec4d()
    for k in range(4):
        scaled[k] = times_pow2(p[k], wp.float64(3 - k) * best_l - top)
    return best_l, scaled


@wp.func
def unbalance_root(x: wp.float64, root_exp: wp.float64, u_max: wp.float64, t_max: wp.float64) -> wp.float64:
    """t = 2^L u for one root part, with escaping (|u| >= u_max) and large parts clamped to t_max."""
    if x == wp.float64(0.0):
        return x
    if wp.abs(x) >= u_max:
        return sign_nonneg(x) * t_max
    if wp.log2(wp.abs(x)) + root_exp >= wp.log2(t_max):
        return sign_nonneg(x) * t_max
    return times_pow2(x, root_exp)


@wp.func
def scaled_root_limit(root_exp: wp.float64, t_max: wp.float64) -> wp.float64:
    """t_max expressed in u = t / 2^L, kept within [2^-1000, 2^1000]."""
    e = wp.log2(t_max) - root_exp
    if e > wp.float64(1000.0):
        return wp.pow(wp.float64(2.0), wp.float64(1000.0))
    if e < wp.float64(-1000.0):
        return wp.pow(wp.float64(2.0), wp.float64(-1000.0))
    return times_pow2(t_max, -root_exp)


# Below this magnitude the terms of a cubic with O(1) coefficients can underflow (x^3 ~ 2^-300):
# brackets and critical points this small are searched in the variable u = x / 2^L.
SMALL_ARGUMENT = wp.constant(wp.float64(7.888609052210118e-31))  # 2^-100


@wp.func
def coefficients_at_scale(q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, root_exp: wp.float64) -> wp.vec4d:
    """Coefficients of 2^K f(2^L u) with K making the largest one ~1 (all scalings exact)."""
    p = wp.vec4d(q, a, b, c)
    e = wp.vec4d()
    for k in range(4):
        if p[k] != wp.float64(0.0):
            e[k] = wp.floor(wp.log2(wp.abs(p[k])))
    top = exponent_spread(p, e, root_exp)[0]
    out = wp.vec4d()
    for k in range(4):
        out[k] = times_pow2(p[k], wp.float64(3 - k) * root_exp - top)
    return out


@wp.func
def cubic_sign_value(q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, x: wp.float64) -> wp.float64:
    """A positive multiple of f(x): exact f(x) for |x| >= 2^-100, else evaluated at the scale of x
    so that tiny terms do not underflow to a spurious zero (only the sign and zero-ness are used)."""
    if x == wp.float64(0.0) or wp.abs(x) >= SMALL_ARGUMENT:
        return cubic_value(q, a, b, c, x)
    root_exp = wp.floor(wp.log2(wp.abs(x)))
    sc = coefficients_at_scale(q, a, b, c, root_exp)
    return cubic_value(sc[0], sc[1], sc[2], sc[3], times_pow2(x, -root_exp))


@wp.func
def newton_bisect(
    q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, x_neg: wp.float64, f_neg: wp.float64, x_pos: wp.float64, f_pos: wp.float64
) -> wp.float64:
    """:func:`newton_bisect_core`; once the bracket is below 2^-100 the search continues in
    u = x / 2^L with rescaled coefficients, so tiny terms never underflow into a false zero."""
    res = newton_bisect_core(q, a, b, c, x_neg, f_neg, x_pos, f_pos, SMALL_ARGUMENT)
    if res[1] == wp.float64(0.0):
        return res[0]
    x_neg = res[2]
    x_pos = res[3]
    big = wp.max(wp.abs(x_neg), wp.abs(x_pos))
    root_exp = wp.floor(wp.log2(big))
    sc = coefficients_at_scale(q, a, b, c, root_exp)
    u_neg = times_pow2(x_neg, -root_exp)
    u_pos = times_pow2(x_pos, -root_exp)
    g_neg = cubic_value(sc[0], sc[1], sc[2], sc[3], u_neg)
    g_pos = cubic_value(sc[0], sc[1], sc[2], sc[3], u_pos)
    if g_neg == wp.float64(0.0):
        return x_neg
    if g_pos == wp.float64(0.0):
        return x_pos
    if g_neg > wp.float64(0.0) or g_pos < wp.float64(0.0):
        # unscaled signs were spoiled by underflow: keep the bracket, search with rescaled values
        # only if they still bracket; otherwise finish unscaled
        return newton_bisect_core(q, a, b, c, x_neg, f_neg, x_pos, f_pos, wp.float64(0.0))[0]
    u = newton_bisect_core(sc[0], sc[1], sc[2], sc[3], u_neg, g_neg, u_pos, g_pos, wp.float64(0.0))[0]
    return times_pow2(u, root_exp)


# --------------------------------------------------------------------------------------------
# quadratic solver (subsection "Quadratic Root Solver")
# --------------------------------------------------------------------------------------------


@wp.func
def power_of_two_scale(m: wp.float64) -> wp.vec2d:
    """Two powers of two (s1, s2) with m * s1 * s2 in [0.5, 2]: exact rescaling, no overflow."""
    e = wp.floor(wp.log2(m))
    e1 = wp.floor(wp.float64(-0.5) * e)
    e2 = -e - e1
    return wp.vec2d(wp.pow(wp.float64(2.0), e1), wp.pow(wp.float64(2.0), e2))


@wp.func
def quadratic_solve_scaled(a: wp.float64, b: wp.float64, c: wp.float64, t_max: wp.float64):
    """Both roots of a t^2 + b t + c with max(|a|,|b|,|c|) in [0.5, 2] (or all zero).

    Returns:
        (vec4d(t-.re, t-.im, t+.re, t+.im), pseudo-sign of a (+1/-1)).
    """
    zero = wp.float64(0.0)
    two = wp.float64(2.0)
    if a == zero and b == zero and c == zero:
        # everything is a root: a double root at 0 with pseudo-sign a > 0
        return wp.vec4d(zero, zero, zero, zero), wp.float64(1.0)
    if a == zero:
        if b == zero:
            # roots +-sqrt(-c/a) -> +-t_max; pseudo-sign of a opposite to c so they are real
            sa = -sign_nonneg(c)
            return wp.vec4d(-sa * t_max, zero, sa * t_max, zero), sa
        # linear root -c/b; the other escapes to (-b/a) * inf with pseudo-sign a > 0
        lin = bounded_quotient(-c, b, t_max)
        if b < zero:
            return wp.vec4d(lin, zero, t_max, zero), wp.float64(1.0)
        return wp.vec4d(-t_max, zero, lin, zero), wp.float64(1.0)
    sa = sign_nonneg(a)
    if c == zero:
        # roots 0 and -b/a exactly (sqrt(b^2) = |b|)
        other = bounded_quotient(-b, a, t_max)
        if b <= zero:
            # t+ = (-b + |b|)/2a = -b/a, t- = 2c/(-b+|b|) = 0 (b<0) or 0 (b=0)
            return wp.vec4d(zero, zero, other, zero), sa
        return wp.vec4d(other, zero, zero, zero), sa
    # discriminant scaled by k^2, k a power of two near max(|b|, 2 sqrt|a| sqrt|c|): no
    # under/overflow, and b/k, a/k, c/k stay exact so an exactly representable discriminant
    # (a dyadic double root) stays exact
    k_raw = wp.max(wp.abs(b), two * wp.sqrt(wp.abs(a)) * wp.sqrt(wp.abs(c)))
    k = wp.float64(1.0)
    if k_raw < wp.float64(6.223015277861142e-61) or k_raw > wp.float64(1.6069380442589903e60):
        # outside [2^-200, 2^200] the squares could under/overflow: rescale
        k = wp.pow(two, wp.floor(wp.log2(k_raw)))
    bk = b / k
    disc = bk * bk - wp.float64(4.0) * (a / k) * (c / k)
    if disc < zero:
        re = bounded_quotient(-b, two * a, t_max)
        im = bounded_quotient(k * wp.sqrt(-disc), two * a, t_max)
        return wp.vec4d(re, -im, re, im), sa
    sq = k * wp.sqrt(disc)
    tp = zero
    tm = zero
    if b <= zero:
        tp = bounded_quotient(-b + sq, two * a, t_max)
    else:
        tp = bounded_quotient(two * c, -b - sq, t_max)
    if b >= zero:
        tm = bounded_quotient(-b - sq, two * a, t_max)
    else:
        tm = bounded_quotient(two * c, -b + sq, t_max)
    return wp.vec4d(tm, zero, tp, zero), sa


@wp.func
def quadratic_solve(a: wp.float64, b: wp.float64, c: wp.float64, t_max: wp.float64):
    """Both roots of a t^2 + b t + c (any finite coefficients) and the pseudo-sign of ``a``.

    The coefficients are rescaled by an exact power of two first (roots are unchanged).

    Returns:
        (vec4d(t-.re, t-.im, t+.re, t+.im), pseudo-sign of a).
    """
    m = wp.max(wp.abs(a), wp.max(wp.abs(b), wp.abs(c)))
    if m != wp.float64(0.0) and needs_balancing(wp.vec4d(wp.float64(0.0), a, b, c), m):
        # coefficients spread beyond 2^960: solve for u = t / 2^L instead
        root_exp, sc = balance(wp.vec4d(wp.float64(0.0), a, b, c))
        u_max = scaled_root_limit(root_exp, t_max)
        ur, sa_u = quadratic_solve_scaled(sc[1], sc[2], sc[3], u_max)
        tr = wp.vec4d()
        for i in range(4):
            tr[i] = unbalance_root(ur[i], root_exp, u_max, t_max)
        return tr, sa_u
    if m == wp.float64(0.0) or (m >= wp.float64(0.5) and m <= NO_RESCALE_MAX):
        # within this range rescaling changes no rounding (only exponents): skip it
        return quadratic_solve_scaled(a, b, c, t_max)
    s = power_of_two_scale(m)
    return quadratic_solve_scaled(a * s[0] * s[1], b * s[0] * s[1], c * s[0] * s[1], t_max)


# --------------------------------------------------------------------------------------------
# cubic solver (subsection "Cubic Root Solver")
# --------------------------------------------------------------------------------------------


@wp.func
def real_roots_in_unit_interval(
    q: wp.float64,
    a: wp.float64,
    b: wp.float64,
    c: wp.float64,
    f_left: wp.float64,
    f_right: wp.float64,
    accept_ends: bool,
):
    """Real roots of q x^3 + a x^2 + b x + c (|coefficients| <= 2) inside [-1, 1].

    The interval is split at the critical points of eq. ``critical_points`` into monotone pieces;
    a piece whose ends have strictly opposite signs holds one root, found by Newton-bisection; a
    point where the cubic evaluates to exactly zero is a root. ``f_left``/``f_right`` are the
    values used at x = -1 / +1 (passed in so that the forward and the reversed cubic agree on
    them bit for bit and no root at |t| = 1 is counted twice or lost).

    Returns:
        (number of roots found (0..3), vec3d of the roots).
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    # critical points of q x^3 + a x^2 + b x + c, written for a positive leading coefficient
    qq = q
    aa = a
    bb = b
    if q < zero:
        qq = -q
        aa = -a
        bb = -b
    n_points = int(0)
    xs = wp.vec4d(-one, zero, zero, one)
    fs = wp.vec4d(f_left, zero, zero, f_right)
    disc = aa * aa - wp.float64(3.0) * qq * bb
    c_left = -one
    c_right = -one
    have_left = False
    have_right = False
    if disc > zero:
        sq = wp.sqrt(disc)
        # eq. critical_points (de-rationalised to avoid cancellation)
        if aa >= zero:
            if qq > zero:
                c_left = (-aa - sq) / (wp.float64(3.0) * qq)
                have_left = True
        else:
            c_left = bb / (-aa + sq)
            have_left = True
        if aa <= zero:
            if qq > zero:
                c_right = (-aa + sq) / (wp.float64(3.0) * qq)
                have_right = True
        else:
            c_right = bb / (-aa - sq)
            have_right = True
        if have_left and have_right and not (c_left < c_right):
            # numerical error broke the ordering: drop both (fewer, larger monotone pieces)
            have_left = False
            have_right = False
    n_points = 1
    if have_left and c_left > -one and c_left < one:
        xs[n_points] = c_left
        fs[n_points] = cubic_sign_value(q, a, b, c, c_left)
        n_points = n_points + 1
    if have_right and c_right > -one and c_right < one:
        xs[n_points] = c_right
        fs[n_points] = cubic_sign_value(q, a, b, c, c_right)
        n_points = n_points + 1
    xs[n_points] = one
    fs[n_points] = f_right
    n_points = n_points + 1

    roots = wp.vec3d(zero, zero, zero)
    count = int(0)
    for i in range(n_points):
        is_end = i == 0 or i == n_points - 1
        if fs[i] == zero and (accept_ends or not is_end):
            if count < 3:
                roots[count] = xs[i]
                count = count + 1
        if i + 1 < n_points:
            fl = fs[i]
            fr = fs[i + 1]
            if (fl < zero and fr > zero) or (fl > zero and fr < zero):
                r = wp.float64(0.0)
                if fl < zero:
                    r = newton_bisect(q, a, b, c, xs[i], fl, xs[i + 1], fr)
                else:
                    r = newton_bisect(q, a, b, c, xs[i + 1], fr, xs[i], fl)
                if count < 3:
                    roots[count] = r
                    count = count + 1
    return count, roots


@wp.func
def deflate(q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, r: wp.float64) -> wp.vec3d:
    """Quadratic factor (A, B, C) of q t^3 + a t^2 + b t + c = (t - r)(A t^2 + B t + C), |r| <= 1.

    Eq. ``cubic_factored`` is forward deflation (B = q r + a, C = B r + b); it cancels
    catastrophically when r is larger than the other roots. Backward deflation from the constant
    term (C = -c / r, B = (C - b) / r) is stable then. C is taken from the constant term (one
    rounding) and B from whichever form cancels less, measured by |terms| / |result|.
    """
    zero = wp.float64(0.0)
    b_fwd = q * r + a
    c_fwd = b_fwd * r + b
    if r == zero:
        return wp.vec3d(q, b_fwd, c_fwd)
    c_bwd = -c / r
    b_bwd = (c_bwd - b) / r
    # cancellation ratios: forward |q r| + |a| against |B|; backward |C| + |b| against |C - b|
    fwd_terms = wp.abs(q * r) + wp.abs(a)
    bwd_terms = wp.abs(c_bwd) + wp.abs(b)
    # compare fwd_terms / |b_fwd| with bwd_terms / |c_bwd - b| without dividing
    use_bwd = fwd_terms * wp.abs(c_bwd - b) > bwd_terms * wp.abs(b_fwd)
    c_out = c_bwd
    if wp.abs(c_bwd) == wp.float64(0.0) and c != zero:
        c_out = c_fwd  # c / r underflowed
    if use_bwd:
        return wp.vec3d(q, b_bwd, c_out)
    return wp.vec3d(q, b_fwd, c_out)


@wp.func
def sort3(x: wp.vec3d) -> wp.vec3d:
    a = x[0]
    b = x[1]
    c = x[2]
    if a > b:
        tmp = a
        a = b
        b = tmp
    if b > c:
        tmp = b
        b = c
        c = tmp
    if a > b:
        tmp = a
        a = b
        b = tmp
    return wp.vec3d(a, b, c)


@wp.func
def assign_cubic_slots(r1: wp.float64, pair: wp.vec4d) -> vec6d:
    """Slots from one real root ``r1`` and the two roots ``pair`` (vec4d re, im, re, im)."""
    zero = wp.float64(0.0)
    if pair[1] == zero and pair[3] == zero:
        s = sort3(wp.vec3d(r1, pair[0], pair[2]))
        return vec6d(s[0], zero, s[1], zero, s[2], zero)
    t_re = pair[0]
    t_im = wp.abs(pair[1])
    if r1 >= t_re:
        # real root right of the pair (reduced c^ <= 0): it is t+; the pair fills t-, tM
        return vec6d(t_re, -t_im, t_re, t_im, r1, zero)
    return vec6d(r1, zero, t_re, -t_im, t_re, t_im)


@wp.func
def cubic_solve_normalized(q: wp.float64, a: wp.float64, b: wp.float64, c: wp.float64, t_max: wp.float64) -> vec6d:
    """All roots of q t^3 + a t^2 + b t + c with q >= 0 and max |coefficient| in [0.5, 2^100]."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if q == zero:
        # the cubic degenerates: two roots from the quadratic, the third escapes to
        # -sign(a) * infinity (eq. root_expansion1 with q -> 0+), sign(a) possibly a pseudo-sign
        quad, sa = quadratic_solve(a, b, c, t_max)
        return assign_cubic_slots(-sa * t_max, quad)

    # Roots with |t| <= 1 are roots of the cubic in [-1, 1]; roots with |t| > 1 are 1/s for the
    # roots s in (-1, 1) of the reversed cubic c s^3 + b s^2 + a s + q. Both searches evaluate
    # polynomials with bounded coefficients on [-1, 1]: nothing overflows for any q > 0.
    f_left = cubic_value(q, a, b, c, -one)
    f_right = cubic_value(q, a, b, c, one)
    n_fwd, fwd = real_roots_in_unit_interval(q, a, b, c, f_left, f_right, True)
    n_rev = int(0)
    rev = wp.vec3d(zero, zero, zero)
    if n_fwd == 0:
        # no root in [-1, 1]: search the reversed cubic g(s) = s^3 f(1/s), g(-1) = -f(-1),
        # g(1) = f(1). (When a root in [-1, 1] exists, deflating by it is as accurate and
        # cheaper: deflate() picks the stable direction whatever the other roots' sizes.)
        n_rev, rev = real_roots_in_unit_interval(c, b, a, q, -f_left, f_right, False)

    n_total = n_fwd + n_rev
    if n_total >= 3:
        t = wp.vec3d(zero, zero, zero)
        k = int(0)
        for i in range(n_fwd):
            if k < 3:
                t[k] = fwd[i]
                k = k + 1
        for i in range(n_rev):
            if k < 3:
                t[k] = bounded_quotient(one, rev[i], t_max)
                k = k + 1
        ordered = sort3(t)
        return vec6d(ordered[0], zero, ordered[1], zero, ordered[2], zero)

    # one (or two) real roots found: deflate with the one that leaves the quadratic factor with
    # the largest (scale-free) discriminant, as the paper recommends, then solve the factor with
    # the robust quadratic solver (eq. cubic_factored, or eq. doubleflip for a reversed root)
    best_score = wp.float64(-1.0e300)
    r1 = wp.float64(0.0)
    qa = wp.float64(0.0)
    qb = wp.float64(0.0)
    qc = wp.float64(0.0)
    for i in range(n_fwd):
        r = fwd[i]
        factor = deflate(q, a, b, c, r)
        fa = factor[0]
        fb = factor[1]
        fc = factor[2]
        m = wp.max(wp.abs(fa), wp.max(wp.abs(fb), wp.abs(fc)))
        score = wp.float64(-1.0e299)
        if m > zero:
            score = ((fb / m) * (fb / m)) - wp.float64(4.0) * (fa / m) * (fc / m)
        if score > best_score:
            best_score = score
            r1 = r
            qa = fa
            qb = fb
            qc = fc
    for i in range(n_rev):
        s = rev[i]
        # eq. doubleflip: the reversed cubic's quadratic factor, read back in t
        factor = deflate(c, b, a, q, s)
        fa = factor[2]
        fb = factor[1]
        fc = factor[0]
        m = wp.max(wp.abs(fa), wp.max(wp.abs(fb), wp.abs(fc)))
        score = wp.float64(-1.0e299)
        if m > zero:
            score = ((fb / m) * (fb / m)) - wp.float64(4.0) * (fa / m) * (fc / m)
        if score > best_score:
            best_score = score
            r1 = bounded_quotient(one, s, t_max)
            qa = fa
            qb = fb
            qc = fc
    # (n_total == 0 cannot happen: the sign-change parities of the two searches add up to one)
    quad, sa = quadratic_solve(qa, qb, qc, t_max)
    return assign_cubic_slots(r1, quad)


@wp.func
def cubic_solve(p: wp.vec4d, t_max: wp.float64) -> vec6d:
    """All three roots of p[0] t^3 + p[1] t^2 + p[2] t + p[3] in the slots of the module docstring.

    The coefficients are scaled by an exact power of two so the largest magnitude lies in
    [0.5, 2^100] and negated when q < 0 (both leave the roots unchanged); coefficients spread over
    more than 2^960 are first balanced by a root scaling t = 2^L u (see :func:`balance`);
    ``q = a = b = c = 0`` gives a triple root at 0.
    """
    zero = wp.float64(0.0)
    m = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.max(wp.abs(p[2]), wp.abs(p[3])))
    if m == zero:
        return vec6d(zero, zero, zero, zero, zero, zero)
    flip = wp.float64(1.0)
    if p[0] < zero:
        flip = wp.float64(-1.0)
    if needs_balancing(p, m):
        # coefficients spread beyond 2^960: solve for u = t / 2^L instead
        root_exp, sc = balance(p)
        u_max = scaled_root_limit(root_exp, t_max)
        ur = cubic_solve_normalized(sc[0] * flip, sc[1] * flip, sc[2] * flip, sc[3] * flip, u_max)
        tr = vec6d()
        for i in range(6):
            tr[i] = unbalance_root(ur[i], root_exp, u_max, t_max)
        return tr
    if m >= wp.float64(0.5) and m <= NO_RESCALE_MAX:
        # a power-of-two rescaling would change exponents only, not one rounding: skip it
        return cubic_solve_normalized(p[0] * flip, p[1] * flip, p[2] * flip, p[3] * flip, t_max)
    s = power_of_two_scale(m)
    # two multiplications keep each step exact (s[0], s[1] are powers of two within range)
    q = (p[0] * s[0]) * s[1] * flip
    a = (p[1] * s[0]) * s[1] * flip
    b = (p[2] * s[0]) * s[1] * flip
    c = (p[3] * s[0]) * s[1] * flip
    return cubic_solve_normalized(q, a, b, c, t_max)


# --------------------------------------------------------------------------------------------
# mollified derivatives
# --------------------------------------------------------------------------------------------


@wp.func
def max_abs3(x: wp.float64, y: wp.float64, z: wp.float64) -> wp.float64:
    return wp.max(wp.abs(x), wp.max(wp.abs(y), wp.abs(z)))


@wp.func
def quadratic_real_row(
    t: wp.float64, a_s: wp.float64, b_s: wp.float64, scale_back: wp.float64, required_sign: wp.float64, limit: wp.float64
) -> wp.vec3d:
    """d t / d(a, b, c) of a real root: -(t^2, t, 1) / (2 a t + b), eq. ``ourapproachderivctilde``.

    The denominator 2 a t + b is evaluated on the power-of-two scaled coefficients (``a_s``,
    ``b_s``) and multiplied back by ``scale_back`` inside the robust division.
    """
    one = wp.float64(1.0)
    at = wp.abs(t)
    direction = wp.vec3d(t * t, t, one)
    n = one
    if at > one:
        inv = one / at
        # (t^2, t, 1) / t^2 without forming t^2 (t may be t_max)
        direction = wp.vec3d(one, sign_nonneg(t) * inv, inv * inv)
        n = at * at
    den = wp.float64(2.0) * a_s * t + b_s
    scalar = robust_multiplier(n, den, scale_back, required_sign, limit)
    return -scalar * direction


@wp.func
def quadratic_root_jacobian(p: wp.vec3d, roots: wp.vec4d, limit: wp.float64) -> mat43d:
    """Mollified Jacobian of both quadratic roots w.r.t. the caller's (raw) coefficients.

    As in the paper's quadratic experiments the raw coefficients enter the formula (no
    normalisation), so the clamp ``limit`` (``M``) acts on d t / d(a, b, c) directly; the
    denominators are evaluated on power-of-two scaled coefficients to avoid overflow.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    jac = mat43d()
    m = max_abs3(p[0], p[1], p[2])
    a_s = p[0]
    b_s = p[1]
    scale_back = one
    if m > zero:
        s = power_of_two_scale(m)
        a_s = p[0] * s[0] * s[1]
        b_s = p[1] * s[0] * s[1]
        scale_back = one / (s[0] * s[1])
    for slot in range(2):
        t_re = roots[2 * slot]
        t_im = roots[2 * slot + 1]
        # Remark clampingderiv: positive for t+, negative for t-
        required = wp.float64(-1.0)
        if slot == 1:
            required = one
        if t_im == zero:
            row = quadratic_real_row(t_re, a_s, b_s, scale_back, required, limit)
            for j in range(3):
                jac[2 * slot, j] = row[j]
        else:
            # top row: -(2 tR, 1, 0) / (2a)  (t_im factored out and cancelled)
            top = wp.vec3d(two * t_re, one, zero)
            n_top = wp.max(one, wp.abs(two * t_re))
            s_top = robust_multiplier(n_top, two * a_s, scale_back, sign_nonneg(a_s), limit)
            # bottom row: (tR^2 - tI^2, tR, 1) / (2 a tI), with (tR + tI)(tR - tI) (Remark splitupforcancelerror)
            bottom = wp.vec3d((t_re + t_im) * (t_re - t_im), t_re, one)
            n_bot = wp.max(one, wp.max(wp.abs(bottom[0]), wp.abs(bottom[1])))
            s_bot = robust_multiplier(
                n_bot, two * a_s * wp.sign(t_im), scale_back * wp.abs(t_im), sign_nonneg(a_s) * sign_nonneg(t_im), limit
            )
            for j in range(3):
                jac[2 * slot, j] = -s_top * (top[j] / n_top)
                jac[2 * slot + 1, j] = s_bot * (bottom[j] / n_bot)
    return jac


@wp.func
def cubic_real_row(
    t: wp.float64, q: wp.float64, a: wp.float64, b: wp.float64, required_sign: wp.float64, limit: wp.float64
) -> wp.vec4d:
    """Eq. ``ourapproachderivcubicorigreal``: -(t^3, t^2, t, 1) / (3 q t^2 + 2 a t + b)."""
    one = wp.float64(1.0)
    at = wp.abs(t)
    direction = wp.vec4d(t * t * t, t * t, t, one)
    n = one
    den_scale = one
    if at > one:
        inv = one / at
        sg = sign_nonneg(t)
        # (t^3, t^2, t, 1) / |t|^3 without forming t^3
        direction = wp.vec4d(sg, inv, sg * inv * inv, inv * inv * inv)
        # N / D = |t|^3 / D computed as (|t|^2 / D) * |t| = (|t|^2 / D) / (1/|t|)
        n = at * at
        den_scale = inv
    den = (wp.float64(3.0) * q * t + wp.float64(2.0) * a) * t + b
    scalar = robust_multiplier(n, den, den_scale, required_sign, limit)
    return -scalar * direction


@wp.func
def largest_abs4(v: wp.vec4d) -> wp.float64:
    return wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.max(wp.abs(v[2]), wp.abs(v[3])))


@wp.func
def cubic_complex_jacobian_rows(
    t_re: wp.float64, t_im: wp.float64, q: wp.float64, a: wp.float64, limit: wp.float64
) -> mat24d:
    """d(Re t, Im t)/d(q, a, b, c) for a complex root of a normalised cubic (q >= 0).

    Uses eq. ``handle_by_factoring`` when q = 0, eq. ``ourapproachderivcubicsecondcase`` when
    3 q tR + a = 0, and eqs. ``ourapproachderivcubicrealmul`` / ``ourapproachderivcubicimagmul``
    otherwise; every scalar multiplier by robust division with the largest entry factored out.
    The root parts are pre-divided by m = max(1, |tR|, |tI|) so no entry overflows even for
    roots at t_max.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    three = wp.float64(3.0)
    rows = mat24d()
    u = three * q * t_re + a
    # entries of degree up to 3 in (tR, tI) are divided by powers of m = max(1, |tR|, |tI|)
    # (numerator and denominator alike) so nothing overflows for roots near t_max
    m = wp.max(one, wp.max(wp.abs(t_re), wp.abs(t_im)))
    x = t_re / m
    y = t_im / m
    if q == zero:
        # eq. handle_by_factoring; a != 0 here (the quadratic factor has complex roots)
        top = wp.vec4d((SQRT3 * t_re + t_im) * (SQRT3 * t_re - t_im), two * t_re, one, zero)
        n_top = wp.max(one, wp.max(wp.abs(top[0]), wp.abs(top[1])))
        s_top = robust_multiplier(n_top, two * a, one, sign_nonneg(a), limit)
        # (tR (tR^2 - 3 tI^2), tR^2 - tI^2, tR, 1) / (2 a tI), all divided by m
        bot = wp.vec4d(m * m * x * (x + SQRT3 * y) * (x - SQRT3 * y), m * (x + y) * (x - y), x, one / m)
        n_bot = wp.max(one / m, largest_abs4(bot))
        s_bot = robust_multiplier(n_bot, two * a * wp.sign(y), wp.abs(y), sign_nonneg(a) * sign_nonneg(t_im), limit)
        for j in range(4):
            rows[0, j] = -s_top * (top[j] / n_top)
            rows[1, j] = s_bot * (bot[j] / n_bot)
        return rows
    if u == zero:
        # eq. ourapproachderivcubicsecondcase; top: (tR^3 - 3 tR tI^2, tR^2 - tI^2, tR, 1) / (2 q tI^2)
        # divided by m^2 on both sides
        top = wp.vec4d(m * x * (x + SQRT3 * y) * (x - SQRT3 * y), (x + y) * (x - y), x / m, one / (m * m))
        n_top = wp.max(one / (m * m), largest_abs4(top))
        s_top = robust_multiplier(n_top, two * q * wp.abs(y), wp.abs(y), one, limit)
        # bottom: (3 tR^2 - tI^2, 2 tR, 1, 0) / (2 q tI), divided by m
        bot = wp.vec4d(m * (SQRT3 * x + y) * (SQRT3 * x - y), two * x, one / m, zero)
        n_bot = wp.max(one / m, largest_abs4(bot))
        s_bot = robust_multiplier(n_bot, two * q * wp.sign(y), wp.abs(y), sign_nonneg(t_im), limit)
        for j in range(4):
            rows[0, j] = s_top * (top[j] / n_top)
            rows[1, j] = s_bot * (bot[j] / n_bot)
        return rows
    # general case; alpha = q tR and w = q tI are bounded (Remark imag_bound)
    w = q * t_im
    alpha = q * t_re
    mu = wp.max(wp.abs(u), wp.abs(w))
    # (u^2 + w^2) = mu^2 * h2 with h2 in [1, 2]
    h2 = (u / mu) * (u / mu) + (w / mu) * (w / mu)
    # eq. ourapproachderivcubicrealmul: -1/2 * v_R / (u^2 + w^2)
    v_r = wp.vec4d(
        (wp.float64(8.0) * alpha + three * a) * t_re * t_re - a * t_im * t_im,
        wp.float64(5.0) * alpha * t_re + w * t_im + two * a * t_re,
        two * alpha + a,
        -q,
    )
    n_r = largest_abs4(v_r)
    s_r = wp.float64(0.0)
    if n_r > zero:
        # N / (2 mu^2 h2) as ((N / (2 h2 mu)) / mu)
        s_r = robust_multiplier(n_r, two * h2 * mu, mu, one, limit)
    # eq. ourapproachderivcubicimagmul: v_I / (2 tI (u^2 + w^2)), every entry divided by m
    v_i = wp.vec4d(
        m * m * (x * x * x * u - (w * y + (wp.float64(6.0) * alpha + three * a) * x) * y * y),
        m * (u * x * x - (alpha + a) * y * y),
        three * alpha * x + w * y + a * x,
        u / m,
    )
    n_i = largest_abs4(v_i)
    s_i = wp.float64(0.0)
    if n_i > zero:
        s_i = robust_multiplier(n_i, two * y * h2 * mu, mu, sign_nonneg(t_im), limit)
    for j in range(4):
        if n_r > zero:
            rows[0, j] = -s_r * (v_r[j] / n_r)
        if n_i > zero:
            rows[1, j] = s_i * (v_i[j] / n_i)
    return rows


@wp.func
def cubic_root_jacobian(p: wp.vec4d, roots: vec6d, limit: wp.float64) -> mat64d:
    """Mollified Jacobian of the three cubic roots w.r.t. the caller's coefficients.

    The formulas are evaluated on the paper's bounded coefficients p = sigma * p_raw / S with
    S = max(1, max |p_raw|) and sigma = sign(q) (so q >= 0, pseudo-sign q > 0 when q = 0), and
    chained back through eq. ``dpboundeddp``: J_raw = J(p) * dp/dp_raw.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    sigma = one
    if p[0] < zero:
        sigma = wp.float64(-1.0)
    k = int(0)
    big = wp.abs(p[0])
    for i in range(1, 4):
        if wp.abs(p[i]) > big:
            big = wp.abs(p[i])
            k = i
    scale = wp.max(one, big)
    # M bounds the derivative w.r.t. the caller's coefficients: the chain of eq. dpboundeddp
    # divides by S, so the clamp in the normalised space is M * S (capped so it stays finite).
    limit = wp.min(limit * scale, wp.float64(1.0e300))
    pn = wp.vec4d(p[0] * sigma / scale, p[1] * sigma / scale, p[2] * sigma / scale, p[3] * sigma / scale)
    q = pn[0]
    a = pn[1]
    b = pn[2]
    jn = mat64d()
    for slot in range(3):
        t_re = roots[2 * slot]
        t_im = roots[2 * slot + 1]
        if t_im == zero:
            # Remark cubicclampingderivs (q >= 0): positive for t-, t+; negative for tM
            required = one
            if slot == 1:
                required = wp.float64(-1.0)
            row = cubic_real_row(t_re, q, a, b, required, limit)
            for j in range(4):
                jn[2 * slot, j] = row[j]
        else:
            rows = cubic_complex_jacobian_rows(t_re, t_im, q, a, limit)
            for j in range(4):
                jn[2 * slot, j] = rows[0, j]
                jn[2 * slot + 1, j] = rows[1, j]
    if big <= one:
        return jn * sigma
    # eq. dpboundeddp: dp_i/dp_raw_j = (sigma / S) (delta_ij - (p_raw_i / S) sign(p_raw_k) delta_jk)
    sk = sign_nonneg(p[k])
    jac = mat64d()
    for r in range(6):
        proj = wp.float64(0.0)
        for i in range(4):
            proj = proj + jn[r, i] * (p[i] / scale)
        for j in range(4):
            val = jn[r, j]
            if j == k:
                val = val - proj * sk
            jac[r, j] = val * sigma / scale
    return jac


# --------------------------------------------------------------------------------------------
# differentiable entry points for kernels (adjoint = mollified implicit derivative)
# --------------------------------------------------------------------------------------------


@wp.func
def quadratic_roots(p: wp.vec3d, t_max: wp.float64, max_derivative: wp.float64) -> wp.vec4d:
    """Roots (t-.re, t-.im, t+.re, t+.im) of p[0] t^2 + p[1] t + p[2]; differentiable under a tape."""
    roots, _sa = quadratic_solve(p[0], p[1], p[2], t_max)
    return roots


@wp.func_grad(quadratic_roots)
def adj_quadratic_roots(p: wp.vec3d, t_max: wp.float64, max_derivative: wp.float64, adj_ret: wp.vec4d):
    roots, _sa = quadratic_solve(p[0], p[1], p[2], t_max)
    jac = quadratic_root_jacobian(p, roots, max_derivative)
    wp.adjoint[p] += wp.transpose(jac) @ adj_ret


@wp.func
def cubic_roots(p: wp.vec4d, t_max: wp.float64, max_derivative: wp.float64) -> vec6d:
    """Roots (t-, tM, t+ as re, im pairs) of the cubic p; differentiable under a tape."""
    return cubic_solve(p, t_max)


@wp.func_grad(cubic_roots)
def adj_cubic_roots(p: wp.vec4d, t_max: wp.float64, max_derivative: wp.float64, adj_ret: vec6d):
    roots = cubic_solve(p, t_max)
    jac = cubic_root_jacobian(p, roots, max_derivative)
    wp.adjoint[p] += wp.transpose(jac) @ adj_ret


# --------------------------------------------------------------------------------------------
# batched kernels behind collision.roots
# --------------------------------------------------------------------------------------------


@wp.kernel
def solve_quadratic_kernel(
    coefficients: wp.array(dtype=wp.vec3d), t_max: wp.float64, roots: wp.array(dtype=wp.vec4d)
):
    i = wp.tid()
    r, _sa = quadratic_solve(coefficients[i][0], coefficients[i][1], coefficients[i][2], t_max)
    roots[i] = r


@wp.kernel
def quadratic_jacobian_kernel(
    coefficients: wp.array(dtype=wp.vec3d),
    t_max: wp.float64,
    max_derivative: wp.float64,
    roots: wp.array(dtype=wp.vec4d),
    jacobians: wp.array(dtype=mat43d),
):
    i = wp.tid()
    p = coefficients[i]
    r, _sa = quadratic_solve(p[0], p[1], p[2], t_max)
    roots[i] = r
    jacobians[i] = quadratic_root_jacobian(p, r, max_derivative)


@wp.kernel
def solve_cubic_kernel(coefficients: wp.array(dtype=wp.vec4d), t_max: wp.float64, roots: wp.array(dtype=vec6d)):
    i = wp.tid()
    roots[i] = cubic_solve(coefficients[i], t_max)


@wp.kernel
def cubic_jacobian_kernel(
    coefficients: wp.array(dtype=wp.vec4d),
    t_max: wp.float64,
    max_derivative: wp.float64,
    roots: wp.array(dtype=vec6d),
    jacobians: wp.array(dtype=mat64d),
):
    i = wp.tid()
    p = coefficients[i]
    r = cubic_solve(p, t_max)
    roots[i] = r
    jacobians[i] = cubic_root_jacobian(p, r, max_derivative)
