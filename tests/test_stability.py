"""Stability at the extremes: settings that cannot be accurate fail fast with a clear message.

* :func:`sim.stability.explicit_substep_limit` against the closed form of one spring between
  two free masses (``2 / omega`` with ``omega^2 = k (1/m1 + 1/m2)``), and the explicit
  integrator bounded just below that limit and growing just above it;
* the scenes refuse a substep far past the limit before the run (``--dt 1e6``) and stop a
  substep whose contacts are past the named limits (``--dt 1`` with the implicit integrator),
  each within seconds, with one line naming ``--dt`` and ``--substeps`` and no traceback;
* ``rollout`` of a cloth with springs far too stiff for its substep raises within the rollout,
  or returns with ``stats["diverged"]`` and no gradient when asked to;
* the per-substep divergence guard catches non-finite values and positions far outside the
  scene's reach.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp

from scenes import cloth_drop, sim_common
from sim.builder import ModelBuilder
from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.rollout import rollout
from sim.stability import DivergenceGuard, SimulationDiverged, explicit_substep_limit

REPO = Path(__file__).resolve().parents[1]


def _small_cloth(gravity=(0.0, 0.0, 0.0)):
    """A 3x3-cell cloth (shear and bending springs too), undamped, no gravity."""
    b = ModelBuilder(gravity=gravity)
    b.add_cloth_grid((0.0, 0.0, 0.0), None, 3, 3, 0.1, 0.1, density=0.2, stretch_stiffness=50.0,
                     shear_stiffness=20.0, bend_stiffness=5.0, damping=0.0)
    return b.finalize("cpu")


def _true_limit(model) -> float:
    """``2 / omega_max`` of the springs linearised at rest (numpy's eigenvalues of
    ``M^-1/2 K M^-1/2``, ``K`` the 3D stiffness ``sum k u u^T`` of every spring)."""
    x = model.particle_q.numpy()
    idx = model.spring_indices.numpy().reshape(-1, 2)
    k = model.spring_stiffness.numpy()
    n = model.particle_count
    K = np.zeros((3 * n, 3 * n))
    for (i, j), ks in zip(idx, k):
        u = (x[j] - x[i]) / np.linalg.norm(x[j] - x[i])
        block = ks * np.outer(u, u)
        for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            K[3 * a:3 * a + 3, 3 * b:3 * b + 3] += sign * block
    w = np.repeat(1.0 / np.sqrt(model.particle_mass.numpy()), 3)
    return 2.0 / math.sqrt(np.linalg.eigvalsh(w[:, None] * K * w[None, :]).max())


def test_explicit_limit_is_a_safe_estimate_of_the_true_limit():
    """Gershgorin's bound is never above the true limit, and within a factor 2 of it."""
    model = _small_cloth()
    estimate, true = explicit_substep_limit(model), _true_limit(model)
    assert 0.5 * true <= estimate <= true * (1.0 + 1e-12)


@pytest.mark.parametrize("factor, bounded", [(0.95, True), (1.05, False)])
def test_explicit_springs_are_stable_below_the_true_limit_and_grow_above(factor, bounded):
    """Semi-implicit Euler is stable iff ``h omega_max < 2``: from a random 1e-4 m nudge of
    every particle, 600 substeps at 0.95x the true limit keep every particle within 2 mm of its
    rest position; at 1.05x the highest mode grows past 1 m (the guard is not set here)."""
    model = _small_cloth()
    h = factor * _true_limit(model)
    integ = SemiImplicitIntegrator(model)
    s, nxt = model.state(), model.state()
    x0 = s.particle_q.numpy().copy()
    nudge = np.random.default_rng(1).normal(0.0, 1e-4, x0.shape)
    s.particle_q = wp.array(x0 + nudge, dtype=wp.vec3d, device="cpu")
    worst = 0.0
    for _ in range(600):
        integ.step(s, nxt, h, 1)
        s, nxt = nxt, s
        dev = np.abs(s.particle_q.numpy() - x0)
        worst = max(worst, float(np.max(dev)) if np.all(np.isfinite(dev)) else math.inf)
        if worst > 1.0:
            break
    if bounded:
        assert worst < 2e-3
    else:
        assert worst > 1.0


def test_scene_refuses_a_substep_far_past_the_limit():
    """``--dt 1e6`` (substeps of 1.25e5 s): refused before the first step."""
    args = sim_common.default_args(steps=2, dt=1e6)
    with pytest.raises(SimulationDiverged, match=r"refused.*--substeps.*--dt"):
        sim_common.simulate(cloth_drop.build, args, None, name="cloth_drop", progress=False)


@pytest.mark.parametrize("limit", ["hits", "solve work"])
def test_scene_stops_a_substep_past_the_contact_limits(monkeypatch, limit):
    """A substep past a named contact limit stops the run at that step with the limit's name and
    the flags to change. The limits are lowered here so that ``cloth_drop``'s first contacts
    (step ~15) pass them: at their real values (8 hits per collision vertex, solve work 1e11)
    ``--dt 1 --integrator implicit`` stops within about 30 s instead of grinding for minutes."""
    import sim.contact.replay
    import sim.contact.detect

    if limit == "hits":
        monkeypatch.setattr(sim.contact.detect, "MAX_HITS_MIN", 10)
        monkeypatch.setattr(sim.contact.detect, "MAX_HITS_PER_VERTEX", 0)
        pattern = r"step \d+: \d+ contacts in one collision round of a substep, more than the limit of 10 .*--substeps.*--dt"
    else:
        monkeypatch.setattr(sim.contact.replay, "MAX_SOLVE_WORK", 1e3)
        pattern = r"step \d+: .*MAX_SOLVE_WORK.*--substeps.*--dt"
    args = sim_common.default_args(steps=25)
    with pytest.raises(SimulationDiverged, match=pattern):
        sim_common.simulate(cloth_drop.build, args, None, name="cloth_drop", progress=False)


def test_cli_huge_dt_exits_fast_with_one_line(tmp_path):
    """``python -m scenes cloth_drop --dt 1e6``: exit status 1 within 30 s of start-up (kernel
    cache warm: the other tests loaded it), one ``error:`` line naming the flags, no traceback,
    and no recording left at ``--out``."""
    out = tmp_path / "x.rrd"
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "scenes", "cloth_drop", "--out", str(out), "--steps", "2",
                           "--dt", "1e6"], cwd=REPO, capture_output=True, text=True, timeout=300)
    elapsed = time.perf_counter() - start
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "--dt" in errors[0] and "--substeps" in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists()
    assert elapsed < 60.0  # 30 s target with a warm cache; slack for a loaded test machine


def _stiff_cloth():
    b = ModelBuilder()
    b.add_cloth_grid((0.0, 0.0, 1.0), None, 8, 8, 0.1, 0.1, density=0.2, stretch_stiffness=2000.0,
                     shear_stiffness=10.0, bend_stiffness=1.0, damping=0.01)
    return b.finalize("cpu")


def test_rollout_of_a_diverging_cloth_raises_or_returns_flagged():
    """An 8x8 cloth with stretch 2000 N/m at one substep of 1/60 s (40x its limit), nudged off
    uniform free fall: the rollout raises within its 30 steps, naming the step; with
    ``on_divergence="return"`` every output is finite, the stats say where it diverged, and the
    backward refuses."""
    model = _stiff_cloth()
    assert 1.0 / 60.0 > 10.0 * explicit_substep_limit(model)
    v0 = torch.from_numpy(np.random.default_rng(0).normal(0.0, 0.01, (model.particle_count, 3)))
    with pytest.raises(SimulationDiverged, match=r"rollout: step \d+ of 30"):
        rollout(model, 30, 1.0 / 60.0, 1, particle_qd=v0)
    v = v0.clone().requires_grad_(True)
    res = rollout(model, 30, 1.0 / 60.0, 1, particle_qd=v, on_divergence="return")
    assert res.stats["diverged"] is True and 1 <= res.stats["diverged_step"] <= 30
    assert "diverged" in res.stats["divergence_message"]
    assert torch.isfinite(res.particle_q).all() and res.particle_q.shape[0] == 31
    with pytest.raises(RuntimeError, match="no gradient"):
        res.particle_q[-1].sum().backward()
    with pytest.raises(ValueError, match="on_divergence"):
        rollout(model, 3, 1.0 / 60.0, 1, on_divergence="ignore")


def test_rollout_that_holds_reports_no_divergence():
    """The same cloth at a stable substep (1/60 s in 60 substeps) is not flagged."""
    model = _stiff_cloth()
    res = rollout(model, 3, 1.0 / 60.0, 60)
    assert res.stats["diverged"] is False and res.stats["diverged_step"] is None


def test_guard_flags_non_finite_and_far_positions():
    """The guard's bounds: 10x the scene's reach (here 0.21 m of box and 4.9 m of fall in 1 s):
    a NaN velocity or a particle 1 km away trips it, the initial state does not."""
    model = _small_cloth(gravity=(0.0, 0.0, -9.81))
    state = model.state()
    guard = DivergenceGuard(model, state, duration=1.0)
    assert not guard.exceeded(state)
    x = state.particle_q.numpy()
    far = model.state()
    x_far = x.copy()
    x_far[1, 0] = 1e3
    far.particle_q = wp.array(x_far, dtype=wp.vec3d, device="cpu")
    assert guard.exceeded(far)
    bad = model.state()
    v = np.zeros((model.particle_count, 3))
    v[0, 2] = np.nan
    bad.particle_qd = wp.array(v, dtype=wp.vec3d, device="cpu")
    assert guard.exceeded(bad)


@pytest.mark.parametrize("row, outcome", [("dt 1 s", "clear error"), ("stiffness x1e6", "clear error"),
                                          ("mass ratio 1e6", "holds"), ("speed 1e3 m/s", "holds"),
                                          ("scale 1e3", "holds")])
def test_extremes_rows(row, outcome):
    """A sample of the extremes table (``benchmarks/extremes.py``, every row there): each holds
    (0 penetrations, energy peak <= 1.01x) or stops with a one-line clear error, in seconds."""
    from benchmarks import extremes

    start = time.perf_counter()
    result = extremes.run_row(row)
    assert result["outcome"] == outcome, result
    if outcome == "clear error":
        assert "--substeps" in result["message"] and "\n" not in result["message"]
    assert time.perf_counter() - start < 60.0
