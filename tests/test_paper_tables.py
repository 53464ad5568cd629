"""The paper's worked optimisation examples, reproduced with the scenes' own Adam loop.

* Quadratic: tables ``bad_a``, ``bad_ab``, ``bad_abc`` (subsection "Examples" of "Proposed Approach
  for Quadratic Equations"), iterations 0-2, every printed column, to the printed 3 significant
  digits. Adam (torch defaults, lr 0.1) through :func:`scenes.paper_quadratic.run_proposed`, i.e.
  :func:`scenes.paper_common.run_adam` + :func:`collision.roots.quadratic_roots` (one
  implementation, shared with the scene).
* Cubic: the walk-throughs of the subsection "Examples" of "Proposed Approach for the Cubic
  Equation": the roots and dL/dp at iteration 0 of each degenerate start, and the branch events
  narrated for ``[0, -1, 0, 1]``.

Coefficient scaling (eq. ``dpboundeddp``). The cubic solver evaluates the derivative on the
coefficients divided by the largest magnitude (when it exceeds 1) and chains it back; its clamp
is ``M * p_max`` there, so ``M`` bounds the derivative w.r.t. the caller's coefficients and the
text's ``dL/dq = -1e153`` for ``[0, 0, -7.1, 6]`` and ``[0, 0, 0, +-6]`` holds literally.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from scenes import paper_cubic, paper_quadratic  # noqa: E402
from scenes.paper_common import T_MAX, TARGET, start  # noqa: E402

# Columns: Itr, a, b, c, (t^R)+, (t^R)-, c~ = -b^2/4 + ac, dL/da, dL/db, dL/dc  (copied from the .tex)
BAD_A = [
    [0, 0.00e00, -5.10e00, 5.00e00, 1.00e150, 9.80e-01, -6.50e00, -1.00e153, -1.00e03, -1.00e-147],
    [1, 1.00e-01, -5.00e00, 5.00e00, 4.90e01, 1.02e00, -5.75e00, -2.43e04, -4.95e02, -1.01e01],
    [2, 1.67e-01, -4.91e00, 5.07e00, 2.83e01, 1.07e00, -5.17e00, -4.90e03, -1.73e02, -6.11e00],
]
BAD_AB = [
    [0, 0.00e00, 0.00e00, 5.00e00, -1.00e150, 1.00e150, 0.00e00, 1.00e153, -1.00e03, 1.00e-147],
    [1, -1.00e-01, 1.00e-01, 5.00e00, -6.59e00, 7.59e00, -5.02e-01, 2.17e02, -3.29e01, 5.00e00],
    [2, -1.67e-01, 1.69e-01, 4.93e00, -4.95e00, 5.96e00, -8.30e-01, 7.32e01, -1.48e01, 2.99e00],
]
BAD_ABC = [
    [0, 0.00e00, 0.00e00, 0.00e00, 0.00e00, 0.00e00, 0.00e00, 0.00e00, 0.00e00, 5.00e02],
    [1, 0.00e00, 0.00e00, -1.00e-01, 1.00e150, -1.00e150, 0.00e00, -1.00e153, -1.00e03, -1.00e-147],
    [2, 7.44e-02, 7.44e-02, -1.67e-01, 1.08e00, -2.08e00, -1.38e-02, -2.87e00, -2.66e00, -2.46e00],
]
TABLES = {"bad_a": ([0.0, -5.1, 5.0], BAD_A), "bad_ab": ([0.0, 0.0, 5.0], BAD_AB), "bad_abc": ([0.0, 0.0, 0.0], BAD_ABC)}
COLUMNS = ["a", "b", "c", "Re t+", "Re t-", "c~", "dL/da", "dL/db", "dL/dc"]

SIG3_RTOL = 5e-3
"""Printed values have 3 significant digits: half a unit of the last digit is <= 5e-3 relative."""


def round_sig3(x: float) -> float:
    """``x`` rounded to 3 significant digits (as the paper's ``%.2e`` columns)."""
    return float(f"{x:.2e}")


def same_to_3_digits(computed: float, printed: float) -> bool:
    """Equal after rounding to 3 significant digits, or within ``SIG3_RTOL`` (rounding edges)."""
    if not math.isfinite(computed):
        return False
    if round_sig3(computed) == printed:  # also 0.0 == -0.0
        return True
    return abs(computed - printed) <= SIG3_RTOL * abs(printed)


@pytest.fixture(scope="module")
def quadratic_run():
    """Iterations 0-2 of the three table starts, batched (Adam is element-wise)."""
    starts = tuple(start(p0, "abc") for p0, _ in TABLES.values())
    return paper_quadratic.run_proposed(starts, iters=2)


@pytest.mark.parametrize("table", list(TABLES))
def test_quadratic_table(quadratic_run, table):
    """Every printed entry of the table, rows 0-2."""
    row = list(TABLES).index(table)
    _, expected = TABLES[table]
    mismatches = []
    for it, *printed in expected:
        a, b, c = quadratic_run.params[it, row]
        roots = quadratic_run.extras["roots"][it, row]  # slots (t-, t+)
        computed = [a, b, c, roots[1].real, roots[0].real, -b * b / 4 + a * c, *quadratic_run.grads[it, row]]
        for name, got, want in zip(COLUMNS, computed, printed):
            if not same_to_3_digits(float(got), want):
                mismatches.append(f"iteration {it} {name}: computed {got:.6e}, table {want:.2e}")
    assert not mismatches, f"table {table}:\n" + "\n".join(mismatches)


def test_quadratic_tables_loss_is_eq_lossagainwitht(quadratic_run):
    """The loss is 1/2 |t+ - 0.5|^2 on (Re, Im) and the first step moves every coefficient by lr."""
    t = quadratic_run.extras["roots"][:, :, 1]
    expected = 0.5 * ((t.real - TARGET) ** 2 + t.imag**2)
    np.testing.assert_allclose(quadratic_run.loss, expected, rtol=1e-12)
    step = quadratic_run.params[1] - quadratic_run.params[0]
    moved = np.abs(quadratic_run.grads[0]) > 1e-6  # Adam's eps (1e-8) swamps tinier gradients
    np.testing.assert_allclose(np.abs(step[moved]), 0.1, rtol=1e-6)


def test_held_fixed_coefficient_never_moves():
    """The Figure example-3 start holds a = 1 exactly while b, c move."""
    s = next(s for s in paper_quadratic.STARTS if s.trainable == (False, True, True))
    run = paper_quadratic.run_proposed((s,), iters=5)
    assert np.all(run.params[:, 0, 0] == 1.0)
    assert np.all(run.grads[:, 0, 0] == 0.0)
    assert np.all(np.abs(run.params[-1, 0, 1:] - run.params[0, 0, 1:]) > 0.1)


# ------------------------------------------------------------------------------------------ cubic


@pytest.fixture(scope="module")
def cubic_first_iterate():
    """Roots and gradient at iteration 0 of every cubic start (tracked slot = t+)."""
    starts = tuple(start(p, "qabc") for p in CUBIC_CASES)
    run = paper_cubic.run_proposed(starts, iters=0)
    return {tuple(p): (run.extras["roots"][0, i], run.grads[0, i], run.loss[0, i]) for i, p in enumerate(CUBIC_CASES)}


CUBIC_CASES = [
    [0.0, 1.0, 0.0, -1.0],
    [0.0, -1.0, 0.0, 1.0],
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 7.1, 6.0],
    [0.0, 0.0, -7.1, 6.0],
    [0.0, 0.0, 0.0, 6.0],
    [0.0, 0.0, 0.0, -6.0],
    [0.0, 0.0, 0.0, 0.0],
]


def test_cubic_t2_minus_1(cubic_first_iterate):
    """``[0, 1, 0, -1]``: t+ = 1, escaping root -1e150 (a > 0); every dL/dp = -1/4."""
    roots, grad, _ = cubic_first_iterate[(0.0, 1.0, 0.0, -1.0)]
    np.testing.assert_allclose(roots, [-T_MAX, -1.0, 1.0], rtol=1e-15)
    np.testing.assert_allclose(grad, [-0.25] * 4, rtol=1e-14)


def test_cubic_minus_t2_plus_1(cubic_first_iterate):
    """``[0, -1, 0, 1]``: t+ = 1e150 (a < 0); dL/dq = -1e153, dL/da 1e150 times smaller."""
    roots, grad, _ = cubic_first_iterate[(0.0, -1.0, 0.0, 1.0)]
    np.testing.assert_allclose(roots, [-1.0, 1.0, T_MAX], rtol=1e-15)
    assert grad[0] == pytest.approx(-1e153, rel=1e-12)
    assert grad[1] == pytest.approx(-1e3, rel=1e-12)


def test_cubic_triple_root(cubic_first_iterate):
    """``[1, 0, 0, 0]``: triple root 0; dL/dc = (0 - 1/2)(-1000) = 500, the rest exactly 0."""
    roots, grad, _ = cubic_first_iterate[(1.0, 0.0, 0.0, 0.0)]
    assert np.all(roots == 0)
    assert grad[3] == pytest.approx(500.0, rel=1e-14)
    assert np.all(grad[:3] == 0)


def test_cubic_all_zero(cubic_first_iterate):
    """``[0, 0, 0, 0]``: triple root 0; dL/dc = 500 is the only nonzero derivative."""
    roots, grad, _ = cubic_first_iterate[(0.0, 0.0, 0.0, 0.0)]
    assert np.all(roots == 0)
    assert grad[3] == pytest.approx(500.0, rel=1e-14)
    assert np.all(grad[:3] == 0)


def test_cubic_linear_bounded_t_plus(cubic_first_iterate):
    """``[0, 0, 7.1, 6]``: both unbounded roots at -1e150, t+ = -6/7.1 with finite derivatives."""
    roots, grad, _ = cubic_first_iterate[(0.0, 0.0, 7.1, 6.0)]
    np.testing.assert_allclose(roots, [-T_MAX, -T_MAX, -6.0 / 7.1], rtol=1e-15)
    assert np.all(np.isfinite(grad)) and np.max(np.abs(grad)) < 10


SCALED_Q_CASES = {
    # start: (roots, p_max) -- roots as narrated in the text
    (0.0, 0.0, -7.1, 6.0): ([-T_MAX, 6.0 / 7.1, T_MAX], 7.1),
    (0.0, 0.0, 0.0, 6.0): ([-T_MAX, T_MAX, T_MAX], 6.0),
    (0.0, 0.0, 0.0, -6.0): ([-T_MAX, -T_MAX, T_MAX], 6.0),
}


@pytest.mark.parametrize("p0", list(SCALED_Q_CASES), ids=lambda p: "_".join(f"{v:g}" for v in p))
def test_cubic_escaping_t_plus_q_gradient(cubic_first_iterate, p0):
    """The text: t+ = 1e150, dt+/dq = -M "because of clamping", so dL/dq = -1e153.

    The solver clamps at ``M * p_max`` in the normalised space so that, after the chain of eq.
    ``dpboundeddp`` (a factor ``1/p_max``), ``M`` bounds the derivative w.r.t. the caller's
    coefficients; this reproduces the text's value for ``p_max > 1``.
    """
    roots, grad, _ = cubic_first_iterate[p0]
    expected_roots, _p_max = SCALED_Q_CASES[p0]
    np.testing.assert_allclose(roots, expected_roots, rtol=1e-15)
    assert grad[0] == pytest.approx(-1e153, rel=1e-12)


def test_cubic_branch_events_minus_t2_plus_1():
    """``[0, -1, 0, 1]`` as narrated: t+ merges with tM at iteration 3; in iterations 26-31 the single
    real root is t+ (t- before and after) while the tracked complex root is unaffected; the tracked
    root is t+ again (real, the larger of the unmerged pair) at iteration 41."""
    s = start([0.0, -1.0, 0.0, 1.0], "qabc")
    run = paper_cubic.run_proposed((s,), iters=41)
    roots, slots = run.extras["roots"][:, 0], run.extras["slot"][:, 0]
    tracked = roots[np.arange(len(slots)), slots]
    real = tracked.imag == 0
    assert real[:3].all() and not real[3:41].any() and real[41], "merge at 3, unmerge at 41"
    single_real_slot = [int(np.flatnonzero(r.imag == 0)[0]) for r in roots[3:41]]
    in_t_plus = [k for k, j in zip(range(3, 41), single_real_slot) if j == paper_cubic.T_PLUS]
    assert in_t_plus == list(range(26, 32)), "the single real root is t+ exactly in iterations 26-31"
    assert slots[41] == paper_cubic.T_PLUS
    # merge rule: the tracked root was the larger merging real root -> the member with Im > 0
    assert tracked[3].imag > 0


def test_root_tracker_through_infinity():
    """A root leaving at +t_max and returning at -t_max stays tracked (chordal metric)."""
    tracker = paper_cubic.RootTracker(1)
    tracker.update(np.array([[-1.0, 1.0, T_MAX]], dtype=complex))
    slot = tracker.update(np.array([[-T_MAX, -1.0, 1.0]], dtype=complex))
    assert slot[0] == 0
