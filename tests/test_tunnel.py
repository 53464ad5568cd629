"""Scene ``tunnel`` (lifted events): from a miss whose wanted root is complex, the proposed
method's gradient creates the hit; the baseline (real roots only, unmollified) has no gradient
there and does not move. Ground truth: the rollout's own contact record (a hit is a velocity
jump of the particle) and the unchanged iterate."""

import json
import subprocess
import sys

import numpy as np
import pytest

from scenes.tunnel import make_problem, optimise


@pytest.fixture(scope="module")
def problem():
    return make_problem(0)


def test_start_is_a_miss_with_a_complex_wanted_root(problem):
    from scenes.tunnel import _event, _rollout

    _, res = _rollout(problem, problem.v0, events=[_event(problem.face, problem.window)])
    assert res.stats["contact_substeps"] == 0
    assert res.event_roots[0, problem.tracked_slot, 1].item() != 0.0
    # and the target is reachable: v* hits once at t_target
    _, hit = _rollout(problem, problem.v_star)
    assert hit.stats["contact_substeps"] == 1
    assert np.allclose(hit.particle_qd[-1, 0].numpy(), problem.v_target)


def test_proposed_leaves_the_miss_baseline_cannot(problem):
    proposed = optimise(problem, 200, "proposed")
    assert any(proposed["history"]["hit"])
    baseline = optimise(problem, 20, "baseline")
    assert not any(baseline["history"]["hit"])
    assert np.all(np.asarray(baseline["history"]["velocity"]) == problem.v0)


def test_cli_reports_both_methods(tmp_path):
    out = tmp_path / "tunnel.rrd"
    proc = subprocess.run([sys.executable, "-m", "scenes", "tunnel", "--out", str(out), "--iters", "3"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(summary["methods"]) == {"proposed", "baseline"}
    for figures in summary["methods"].values():
        assert {"reached_target", "final_loss", "iterations_to_target"} <= set(figures)
    assert out.stat().st_size > 0
