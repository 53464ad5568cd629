"""Accuracy of ``collision.roots.solve_cubic`` / ``solve_quadratic`` against exact ground truth.

Per input category (see ``groundtruth.CUBIC_CATEGORIES`` / ``QUADRATIC_CATEGORIES``; 200 fixed
seeded samples each) :func:`test_accuracy` checks

(a) backward error: every returned root that is not clamped (|Re|, |Im| < t_max) has
    |p(z)| / sum_k |c_k| |z|^k <= ``BACKWARD_ULPS`` ulp, evaluated in mpmath on the float
    coefficients exactly as given;
(b) forward error against the exact roots (mpmath, or the exact dyadic construction), measured
    *relative to |root|* (absolute below the smallest normal float64, so an exact zero root must
    be returned as exactly zero). The solver is "never worse than numpy.roots" when, over all
    roots that both return (numpy.roots drops leading zero coefficients, so it may return fewer;
    true roots beyond t_max are excluded), both its maximum and its median forward error are at
    most numpy's plus ``SLACK`` (2 ulp, absolute);
(c) every exact root beyond t_max is matched by a root clamped to the t_max box with the right
    sign, and no finite exact root is left without a computed root.

The slot conventions of design.md ("Root slot conventions") and the degenerate patterns (q = 0,
q = a = 0, constants, zero polynomial, c = 0) are checked by the ``test_*_slots`` tests; power of
two scaling and sign flips must leave the roots bit-identical.

Run with ``-s`` to see the measured figures of every category.
"""

from __future__ import annotations

import os
import sys
from fractions import Fraction
from functools import lru_cache

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
import groundtruth as gt  # noqa: E402

from collision.roots import solve_cubic, solve_quadratic  # noqa: E402

T_MAX = 1e150
ULP = 2.0**-52
# (a) a backward-stable solver returns each root with |p(z)| of a few rounding errors of the
# Horner sum; the brief's bound is 8 ulp (rounding z itself to float64 alone costs up to ~3 ulp).
BACKWARD_ULPS = 8
# (b) absolute slack on the relative forward error when comparing with numpy.roots: 2 ulp.
SLACK = 2 * ULP
N_SAMPLES = 200


@lru_cache(maxsize=None)
def _evaluated(kind: str, name: str):
    gen, solve = (gt.cubic_category, solve_cubic) if kind == "cubic" else (gt.quadratic_category, solve_quadratic)
    p, exact = gen(name, N_SAMPLES)
    ours = solve(p)
    return p, ours, gt.evaluate(p, exact, ours, T_MAX)


def _fmt_input(p, ours, i):
    return f"  p={p[i].tolist()!r}\n    ours={ours[i].tolist()!r}\n    numpy={np.roots(p[i]).tolist()!r}"


CASES = [("cubic", c) for c in gt.CUBIC_CATEGORIES] + [("quadratic", c) for c in gt.QUADRATIC_CATEGORIES]


@pytest.mark.parametrize("kind,name", CASES, ids=[f"{k}-{n}" for k, n in CASES])
def test_accuracy(kind, name):
    p, ours, res = _evaluated(kind, name)
    problems = []

    # (a) backward error of every unclamped root
    bw = res["backward"]
    bw_max = max((b for _, _, b in bw), default=0.0)
    bad_bw = [(i, s, b) for i, s, b in bw if not b <= BACKWARD_ULPS * ULP]
    if bad_bw:
        problems.append(f"backward error > {BACKWARD_ULPS} ulp in {len(bad_bw)} roots; worst:")
        for i, s, b in sorted(bad_bw, key=lambda x: -x[2])[:5]:
            problems.append(f"  slot {s}: {b / ULP:.3g} ulp\n" + _fmt_input(p, ours, i))

    # (b) forward error vs numpy.roots on the roots both return
    both = [(i, s, f, g) for i, s, f, g in res["forward"] if g is not None]
    ours_all = np.array([f for _, _, f, _ in res["forward"]])
    f_ours = np.array([f for _, _, f, _ in both])
    f_np = np.array([g for _, _, _, g in both])
    if len(both):
        ours_max, np_max = f_ours.max(), f_np.max()
        ours_med, np_med = np.median(f_ours), np.median(f_np)
        if not ours_max <= np_max + SLACK:
            worst = max(both, key=lambda x: x[2])
            problems.append(
                f"max forward error {ours_max:.3e} > numpy's {np_max:.3e} (+2 ulp); worst sample "
                f"(ours {worst[2]:.3e}, numpy {worst[3]:.3e} on that root):\n" + _fmt_input(p, ours, worst[0])
            )
        if not ours_med <= np_med + SLACK:
            problems.append(f"median forward error {ours_med:.3e} > numpy's {np_med:.3e} (+2 ulp)")
    else:
        ours_max = np_max = ours_med = np_med = float("nan")

    # (c) roots beyond t_max come back clamped with the right sign; nothing unmatched
    for i, s, t, z in res["beyond"]:
        ok_re = abs(t.real) <= T_MAX or (abs(z.real) == T_MAX and np.sign(z.real) == np.sign(float(t.real)))
        ok_im = abs(t.imag) <= T_MAX or (abs(z.imag) == T_MAX and np.sign(z.imag) == np.sign(float(t.imag)))
        if not (ok_re and ok_im):
            problems.append(f"root beyond t_max not clamped: true {complex(t)!r}, got {z!r}\n" + _fmt_input(p, ours, i))
    if res["unmatched"]:
        problems.append(f"samples with fewer computed than exact finite roots: {res['unmatched'][:5]}")

    print(
        f"\n[{kind}/{name}] backward max {bw_max / ULP:.3g} ulp | forward (vs true, both returned n={len(both)}) "
        f"ours max {ours_max:.3e} med {ours_med:.3e} | numpy max {np_max:.3e} med {np_med:.3e} | "
        f"ours over all {len(ours_all)} roots max {ours_all.max() if len(ours_all) else 0:.3e} | "
        f"beyond t_max {len(res['beyond'])}"
    )
    assert not problems, f"{kind}/{name}:\n" + "\n".join(problems)


# ---------------------------------------------------------------------------------------------
# slot conventions
# ---------------------------------------------------------------------------------------------


def _reduced_c_sign(p) -> int:
    """Exact sign of the reduced c^ = (2a^3 - 9abq + 27cq^2) / (27 q^3) after flipping to q > 0."""
    q, a, b, c = (Fraction(float(x)) for x in p)
    if q < 0:
        q, a, b, c = -q, -a, -b, -c
    v = 2 * a**3 - 9 * a * b * q + 27 * c * q**2
    return (v > 0) - (v < 0)


def _truth_kind(p):
    """'real3' (three real roots, pairwise relative gap > 1e-6), 'pair' (one real root and a pair
    with |Im| > 1e-6 |z|) or None (ambiguous, skipped) — from the exact roots."""
    roots, n_inf = gt.true_roots(p)
    if roots is None or n_inf or len(roots) != 3:
        return None
    if all(r.imag == 0 for r in roots):
        xs = sorted(float(r.real) for r in roots)
        scale = max(abs(x) for x in xs)
        if min(xs[1] - xs[0], xs[2] - xs[1]) > 1e-6 * scale:
            return "real3"
        return None
    cplx = [r for r in roots if r.imag != 0]
    if abs(cplx[0].imag) > 1e-6 * abs(cplx[0]):
        return "pair"
    return None


@lru_cache(maxsize=None)
def _cubic_convention_inputs():
    rows = []
    for name in ("uniform", "spread_real", "complex_tiny_im", "mixed_mag", "q_tiny"):
        p, _ = gt.cubic_category(name, 120)
        for row in p:
            k = _truth_kind(row)
            if k is not None:
                rows.append((row, k))
    return rows


def test_cubic_slots_real_and_pair():
    """Three real roots ascend; one real root is t+ iff reduced c^ <= 0, the pair's
    larger-labelled slot has +Im and the two pair slots are conjugates."""
    rows = _cubic_convention_inputs()
    p = np.array([r for r, _ in rows])
    z = solve_cubic(p)
    n_real3 = n_pair = 0
    bad = []
    for i, (row, kind) in enumerate(rows):
        r = z[i]
        if kind == "real3":
            n_real3 += 1
            if not (np.all(r.imag == 0) and r.real[0] <= r.real[1] <= r.real[2]):
                bad.append(f"three real roots not ascending/real: p={row.tolist()!r} got {r.tolist()!r}")
        else:
            n_pair += 1
            if np.all(np.abs(r.real) == T_MAX) or np.any(np.abs(r.imag) == T_MAX):
                continue  # clamped: the pair structure is not observable
            real_slot = 2 if _reduced_c_sign(row) <= 0 else 0
            pair = [0, 1] if real_slot == 2 else [1, 2]
            ok = (
                r[real_slot].imag == 0
                and r[pair[0]].real == r[pair[1]].real
                and r[pair[1]].imag > 0
                and r[pair[0]].imag == -r[pair[1]].imag
            )
            if not ok:
                bad.append(
                    f"one real root (reduced c^ sign {_reduced_c_sign(row)}): expected real in slot {real_slot}, "
                    f"+Im in slot {pair[1]}: p={row.tolist()!r} got {r.tolist()!r}"
                )
    print(f"\nconvention inputs: {n_real3} with three real roots, {n_pair} with a complex pair")
    assert n_real3 > 100 and n_pair > 100
    assert not bad, f"{len(bad)} violations:\n" + "\n".join(bad[:10])


def test_cubic_slots_degenerate():
    """q = 0: escaping root -sign(a) t_max (slot 0 if a > 0, slot 2 if a < 0); q = a = 0: roots
    {-t_max, -c/b, -sign(b) t_max} ascending; constant c: {sign(c), sign(c), -sign(c)} * t_max
    ascending; zero polynomial: triple 0; c = 0 (q != 0): an exact zero root."""
    rng = np.random.default_rng(7)
    bad = []
    # q = 0
    p = rng.uniform(-1, 1, (300, 4))
    p[:, 0] = 0.0
    z = solve_cubic(p)
    for row, r in zip(p, z):
        slot = 0 if row[1] > 0 else 2
        if not (r[slot] == -np.sign(row[1]) * T_MAX):
            bad.append(f"q=0: expected {-np.sign(row[1]) * T_MAX:g} in slot {slot}: p={row.tolist()!r} got {r.tolist()!r}")
    # q = a = 0
    p = rng.uniform(-1, 1, (300, 4))
    p[:, :2] = 0.0
    p[:20, 3] = 0.0  # linear root exactly 0
    z = solve_cubic(p)
    for row, r in zip(p, z):
        b, c = row[2], row[3]
        lin = -c / b
        expect = sorted([-T_MAX, lin, -np.sign(b) * T_MAX])
        if not (np.all(r.imag == 0) and np.allclose(r.real, expect, rtol=2 * ULP, atol=0)):
            bad.append(f"q=a=0: expected {expect} got {r.tolist()!r} for p={row.tolist()!r}")
    # constants
    for c in (1.0, -1.0, 5e-324, -1e300, 3.5):
        r = solve_cubic(np.array([0.0, 0.0, 0.0, c]))
        s = np.sign(c)
        expect = sorted([s * T_MAX, s * T_MAX, -s * T_MAX])
        if not (np.all(r.imag == 0) and np.array_equal(r.real, expect)):
            bad.append(f"constant {c!r}: expected {expect} got {r.tolist()!r}")
    # zero polynomial, both zero signs
    for row in ([0.0, 0.0, 0.0, 0.0], [-0.0, 0.0, -0.0, 0.0]):
        r = solve_cubic(np.array(row))
        if not np.array_equal(r, np.zeros(3, complex)):
            bad.append(f"zero polynomial {row}: expected triple 0, got {r.tolist()!r}")
    # c = 0: one root exactly zero
    p = rng.uniform(-1, 1, (300, 4))
    p[:, 3] = 0.0
    z = solve_cubic(p)
    for row, r in zip(p, z):
        if not np.any(r == 0):
            bad.append(f"c=0: no exact zero root: p={row.tolist()!r} got {r.tolist()!r}")
    assert not bad, f"{len(bad)} violations:\n" + "\n".join(bad[:10])


def test_quadratic_slots():
    """t+ = (-b + sqrt(b^2-4ac)) / 2a: real pair has sign(a) (t+ - t-) >= 0; complex pair has
    Im t+ = +sqrt(4ac-b^2)/(2a) (sign of a) and conjugate slots; a = 0, b < 0: (-c/b, +t_max);
    a = 0, b > 0: (-t_max, -c/b); a = b = 0: (sign(c), -sign(c)) t_max; zero: double 0."""
    rng = np.random.default_rng(11)
    bad = []
    p = rng.uniform(-1, 1, (2000, 3))
    z = solve_quadratic(p)
    for row, r in zip(p, z):
        a, b, c = row
        disc = Fraction(b) ** 2 - 4 * Fraction(a) * Fraction(c)
        if disc > 0:
            if not (np.all(r.imag == 0) and np.sign(a) * (r[1].real - r[0].real) >= 0):
                bad.append(f"real: p={row.tolist()!r} got {r.tolist()!r}")
        elif disc < 0:
            if not (r[0].real == r[1].real and r[0].imag == -r[1].imag and np.sign(r[1].imag) == np.sign(a)):
                bad.append(f"complex: p={row.tolist()!r} got {r.tolist()!r}")
    p = rng.uniform(-1, 1, (200, 3))
    p[:, 0] = 0.0
    for row, r in zip(p, solve_quadratic(p)):
        b, c = row[1], row[2]
        expect = [-c / b, T_MAX] if b < 0 else [-T_MAX, -c / b]
        if not (np.all(r.imag == 0) and np.allclose(r.real, expect, rtol=2 * ULP, atol=0)):
            bad.append(f"a=0: expected {expect} got {r.tolist()!r} for p={row.tolist()!r}")
    for c in (5.0, -5.0, 5e-324, -1e308):
        r = solve_quadratic(np.array([0.0, 0.0, c]))
        expect = [np.sign(c) * T_MAX, -np.sign(c) * T_MAX]
        if not (np.all(r.imag == 0) and np.array_equal(r.real, expect)):
            bad.append(f"a=b=0, c={c!r}: expected {expect} got {r.tolist()!r}")
    r = solve_quadratic(np.zeros(3))
    if not np.array_equal(r, np.zeros(2, complex)):
        bad.append(f"zero polynomial: expected double 0, got {r.tolist()!r}")
    # c = 0: roots exactly 0 and -b/a
    p = rng.uniform(-1, 1, (200, 3))
    p[:, 2] = 0.0
    for row, r in zip(p, solve_quadratic(p)):
        r = sorted(r, key=abs)
        if not (r[0] == 0 and r[1].imag == 0 and np.isclose(r[1].real, -row[1] / row[0], rtol=2 * ULP, atol=0)):
            bad.append(f"c=0: expected 0 and {-row[1] / row[0]!r}, got {r!r}")
    assert not bad, f"{len(bad)} violations:\n" + "\n".join(bad[:10])


def test_t_max_keyword_clamps():
    """Roots beyond a user t_max are clamped to it (here 1e10) with the right sign."""
    p = np.array([[1e-12, 1.0, -3.0, 2.0], [-1e-12, 1.0, -3.0, 2.0]])  # roots 1, 2 and -/+ ~1e12
    z = solve_cubic(p, t_max=1e10)
    assert np.all(z.imag == 0) and np.all(np.abs(z.real) <= 1e10)
    assert z[0].real.min() == -1e10 and z[1].real.max() == 1e10
    np.testing.assert_allclose(np.sort(z.real, axis=1)[0, 1:], [1.0, 2.0], rtol=1e-11)
    zq = solve_quadratic(np.array([1e-12, 1.0, -1.0]), t_max=1e10)  # roots ~1 and ~-1e12
    assert np.all(np.abs(zq.real) <= 1e10) and zq.real.min() == -1e10


def test_scale_and_sign_invariance():
    """Multiplying all coefficients by 2^k (exact) or by -1 (q != 0) leaves every cubic root
    bit-identical (the solver normalises by a power of two and flips to q >= 0); for the quadratic, 2^k leaves
    the roots bit-identical and -1 swaps the slots t- <-> t+ (t+ = (-b + sqrt)/2a), a != 0."""
    rows = []
    for name in ("uniform", "spread_real", "double", "triple", "complex_tiny_im", "q_zero", "qa_zero", "c_zero"):
        rows.append(gt.cubic_category(name, 100)[0])
    p = np.concatenate(rows)
    base = solve_cubic(p)
    for factor in (2.0**990, 2.0**-900, 2.0**40, -1.0, -(2.0**-500)):
        scaled = p * factor
        assert np.array_equal(scaled / factor, p)  # the scaling is exact
        got = solve_cubic(scaled)
        changed = np.any(got != base, axis=1)
        if factor < 0:
            # q = 0 has pseudo-sign q > 0, so its escaping root -sign(a) t_max follows the sign
            changed &= p[:, 0] != 0
        diff = np.nonzero(changed)[0]
        assert len(diff) == 0, (
            f"factor {factor!r}: {len(diff)} cubics changed, e.g. p={p[diff[0]].tolist()!r}: "
            f"{base[diff[0]].tolist()!r} -> {got[diff[0]].tolist()!r}"
        )
    rows = [gt.quadratic_category(n, 100)[0] for n in ("uniform", "spread_real", "double", "complex_tiny_im", "c_zero")]
    p = np.concatenate(rows)
    base = solve_quadratic(p)
    for factor in (2.0**990, 2.0**-900, -1.0, -(2.0**40)):
        got = solve_quadratic(p * factor)
        expect = base[:, ::-1] if factor < 0 else base
        diff = np.nonzero(np.any(got != expect, axis=1))[0]
        assert len(diff) == 0, (
            f"factor {factor!r}: {len(diff)} quadratics changed, e.g. p={p[diff[0]].tolist()!r}: "
            f"expected {expect[diff[0]].tolist()!r}, got {got[diff[0]].tolist()!r}"
        )


def test_groundtruth_self_consistency():
    """The ground truth agrees with mpmath.polyroots on moderate inputs and with the exact
    dyadic constructions (double/triple/1e-12 pairs) — so the other tests measure the solver."""
    from mpmath import mp, mpc

    def rel(z, t):
        with mp.workdps(60):
            return float(abs(mpc(z) - t) / max(abs(t), 1e-300))

    p, _ = gt.cubic_category("uniform", 30)
    for row in p:
        mine, _ = gt.true_roots(row)
        ref = gt.true_roots_polyroots(row)
        for i, j in gt.match_roots(ref, mine, cost=rel):
            assert rel(ref[i], mine[j]) < 1e-40
    for name in ("double", "triple", "pair_1e-12", "complex_tiny_im"):
        p, exact = gt.cubic_category(name, 20)
        for row, ex in zip(p, exact):
            if ex is None:
                continue
            mine, _ = gt.true_roots(row)
            for i, j in gt.match_roots(mine, ex, cost=rel):
                assert rel(mine[i], ex[j]) < 1e-40, (name, row, mine, ex)
