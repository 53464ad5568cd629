"""Eq. ``orthogonal_clamping_real_side``: a real root's derivative split into the part that
merges or separates a pair (clamped) and the rest (exact). Ground truth from mpmath at 50
digits and the quadratic formula; the optimisation is the paper's example (Table ``exp4``)."""

import mpmath as mp
import numpy as np
import pytest
import torch

from collision.ccd import coplanarity_roots
from collision.roots import (
    _cubic_jacobian_raw,
    _quadratic_jacobian_raw,
    orthogonal_clamped_jacobian,
    quadratic_roots,
)

mp.mp.dps = 50
T_MAX = 1.0e150


def _exact_real_roots_and_gradients(p):
    """Real roots of p (highest degree first) and the exact implicit derivative -v(t)/p'(t) of
    each w.r.t. the coefficients, at 50 digits."""
    coeffs = [mp.mpf(float(x)) for x in p]
    n = len(coeffs)
    roots = [mp.re(r) for r in mp.polyroots(coeffs, maxsteps=400, extraprec=400) if abs(mp.im(r)) < mp.mpf(10) ** -40]
    out = []
    for t in sorted(roots):
        dp = sum((n - 1 - k) * coeffs[k] * t ** (n - 2 - k) for k in range(n - 1))
        out.append((t, [-(t ** (n - 1 - k)) / dp for k in range(n)]))
    return out


def _critical_point_near(p, t):
    coeffs = [mp.mpf(float(x)) for x in p]
    n = len(coeffs)
    derivative = [(n - 1 - k) * coeffs[k] for k in range(n - 1)]
    crit = [mp.re(c) for c in mp.polyroots(derivative, maxsteps=400, extraprec=400)] if n > 2 else []
    return min(crit, key=lambda c: abs(c - t))


def _orthogonal(p, M):
    p = np.asarray(p, dtype=np.float64)[None]
    raw = _quadratic_jacobian_raw if p.shape[-1] == 3 else _cubic_jacobian_raw
    roots, jac = raw(p, T_MAX, M)
    return roots[0], jac[0], orthogonal_clamped_jacobian(p, roots, jac, M, T_MAX)[0]


@pytest.mark.parametrize("p", [
    [2.0, -3.0, -5.0, 1.0],
    [1.0, -6.0, 11.0, -6.0],
    [-0.5, 0.2, 3.0, 0.7],
    [1.0, -0.3, -2.0],
    [3.0, 1.0, -4.0],
])
def test_exact_where_the_clamp_is_inactive(p):
    """Well separated real roots: the orthogonal derivative is the exact implicit one (and the
    mollified one agrees: neither clamp binds)."""
    roots, jac, orth = _orthogonal(p, 1000.0)
    exact = _exact_real_roots_and_gradients(p)
    real_slots = [s for s in range(roots.shape[0]) if roots[s, 1] == 0.0]
    assert len(real_slots) == len(exact)
    for s, (t, g) in zip(sorted(real_slots, key=lambda s: roots[s, 0]), exact):
        assert roots[s, 0] == pytest.approx(float(t), rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(orth[s, 0], np.array([float(x) for x in g]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(jac[s, 0], orth[s, 0], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("p", [
    [1.0, -3.0, 9.0 / 4.0 - 1e-12],                 # the paper's start: c~ = -1e-12
    [1.0, -3.0, 9.0 / 4.0 - 1e-6],
    [1.0, -1.0 - 2e-7, 1e-7 - 1.0, 1.0],            # (t - 1)^2 (t + 1) split by ~3e-4
    [2.0, 0.0, -6.0, 4.0 - 1e-9],                   # 2 (t - 1)^2 (t + 2), split by ~3e-5
])
def test_near_merging_pair(p):
    """Near a double root the exact derivative blows up (|alpha| >> M): the orthogonal one keeps
    the exact part orthogonal to n = v(t_c) (to 1e-6) and clamps the part along n to |alpha| = M
    with the exact sign, all on the polynomial scaled to a largest coefficient of 1."""
    M = 10.0
    roots, _, orth = _orthogonal(p, M)
    scale = max(abs(x) for x in p)
    n_coef = len(p)
    clamped = 0
    for t, g in _exact_real_roots_and_gradients(p):
        slot = int(np.argmin(np.abs(roots[:, 0] - float(t)) + np.abs(roots[:, 1])))
        tc = _critical_point_near(p, t)
        nvec = mp.matrix([tc ** (n_coef - 1 - k) for k in range(n_coef)])
        g_scaled = mp.matrix(g) * scale  # d t / d(p / scale)
        alpha = (g_scaled.T * nvec)[0] / (nvec.T * nvec)[0]
        perp = g_scaled - alpha * nvec
        ours = orth[slot, 0] * scale
        ours_alpha = float(np.dot(ours, [float(x) for x in nvec]) / float((nvec.T * nvec)[0]))
        ours_perp = ours - ours_alpha * np.array([float(x) for x in nvec])
        np.testing.assert_allclose(ours_perp, [float(x) for x in perp], rtol=1e-6, atol=1e-8)
        if abs(alpha) > M:
            clamped += 1
            assert ours_alpha == pytest.approx(M * float(mp.sign(alpha)), rel=1e-9)
            assert abs(float(alpha)) > 10 * M  # the exact one is far beyond the clamp
        else:
            assert ours_alpha == pytest.approx(float(alpha), rel=1e-6)
        assert np.all(np.isfinite(orth[slot]))
    assert clamped >= 2  # both members of the merging pair


def test_paper_example_converges_with_the_orthogonal_clamp():
    """The paper's example (Table ``exp4``): t^2 + b t + c from (b, c) = (-3, 9/4 - 1e-12) (roots
    1.5 +- 1e-6), loss 0.5 (t+ - 1/2)^2. Adam (rate 0.1) with the orthogonal clamp (M = 1)
    reaches the target within 200 iterations; with the plain implicit derivative (M = 1e300) it
    does not. The final root is checked with the quadratic formula, not the solver."""

    def run(derivative, M, iters=200):
        x = torch.tensor([-3.0, 9.0 / 4.0 - 1e-12], dtype=torch.float64, requires_grad=True)
        opt = torch.optim.Adam([x], lr=0.1)
        target = torch.tensor([0.5, 0.0], dtype=torch.float64)
        for it in range(iters):
            opt.zero_grad()
            r = quadratic_roots(torch.cat([torch.ones(1, dtype=torch.float64), x]), max_derivative=M, derivative=derivative)
            b, c = x.detach().numpy()
            disc = b * b / 4.0 - c
            if disc >= 0.0 and abs(-b / 2.0 + np.sqrt(disc) - 0.5) < 1e-6:
                return it
            loss = 0.5 * ((r[1] - target) ** 2).sum()
            loss.backward()
            opt.step()
        return None

    assert run("orthogonal", 1.0) is not None
    assert run("mollified", 1e300) is None


def test_coplanarity_roots_orthogonal_matches_finite_differences():
    """A transversal vertex-face pair: the orthogonal event roots are the mollified ones, and
    their position gradient matches central differences (the clamp does not bind there)."""
    x0 = torch.tensor([[[0.2, 0.1, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [0.0, 1.0, -0.1]]], dtype=torch.float64)
    x1 = x0.clone()
    x1[0, 0] = torch.tensor([0.3, 0.2, -1.0], dtype=torch.float64)
    x1[0, 2] += torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64)
    x1[0, 3] += torch.tensor([0.05, -0.1, 0.15], dtype=torch.float64)  # a true cubic (q != 0)
    xs = x0.clone().requires_grad_(True)
    mollified = coplanarity_roots(x0, x1)
    orth = coplanarity_roots(xs, x1, derivative="orthogonal")
    np.testing.assert_allclose(orth.detach().numpy(), mollified.numpy(), rtol=1e-13, atol=1e-15)
    real = [s for s in range(3) if orth[0, s, 1].item() == 0.0 and 0.0 <= orth[0, s, 0].item() <= 1.0]
    assert real
    orth[0, real[0], 0].backward()
    t_hit = orth[0, real[0], 0].item()

    def hit_root(x):  # the root nearest the hit (slots reorder when the far roots move)
        r = coplanarity_roots(x, x1)[0].numpy()
        return r[np.argmin(np.abs(r[:, 0] - t_hit) + np.abs(r[:, 1])), 0]

    h = 1e-6
    fd = np.zeros((4, 3))
    for i in range(4):
        for k in range(3):
            xp, xm = x0.clone(), x0.clone()
            xp[0, i, k] += h
            xm[0, i, k] -= h
            fd[i, k] = (hit_root(xp) - hit_root(xm)) / (2 * h)
    np.testing.assert_allclose(xs.grad[0].numpy(), fd, rtol=1e-6, atol=1e-9)


def test_bad_derivative_names_the_argument():
    x = torch.zeros((1, 4, 3), dtype=torch.float64)
    with pytest.raises(ValueError, match="derivative"):
        coplanarity_roots(x, x, derivative="clamped")
    with pytest.raises(ValueError, match="derivative"):
        quadratic_roots(torch.tensor([1.0, 0.0, -1.0], dtype=torch.float64), derivative="nope")
    with pytest.raises(ValueError, match="3 or 4"):
        orthogonal_clamped_jacobian(np.ones((1, 5)), np.zeros((1, 4, 2)), np.zeros((1, 4, 2, 5)))


def test_a_nearly_escaping_root_keeps_the_mollified_row():
    """q = 1e-8: a real root near -a/q = -1e8 is no merging pair; its exact derivative is about
    1e16, the mollified one bounded. The orthogonal Jacobian keeps the mollified row there."""
    roots, jac, orth = _orthogonal([1e-8, 1.0, -1.0, 0.1], 1000.0)
    far = int(np.argmax(np.abs(roots[:, 0])))
    assert abs(roots[far, 0]) > 1e7 and roots[far, 1] == 0.0
    np.testing.assert_array_equal(orth[far], jac[far])
    assert np.all(np.isfinite(orth)) and np.abs(orth[far]).max() <= 1e4
