"""Generated precision / knob variants of the root solver and the narrow-phase CCD
(:mod:`kernels.variants`, the ``precision=`` / knob arguments of :mod:`collision.roots` and
:mod:`collision.ccd`).

Ground truth: mpmath (``groundtruth.true_roots`` of the float32-rounded coefficients, i.e. of the
polynomial the float32 kernel is actually given), exact constructions (double / triple dyadic
roots), closed-form geometry, the sample queries' own truth flags. Nothing is compared with the
code under test except where bit-identity *is* the claim (the generated float64 copy).

Measured figures behind the bounds (this machine, the seeds below; u32 = 2^-24):

* float32, well-conditioned (distinct real roots >= 0.5 apart, |root| in [0.25, 4]; complex
  pairs with |Im| >= 0.5): relative forward error max 23 u32 (cubics) / 4.3 u32 (quadratics),
  backward error max 1.96 u32; bounds: forward 256 u32, backward 8 u32. Tiny roots (2^-38):
  11 u32;
* float32 double roots (exact dyadic): max relative error 2.8 sqrt(u32), bound 16 sqrt(u32);
  triple: 1.6 u32^(1/3), bound 8 u32^(1/3);
* knobs (float64, the well-separated cubics): default max error 1.1e-15; ``max_iterations=1``
  3.7e149 (garbage roots: the deflation works from an unconverged root); ``tolerance=1e-2``
  5.8e-4;
* float32 CCD on the sample queries: FN 0 / 0, FP 195 / 302 (vertex-face / edge-edge); float64
  FN 0 / 0, FP 72 / 131.

Several tests exist to catch a float32 constant left at its float64 value (checked by mutating
:data:`kernels.variants.FLOAT32_CONSTANTS`): ``NO_RESCALE_MAX`` (power-of-two invariance),
``SMALL_ARGUMENT`` (tiny roots), ``COPLANAR_RELATIVE`` (sample-query false negatives); literals
outside float32's range are refused by the generator itself.

The first run compiles five forward-only Warp variant modules (~35 s on 2 cores, besides the
original kernels if they are not cached yet); later runs load them from the Warp kernel cache
(the whole file then takes ~6 s).
"""

from __future__ import annotations

import os
import sys
from fractions import Fraction

import numpy as np
import pytest
import warp as wp

sys.path.insert(0, os.path.dirname(__file__))
import ccd_queries  # noqa: E402
import groundtruth as gt  # noqa: E402

import collision.roots as croots  # noqa: E402
import kernels.ccd  # noqa: E402
import kernels.roots  # noqa: E402
from collision.ccd import edge_edge_ccd, narrow_phase, point_triangle_ccd  # noqa: E402
from collision.roots import FLOAT32_T_MAX, cubic_root_jacobian, solve_cubic, solve_quadratic  # noqa: E402
from kernels import variants  # noqa: E402

U32 = 2.0**-24
FORWARD_BOUND_U32 = 256
BACKWARD_BOUND_U32 = 8
DOUBLE_BOUND = 16 * np.sqrt(U32)
TRIPLE_BOUND = 8 * U32 ** (1.0 / 3.0)
# float32 CCD on the sample queries: measured FN 0 for both kinds; FP measured 195 / 302.
CCD32_FN_BOUND = 0
CCD32_FP_BOUND = {"vertex-face": 200, "edge-edge": 310}
SEEDS = {"cubic_real": 1, "cubic_complex": 2, "quadratic_real": 3, "quadratic_complex": 4}


# ------------------------------------------------------------------------------ well-conditioned inputs


def _roots_apart(rng, count, gap):
    """count roots with |r| in [0.25, 4], random signs, pairwise at least ``gap`` apart."""
    while True:
        r = rng.choice([-1.0, 1.0], count) * rng.uniform(0.25, 4.0, count)
        if count == 1 or np.min(np.diff(np.sort(r))) >= gap:
            return r


def _well_conditioned(kind: str, n: int, seed: int):
    """(coefficients rounded to float32 (as float64), exact roots of *those* coefficients (mpmath))."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n):
        lead = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 2.0)
        if kind == "cubic_real":
            p = lead * np.poly(_roots_apart(rng, 3, 0.5))
        elif kind == "cubic_complex":
            x, s = _roots_apart(rng, 2, 0.5)
            y = rng.uniform(0.5, 2.0)
            p = lead * np.polymul([1.0, -s], [1.0, -2 * x, x * x + y * y])
        elif kind == "quadratic_real":
            p = lead * np.poly(_roots_apart(rng, 2, 0.5))
        else:
            x = rng.choice([-1.0, 1.0]) * rng.uniform(0.25, 4.0)
            y = rng.uniform(0.5, 2.0)
            p = lead * np.array([1.0, -2 * x, x * x + y * y])
        rows.append(p)
    p32 = np.array(rows).astype(np.float32).astype(np.float64)
    return p32, [gt.true_roots(row)[0] for row in p32]


# ------------------------------------------------------------------------------ the generator


def test_default_settings_return_the_original_modules():
    v = variants.kernel_variant()
    assert v.roots is kernels.roots and v.ccd is kernels.ccd and v.package is None
    # the defaults spelled out are still the defaults
    w = variants.kernel_variant("float64", max_iterations=256, tolerance=2.0**-51, tolerance_scale=1.0)
    assert w.roots is kernels.roots and w.ccd is kernels.ccd
    assert croots.root_kernels("float64", None, None) is kernels.roots


def test_generated_float64_copy_gives_bit_identical_roots():
    v = variants.kernel_variant(generate=True)
    assert v.roots is not kernels.roots and v.package and (v.directory / "roots.py").is_file()
    rng = np.random.default_rng(7)
    cubics = np.concatenate([rng.uniform(-1, 1, (2000, 4)), gt.fuzz_inputs(rng, 2000, 4),
                             gt.cubic_category("double", 200)[0], gt.cubic_category("mixed_mag", 200)[0]])
    quads = np.concatenate([rng.uniform(-1, 1, (1000, 3)), gt.fuzz_inputs(rng, 1000, 3)])
    (copy_c,) = croots.launch_root_kernel(v.roots.solve_cubic_kernel, cubics, wp.vec4d, [1e150], [v.roots.vec6d])
    (copy_q,) = croots.launch_root_kernel(v.roots.solve_quadratic_kernel, quads, wp.vec3d, [1e150], [wp.vec4d])
    orig_c = solve_cubic(cubics).view(np.float64).reshape(copy_c.shape)
    orig_q = solve_quadratic(quads).view(np.float64).reshape(copy_q.shape)
    assert np.array_equal(copy_c.view(np.uint64), orig_c.view(np.uint64))
    assert np.array_equal(copy_q.view(np.uint64), orig_q.view(np.uint64))


def test_float32_source_is_float32_throughout():
    src = variants.generate_sources(variants.check_settings("float32"), "pkg")
    for name, text in src.items():
        code = variants._code_only(text)
        assert "float64" not in code and "vec3d" not in code.replace("wp.vec3f", ""), name
        assert "from pkg." in text or name == "roots" or name == "ccd_common"
    assert "UNIT_ROUNDOFF = wp.constant(wp.float32(5.960464477539063e-08))" in src["ccd_common"]
    assert "NEWTON_RELATIVE_TOLERANCE = wp.constant(wp.float32(2.384185791015625e-07))" in src["roots"]
    assert "CCD_T_MAX = wp.constant(wp.float32(9.999999843067494e+17))" in src["ccd_common"]


def test_generator_refuses_a_source_it_no_longer_matches(monkeypatch):
    real = variants._sources

    def edited():
        s = real()
        s["roots"] = s["roots"].replace("1.0261652496336e-289", "1.0e-289")  # BALANCE_SPREAD edited
        return s

    monkeypatch.setattr(variants, "_sources", edited)
    with pytest.raises(RuntimeError, match="BALANCE_SPREAD"):
        variants.generate_sources(variants.check_settings("float32"), "pkg")

    def new_literal():
        s = real()
        s["ccd"] = s["ccd"].replace("wp.float64(0.9) * gap", "wp.float64(0.9e-300) * gap")
        return s

    monkeypatch.setattr(variants, "_sources", new_literal)
    with pytest.raises(RuntimeError, match="0.9e-300"):
        variants.generate_sources(variants.check_settings("float32"), "pkg")


# ------------------------------------------------------------------------------ float32 roots


@pytest.mark.parametrize("kind", ["cubic_real", "cubic_complex", "quadratic_real", "quadratic_complex"])
def test_float32_roots_are_accurate_on_well_conditioned_inputs(kind):
    p, truth = _well_conditioned(kind, 150, seed=SEEDS[kind])
    solve = solve_cubic if kind.startswith("cubic") else solve_quadratic
    ours = solve(p, precision="float32")
    assert ours.dtype == np.complex128
    # computed in float32: every part is a float32 value, and not the float64 answer
    assert np.array_equal(ours.real.astype(np.float32).astype(np.float64), ours.real)
    assert not np.array_equal(ours, solve(p))
    fwd, bwd = [], []
    for i in range(len(p)):
        pairs = gt.match_roots(list(ours[i]), truth[i])
        assert len(pairs) == len(truth[i]) == ours.shape[1]
        fwd += [gt.forward_error(ours[i][s], truth[i][j]) for s, j in pairs]
        bwd += [gt.backward_error(p[i], z) for z in ours[i]]
    fwd_u, bwd_u = max(fwd) / U32, max(bwd) / U32
    print(f"\n[{kind}] float32 forward error max {fwd_u:.3g} u32 (median {np.median(fwd) / U32:.3g}), "
          f"backward max {bwd_u:.3g} u32")
    assert fwd_u <= FORWARD_BOUND_U32
    assert bwd_u <= BACKWARD_BOUND_U32


def test_float32_degenerate_cubics_and_quadratics():
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, (200, 4))
    q0 = p.copy()
    q0[:, 0] = 0.0  # leading zero: the third root escapes to -sign(a) t_max
    r = solve_cubic(q0, precision="float32")
    assert r.shape == (200, 3) and np.isfinite(r).all()
    escaped = np.abs(r.real) == FLOAT32_T_MAX
    assert np.all(escaped.sum(axis=1) == 1)
    assert np.array_equal(np.sign(r.real[escaped]), -np.sign(q0[:, 1]))
    qa0 = p.copy()
    qa0[:, :2] = 0.0  # linear: two roots at +-t_max, one finite
    r = solve_cubic(qa0, precision="float32")
    assert np.isfinite(r).all() and np.all((np.abs(r.real) == FLOAT32_T_MAX).sum(axis=1) == 2)
    lin = r[np.abs(r.real) < FLOAT32_T_MAX].real
    np.testing.assert_allclose(lin, -qa0[:, 3].astype(np.float32) / qa0[:, 2].astype(np.float32), rtol=4 * U32)
    assert np.array_equal(solve_cubic(np.zeros((3, 4)), precision="float32"), np.zeros((3, 3)))
    assert np.array_equal(solve_quadratic(np.zeros((3, 3)), precision="float32"), np.zeros((3, 2)))
    r = solve_quadratic(np.column_stack([np.zeros(50), p[:50, 1:3]]), precision="float32")
    assert np.isfinite(r).all() and np.all((np.abs(r.real) == FLOAT32_T_MAX).sum(axis=1) == 1)
    # exact dyadic double and triple roots (coefficients exactly float32)
    for name, bound, mult in (("double", DOUBLE_BOUND, 2), ("triple", TRIPLE_BOUND, 3)):
        c, exact = gt.cubic_category(name, 200)
        assert np.array_equal(c.astype(np.float32).astype(np.float64), c)
        r = solve_cubic(c, precision="float32")
        assert np.isfinite(r).all()
        worst = 0.0
        for i in range(len(c)):
            pairs = gt.match_roots(list(r[i]), exact[i])
            errs = [gt.forward_error(r[i][s], exact[i][j]) for s, j in pairs]
            worst = max(worst, max(errs))
        print(f"\n[{name}] float32 max relative error {worst:.3g} ({worst / U32 ** (1 / mult):.3g} u32^(1/{mult}))")
        assert worst <= bound
    c, _ = gt.quadratic_category("double", 200)
    r = solve_quadratic(c, precision="float32")
    assert np.isfinite(r).all() and r.shape == (200, 2)


def test_float32_power_of_two_scaling_leaves_the_roots_bit_identical():
    """Scaling all coefficients by 2^e (exact while they stay normal float32) must not change a
    single bit of the float32 roots, up to coefficients of 2^100 and down to 2^-100 (design.md's
    invariance, in float32): catches a rescaling threshold left at its float64 value (e.g.
    ``NO_RESCALE_MAX = 2^100``: squares of 2^60 coefficients overflow float32; measured 209 of
    4600 rows differing at 2^60)."""
    rng = np.random.default_rng(2)
    p = np.concatenate([rng.uniform(-1, 1, (4000, 4)), gt.cubic_category("double", 300)[0],
                        gt.cubic_category("spread_real", 300)[0]]).astype(np.float32).astype(np.float64)
    base = solve_cubic(p, precision="float32")
    for e in (-100, -60, -30, 20, 40, 60, 90, 100):
        q = p * 2.0**e
        assert np.all((q == 0) | (np.abs(q) >= 2.0**-126)) and np.all(np.abs(q) < 2.0**127)
        r = solve_cubic(q, precision="float32")
        assert np.array_equal(r, base), (e, int((r != base).any(axis=1).sum()))


def test_float32_tiny_roots_are_accurate():
    """Well-separated dyadic roots scaled to 2^-20 .. 2^-38 (coefficients exactly float32, down to
    ~2^-120), every other cubic with one root exactly 0 (c = 0), which must come back exactly 0
    (the relative error is absolute below 2^-1022): relative error within the well-conditioned
    bound. Catches ``SMALL_ARGUMENT`` left at 2^-100 (the rescaled search never starts and the
    zero root comes back as ~1e-22: measured errors of 1e292 "u32")."""
    rng = np.random.default_rng(4)
    worst = 0.0
    for e in (20, 30, 38):
        rows = []
        for n in range(100):
            ks = [Fraction(int(round(k * 16)), 16 * 2**e) for k in _roots_apart(rng, 3, 0.5)]
            if n % 2:
                ks[int(np.argmin([abs(k) for k in ks]))] = Fraction(0)
            rows.append((ks, [], 1))
        p, exact = gt._from_roots(rows, 3)
        assert np.array_equal(p.astype(np.float32).astype(np.float64), p) and all(x is not None for x in exact)
        got = solve_cubic(p, precision="float32")
        for i in range(len(p)):
            for s, j in gt.match_roots(list(got[i]), exact[i]):
                worst = max(worst, gt.forward_error(got[i][s], exact[i][j]))
    print(f"\ntiny roots: float32 max relative error {worst / U32:.3g} u32")
    assert worst <= FORWARD_BOUND_U32 * U32


def test_float32_jacobian_is_finite_and_close_to_float64():
    rng = np.random.default_rng(5)
    p, _ = _well_conditioned("cubic_real", 100, seed=11)
    j32 = cubic_root_jacobian(p, precision="float32")
    j64 = cubic_root_jacobian(p)
    assert j32.dtype == np.float64 and np.isfinite(j32).all()
    scale = np.abs(j64).max(axis=(-1, -2, -3), keepdims=True)
    assert np.abs(j32 - j64).max() / scale.max() < 1e-3
    assert np.isfinite(cubic_root_jacobian(rng.uniform(-1, 1, (500, 4)), precision="float32")).all()


def test_float32_outputs_are_finite_on_adversarial_inputs():
    """Every root and Jacobian entry finite over the float32 range: the project's fuzz inputs that
    fit float32, float32 special values (subnormals, FLT_MIN, FLT_MAX, 2^-24 ...) and magnitudes
    log-uniform over 1e-45 .. 3e38 (these exercise the substituted rescaling / balancing
    constants: a float64 one left in place overflows or underflows there)."""
    rng = np.random.default_rng(9)
    special = np.array([0.0, 1.4e-45, 1e-40, 1.1754944e-38, 1e-30, 2.0**-24, 0.5, 1.0, 3.0, 1e20, 1e38, 3.4028234e38])
    for width, fns in ((4, (solve_cubic, cubic_root_jacobian)), (3, (solve_quadratic, croots.quadratic_root_jacobian))):
        fuzz = gt.fuzz_inputs(rng, 8000, width)
        logu = rng.choice([-1.0, 1.0], (8000, width)) * 10.0 ** rng.uniform(-45, 38.5, (8000, width))
        spec = rng.choice(special, (8000, width)) * rng.choice([-1.0, 1.0], (8000, width))
        x = np.concatenate([fuzz, logu, spec])
        with np.errstate(over="ignore"):
            x = x[np.isfinite(x.astype(np.float32)).all(axis=1)]
        assert len(x) > 15000
        for fn in fns:
            out = fn(x, precision="float32")
            bad = ~np.isfinite(out).reshape(len(x), -1).all(axis=1)
            assert not bad.any(), (fn.__name__, x[bad][:3].tolist())


def test_float32_coefficients_out_of_range_are_rejected():
    with pytest.raises(ValueError, match="overflow float32"):
        solve_cubic(np.array([1e300, 1.0, 0.0, 1.0]), precision="float32")


# ------------------------------------------------------------------------------ knobs


def _spread_real(n=100):
    """Cubics with three real roots >= 0.5 apart, and their exact roots (mpmath)."""
    return _well_conditioned("cubic_real", n, seed=21)


def _max_error(p, exact, roots):
    worst = 0.0
    for i in range(len(p)):
        for s, j in gt.match_roots(list(roots[i]), exact[i]):
            worst = max(worst, gt.forward_error(roots[i][s], exact[i][j]))
    return worst


def test_max_iterations_knob_changes_the_roots():
    p, exact = _spread_real()
    default = _max_error(p, exact, solve_cubic(p))
    capped = _max_error(p, exact, solve_cubic(p, max_iterations=1))
    print(f"\nfloat64 max error: default {default:.3g}, max_iterations=1 {capped:.3g}")
    assert default < 1e-12
    assert capped > 1e3 * max(default, 1e-16)


def test_tolerance_knob_changes_the_roots():
    p, exact = _spread_real()
    default = _max_error(p, exact, solve_cubic(p))
    loose = _max_error(p, exact, solve_cubic(p, tolerance=1e-2))
    print(f"\nfloat64 max error: default {default:.3g}, tolerance=1e-2 {loose:.3g}")
    assert loose > 1e3 * max(default, 1e-16)


@pytest.mark.parametrize("call", ["solve_cubic", "solve_quadratic", "narrow_phase", "point_triangle_ccd", "kernel_variant"])
def test_bad_settings_raise_value_errors_naming_the_argument(call):
    p4, p3 = np.ones(4), np.ones(3)
    q = np.zeros((1, 8, 3))
    fns = {
        "solve_cubic": lambda **kw: solve_cubic(p4, **kw),
        "solve_quadratic": lambda **kw: solve_quadratic(p3, **kw),
        "narrow_phase": lambda **kw: narrow_phase(0, q, **kw),
        "point_triangle_ccd": lambda **kw: point_triangle_ccd(*q.transpose(1, 0, 2), **kw),
        "kernel_variant": lambda precision="float64", **kw: variants.kernel_variant(precision, **kw),
    }
    fn = fns[call]
    bad = [("precision", "float16"), ("precision", "FLOAT32"), ("max_iterations", 0), ("max_iterations", -3),
           ("max_iterations", 2.5), ("max_iterations", True), ("tolerance", 0.0), ("tolerance", -1e-3),
           ("tolerance", float("nan")), ("tolerance", float("inf"))]
    if call in ("narrow_phase", "point_triangle_ccd", "kernel_variant"):
        bad += [("tolerance_scale", 0.0), ("tolerance_scale", -2.0), ("tolerance_scale", float("inf"))]
    for name, value in bad:
        with pytest.raises(ValueError, match=name):
            fn(**{name: value})


# ------------------------------------------------------------------------------ CCD


def test_tolerance_scale_knob_widens_the_contact_test():
    """A vertex passing the triangle's plane at a distance d beside its edge: with d between the
    default distance tolerance (256 u * extent, ~1e-13 here) and 1000 times it, the default
    narrow phase reports a miss and ``tolerance_scale=1000`` a hit (closed-form geometry)."""
    tri = (np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    d = 2.0**-36  # ~1.5e-11
    p0, p1 = np.array([[-d, 0.25, 1.0]]), np.array([[-d, 0.25, -1.0]])
    hit, _ = point_triangle_ccd(p0, *tri, p1, *tri)
    assert not hit[0]
    hit, toi = point_triangle_ccd(p0, *tri, p1, *tri, tolerance_scale=1000.0)
    assert hit[0] and toi[0] == pytest.approx(0.5, abs=1e-9)
    # an exact hit stays a hit in every setting
    for kw in ({}, {"tolerance_scale": 1000.0}, {"precision": "float32"}):
        hit, toi = point_triangle_ccd(np.array([[0.25, 0.25, 1.0]]), *tri, np.array([[0.25, 0.25, -1.0]]), *tri, **kw)
        assert hit[0] and toi[0] == 0.5, kw
    ea = (np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 1.0]]))
    eb = (np.array([[0.5, -0.5, 0.0]]), np.array([[0.5, 0.5, 0.0]]))
    hit, toi = edge_edge_ccd(*ea, *eb, ea[0] - [0, 0, 2.0], ea[1] - [0, 0, 2.0], *eb, precision="float32")
    assert hit[0] and toi[0] == 0.5


@pytest.mark.skipif(not ccd_queries.available() and not os.environ.get("CI"),
                    reason="sample queries not found (set TUNNELSIM_CCD_QUERIES)")
def test_float32_ccd_on_the_sample_queries():
    """float32 narrow phase (queries rounded to float32, float32 arithmetic) against the data set's
    truth (of the exact rationals). Measured: FN 0 / 0, FP 195 / 302 (float64: FP 72 / 131)."""
    for kind_index, kind in enumerate(ccd_queries.KINDS):
        qs = ccd_queries.load_queries(kind)
        hit, toi, _ = narrow_phase(kind_index, qs.points, precision="float32")
        assert toi.dtype == np.float64 and np.all((toi[hit] >= 0) & (toi[hit] <= 1)) and np.all(np.isinf(toi[~hit]))
        fn = int(np.sum(qs.truth & ~hit))
        fp = int(np.sum(~qs.truth & hit))
        fp64 = int(np.sum(~qs.truth & narrow_phase(kind_index, qs.points)[0]))
        print(f"\n[{kind}] float32: FN {fn}, FP {fp} (float64 FP {fp64}) of {len(hit)} queries")
        assert fn <= CCD32_FN_BOUND, [qs.ids[i] for i in np.flatnonzero(qs.truth & ~hit)][:5]
        assert fp <= CCD32_FP_BOUND[kind]
