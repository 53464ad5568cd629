"""Derivatives of the roots: ``cubic_root_jacobian`` / ``quadratic_root_jacobian`` and the torch
autograd functions ``cubic_roots`` / ``quadratic_roots``.

* Where the mollification is inactive (well separated roots, |t| far below t_max, every robust
  division multiplier well below M) the Jacobian must equal the true derivative of the root:
  central finite differences in mpmath (step 1e-20 times the coefficient scale, mp.dps = 50,
  each exact root tracked by proximity) agree to a relative ``FD_RTOL`` = 1e-7 of the root's
  largest derivative entry — real and complex roots, quadratic and cubic, q = 0 cubics, raw
  coefficients of scale 1e-2 .. 1e3 and negative leading coefficients (the normalisation of
  eq. ``dpboundeddp`` is chained back).
* ``torch.autograd.gradcheck`` passes on ``quadratic_roots`` / ``cubic_roots`` there.
* At repeated roots, 1e-12 clusters, a = 0 / q = 0 / all-zero patterns and roots clamped at t_max
  the Jacobian is finite and bounded: every entry <= ``BOUND_FACTOR`` * M (M = 1000). The robust
  division bounds each multiplier by M with unit direction vectors, and chaining back the
  normalisation by S = max(1, max|p|) adds at most 4 M / S — so 5 M bounds every entry.
* The clamped signs of Remarks ``clampingderiv`` / ``cubicclampingderivs`` at exact double roots,
  and the first rows of the paper's tables ``bad_a``, ``bad_ab``, ``bad_abc`` (L = (t+ - 0.5)^2/2).

Run with ``-s`` to see the measured figures.
"""

from __future__ import annotations

import os
import sys
from functools import lru_cache

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
import groundtruth as gt  # noqa: E402

from collision.roots import (  # noqa: E402
    cubic_root_jacobian,
    cubic_roots,
    quadratic_root_jacobian,
    quadratic_roots,
    solve_cubic,
    solve_quadratic,
)

M = 1000.0
T_MAX = 1e150
# Relative agreement with mpmath finite differences where the clamp is inactive (the brief's
# 1e-7; the Jacobian is evaluated at the float64 root, so ~1e-15 * conditioning is expected).
FD_RTOL = 1e-7
# "Clamp inactive" margin: the conservative multiplier estimate must stay below M / 100.
CLAMP_MARGIN = 100.0
# Universal bound on Jacobian entries in units of M (see module docstring).
BOUND_FACTOR = 5.0
N_FD = 30


def _cubic_fd_inputs(kind: str, n: int):
    """Well-conditioned cubics: 'real3', 'pair', 'q0_real', 'q0_pair' (q = 0), times scale/sign."""
    rng = np.random.default_rng({"real3": 1, "pair": 2, "q0_real": 3, "q0_pair": 4}[kind])
    out = []
    scales = [1.0, 1e3, 1e-2, -1.0, -30.0]
    for i in range(n):
        lam = scales[i % len(scales)] * rng.uniform(0.5, 2.0)
        if kind == "real3":
            r = gt._separated(rng, 3, -2, 2, 0.5)
            p = np.poly(r)
        elif kind == "pair":
            s, x = gt._separated(rng, 2, -2, 2, 0.5)
            if rng.random() < 0.5:
                s, x = x, s
            y = rng.uniform(0.3, 2.0)
            p = np.polymul([1.0, -s], [1.0, -2 * x, x * x + y * y])
        elif kind == "q0_real":
            r = gt._separated(rng, 2, -2, 2, 0.5)
            p = np.concatenate([[0.0], np.poly(r)])
        else:
            x, y = rng.uniform(-2, 2), rng.uniform(0.3, 2.0)
            p = np.array([0.0, 1.0, -2 * x, x * x + y * y])
        out.append(p * lam)
    return np.array(out)


def _quadratic_fd_inputs(kind: str, n: int):
    rng = np.random.default_rng({"real2": 5, "pair": 6}[kind])
    out = []
    scales = [1.0, 1e3, 1e-2, -1.0, -30.0]
    for i in range(n):
        lam = scales[i % len(scales)] * rng.uniform(0.5, 2.0)
        if kind == "real2":
            p = np.poly(gt._separated(rng, 2, -2, 2, 0.5))
        else:
            x, y = rng.uniform(-2, 2), rng.uniform(0.3, 2.0)
            p = np.array([1.0, -2 * x, x * x + y * y])
        out.append(p * lam)
    return np.array(out)


def _clamp_inactive(p, t, deg) -> bool:
    """Conservative test that no robust division of the root t saturates.

    The largest multiplier is bounded by |dt/dp|_max * S * max(1, |t|)^deg, with S the
    normalisation scale (cubic: max(1, max|p|); quadratic: raw coefficients, S = 1)."""
    ex = gt.exact_derivative(p, t)
    dmax = max(abs(v) for row in ex for v in row)
    s = max(1.0, float(np.max(np.abs(p)))) if deg == 3 else 1.0
    return dmax * s * max(1.0, abs(complex(t))) ** deg * CLAMP_MARGIN < M


def _compare_fd(p, roots, jac, deg):
    """Per computed root: (relative error vs FD, clamp inactive?) using proximity matching."""
    fd = gt.fd_root_jacobians(p)
    exact = [t for t, _ in fd]
    pairs = gt.match_roots(list(roots), exact)
    out = []
    for s, j in pairs:
        t, jf = fd[j]
        if abs(roots[s].real) >= T_MAX or abs(roots[s].imag) >= T_MAX:
            continue
        jf = np.array(jf)
        err = np.max(np.abs(jac[s] - jf)) / np.max(np.abs(jf))
        out.append((s, err, _clamp_inactive(p, t, deg), jf))
    return out


@lru_cache(maxsize=None)
def _fd_results(kind: str):
    if kind.startswith("quadratic_"):
        p = _quadratic_fd_inputs(kind.split("_", 1)[1], N_FD)
        roots, jac, deg = solve_quadratic(p), quadratic_root_jacobian(p), 2
    else:
        p = _cubic_fd_inputs(kind.split("_", 1)[1], N_FD)
        roots, jac, deg = solve_cubic(p), cubic_root_jacobian(p), 3
    return p, roots, jac, [_compare_fd(p[i], roots[i], jac[i], deg) for i in range(len(p))]


FD_KINDS = ["cubic_real3", "cubic_pair", "cubic_q0_real", "cubic_q0_pair", "quadratic_real2", "quadratic_pair"]


@pytest.mark.parametrize("kind", FD_KINDS)
def test_jacobian_matches_finite_differences(kind):
    p, roots, jac, results = _fd_results(kind)
    checked, skipped, worst, bad = 0, 0, 0.0, []
    for i, res in enumerate(results):
        for s, err, inactive, jf in res:
            if not inactive:
                skipped += 1
                continue
            checked += 1
            worst = max(worst, err)
            if not err <= FD_RTOL:
                bad.append(
                    f"p={p[i].tolist()!r} slot {s} root {roots[i][s]!r}: rel err {err:.3e}\n"
                    f"    jacobian={jac[i][s].tolist()!r}\n    finite differences={jf.tolist()!r}"
                )
    print(
        f"\n[{kind}] {checked} roots with inactive clamp ({skipped} skipped as possibly clamped), "
        f"max relative error vs mpmath FD {worst:.3e}"
    )
    assert checked >= N_FD // 2, f"only {checked} roots qualified"
    assert not bad, f"{len(bad)} roots disagree:\n" + "\n".join(bad[:6])


def test_gradcheck_quadratic():
    p = np.concatenate([_quadratic_fd_inputs("real2", 5), _quadratic_fd_inputs("pair", 5)])
    x = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(quadratic_roots, (x,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_cubic():
    p = np.concatenate([_cubic_fd_inputs("real3", 5), _cubic_fd_inputs("pair", 5)])
    x = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cubic_roots, (x,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_torch_forward_and_backward_shapes():
    x = torch.tensor([[1.0, -6.0, 11.0, -6.0], [1.0, 0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    out = cubic_roots(x)
    assert out.shape == (2, 3, 2)
    np.testing.assert_array_equal(out.detach().numpy()[..., 0] + 1j * out.detach().numpy()[..., 1], solve_cubic(x.detach().numpy()))
    g = torch.randn(2, 3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (gx,) = torch.autograd.grad(out, x, g)
    jacobian = cubic_root_jacobian(x.detach().numpy())
    expect = np.einsum("nsr,nsrk->nk", g.numpy(), jacobian)
    # the same sum of products in another order: equal to its rounding, 1e-14 of the summed
    # magnitudes (an entry can cancel far below its terms: relative to it, that fails by chance)
    terms = np.einsum("nsr,nsrk->nk", np.abs(g.numpy()), np.abs(jacobian))
    assert (np.abs(gx.numpy() - expect) <= 1e-14 * terms).all(), (gx.numpy(), expect)
    y = torch.tensor([1.0, -3.0, 2.0], dtype=torch.float64, requires_grad=True)
    out = quadratic_roots(y)
    assert out.shape == (2, 2)
    (gy,) = torch.autograd.grad(out[1, 0], y)  # d t+ / d(a, b, c), t+ = 2
    np.testing.assert_allclose(gy.numpy(), quadratic_root_jacobian(y.detach().numpy())[1, 0], rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# degenerate inputs: finite and bounded
# ---------------------------------------------------------------------------------------------


def _degenerate_cubics():
    parts = {name: gt.cubic_category(name, 200)[0] for name in
             ("double", "triple", "pair_1e-12", "pair_1e-8", "complex_tiny_im", "q_zero", "qa_zero", "q_tiny", "c_zero")}
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, (200, 4))
    p[:, :3] = 0.0
    parts["constant"] = p
    parts["zero"] = np.zeros((4, 4))
    # near-double / near-triple roots approached from both sides of the discriminant
    base = gt.cubic_category("double", 100)[0]
    parts["double_perturbed"] = base + rng.choice([-1, 1], base.shape) * np.abs(base) * 2.0**-50
    return parts


def _degenerate_quadratics():
    parts = {name: gt.quadratic_category(name, 200)[0] for name in
             ("double", "pair_1e-12", "pair_1e-8", "complex_tiny_im", "a_zero", "a_tiny", "c_zero")}
    rng = np.random.default_rng(4)
    p = rng.uniform(-1, 1, (200, 3))
    p[:, :2] = 0.0
    parts["constant"] = p
    parts["zero"] = np.zeros((4, 3))
    base = gt.quadratic_category("double", 100)[0]
    parts["double_perturbed"] = base + rng.choice([-1, 1], base.shape) * np.abs(base) * 2.0**-50
    return parts


@pytest.mark.parametrize("deg", [2, 3])
def test_jacobian_bounded_at_degeneracies(deg):
    parts = _degenerate_cubics() if deg == 3 else _degenerate_quadratics()
    jac_fn = cubic_root_jacobian if deg == 3 else quadratic_root_jacobian
    bad, summary = [], []
    for name, p in parts.items():
        jac = jac_fn(p)
        finite = np.isfinite(jac).all(axis=(1, 2, 3))
        peak = np.max(np.abs(np.where(np.isfinite(jac), jac, 0)), axis=(1, 2, 3))
        summary.append(f"{name} {peak.max() / M:.3g}M")
        for i in np.nonzero(~finite | (peak > BOUND_FACTOR * M))[0][:3]:
            bad.append(f"{name}: p={p[i].tolist()!r} max |J| {peak[i]:.4g} finite={finite[i]}")
    print(f"\n[degree {deg}] max |J| entry per pattern: " + ", ".join(summary))
    assert not bad, "\n".join(bad)


def test_clamped_signs_at_double_roots():
    """Remark clampingderiv (quadratic): at a double root the denominator 2 a t + b is clamped
    positive for t+ and negative for t-, so d t+/dc = -M min(1, 1/t^2) and d t-/dc = +M min(...).
    Remark cubicclampingderivs (q > 0, max|p| <= 1): t-, t+ positive, tM negative, so of the two
    merging roots the outer one (t- or t+) gets d/dc = -M min(1, 1/|t|^3), tM gets +M min(...)."""
    bad = []
    p, _ = gt.quadratic_category("double", 200)
    z = solve_quadratic(p)
    jac = quadratic_root_jacobian(p)
    n_checked = 0
    for i in range(len(p)):
        if not (z[i][0] == z[i][1] and z[i][0].imag == 0):
            continue
        n_checked += 1
        t = z[i][0].real
        mag = M if abs(t) <= 1 else M / t**2
        if not (np.isclose(jac[i, 1, 0, 2], -mag, rtol=1e-12) and np.isclose(jac[i, 0, 0, 2], mag, rtol=1e-12)):
            bad.append(f"quadratic p={p[i].tolist()!r}: dt+/dc={jac[i, 1, 0, 2]!r}, dt-/dc={jac[i, 0, 0, 2]!r}, expected -/+{mag!r}")
    print(f"\nquadratic double roots returned exactly: {n_checked}/200")
    assert n_checked > 100

    p, _ = gt.cubic_category("double", 200)
    # q > 0 and max |p| <= 1 (so the normalisation is the identity) by an exact power of two
    p = p * np.sign(p[:, :1]) / 2.0 ** np.ceil(np.log2(np.max(np.abs(p), axis=1, keepdims=True)))
    assert np.max(np.abs(p)) <= 1.0
    z = solve_cubic(p)
    jac = cubic_root_jacobian(p)
    n_checked = 0
    for i in range(len(p)):
        r = z[i]
        if not np.all(r.imag == 0):
            continue
        if r[0] == r[1] != r[2]:
            outer, mid = 0, 1
        elif r[1] == r[2] != r[0]:
            outer, mid = 2, 1
        else:
            continue
        n_checked += 1
        t = r[mid].real
        mag = M if abs(t) <= 1 else M / abs(t) ** 3
        if not (np.isclose(jac[i, outer, 0, 3], -mag, rtol=1e-12) and np.isclose(jac[i, mid, 0, 3], mag, rtol=1e-12)):
            bad.append(
                f"cubic p={p[i].tolist()!r} roots {r.tolist()!r}: d/dc outer={jac[i, outer, 0, 3]!r} "
                f"middle={jac[i, mid, 0, 3]!r}, expected -/+{mag!r}"
            )
    print(f"cubic double roots returned exactly: {n_checked}/200")
    assert n_checked > 100
    assert not bad, f"{len(bad)} sign violations:\n" + "\n".join(bad[:6])


# The first iterations of the paper's tables (subsection "Examples" of the quadratic proposed
# approach): [a, b, c], (t+, t-), dL/d(a, b, c) for L = (t+ - 0.5)^2 / 2, printed to 3 digits.
PAPER_ROWS = [
    ("bad_a/0", [0.0, -5.1, 5.0], (1e150, 9.80e-1), (-1.00e153, -1.00e3, -1.00e-147)),
    ("bad_a/1", [0.1, -5.0, 5.0], (4.90e1, 1.02), (-2.43e4, -4.95e2, -1.01e1)),
    ("bad_ab/0", [0.0, 0.0, 5.0], (-1e150, 1e150), (1.00e153, -1.00e3, 1.00e-147)),
    ("bad_ab/1", [-0.1, 0.1, 5.0], (-6.59, 7.59), (2.17e2, -3.29e1, 5.00)),
    ("bad_abc/0", [0.0, 0.0, 0.0], (0.0, 0.0), (0.0, 0.0, 5.00e2)),
    ("bad_abc/1", [0.0, 0.0, -0.1], (1e150, -1e150), (-1.00e153, -1.00e3, -1.00e-147)),
]


@pytest.mark.parametrize("name,p,roots,grad", PAPER_ROWS, ids=[r[0] for r in PAPER_ROWS])
def test_paper_tables_first_rows(name, p, roots, grad):
    p = np.array(p)
    z = solve_quadratic(p)
    t_plus, t_minus = z[1].real, z[0].real
    np.testing.assert_allclose([t_plus, t_minus], roots, rtol=6e-3, atol=0)
    dl = (t_plus - 0.5) * quadratic_root_jacobian(p)[1, 0]
    np.testing.assert_allclose(dl, grad, rtol=6e-3, atol=0)
