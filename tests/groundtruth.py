"""Ground truth for the root-solver tests: exact/high-precision roots, errors and matching.

Pure Python (mpmath, fractions); nothing here calls the package. The solver under test lives
in :mod:`kernels.roots`; these helpers are deliberately *independent* of it and of each other's
shortcuts:

* :func:`true_roots` — every root of a float64 polynomial of degree <= 3, computed from the
  float coefficients *as given* (converted exactly to mpmath numbers) at a working precision
  that grows with the spread of the coefficients' magnitudes. Real roots of a cubic are
  bracketed between the critical points and found by safeguarded Newton/bisection on exact
  sign evaluations; the complex pair comes from the deflated quadratic and is polished by
  complex Newton on the original cubic. (``mpmath.polyroots`` — Durand-Kerner — does not
  converge when coefficients span 1e+-150, which is why it is only used as a cross-check.)
* :func:`poly_from_roots` — exact construction (``fractions.Fraction``) of a polynomial with
  chosen roots; when every coefficient is exactly a float64 the chosen roots *are* the ground
  truth (double and triple roots included).
* :func:`backward_error`, :func:`forward_error`, :func:`match_roots` — the measures used by the
  accuracy tests, evaluated in mpmath.
* :func:`fd_root_jacobian` — central finite differences of a tracked root at mp.dps = 50.
"""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import mpmath
from mpmath import mp, mpc, mpf

# Working precision of the ground truth: 60 decimal digits beyond what magnitude spreads eat;
# roots are iterated to a relative accuracy of 1e-50 (the tests resolve errors of ~1e-17).
BASE_DPS = 60
TARGET_DPS = 50
# Smallest positive normal float64: below it "relative" error is measured absolutely.
TINY = 2.0**-1022
ULP = 2.0**-52


# --------------------------------------------------------------------------------------------
# exact construction
# --------------------------------------------------------------------------------------------


def _frac(x) -> Fraction:
    if isinstance(x, Fraction):
        return x
    if isinstance(x, float):
        return Fraction(x)  # exact
    return Fraction(x)


def poly_from_roots(real_roots=(), complex_pairs=(), lead=1):
    """Exact coefficients (highest degree first) of ``lead * prod (t - r) * prod ((t-x)^2 + y^2)``.

    Args:
        real_roots: real roots (float, int or Fraction; exact).
        complex_pairs: (x, y) for each conjugate pair x +- i y.
        lead: leading coefficient.

    Returns:
        (coefficients as floats, exact: bool, roots as mpc list) — ``exact`` is True when every
        coefficient is exactly representable in float64 (then the listed roots are exact).
    """
    poly = [_frac(lead)]
    for r in real_roots:
        poly = _polymul(poly, [Fraction(1), -_frac(r)])
    for x, y in complex_pairs:
        x, y = _frac(x), _frac(y)
        poly = _polymul(poly, [Fraction(1), -2 * x, x * x + y * y])
    floats = [float(c) for c in poly]
    exact = all(Fraction(f) == c for f, c in zip(floats, poly)) and all(math.isfinite(f) for f in floats)
    roots = [mpc(mpf(r.numerator) / r.denominator) for r in map(_frac, real_roots)]
    with mp.workdps(BASE_DPS):
        for x, y in complex_pairs:
            x, y = _frac(x), _frac(y)
            xr = mpf(x.numerator) / x.denominator
            yr = mpf(y.numerator) / y.denominator
            roots += [mpc(xr, -yr), mpc(xr, yr)]
    return floats, exact, roots


def _polymul(p, r):
    out = [Fraction(0)] * (len(p) + len(r) - 1)
    for i, pi in enumerate(p):
        for j, rj in enumerate(r):
            out[i + j] += pi * rj
    return out


# --------------------------------------------------------------------------------------------
# high-precision roots of the float polynomial
# --------------------------------------------------------------------------------------------


def working_dps(coeffs) -> int:
    """Decimal digits needed so cancellation between roots of very different size is harmless."""
    mags = [abs(float(c)) for c in coeffs if float(c) != 0.0]
    if len(mags) < 2:
        return BASE_DPS
    spread = math.log10(max(mags)) - math.log10(min(mags))
    return BASE_DPS + int(1.5 * spread) + 20


def _polyval(c, x):
    acc = mpc(0) if isinstance(x, mpc) else mpf(0)
    for ck in c:
        acc = acc * x + ck
    return acc


def _polyder(c):
    n = len(c) - 1
    return [c[k] * (n - k) for k in range(n)]


def _quadratic_mp(a, b, c):
    """Roots of a t^2 + b t + c (a != 0) at the current precision, cancellation free."""
    disc = b * b - 4 * a * c
    if disc >= 0:
        sq = mpmath.sqrt(disc)
        s = -(b + (sq if b >= 0 else -sq)) / 2
        if s == 0:  # b == 0 and disc == 0 -> c == 0: double root 0
            return [mpc(0), mpc(0)]
        return [mpc(s / a), mpc(c / s)]
    re = -b / (2 * a)
    im = mpmath.sqrt(-disc) / (2 * a)
    return [mpc(re, -abs(im)), mpc(re, abs(im))]


def _split(lo, hi):
    """A point inside (lo, hi): 0 if straddled, the geometric mean across orders of magnitude."""
    if lo < 0 < hi:
        return mpf(0)
    if lo >= 0:
        if lo == 0:
            return hi * mpf(2) ** -64
        if hi > 16 * lo:
            return mpmath.sqrt(lo * hi)
    else:
        if hi == 0:
            return lo * mpf(2) ** -64
        if lo < 16 * hi:
            return -mpmath.sqrt(lo * hi)
    return (lo + hi) / 2


def _bracket_root(c, lo, hi, flo, fhi):
    """Root of the real polynomial c in [lo, hi] with sign(flo) != sign(fhi).

    Safeguarded Newton (the ``rtsafe`` rule: Newton only while it stays inside the bracket and
    at least halves the step before last), geometric bisection otherwise.
    """
    d = _polyder(c)
    eps = mpf(10) ** (-TARGET_DPS)
    x = _split(lo, hi)
    dx_old = dx = hi - lo
    for _ in range(40 * mp.prec):
        fx = _polyval(c, x)
        if fx == 0:
            return x
        if (fx < 0) == (flo < 0):
            lo, flo = x, fx
        else:
            hi, fhi = x, fx
        if hi - lo <= eps * max(abs(lo), abs(hi)):
            return x
        dfx = _polyval(d, x)
        newton_ok = dfx != 0
        if newton_ok:
            step = fx / dfx
            xn = x - step
            newton_ok = lo < xn < hi and 2 * abs(step) <= abs(dx_old)
        if newton_ok:
            dx_old, dx = dx, step
            if abs(step) <= eps * abs(xn):
                return xn
            x = xn
        else:
            xn = _split(lo, hi)
            dx_old, dx = dx, xn - x
            x = xn
    raise RuntimeError("ground truth bracket search did not converge")


def _polish_complex(c, z, iters=200):
    """Complex Newton on polynomial c from z; returns the converged root."""
    d = _polyder(c)
    eps = mpf(10) ** (-TARGET_DPS)
    for _ in range(iters):
        fz = _polyval(c, z)
        dz = _polyval(d, z)
        if fz == 0 or dz == 0:
            return z
        step = fz / dz
        z = z - step
        if abs(step) <= eps * abs(z):
            return z
    raise RuntimeError(f"complex Newton did not converge at {z}")


def _cubic_real_roots(c):
    """Real roots (with multiplicity) of the real cubic c (c[0] > 0, c[3] != 0)."""
    q, a, b, cc = c
    roots = []
    # Fujiwara bound: every root has |t| < 2 max(|a/q|, |b/q|^(1/2), |c/(2q)|^(1/3))
    bound = 2 * max(abs(a / q), mpmath.sqrt(abs(b / q)), mpmath.cbrt(abs(cc / (2 * q)))) * 2 + 1
    crits = []
    da, db, dc = 3 * q, 2 * a, b
    if db * db - 4 * da * dc >= 0:
        crits = sorted(set(r.real for r in _quadratic_mp(da, db, dc)))
    points = [-bound] + [x for x in crits if -bound < x < bound] + [bound]
    values = [_polyval(c, x) for x in points]
    for i, (x, fx) in enumerate(zip(points, values)):
        if fx == 0 and 0 < i < len(points) - 1:
            # root exactly at a critical point: multiplicity 2 (or 3 if p'' vanishes too)
            mult = 3 if _polyval(_polyder(_polyder(c)), x) == 0 else 2
            roots += [x] * mult
    for i in range(len(points) - 1):
        lo, hi, flo, fhi = points[i], points[i + 1], values[i], values[i + 1]
        if flo != 0 and fhi != 0 and (flo < 0) != (fhi < 0):
            roots.append(_bracket_root(c, lo, hi, flo, fhi))
    return sorted(roots)


def true_roots(coeffs, dps: int | None = None):
    """All finite roots of the float polynomial ``coeffs`` (highest degree first, length 2..4).

    Args:
        coeffs: float64 coefficients, taken exactly.
        dps: decimal working precision (default: :func:`working_dps`).

    Returns:
        (list of mpc finite roots with multiplicity, number of infinite roots); ``None`` for
        the roots of the zero polynomial (every t is a root).
    """
    coeffs = [float(x) for x in coeffs]
    n = len(coeffs) - 1
    if dps is None:
        dps = working_dps(coeffs)
    with mp.workdps(dps):
        c = [mpf(x) for x in coeffs]
        lead = 0
        while lead <= n and c[lead] == 0:
            lead += 1
        if lead > n:
            return None, 0
        n_inf = lead
        c = c[lead:]
        zeros = 0
        while len(c) > 1 and c[-1] == 0:
            c = c[:-1]
            zeros += 1
        out = [mpc(0)] * zeros
        deg = len(c) - 1
        if deg == 1:
            out.append(mpc(-c[1] / c[0]))
        elif deg == 2:
            out += _quadratic_mp(*c)
        elif deg == 3:
            if c[0] < 0:
                c = [-x for x in c]
            reals = _cubic_real_roots(c)
            if len(reals) == 3:
                out += [mpc(r) for r in reals]
            elif len(reals) == 1:
                r1 = reals[0]
                # deflate: (t - r1)(q t^2 + B t + C) with C = -c / r1 (no cancellation) and
                # B = a + q r1 or (C - b) / r1, whichever cancels less; then polish on the cubic
                q, a, b, cc = c
                big_c = -cc / r1
                b1 = a + q * r1
                b2 = (big_c - b) / r1
                loss1 = max(abs(a), abs(q * r1)) / abs(b1) if b1 != 0 else mpmath.inf
                loss2 = max(abs(big_c), abs(b)) / abs(big_c - b) if big_c != b else mpmath.inf
                big_b = b1 if loss1 <= loss2 else b2
                pair = _quadratic_mp(q, big_b, big_c)
                z = pair[1] if pair[1].imag != 0 else mpc(pair[1].real, abs(pair[1].real) * 1e-30 + 1e-300)
                z = _polish_complex(c, z)
                # Vieta check: r1 |z|^2 = -c/q has no cancellation, so it holds to ~TARGET_DPS digits
                prod = r1 * (z.real**2 + z.imag**2)
                if z.imag == 0 or abs(prod + cc / q) > abs(cc / q) * mpf(10) ** (-(TARGET_DPS - 10)):
                    raise RuntimeError(f"cubic {coeffs}: complex pair polish failed ({z}, r1={r1})")
                out += [mpc(r1), mpc(z.real, -abs(z.imag)), mpc(z.real, abs(z.imag))]
            else:
                raise RuntimeError(f"cubic {coeffs}: found {len(reals)} real roots")
        return out, n_inf


def true_roots_polyroots(coeffs, dps: int = BASE_DPS):
    """Cross-check of :func:`true_roots` with ``mpmath.polyroots`` (moderate inputs only)."""
    with mp.workdps(dps):
        c = [mpf(float(x)) for x in coeffs]
        while c and c[0] == 0:
            c = c[1:]
        if len(c) <= 1:
            return []
        return [mpc(r) for r in mpmath.polyroots(c, maxsteps=2000, extraprec=4 * dps * 4)]


# --------------------------------------------------------------------------------------------
# error measures and matching
# --------------------------------------------------------------------------------------------


def backward_error(coeffs, z) -> float:
    """|p(z)| / sum_k |c_k| |z|^k for a float64 (complex) z, evaluated at mp.dps = 80.

    0 when the denominator vanishes (only possible for p(z) = 0 too, at z = 0 with c = 0).
    """
    with mp.workdps(BASE_DPS + 20):
        zz = mpc(float(z.real), float(z.imag))
        cs = [mpf(float(x)) for x in coeffs]
        num = abs(_polyval(cs, zz))
        az = abs(zz)
        den = mpf(0)
        for ck in cs:
            den = den * az + abs(ck)
        if den == 0:
            return 0.0
        return float(num / den)


# Absolute spacing of float64 at the bottom of the subnormal range.
SUBNORMAL_STEP = 2.0**-1074


def excess_backward_error(coeffs, z) -> float:
    """Backward error beyond what representing the root in float64 forces.

    A root rounded to the float grid carries a relative error up to 2^-53 (normal range) or
    2^-1075 / |z| (subnormal range), and |z p'(z)| <= deg * sum |c_k||z|^k, so the representable
    root nearest to an exact one has a backward error up to about deg * that. The ulp bound of
    the tests applies to ``backward_error - deg * 2^-1075 / |z|`` (the normal-range part stays
    in the bound). A root returned as exactly 0 for a polynomial with p(0) != 0 is excused only
    when an exact root has |t| <= 2^-1075 (it rounds to 0); otherwise its backward error counts.
    """
    deg = len(coeffs) - 1
    bw = backward_error(coeffs, z)
    if z != 0:
        return max(0.0, bw - deg * (SUBNORMAL_STEP / abs(z)) / 2)
    if float(coeffs[-1]) == 0.0 or bw == 0.0:
        return 0.0
    roots, _ = true_roots(coeffs)
    if roots is not None and any(abs(t) <= mpf(2) ** -1075 for t in roots):
        return 0.0
    return bw


def forward_error(z, t) -> float:
    """Relative forward error |z - t| / max(|t|, TINY) of a float64 root z against exact t.

    Relative to |t| (not max(1, |t|)): a root's scale is meaningless to the solver, so tiny
    roots must be as relatively accurate as big ones; below the smallest normal float64 the
    measure is absolute (``TINY``), so an exact zero root is only matched by an exact zero.
    """
    with mp.workdps(BASE_DPS):
        zz = mpc(float(z.real), float(z.imag))
        return float(abs(zz - t) / max(abs(t), mpf(TINY)))


def clamp_root(t, t_max: float):
    """The root as a solver that clamps Re and Im to [-t_max, t_max] would report it."""
    with mp.workdps(BASE_DPS):
        re = min(max(mpf(t.real), -mpf(t_max)), mpf(t_max))
        im = min(max(mpf(t.imag), -mpf(t_max)), mpf(t_max))
        return mpc(re, im)


def beyond(t, t_max: float) -> bool:
    """True when the exact root lies outside the clamp box (its Re or Im beyond t_max)."""
    return abs(t.real) > t_max or abs(t.imag) > t_max


def match_roots(computed, truth, cost=None):
    """Minimal-cost injective assignment of truth roots to computed roots (brute force, n <= 3).

    Args:
        computed: sequence of complex computed roots (length m).
        truth: sequence of exact roots (length k; k <= m or k > m — the smaller side is matched).
        cost: cost(z, t) -> float; default the relative forward error.

    Returns:
        list of (i_computed, j_truth) pairs of length min(m, k), minimising the summed cost.
    """
    if cost is None:
        cost = forward_error
    m, k = len(computed), len(truth)
    if m == 0 or k == 0:
        return []
    table = [[cost(computed[i], truth[j]) for j in range(k)] for i in range(m)]
    best, best_pairs = None, None
    if m >= k:
        for perm in itertools.permutations(range(m), k):
            s = sum(min(table[perm[j]][j], 1e300) for j in range(k))
            if best is None or s < best:
                best, best_pairs = s, [(perm[j], j) for j in range(k)]
    else:
        for perm in itertools.permutations(range(k), m):
            s = sum(min(table[i][perm[i]], 1e300) for i in range(m))
            if best is None or s < best:
                best, best_pairs = s, [(i, perm[i]) for i in range(m)]
    return best_pairs


# --------------------------------------------------------------------------------------------
# finite-difference derivatives
# --------------------------------------------------------------------------------------------


def fd_root_jacobians(coeffs, h: float = 1e-20, dps: int = 50):
    """Central finite differences d(Re, Im)/d(coeff_k) of every finite exact root.

    Each coefficient k is perturbed by +-h times the largest coefficient magnitude; the perturbed
    polynomial's roots are computed at ``dps`` digits and each unperturbed exact root is tracked
    to the perturbed root nearest to it (so slots and orderings play no part).

    Returns:
        list of (exact root (mpc), 2 x n list [[dRe/dc_0 ...], [dIm/dc_0 ...]] of floats) —
        one entry per finite root of the unperturbed polynomial (n = len(coeffs)).
    """
    n = len(coeffs)
    scale = max(abs(float(x)) for x in coeffs)
    base, _ = true_roots(coeffs, dps=dps + 20)
    with mp.workdps(dps):
        step = mpf(h) * mpf(scale)
        jacs = [[[0.0] * n, [0.0] * n] for _ in base]
        for k in range(n):
            perturbed = []
            for sgn in (1, -1):
                c = [mpf(float(x)) for x in coeffs]
                c[k] += sgn * step
                while c and c[0] == 0:
                    c = c[1:]
                perturbed.append(_roots_mp(c))
            for r, t0 in enumerate(base):
                up = min(perturbed[0], key=lambda t: abs(t - t0))
                dn = min(perturbed[1], key=lambda t: abs(t - t0))
                d = (up - dn) / (2 * step)
                jacs[r][0][k] = float(d.real)
                jacs[r][1][k] = float(d.imag)
        return list(zip(base, jacs))


def _roots_mp(c):
    """Roots of an mp-coefficient polynomial (nonzero leading coefficient) at current precision."""
    c = list(c)
    deg = len(c) - 1
    if deg == 1:
        return [mpc(-c[1] / c[0])]
    if deg == 2:
        return _quadratic_mp(*c)
    return [mpc(r) for r in mpmath.polyroots(c, maxsteps=500, extraprec=4 * mp.prec)]


def exact_derivative(coeffs, t):
    """Analytic implicit derivative dt/dc_k = -t^(n-k) / p'(t) of a simple root (mpc), as 2 x n."""
    with mp.workdps(BASE_DPS):
        cs = [mpf(float(x)) for x in coeffs]
        n = len(cs) - 1
        dp = _polyval(_polyder(cs), t)
        row = [-(t ** (n - k)) / dp for k in range(n + 1)]
        return [[float(r.real) for r in row], [float(r.imag) for r in row]]


# --------------------------------------------------------------------------------------------
# test categories (shared by tests/test_roots_accuracy.py and benchmarks/roots.py)
# --------------------------------------------------------------------------------------------
#
# Each generator returns (coefficients: float64 (n, deg+1), exact roots: list per sample, or None
# per sample when the ground truth must come from :func:`true_roots`). Seeds are fixed per
# category so every run sees the same inputs.

import zlib  # noqa: E402

import numpy as np  # noqa: E402


def _rng(kind: str, name: str) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32(f"{kind}/{name}".encode()))


def _dyadic(rng, lo_num: int, hi_num: int, bits: int, size=None):
    """Random dyadic rationals k / 2^bits with k in [lo_num, hi_num] (as Fractions)."""
    ks = rng.integers(lo_num, hi_num + 1, size=size)
    return [Fraction(int(k), 2**bits) for k in np.atleast_1d(ks)]


def _from_roots(rows, deg):
    """rows: list of (real_roots, complex_pairs, lead) -> (coeffs array, exact-roots list)."""
    coeffs = np.empty((len(rows), deg + 1))
    exact = []
    for i, (rr, cp, lead) in enumerate(rows):
        f, ok, roots = poly_from_roots(rr, cp, lead)
        coeffs[i] = f
        exact.append(roots if ok else None)
    return coeffs, exact


def _separated(rng, count, lo, hi, gap, as_dyadic_bits=None):
    while True:
        if as_dyadic_bits is None:
            r = np.sort(rng.uniform(lo, hi, count))
        else:
            k = rng.integers(int(lo * 2**as_dyadic_bits), int(hi * 2**as_dyadic_bits) + 1, count)
            r = np.sort(k / 2.0**as_dyadic_bits)
        if np.all(np.diff(r) >= gap):
            return r


def cubic_category(name: str, n: int = 200):
    """Inputs of one accuracy category for the cubic [q, a, b, c]. See CUBIC_CATEGORIES."""
    rng = _rng("cubic", name)
    none = [None] * n
    sgn = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
    if name == "uniform":
        return rng.uniform(-1, 1, (n, 4)), none
    if name == "spread_real":
        # three real roots in [-10, 10], at least 1 apart; float (rounded) coefficients
        out = np.empty((n, 4))
        for i in range(n):
            r = _separated(rng, 3, -10, 10, 1.0)
            lead = sgn() * rng.uniform(0.1, 10)
            out[i] = lead * np.poly(r)
        return out, none
    if name.startswith("pair_"):
        # dyadic roots r, r + delta, s with delta = 2^-13 / 2^-27 / 2^-40 (~1e-4 / 1e-8 / 1e-12)
        delta = Fraction(1, 2 ** {"pair_1e-4": 13, "pair_1e-8": 27, "pair_1e-12": 40}[name])
        rows = []
        for _ in range(n):
            r, s = (Fraction(int(x), 64) for x in _separated(rng, 2, -128, 128, 32))
            if rng.random() < 0.5:
                r, s = s, r
            rows.append(([r, r + delta, s], [], int(sgn())))
        return _from_roots(rows, 3)
    if name == "double":
        rows = []
        for _ in range(n):
            r, s = (Fraction(int(x), 32) for x in _separated(rng, 2, -64, 64, 4))
            if rng.random() < 0.5:
                r, s = s, r
            lead = sgn() * (1 + Fraction(int(rng.integers(0, 8)), 8))
            rows.append(([r, r, s], [], lead))
        return _from_roots(rows, 3)
    if name == "triple":
        rows = []
        for _ in range(n):
            r = Fraction(int(rng.integers(-64, 65)), 32)
            lead = sgn() * (1 + Fraction(int(rng.integers(0, 8)), 8))
            rows.append(([r, r, r], [], lead))
        return _from_roots(rows, 3)
    if name == "complex_tiny_im":
        # pair x +- i y with y / max(1,|x|) = 2^-10 .. 2^-26, real root s away from it
        rows = []
        for _ in range(n):
            x, s = (Fraction(int(v), 64) for v in _separated(rng, 2, -128, 128, 32))
            y = Fraction(int(rng.integers(1, 8)) * 2 + 1, 2 ** int(rng.integers(10, 27)))
            rows.append(([s], [(x, y)], int(sgn())))
        return _from_roots(rows, 3)
    if name == "q_tiny":
        p = rng.uniform(-1, 1, (n, 4))
        p[:, 0] = np.sign(p[:, 0]) * 10.0 ** -rng.uniform(12, 200, n)
        return p, none
    if name == "c_zero":
        p = rng.uniform(-1, 1, (n, 4))
        p[:, 3] = 0.0
        return p, none
    if name == "q_zero":
        p = rng.uniform(-1, 1, (n, 4))
        p[:, 0] = 0.0
        return p, none
    if name == "qa_zero":
        p = rng.uniform(-1, 1, (n, 4))
        p[:, :2] = 0.0
        return p, none
    if name in ("scaled_up", "scaled_down"):
        k = 990 if name == "scaled_up" else -990
        parts = [cubic_category(c, n // 4 + 1) for c in ("uniform", "spread_real", "double", "complex_tiny_im")]
        p = np.concatenate([x[0] for x in parts])[:n] * 2.0**k
        ex = sum((x[1] for x in parts), [])[:n]
        # exact roots survive exact (power-of-two) scaling; drop them where scaling rounded
        ex = [e if np.all(np.abs(row) >= 2.0**-1022) or not np.any(row) else None for e, row in zip(ex, p)]
        return p, ex
    if name == "mixed_mag":
        p = rng.choice([-1.0, 1.0], (n, 4)) * 10.0 ** rng.uniform(-150, 150, (n, 4))
        return p, none
    raise KeyError(name)


def quadratic_category(name: str, n: int = 200):
    """Inputs of one accuracy category for the quadratic [a, b, c]. See QUADRATIC_CATEGORIES."""
    rng = _rng("quadratic", name)
    none = [None] * n
    sgn = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
    if name == "uniform":
        return rng.uniform(-1, 1, (n, 3)), none
    if name == "spread_real":
        out = np.empty((n, 3))
        for i in range(n):
            r = _separated(rng, 2, -10, 10, 1.0)
            out[i] = sgn() * rng.uniform(0.1, 10) * np.poly(r)
        return out, none
    if name.startswith("pair_"):
        delta = Fraction(1, 2 ** {"pair_1e-4": 13, "pair_1e-8": 27, "pair_1e-12": 40}[name])
        rows = []
        for _ in range(n):
            r = Fraction(int(rng.integers(-128, 129)), 64)
            rows.append(([r, r + delta], [], int(sgn())))
        return _from_roots(rows, 2)
    if name == "double":
        rows = []
        for _ in range(n):
            r = Fraction(int(rng.integers(-128, 129)), 32)
            rows.append(([r, r], [], sgn() * (1 + Fraction(int(rng.integers(0, 8)), 8))))
        return _from_roots(rows, 2)
    if name == "complex_tiny_im":
        rows = []
        for _ in range(n):
            x = Fraction(int(rng.integers(-128, 129)), 64)
            y = Fraction(int(rng.integers(1, 8)) * 2 + 1, 2 ** int(rng.integers(10, 27)))
            rows.append(([], [(x, y)], int(sgn())))
        return _from_roots(rows, 2)
    if name == "a_tiny":
        p = rng.uniform(-1, 1, (n, 3))
        p[:, 0] = np.sign(p[:, 0]) * 10.0 ** -rng.uniform(12, 200, n)
        return p, none
    if name == "c_zero":
        p = rng.uniform(-1, 1, (n, 3))
        p[:, 2] = 0.0
        return p, none
    if name == "a_zero":
        p = rng.uniform(-1, 1, (n, 3))
        p[:, 0] = 0.0
        return p, none
    if name in ("scaled_up", "scaled_down"):
        k = 990 if name == "scaled_up" else -990
        parts = [quadratic_category(c, n // 4 + 1) for c in ("uniform", "spread_real", "double", "complex_tiny_im")]
        p = np.concatenate([x[0] for x in parts])[:n] * 2.0**k
        ex = sum((x[1] for x in parts), [])[:n]
        ex = [e if np.all(np.abs(row) >= 2.0**-1022) or not np.any(row) else None for e, row in zip(ex, p)]
        return p, ex
    if name == "mixed_mag":
        p = rng.choice([-1.0, 1.0], (n, 3)) * 10.0 ** rng.uniform(-150, 150, (n, 3))
        return p, none
    raise KeyError(name)


CUBIC_CATEGORIES = [
    "uniform", "spread_real", "pair_1e-4", "pair_1e-8", "pair_1e-12", "double", "triple",
    "complex_tiny_im", "q_tiny", "c_zero", "q_zero", "qa_zero", "scaled_up", "scaled_down",
    "mixed_mag",
]
QUADRATIC_CATEGORIES = [
    "uniform", "spread_real", "pair_1e-4", "pair_1e-8", "pair_1e-12", "double",
    "complex_tiny_im", "a_tiny", "c_zero", "a_zero", "scaled_up", "scaled_down", "mixed_mag",
]


def numpy_roots(coeffs):
    """numpy.roots of one polynomial (drops leading zeros, so it may return fewer roots)."""
    return list(np.roots(np.asarray(coeffs, dtype=np.float64)))


def evaluate(coeffs, exact, ours, t_max: float = 1e150, with_numpy: bool = True):
    """Backward and forward errors of ``ours`` (and numpy.roots) on one category.

    Args:
        coeffs: (n, deg+1) float64 inputs.
        exact: per sample, exact roots (mpc list) or None (then :func:`true_roots` is used).
        ours: (n, deg) complex128 roots from the solver under test.

    Returns:
        dict with
          ``backward``: list of (sample, slot, :func:`excess_backward_error`) of every unclamped
            root of ours;
          ``forward``: list of (sample, slot, err ours, err numpy or None) over true roots inside
            the clamp box (numpy None when numpy.roots returned no root for it);
          ``beyond``: list of (sample, slot, true root, our root) for true roots beyond t_max;
          ``unmatched``: samples where the truth has more finite roots than ours returned.
    """
    res = {"backward": [], "forward": [], "beyond": [], "unmatched": []}
    for i in range(len(coeffs)):
        p = coeffs[i]
        z = [complex(v) for v in ours[i]]
        for s, zz in enumerate(z):
            if abs(zz.real) < t_max and abs(zz.imag) < t_max:
                res["backward"].append((i, s, excess_backward_error(p, zz)))
        if exact[i] is not None:
            truth = exact[i]
        else:
            truth, _ = true_roots(p)
            if truth is None:  # zero polynomial
                continue
        if len(truth) > len(z):
            res["unmatched"].append(i)
            continue
        clamped_truth = [clamp_root(t, t_max) for t in truth]
        pairs = match_roots(z, clamped_truth)
        np_pairs = {}
        if with_numpy:
            nz = numpy_roots(p)
            for k, j in match_roots(nz, clamped_truth):
                np_pairs[j] = forward_error(nz[k], truth[j]) if not beyond(truth[j], t_max) else None
        for s, j in pairs:
            t = truth[j]
            if beyond(t, t_max):
                res["beyond"].append((i, s, t, z[s]))
                continue
            res["forward"].append((i, s, forward_error(z[s], t), np_pairs.get(j)))
    return res


# --------------------------------------------------------------------------------------------
# fuzz inputs (shared by tests/test_roots_fuzz.py and benchmarks/fuzz_roots.py)
# --------------------------------------------------------------------------------------------

SPECIAL_VALUES = np.array([
    0.0, -0.0, 5e-324, -5e-324, 1e-320, 2.2250738585072014e-308, -2.2250738585072014e-308,
    1e-300, -1e-300, 1e-200, 1e-150, -1e-150, 1e-16, 2.0**-52, 0.5, 1.0, -1.0, 1.0 + 2.0**-52, 2.0, -3.0,
    1e16, 1e150, -1e150, 1e200, 1e300, -1e300, 1.7976931348623157e308, -1.7976931348623157e308,
])

FUZZ_MODES = ("uniform", "log_uniform", "special", "sparse", "repeated_root", "equal_magnitude", "raw_bits")


def fuzz_inputs(rng: np.random.Generator, n: int, width: int) -> np.ndarray:
    """n finite adversarial coefficient rows of length ``width`` (4 cubic, 3 quadratic).

    Modes (equal shares): uniform(-1, 1); sign * 10^U(-323, 308) per entry (denormals to huge);
    entries drawn from SPECIAL_VALUES (zeros, +-5e-324, 1e+-300, max float ...); sparse (each entry
    of a log-uniform row zeroed with probability 1/2); repeated roots (exact (t-r)^2(t-s) or
    (t-r)^3 / (t-r)^2, scaled by 2^k and optionally nudged by one ulp); equal magnitudes with
    random signs; raw random float64 bit patterns (non-finite ones replaced by 0).
    """
    modes = rng.integers(0, len(FUZZ_MODES), n)
    out = np.empty((n, width))
    for m, name in enumerate(FUZZ_MODES):
        idx = np.nonzero(modes == m)[0]
        k = len(idx)
        if k == 0:
            continue
        if name == "uniform":
            v = rng.uniform(-1, 1, (k, width))
        elif name == "log_uniform":
            v = rng.choice([-1.0, 1.0], (k, width)) * 10.0 ** rng.uniform(-323.5, 308.2, (k, width))
        elif name == "special":
            v = rng.choice(SPECIAL_VALUES, (k, width)) * rng.choice([-1.0, 1.0], (k, width))
        elif name == "sparse":
            v = rng.choice([-1.0, 1.0], (k, width)) * 10.0 ** rng.uniform(-323.5, 308.2, (k, width))
            v[rng.random((k, width)) < 0.5] = 0.0
        elif name == "repeated_root":
            r = rng.integers(-64, 65, (k, 1)) / 16.0
            s = rng.integers(-64, 65, (k, 1)) / 16.0
            if width == 4:
                v = np.where(rng.random((k, 1)) < 0.5,
                             np.stack([np.ones(k), -(2 * r + s)[:, 0], (r * r + 2 * r * s)[:, 0], -(r * r * s)[:, 0]], 1),
                             np.stack([np.ones(k), -3 * r[:, 0], 3 * r[:, 0] ** 2, -r[:, 0] ** 3], 1))
            else:
                v = np.stack([np.ones(k), -2 * r[:, 0], r[:, 0] ** 2], 1)
            e = rng.integers(-1000, 1000, (k, 1)).astype(float)
            with np.errstate(over="ignore", under="ignore"):
                v = v * 2.0**e
            nudge = rng.random((k, width)) < 0.3
            v = np.where(nudge, np.nextafter(v, rng.choice([-np.inf, np.inf], (k, width))), v)
        elif name == "equal_magnitude":
            mag = 10.0 ** rng.uniform(-323.5, 308.2, (k, 1))
            v = rng.choice([-1.0, 1.0], (k, width)) * mag
        else:  # raw_bits
            v = rng.integers(0, 2**64, (k, width), dtype=np.uint64).view(np.float64).copy()
        v = np.where(np.isfinite(v), v, 0.0)
        out[idx] = v
    return out
