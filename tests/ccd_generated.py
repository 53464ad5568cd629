"""CCD queries that touch exactly by construction, with every coordinate exactly a float64.

    from ccd_generated import generate_queries
    g = generate_queries(n_per_case=3, seed=0)
    g.points   # (N, 8, 3) float64, rows in ipctk order (see ccd_queries.py)
    g.kinds    # (N,) str: "vertex-face" | "edge-edge"
    g.tois     # list of Fraction: the exact earliest time of contact in [0, 1]
    g.labels   # list of str "<case>/<instance>/<scale>", e.g. "vf-edge/0/s=2^20"
    m = generate_near_misses()   # same fields, tois all None (miss by ~2^-30)
    pts, tois, labels = g.select("edge-edge")

Construction (all in exact rationals with power-of-two denominators, then checked to convert to
float64 exactly). A contact configuration is built at the contact time t* (a dyadic in (0, 1),
or 0 / 1 for the endpoint cases) in a canonical frame where the contact plane is z = 0 (or the
contact line is the x axis); every vertex gets a dyadic velocity and x(0) = x(t*) - t* v,
x(1) = x(t*) + (1 - t*) v. "No earlier contact" is guaranteed by a separating argument:
* transversal cases: every vertex has z(t) = w (t - t*) with max w of one primitive < min w of
  the other, so before t* one primitive is strictly above the other (contact needs a convex
  combination of one side's z to equal one of the other's); in-plane velocities are arbitrary;
* in-plane (coplanar for the whole step) cases: the primitives are rigid and translate towards
  each other across a separating line, resp. along a common line with every point of one
  primitive left of every point of the other before t*.
Then transforms that keep t* exactly: a common (Galilean) dyadic velocity for all four vertices,
an invertible integer 3x3 matrix (affine maps keep coplanarity, convex combinations and linear
motion), a scale 2^0 / 2^20 / 2^-20 and a dyadic translation. ``n_per_case`` random instances
of each case and each of the three scales.
"""

from __future__ import annotations

import random
from fractions import Fraction
from typing import NamedTuple

import numpy as np

F = Fraction
SCALES = (("s=1", F(1)), ("s=2^20", F(2**20)), ("s=2^-20", F(1, 2**20)))


def _is_double(x: Fraction) -> bool:
    return Fraction(float(x)) == x


class GeneratedQueries(NamedTuple):
    points: np.ndarray  # (N, 8, 3) float64
    kinds: np.ndarray  # (N,) str
    tois: list  # N Fractions
    labels: list  # N str

    def select(self, kind: str):
        """(points (M, 8, 3), tois (list of Fraction), labels) of one kind."""
        idx = [i for i, k in enumerate(self.kinds) if k == kind]
        return self.points[idx], [self.tois[i] for i in idx], [self.labels[i] for i in idx]

    def exact(self, i: int):
        """Query i as (8, 3) Fractions (the floats are exact)."""
        return [[Fraction(float(x)) for x in row] for row in self.points[i]]


class _Rng:
    def __init__(self, seed):
        self.r = random.Random(seed)

    def dy(self, lo: int, hi: int, bits: int = 2) -> Fraction:
        """Dyadic k / 2^bits with integer k in [lo, hi]."""
        return F(self.r.randint(lo, hi), 2**bits)

    def vec(self, lo=-8, hi=8, bits=2):
        return [self.dy(lo, hi, bits) for _ in range(3)]

    def vec2(self, lo=-8, hi=8, bits=2):
        return [self.dy(lo, hi, bits), self.dy(lo, hi, bits), F(0)]

    def tstar(self) -> Fraction:
        return F(self.r.randint(1, 15), 16)

    def choice(self, seq):
        return self.r.choice(seq)

    def randint(self, a, b):
        return self.r.randint(a, b)


def _add(u, v):
    return [a + b for a, b in zip(u, v)]


def _sub(u, v):
    return [a - b for a, b in zip(u, v)]


def _mul(s, u):
    return [s * a for a in u]


def _cross2(u, v):
    return u[0] * v[1] - u[1] * v[0]


def _query(pos_star, vel, tstar):
    """8 rows (t0 rows, then t1 rows) from positions at t* and velocities."""
    t0 = [_sub(x, _mul(tstar, v)) for x, v in zip(pos_star, vel)]
    t1 = [_add(x, _mul(1 - tstar, v)) for x, v in zip(pos_star, vel)]
    return t0 + t1


def _triangle(rng):
    """A non-degenerate triangle in z = 0 with dyadic vertices."""
    while True:
        a, b, c = rng.vec2(), rng.vec2(), rng.vec2()
        if _cross2(_sub(b, a), _sub(c, a)) != 0:
            return a, b, c


def _z_sep_velocities(rng, n_low: int, n_high: int):
    """z velocities: the first n_low all strictly below the last n_high (w_low max < w_high min).
    For t < t* the 'low' group is above the 'high' group (z = w (t - t*)), for t > t* below."""
    cut = rng.randint(-4, 4)
    low = [F(rng.randint(-12, cut * 2 - 1), 4) for _ in range(n_low)]
    high = [F(rng.randint(cut * 2 + 1, 12), 4) for _ in range(n_high)]
    return low + high


def _inplane_vel(rng):
    return rng.vec2(-6, 6)


# ----------------------------------------------------------------------- vertex-face base cases


def _vf_transversal(rng, tstar, where, gap=F(0)):
    """Triangle in z = 0 at t* with the point on it ('interior', 'edge' or 'vertex'); with
    gap > 0 the point is instead just outside, across an edge ('edge') or beyond a corner."""
    a, b, c = _triangle(rng)
    # dyadic barycentric weights k_i / 16 (sum exactly 1)
    if where == "interior":
        k1 = rng.randint(1, 14)
        k2 = rng.randint(1, 15 - k1)
        w = [F(k1, 16), F(k2, 16), F(16 - k1 - k2, 16)]
    elif where == "edge":
        k1 = rng.randint(1, 15)
        w = [F(k1, 16) + gap, F(16 - k1, 16), -gap]
    else:  # vertex
        w = [1 + gap, -gap / 2, -gap / 2]
    rng.r.shuffle(w)
    p = [w[0] * a[i] + w[1] * b[i] + w[2] * c[i] for i in range(3)]
    zv = _z_sep_velocities(rng, 1, 3)  # point above the triangle before t*, below after
    vel = [_add(_inplane_vel(rng), [0, 0, z]) for z in zv]
    return _query([p, a, b, c], vel, tstar)


def _vf_sliding(rng, tstar, where):
    """All four points in z = 0 for the whole step; rigid triangle, point enters across an edge
    (where='edge') or through a corner (where='vertex')."""
    a, b, c = _triangle(rng)
    tri = [a, b, c]
    if _cross2(_sub(b, a), _sub(c, a)) < 0:
        tri = [a, c, b]  # counter-clockwise
    i = rng.randint(0, 2)
    u, v, o = tri[i], tri[(i + 1) % 3], tri[(i + 2) % 3]
    if where == "edge":
        s = F(rng.randint(1, 3), 4)
        p = _add(u, _mul(s, _sub(v, u)))
        e = _sub(v, u)
        while True:  # inward: left of u->v (ccw), i.e. cross(e, dir) > 0
            d = rng.vec2(-6, 6)
            if _cross2(e, d) > 0:
                break
    else:
        p = list(u)
        # a direction strictly inside the corner cone at u: positive combination of the edges
        d = _add(_mul(F(rng.randint(1, 4)), _sub(v, u)), _mul(F(rng.randint(1, 4)), _sub(o, u)))
        d = _mul(F(1, 4), d)
    vt = _inplane_vel(rng)  # common translation of the rigid triangle
    vel = [_add(vt, d), vt, vt, vt]
    return _query([p, a, b, c], vel, tstar)


# ------------------------------------------------------------------------- edge-edge base cases


def _ee_transversal(rng, tstar, where, gap=F(0)):
    """At t* both edges in z = 0 touching: 'cross' interior-interior, 'vertex-edge' an endpoint of
    b on the interior of a, 'vertex-vertex' shared endpoint. With gap > 0 the lines still cross
    but just outside a ('cross') or just past b's end ('vertex-edge')."""
    while True:
        x = rng.vec2()
        da, db = rng.vec2(-6, 6), rng.vec2(-6, 6)
        if _cross2(da, db) != 0:
            break
    if where == "cross":
        s, u = F(rng.randint(1, 7), 8), F(rng.randint(1, 7), 8)
        if gap:
            s = -gap
    elif where == "vertex-edge":
        s, u = F(rng.randint(1, 7), 8), F(rng.choice([0, 1]))
        if gap:
            u = -gap if u == 0 else 1 + gap
    else:
        s, u = F(rng.choice([0, 1])), F(rng.choice([0, 1]))
    a0, a1 = _sub(x, _mul(s, da)), _add(x, _mul(1 - s, da))
    b0, b1 = _sub(x, _mul(u, db)), _add(x, _mul(1 - u, db))
    zv = _z_sep_velocities(rng, 2, 2)  # a above b before t*, below after
    vel = [_add(_inplane_vel(rng), [0, 0, z]) for z in zv]
    return _query([a0, a1, b0, b1], vel, tstar)


def _ee_sliding(rng, tstar):
    """Coplanar for the whole step: rigid b translates in z = 0 until its endpoint b0 hits the
    interior of rigid a (a on the x axis in a's frame; b strictly above y = 0 before t*)."""
    L = F(rng.randint(2, 8), 2)
    a0, a1 = [F(0), F(0), F(0)], [L, F(0), F(0)]
    b0 = [L * F(rng.randint(1, 7), 8), F(0), F(0)]
    b1 = [rng.dy(-8, 8), rng.dy(1, 8), F(0)]
    vb = [rng.dy(-6, 6), rng.dy(-6, -1), F(0)]
    va = _inplane_vel(rng)
    vel = [va, va, _add(va, vb), _add(va, vb)]
    return _query([a0, a1, b0, b1], vel, tstar)


def _ee_parallel(rng, tstar):
    """Edges parallel to x for the whole step (coplanarity cubic identically zero): b's line
    reaches a's line at t* (both lines differ before), x ranges overlapping at t*."""
    a_lo = rng.dy(-8, 0)
    a_hi = a_lo + rng.dy(1, 8)
    b_lo = rng.dy(-8, 8)
    if b_lo > a_hi:
        b_lo = a_hi  # touching end to end at t* at worst
    b_hi = max(b_lo + rng.dy(1, 8), a_lo)
    a0, a1 = [a_lo, F(0), F(0)], [a_hi, F(0), F(0)]
    b0, b1 = [b_lo, F(0), F(0)], [b_hi, F(0), F(0)]
    if rng.randint(0, 1):
        b0, b1 = b1, b0
    yz = [rng.dy(-6, 6), rng.dy(-6, 6), F(0)]
    yz = [F(0), yz[0] or F(1), yz[1]]  # b's (y, z) velocity relative to a, nonzero
    vel = [[rng.dy(-6, 6), F(0), F(0)] for _ in range(2)]
    vel += [_add([rng.dy(-6, 6), F(0), F(0)], yz) for _ in range(2)]
    return _query([a0, a1, b0, b1], vel, tstar)


def _ee_collinear(rng, tstar, overlap):
    """All four points on the x axis for the whole step. overlap=False: every point of a is left
    of every point of b before t*, a1 == b0 at t*; overlap=True: overlapping throughout (t* = 0)."""
    if overlap:
        a_lo = rng.dy(-8, 0)
        a_hi = a_lo + rng.dy(2, 8)
        b_lo = a_lo + rng.dy(1, 1)
        b_hi = a_hi + rng.dy(1, 4)
        va = rng.dy(-2, 2)
        vel = [[va, F(0), F(0)]] * 2 + [[va + rng.dy(-1, 1, 4), F(0), F(0)]] * 2
    else:
        a_lo = rng.dy(-8, 0)
        a_hi = a_lo + rng.dy(1, 8)
        b_lo = a_hi
        b_hi = b_lo + rng.dy(1, 8)
        cut = rng.randint(-4, 4)
        vel = [[F(rng.randint(cut + 1, 12), 4), F(0), F(0)] for _ in range(2)]
        vel += [[F(rng.randint(-12, cut - 1), 4), F(0), F(0)] for _ in range(2)]
    a0, a1 = [a_lo, F(0), F(0)], [a_hi, F(0), F(0)]
    b0, b1 = [b_lo, F(0), F(0)], [b_hi, F(0), F(0)]
    if rng.randint(0, 1):
        a0, a1 = a1, a0
        vel[0], vel[1] = vel[1], vel[0]
    if rng.randint(0, 1):
        b0, b1 = b1, b0
        vel[2], vel[3] = vel[3], vel[2]
    return _query([a0, a1, b0, b1], vel, tstar)


def _pick(*options):
    return lambda rng: rng.choice(list(options))


# label, kind, builder(rng, t*) -> 8 rows, t* ("random": k/16, 1 <= k <= 15, or 0 / 1),
# separated_after (no contact for t > t* either: moving t* below 0 gives a near miss)
_CASES = [
    ("vf-interior", "vertex-face", lambda r, t: _vf_transversal(r, t, "interior"), "random", True),
    ("vf-edge", "vertex-face", lambda r, t: _vf_transversal(r, t, "edge"), "random", True),
    ("vf-vertex", "vertex-face", lambda r, t: _vf_transversal(r, t, "vertex"), "random", True),
    ("vf-sliding-edge", "vertex-face", lambda r, t: _vf_sliding(r, t, "edge"), "random", False),
    ("vf-sliding-vertex", "vertex-face", lambda r, t: _vf_sliding(r, t, "vertex"), "random", False),
    ("vf-t0", "vertex-face", lambda r, t: _vf_transversal(r, t, _pick("interior", "edge", "vertex")(r)), 0, True),
    ("vf-t1", "vertex-face", lambda r, t: _vf_transversal(r, t, _pick("interior", "edge", "vertex")(r)), 1, True),
    ("vf-sliding-t0", "vertex-face", lambda r, t: _vf_sliding(r, t, _pick("edge", "vertex")(r)), 0, False),
    ("vf-sliding-t1", "vertex-face", lambda r, t: _vf_sliding(r, t, _pick("edge", "vertex")(r)), 1, False),
    ("ee-cross", "edge-edge", lambda r, t: _ee_transversal(r, t, "cross"), "random", True),
    ("ee-vertex-edge", "edge-edge", lambda r, t: _ee_transversal(r, t, "vertex-edge"), "random", True),
    ("ee-vertex-vertex", "edge-edge", lambda r, t: _ee_transversal(r, t, "vertex-vertex"), "random", True),
    ("ee-sliding", "edge-edge", lambda r, t: _ee_sliding(r, t), "random", False),
    ("ee-parallel", "edge-edge", lambda r, t: _ee_parallel(r, t), "random", True),
    ("ee-collinear-touch", "edge-edge", lambda r, t: _ee_collinear(r, t, False), "random", False),
    ("ee-collinear-overlap", "edge-edge", lambda r, t: _ee_collinear(r, t, True), 0, None),
    ("ee-t0", "edge-edge", lambda r, t: _ee_transversal(r, t, _pick("cross", "vertex-edge")(r)), 0, True),
    ("ee-t1", "edge-edge", lambda r, t: _ee_transversal(r, t, _pick("cross", "vertex-edge")(r)), 1, True),
]
CASE_LABELS = tuple(c[0] for c in _CASES)

# near misses: label, kind, builder(rng, t*, gap) -> rows (spatially outside by ~gap at t*)
_MISS_CASES = [
    ("vf-outside-edge", "vertex-face", lambda r, t, g: _vf_transversal(r, t, "edge", g)),
    ("vf-outside-vertex", "vertex-face", lambda r, t, g: _vf_transversal(r, t, "vertex", g)),
    ("ee-outside-cross", "edge-edge", lambda r, t, g: _ee_transversal(r, t, "cross", g)),
    ("ee-outside-vertex-edge", "edge-edge", lambda r, t, g: _ee_transversal(r, t, "vertex-edge", g)),
]


# ------------------------------------------------------------------------------- transforms


def _random_matrix(rng):
    while True:
        m = [[F(rng.randint(-2, 2)) for _ in range(3)] for _ in range(3)]
        det = (
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
        )
        if det != 0:
            return m


def _linear_part(rows, rng, canonical):
    """Galilean boost and integer matrix (t* unchanged); identity when canonical."""
    rows = [list(r) for r in rows]
    if canonical:
        return rows
    boost = rng.vec(-4, 4)
    rows = [r if i < 4 else _add(r, boost) for i, r in enumerate(rows)]
    m = _random_matrix(rng)
    return [[sum(m[k][j] * r[j] for j in range(3)) for k in range(3)] for r in rows]


def _scaled_translated(rows, rng, scale):
    """Scale by a power of two, then a dyadic translation a few binary orders above the scene's
    scale (t* unchanged)."""
    off = [scale * F(rng.randint(-(2**12), 2**12), 2**4) for _ in range(3)]
    return [_add(_mul(scale, r), off) for r in rows]


def _tstar(rng, mode) -> Fraction:
    return rng.tstar() if mode == "random" else F(mode)


def _emit(out, trng, label, kind, rows, toi, canonical):
    """Append the three scaled/translated copies of one construction: the same boost and matrix
    for all three (so the copies are the same query up to scale and translation); translations
    are redrawn until every coordinate is exactly a float64."""
    pts, kinds, tois, labels = out
    for _attempt in range(20):
        base = _linear_part(rows, trng, canonical)
        copies = []
        for sname, scale in SCALES:
            for _t in range(50):
                moved = _scaled_translated(base, trng, scale)
                if all(_is_double(x) for r in moved for x in r):
                    copies.append((sname, moved))
                    break
            else:
                break
        if len(copies) == len(SCALES):
            break
    else:  # pragma: no cover
        raise RuntimeError(f"{label}: could not make an exactly representable instance")
    for sname, moved in copies:
        pts.append([[float(x) for x in r] for r in moved])
        kinds.append(kind)
        tois.append(toi)
        labels.append(f"{label}/{sname}")


def _pack(out) -> GeneratedQueries:
    pts, kinds, tois, labels = out
    return GeneratedQueries(np.array(pts, dtype=np.float64).reshape(-1, 8, 3), np.array(kinds), tois, labels)


def generate_queries(n_per_case: int = 3, seed: int = 0, canonical_first: bool = True) -> GeneratedQueries:
    """Touching queries: ``n_per_case`` random instances of every case in ``CASE_LABELS``, each at
    the scales 1, 2^20, 2^-20 (3 * n_per_case * 18 queries); ``tois`` are the exact contact times.
    Labels are "<case>/<instance>/<scale>"; the three scales of one instance are the same query up
    to the power-of-two scale and a translation.

    With ``canonical_first`` the first instance of each case skips the boost and integer matrix
    (axis-aligned contact plane / line, the most degenerate-looking input); all get a translation.
    """
    rng, trng = _Rng(seed), _Rng(seed + 7919)
    out = ([], [], [], [])
    for label, kind, build, mode, _sep in _CASES:
        for inst in range(n_per_case):
            t = _tstar(rng, mode)
            _emit(out, trng, f"{label}/{inst}", kind, build(rng, t), t, canonical_first and inst == 0)
    return _pack(out)


def generate_near_misses(n_per_case: int = 2, seed: int = 1, gap: Fraction = F(1, 2**30)) -> GeneratedQueries:
    """Queries that miss by a tiny margin (``tois`` all None), from the same constructions:
    * "<case>-late": contact time moved to 1 + gap (every case with no contact before t*);
    * "<case>-early": contact time moved to -gap (cases also separated after t*);
    * "vf-outside-*", "ee-outside-*": at t* the point / line crossing is just outside, by ~gap.
    """
    rng, trng = _Rng(seed), _Rng(seed + 7919)
    out = ([], [], [], [])
    for label, kind, build, _mode, sep in _CASES:
        if sep is None:
            continue
        for suffix, t in (("late", 1 + gap), ("early", -gap)) if sep else (("late", 1 + gap),):
            for inst in range(n_per_case):
                _emit(out, trng, f"{label}-{suffix}/{inst}", kind, build(rng, t), None, inst == 0)
    for label, kind, build in _MISS_CASES:
        for inst in range(n_per_case):
            _emit(out, trng, f"{label}/{inst}", kind, build(rng, rng.tstar(), gap), None, inst == 0)
    return _pack(out)


if __name__ == "__main__":
    for g in (generate_queries(), generate_near_misses()):
        print(len(g.tois), "queries;", {k: int((g.kinds == k).sum()) for k in ("vertex-face", "edge-edge")})
        print("max |coordinate|", np.abs(g.points).max(), "min nonzero", np.abs(g.points[g.points != 0]).min())
