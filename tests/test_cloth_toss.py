"""Scene ``cloth_toss``: a cloth's initial linear and angular velocity, optimised so it lands
draped over a sphere. Ground truth: closed-form ballistics (the aimed throw), central finite
differences of the same rollout's forward, and a fresh rollout of the reported iterate."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from scenes import cloth_toss as C


@pytest.fixture(scope="module")
def problem():
    return C.build(0)


def _loss(problem, u):
    with torch.no_grad():
        _, res = C.simulate(problem, np.asarray(u, dtype=np.float64))
        return float(C.drape_loss(problem, res)), res


def test_start_lands_on_the_floor_beside_the_sphere(problem):
    loss, res = _loss(problem, problem.u0)
    middle = res.particle_q[-1, problem.middle].numpy()
    assert middle[2] < 0.02 and np.hypot(middle[0], middle[1]) > C.RADIUS
    assert loss > 0.1
    assert np.linalg.norm(problem.u0[3:]) >= C.START_SPIN[0] - 1e-12


def test_aimed_throw_drapes_the_cloth_over_the_sphere(problem):
    """The middle particle thrown ballistically at the sphere's top (no spin) lands there and
    the cloth stays on: the drape loss is under a tenth of the start's (the scene's goal is
    reachable)."""
    g = 9.81
    v = (problem.top - problem.rest[problem.middle]) / C.FLIGHT_TIME
    v[2] += 0.5 * g * C.FLIGHT_TIME
    loss, res = _loss(problem, np.concatenate([v, np.zeros(3)]))
    middle = res.particle_q[-1, problem.middle].numpy()
    assert np.linalg.norm(middle - problem.top) < 0.05 and middle[2] > 2 * C.RADIUS - 0.03
    assert res.stats["contact_substeps"] > 0 and res.stats["failsafe_substeps"] == 0
    assert loss < 0.1 * _loss(problem, problem.u0)[0]


def test_gradient_matches_central_differences_through_the_sphere_contact(problem):
    u, res = C.simulate(problem, problem.u0, grad=True)
    C.drape_loss(problem, res).backward()
    assert res.stats["contact_substeps"] > 0 and res.stats["failsafe_substeps"] == 0
    step = 1e-6
    fd = np.zeros(6)
    for k in range(6):
        plus, minus = problem.u0.copy(), problem.u0.copy()
        plus[k] += step
        minus[k] -= step
        fd[k] = (_loss(problem, plus)[0] - _loss(problem, minus)[0]) / (2 * step)
    assert np.linalg.norm(u.grad.numpy() - fd) < 1e-5 * np.linalg.norm(fd)


def test_proposed_more_than_halves_the_loss_in_four_rollouts_checked_on_a_fresh_rollout(problem):
    """The first rollouts of the proposed method, where its path is robust to rounding.

    Later on, the cloth's many contacts amplify rounding the way a contact-rich forward run does:
    moving the start velocity by 1e-12 relative changes whether seed 0 reaches the 90 % cut
    (``benchmarks/results/cloth_toss_rounding.md``: 2 of 4 such starts do within 11 rollouts, the
    other two turn back above 0.1 m^2 after their 5th), while all four are at 0.111-0.112 m^2
    after their 4th rollout (from 0.307). The 90 % cut is measured over seeds 0-4 and 40 rollouts
    in ``benchmarks/inverse.py``; here the first 4 rollouts must cut the loss by more than half."""
    result = C.optimise(problem, 3, "proposed")
    losses = result["history"]["loss"]
    assert all(b < a for a, b in zip(losses, losses[1:])), losses
    assert result["final_loss"] < 0.5 * result["initial_loss"], losses
    loss, _ = _loss(problem, result["best_u"])
    assert loss == result["final_loss"]


def test_unknown_method_is_rejected(problem):
    with pytest.raises(ValueError, match="method"):
        C.optimise(problem, 1, "adam")


def test_cli_writes_a_recording_and_reports_each_method(tmp_path):
    out = tmp_path / "toss.rrd"
    proc = subprocess.run([sys.executable, "-m", "scenes", "cloth_toss", "--out", str(out), "--iters", "2",
                           "--methods", "proposed,cma", "--cloth-res", "4", "--substeps", "6", "--max-derivative", "100"],
                          check=False, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(summary["methods"]) == {"proposed", "cma"}
    assert (summary["substeps"], summary["max_derivative"], summary["ccd_options"]) == (6, 100.0, {})
    for figures in summary["methods"].values():  # --iters 2: two steps, the start and both results rolled out
        assert figures["rollouts"] == 3 and np.isfinite(figures["final_loss"])
    assert out.stat().st_size > 0


def test_inverse_benchmark_cloth_smoke(tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "inverse"
    proc = subprocess.run([sys.executable, os.path.join(root, "benchmarks", "inverse.py"), "--scenes", "cloth_toss",
                           "--cloth-seeds", "1", "--cloth-iters", "2", "--jobs", "1", "--out", str(out)],
                          check=False, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "inverse_cloth_toss.json").read_text())
    assert set(data["summary"]) == set(C.METHODS)
    assert data["profile"]["backward_s"] > 0 and data["profile"]["peak_rss_mib"] > 0
    assert (tmp_path / "inverse_cloth_toss.png").stat().st_size > 0
