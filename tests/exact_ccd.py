"""Exact (rational / real-algebraic) ground truth for one CCD query. Tests only; slow.

    from exact_ccd import exact_ccd
    r = exact_ccd(query, "vertex-face")   # query: (8, 3) of Fraction / int / float (floats taken exactly)
    r.hit          # True iff the primitives touch (distance exactly 0) at some t in [0, 1]
    r.toi          # earliest such t: a Fraction, a RealAlgebraic (irrational root), or None
    r.toi_float    # toi correctly rounded to float64 (math.inf when no hit)
    r.coplanar     # True when the coplanarity cubic is identically zero (the degenerate sweep ran)

Row order as ipctk / the sample-query CSVs: vertex-face ``p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1,
t1_t1, t2_t1``; edge-edge ``ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1``; every
vertex moves linearly, x(t) = x_t0 + t (x_t1 - x_t0).

Method. Contact at t is a boolean combination of sign conditions of polynomials in t (the decision
procedures ``vf_contact`` / ``ee_contact`` below; every branch, degenerate triangles, points and
parallel or collinear edges included, is decided by exact signs). The contact set is closed
(distance is continuous), so the earliest contact is 0 or a time where some deciding polynomial
changes sign, i.e. one of its real roots:
* coplanarity cubic f(t) not identically zero: contact needs f(t) = 0, so the candidates are the
  roots of f in [0, 1];
* f identically zero (coplanar during the whole step): the candidates are 0, 1 and the roots in
  [0, 1] of every polynomial the decision procedure can query (``_vf_event_polys``,
  ``_ee_event_polys``); between consecutive candidates contact is constant, which is asserted at
  one rational point per gap.
Candidates are visited in increasing order and the decision procedure is run exactly at each:
rational roots with ``Fraction``; irrational roots (irreducible factor over Q, found by sympy's
``factor_list``) in the number field Q(theta) (``_AlgNum``: polynomials mod the minimal
polynomial; an element is zero iff its reduced form is, and a nonzero element's sign is found
by bisecting theta's isolating interval until a centred-form bound excludes zero).
"""

from __future__ import annotations

import math
from fractions import Fraction
from functools import cmp_to_key
from typing import NamedTuple, Sequence

import sympy

KINDS = ("vertex-face", "edge-edge")
_X = sympy.Symbol("x")


# --------------------------------------------------------------------------------------------
# exact scalars


def to_fraction(v) -> Fraction:
    """Exact Fraction of an int, float (its exact binary value), Fraction, numpy or sympy scalar."""
    if isinstance(v, Fraction):
        return v
    if isinstance(v, int):
        return Fraction(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"non-finite coordinate {v!r}")
        return Fraction(v)
    if hasattr(v, "p") and hasattr(v, "q"):  # sympy Rational
        return Fraction(int(v.p), int(v.q))
    if hasattr(v, "numerator") and hasattr(v, "denominator"):
        return Fraction(int(v.numerator), int(v.denominator))
    if hasattr(v, "item"):  # numpy scalar
        return to_fraction(v.item())
    raise TypeError(f"cannot take {type(v).__name__} exactly")


def _peval(c: Sequence[Fraction], x):
    """Horner evaluation, coefficients low -> high."""
    acc = Fraction(0)
    for a in reversed(c):
        acc = acc * x + a
    return acc


def _sgn(v) -> int:
    if isinstance(v, _AlgNum):
        return v.sign()
    return (v > 0) - (v < 0)


class RealAlgebraic:
    """An irrational real root of a monic irreducible polynomial over Q (degree >= 2), with a
    rational isolating interval (lo, hi) that shrinks as it is refined. Comparable with
    Fractions, ints, floats (exactly) and other RealAlgebraic; ``float()`` is correctly rounded."""

    __slots__ = ("poly", "lo", "hi", "_slo")

    def __init__(self, poly: tuple, lo: Fraction, hi: Fraction):
        self.poly = poly  # monic, low -> high
        self.lo, self.hi = lo, hi
        self._slo = _sgn(_peval(poly, lo))
        if self._slo == 0 or self._slo == _sgn(_peval(poly, hi)):
            raise ValueError("interval does not isolate a simple irrational root")

    def refine(self) -> None:
        m = (self.lo + self.hi) / 2
        s = _sgn(_peval(self.poly, m))
        if s == 0:  # impossible for an irreducible polynomial of degree >= 2
            raise AssertionError("rational root of an irreducible polynomial")
        if s == self._slo:
            self.lo = m
        else:
            self.hi = m

    def _cmp_rational(self, q: Fraction) -> int:
        while self.lo <= q <= self.hi:  # theta != q (irrational)
            self.refine()
        return 1 if q < self.lo else -1

    def cmp(self, other) -> int:
        if isinstance(other, RealAlgebraic):
            if other is self or (other.poly == self.poly and _overlap(self, other) and _same_root(self, other)):
                return 0
            while not (self.hi < other.lo or other.hi < self.lo):
                self.refine()
                other.refine()
            return -1 if self.hi < other.lo else 1
        return self._cmp_rational(to_fraction(other))

    def __lt__(self, o):
        return self.cmp(o) < 0

    def __le__(self, o):
        return self.cmp(o) <= 0

    def __gt__(self, o):
        return self.cmp(o) > 0

    def __ge__(self, o):
        return self.cmp(o) >= 0

    def __eq__(self, o):
        try:
            return self.cmp(o) == 0
        except TypeError:
            return NotImplemented

    def __hash__(self):
        return hash(self.poly)

    def __float__(self) -> float:
        while float(self.lo) != float(self.hi):
            self.refine()
        return float(self.lo)

    def __repr__(self) -> str:
        return f"RealAlgebraic(root of {self.poly} in [{float(self.lo)!r}, {float(self.hi)!r}])"


def _overlap(a: RealAlgebraic, b: RealAlgebraic) -> bool:
    return not (a.hi < b.lo or b.hi < a.lo)


def _same_root(a: RealAlgebraic, b: RealAlgebraic) -> bool:
    # same minimal polynomial, overlapping intervals: same root iff the union holds one root.
    lo, hi = min(a.lo, b.lo), max(a.hi, b.hi)
    return len(_isolate(a.poly, lo, hi)) == 1


class _AlgNum:
    """Element of Q(theta) = Q[x]/(h): coefficients low -> high, length deg h."""

    __slots__ = ("r", "c")

    def __init__(self, r: RealAlgebraic, c):
        self.r = r
        d = len(r.poly) - 1
        c = list(c) + [Fraction(0)] * (d - len(c))
        self.c = tuple(c)

    def _coerce(self, o):
        if isinstance(o, _AlgNum):
            return o.c
        return (to_fraction(o),) + (Fraction(0),) * (len(self.c) - 1)

    def __add__(self, o):
        oc = self._coerce(o)
        return _AlgNum(self.r, [a + b for a, b in zip(self.c, oc)])

    __radd__ = __add__

    def __sub__(self, o):
        oc = self._coerce(o)
        return _AlgNum(self.r, [a - b for a, b in zip(self.c, oc)])

    def __rsub__(self, o):
        oc = self._coerce(o)
        return _AlgNum(self.r, [b - a for a, b in zip(self.c, oc)])

    def __neg__(self):
        return _AlgNum(self.r, [-a for a in self.c])

    def __mul__(self, o):
        oc = self._coerce(o)
        d = len(self.c)
        prod = [Fraction(0)] * (2 * d - 1)
        for i, a in enumerate(self.c):
            if a:
                for j, b in enumerate(oc):
                    if b:
                        prod[i + j] += a * b
        h = self.r.poly  # monic, degree d
        for k in range(2 * d - 2, d - 1, -1):
            ck = prod[k]
            if ck:
                for j in range(d + 1):
                    prod[k - d + j] -= ck * h[j]
        return _AlgNum(self.r, prod[:d])

    __rmul__ = __mul__

    def sign(self) -> int:
        c = self.c
        if not any(c):
            return 0  # 1, theta, ..., theta^(d-1) are linearly independent over Q
        r = self.r
        while True:
            m = (r.lo + r.hi) / 2
            rad = (r.hi - r.lo) / 2
            tay = _taylor(c, m)
            bound = Fraction(0)
            p = Fraction(1)
            for a in tay[1:]:
                p *= rad
                bound += abs(a) * p
            if abs(tay[0]) > bound:
                return _sgn(tay[0])
            r.refine()


def _taylor(c, m):
    """Coefficients of p(m + s) in s (repeated synthetic division)."""
    c = list(c)
    n = len(c)
    for i in range(n):
        for k in range(n - 2, i - 1, -1):
            c[k] += m * c[k + 1]
    return c


# --------------------------------------------------------------------------------------------
# polynomials in t with Fraction coefficients (low -> high)


class _Pol:
    __slots__ = ("c",)

    def __init__(self, c):
        c = list(c)
        while c and c[-1] == 0:
            c.pop()
        self.c = tuple(c)

    @staticmethod
    def _co(o):
        return o.c if isinstance(o, _Pol) else (to_fraction(o),)

    def __add__(self, o):
        a, b = self.c, self._co(o)
        n = max(len(a), len(b))
        return _Pol([(a[i] if i < len(a) else 0) + (b[i] if i < len(b) else 0) for i in range(n)])

    __radd__ = __add__

    def __neg__(self):
        return _Pol([-x for x in self.c])

    def __sub__(self, o):
        return self + (-_Pol(self._co(o)))

    def __rsub__(self, o):
        return _Pol(self._co(o)) - self

    def __mul__(self, o):
        a, b = self.c, self._co(o)
        if not a or not b:
            return _Pol(())
        out = [Fraction(0)] * (len(a) + len(b) - 1)
        for i, x in enumerate(a):
            if x:
                for j, y in enumerate(b):
                    out[i + j] += x * y
        return _Pol(out)

    __rmul__ = __mul__

    def is_zero(self) -> bool:
        return not self.c


# --------------------------------------------------------------------------------------------
# vectors over any of Fraction / _AlgNum / _Pol


def _sub(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


def _cross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


# --------------------------------------------------------------------------------------------
# exact decision procedures at one instant (inputs: 3-tuples of exact scalars)


def point_on_segment(p, u, v) -> bool:
    """p in the closed segment [u, v] (u == v allowed)."""
    d = _sub(v, u)
    w = _sub(p, u)
    if any(_sgn(x) for x in _cross(d, w)):
        return False
    dd = _dot(d, d)
    if _sgn(dd) == 0:
        return not any(_sgn(x) for x in w)
    s = _dot(w, d)
    return _sgn(s) >= 0 and _sgn(dd - s) >= 0


def vf_contact(p, a, b, c) -> bool:
    """p in the closed triangle conv{a, b, c} (degenerate triangles: their convex hull)."""
    ab, ac, ap = _sub(b, a), _sub(c, a), _sub(p, a)
    n = _cross(ab, ac)
    if _sgn(_dot(n, ap)) != 0:
        return False
    if any(_sgn(x) for x in n):
        for u, v in ((a, b), (b, c), (c, a)):
            if _sgn(_dot(n, _cross(_sub(v, u), _sub(p, u)))) < 0:
                return False
        return True
    # a, b, c collinear (or coincident): the hull is the union of the three segments
    return point_on_segment(p, a, b) or point_on_segment(p, b, c) or point_on_segment(p, c, a)


def ee_contact(a0, a1, b0, b1) -> bool:
    """Closed segments [a0, a1] and [b0, b1] intersect (degenerate segments allowed)."""
    da, db = _sub(a1, a0), _sub(b1, b0)
    if _sgn(_dot(_cross(da, _sub(b0, a0)), _sub(b1, a0))) != 0:
        return False
    n = _cross(da, db)
    if any(_sgn(x) for x in n):
        o1 = _sgn(_dot(n, _cross(da, _sub(b0, a0))))
        o2 = _sgn(_dot(n, _cross(da, _sub(b1, a0))))
        o3 = _sgn(_dot(n, _cross(db, _sub(a0, b0))))
        o4 = _sgn(_dot(n, _cross(db, _sub(a1, b0))))
        return o1 * o2 <= 0 and o3 * o4 <= 0
    # parallel, or one/both segments a point: contact iff an endpoint lies on the other segment
    return (
        point_on_segment(a0, b0, b1)
        or point_on_segment(a1, b0, b1)
        or point_on_segment(b0, a0, a1)
        or point_on_segment(b1, a0, a1)
    )


# every polynomial whose sign the procedures above can query (f itself excluded: it is zero)


def _pos_polys(p, u, v):
    d, w = _sub(v, u), _sub(p, u)
    dd, s = _dot(d, d), _dot(w, d)
    return [*_cross(d, w), dd, *w, s, dd - s]


def _vf_event_polys(p, a, b, c):
    n = _cross(_sub(b, a), _sub(c, a))
    out = list(n)
    for u, v in ((a, b), (b, c), (c, a)):
        out.append(_dot(n, _cross(_sub(v, u), _sub(p, u))))
        out += _pos_polys(p, u, v)
    return out


def _ee_event_polys(a0, a1, b0, b1):
    da, db = _sub(a1, a0), _sub(b1, b0)
    n = _cross(da, db)
    out = list(n)
    out.append(_dot(n, _cross(da, _sub(b0, a0))))
    out.append(_dot(n, _cross(da, _sub(b1, a0))))
    out.append(_dot(n, _cross(db, _sub(a0, b0))))
    out.append(_dot(n, _cross(db, _sub(a1, b0))))
    for p, u, v in ((a0, b0, b1), (a1, b0, b1), (b0, a0, a1), (b1, a0, a1)):
        out += _pos_polys(p, u, v)
    return out


# --------------------------------------------------------------------------------------------
# real roots in [0, 1]


def _isolate(h: tuple, lo: Fraction, hi: Fraction):
    """Isolating intervals of the real roots of h in [lo, hi] (sympy; h square-free)."""
    P = sympy.Poly([sympy.Rational(x.numerator, x.denominator) for x in reversed(h)], _X, domain=sympy.QQ)
    ivs = P.intervals(inf=sympy.Rational(lo.numerator, lo.denominator), sup=sympy.Rational(hi.numerator, hi.denominator))
    return [(to_fraction(a), to_fraction(b)) for (a, b), _k in ivs]


def _roots01(pol: _Pol, cache: dict) -> list:
    """Distinct real roots of pol in [0, 1]: Fractions and RealAlgebraic (shared via cache)."""
    if len(pol.c) <= 1:
        return []
    P = sympy.Poly([sympy.Rational(x.numerator, x.denominator) for x in reversed(pol.c)], _X, domain=sympy.QQ)
    out = []
    for fac, _mult in P.factor_list()[1]:
        co = [to_fraction(x) for x in reversed(fac.all_coeffs())]
        lead = co[-1]
        h = tuple(x / lead for x in co)  # monic
        if len(h) == 2:
            r = -h[0]
            if 0 <= r <= 1:
                out.append(r)
            continue
        if h not in cache:
            roots = []
            for lo, hi in _isolate(h, Fraction(0), Fraction(1)):
                if lo == hi:  # cannot happen (irrational), but keep the invariant explicit
                    raise AssertionError("rational root of an irreducible factor")
                roots.append(RealAlgebraic(h, lo, hi))
            # a root may sit in an interval reaching outside [0, 1]: theta != 0, 1 (irrational)
            cache[h] = [r for r in roots if r > 0 and r < 1]
        out += cache[h]
    return out


def _cmp(a, b) -> int:
    if isinstance(a, RealAlgebraic):
        return a.cmp(b)
    if isinstance(b, RealAlgebraic):
        return -b.cmp(a)
    return (a > b) - (a < b)


def _sorted_unique(vals) -> list:
    vals = sorted(vals, key=cmp_to_key(_cmp))
    out = []
    for v in vals:
        if out and _cmp(out[-1], v) == 0:
            continue
        out.append(v)
    return out


def _between(a, b) -> Fraction:
    """A rational strictly between a < b."""
    while True:
        ahi = a.hi if isinstance(a, RealAlgebraic) else a
        blo = b.lo if isinstance(b, RealAlgebraic) else b
        if ahi < blo:
            return (ahi + blo) / 2
        if isinstance(a, RealAlgebraic):
            a.refine()
        if isinstance(b, RealAlgebraic):
            b.refine()


# --------------------------------------------------------------------------------------------
# the query


class ExactResult(NamedTuple):
    hit: bool
    toi: Fraction | RealAlgebraic | None
    coplanar: bool  # coplanarity cubic identically zero

    @property
    def toi_float(self) -> float:
        return math.inf if self.toi is None else float(self.toi)


def _exact_query(query) -> list:
    if len(query) != 8:
        raise ValueError("a query is 8 points (t0 rows then t1 rows)")
    q = [tuple(to_fraction(x) for x in row) for row in query]
    if any(len(r) != 3 for r in q):
        raise ValueError("points must be 3D")
    return q


def _at(q, t):
    """The 4 points at time t (Fraction or RealAlgebraic)."""
    pts = []
    for i in range(4):
        x0, x1 = q[i], q[i + 4]
        if isinstance(t, RealAlgebraic):
            pts.append(tuple(_AlgNum(t, (x0[k], x1[k] - x0[k])) for k in range(3)))
        else:
            pts.append(tuple(x0[k] + t * (x1[k] - x0[k]) for k in range(3)))
    return pts


def _trajectory_polys(q):
    return [tuple(_Pol((q[i][k], q[i + 4][k] - q[i][k])) for k in range(3)) for i in range(4)]


def contact_at(query, kind: str, t) -> bool:
    """Exact contact test at one time t (int/float/Fraction, or a RealAlgebraic)."""
    q = _exact_query(query)
    pred = _predicate(kind)
    if not isinstance(t, RealAlgebraic):
        t = to_fraction(t)
    return pred(*_at(q, t))


def _predicate(kind):
    if kind == "vertex-face":
        return vf_contact
    if kind == "edge-edge":
        return ee_contact
    raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")


def coplanarity_cubic(query, kind: str) -> tuple:
    """Exact coefficients (low -> high, Fractions, trailing zeros stripped) of the coplanarity
    polynomial: vertex-face det(t1-t0, t2-t0, p-t0); edge-edge det(ea1-ea0, eb0-ea0, eb1-ea0)."""
    _predicate(kind)
    x = _trajectory_polys(_exact_query(query))
    if kind == "vertex-face":
        p, a, b, c = x
        return _dot(_cross(_sub(b, a), _sub(c, a)), _sub(p, a)).c
    a0, a1, b0, b1 = x
    return _dot(_cross(_sub(a1, a0), _sub(b0, a0)), _sub(b1, a0)).c


def exact_ccd(query, kind: str, check_gaps: bool = True) -> ExactResult:
    """Exact earliest contact time in [0, 1] of a vertex-face or edge-edge query (see module doc).

    ``check_gaps`` (coplanar case only): assert that contact is off at one rational point of every
    gap between consecutive candidate times before the answer (a self-check of the method)."""
    pred = _predicate(kind)
    q = _exact_query(query)
    f = _Pol(coplanarity_cubic(q, kind))
    cache: dict = {}
    if not f.is_zero():
        for r in _sorted_unique(_roots01(f, cache)):
            if pred(*_at(q, r)):
                return ExactResult(True, r, False)
        return ExactResult(False, None, False)
    x = _trajectory_polys(q)
    polys = _vf_event_polys(*x) if kind == "vertex-face" else _ee_event_polys(*x)
    cands = [Fraction(0), Fraction(1)]
    for g in polys:
        cands += _roots01(g, cache)
    prev = None
    for r in _sorted_unique(cands):
        if check_gaps and prev is not None:
            # contact is constant on (prev, r); the contact set is closed, so contact there
            # would have meant contact at prev, which was already found false
            if pred(*_at(q, _between(prev, r))):
                raise AssertionError("contact inside a gap between candidate times: missing event polynomial")
        if pred(*_at(q, r)):
            return ExactResult(True, r, True)
        prev = r
    return ExactResult(False, None, True)


def exact_point_triangle(query) -> ExactResult:
    return exact_ccd(query, "vertex-face")


def exact_edge_edge(query) -> ExactResult:
    return exact_ccd(query, "edge-edge")
