"""Scene ``bank_shot`` (Newton's ``diffsim_ball`` problem with exact CCD impulses).

Ground truth: closed-form ballistics and mirror reflection (no code under test), central finite
differences of the same forward, and the rollout's contact record (a bounce is a velocity jump)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from scenes import bank_shot as B


@pytest.fixture(scope="module")
def model():
    return B.build()


def test_newton_start_bounces_off_floor_then_wall_as_closed_form_ballistics(model):
    """Elastic, frictionless: floor at t1 (1 - 5 t - g t^2 / 2 = 0 from z = 1 m, v_z = -5 m/s),
    wall face y = 1.75 m at t = 2.25 / 5 = 0.45 s, then back at -5 m/s: the end point in closed
    form. Up to the semi-implicit Euler's gravity error (8 substeps of 1/480 s: O(g h T))."""
    _, res = B.simulate(model, B.STARTS["newton"])
    hits = B.bounces(res)
    assert hits == {"floor": 1, "wall": 1} and B.banked(hits)
    g, T = 9.81, B.FRAMES * B.DT
    t1 = (-5.0 + np.sqrt(25.0 + 2.0 * g)) / g
    vz1 = 5.0 + g * t1  # speed at the floor, reflected upwards
    z_end = vz1 * (T - t1) - 0.5 * g * (T - t1) ** 2
    y_end = 1.75 - 5.0 * (T - 0.45)
    end = res.particle_q[-1, 0].numpy()
    # the impulse solve's 1e-8 regularisation leaves the reflected speed 1e-8 relative short
    assert abs(end[0]) < 1e-12 and abs(end[1] - y_end) < 1e-7
    assert abs(end[2] - z_end) < g * (T / (B.FRAMES * B.SUBSTEPS)) * T  # O(g h T)


def test_miss_start_passes_the_wall(model):
    _, res = B.simulate(model, B.STARTS["miss"])
    assert B.bounces(res) == {"floor": 1, "wall": 0}


@pytest.mark.parametrize("start", ["newton", "miss"])
def test_gradient_matches_central_differences_of_the_same_forward(model, start):
    """Off the measure-zero points where a contact falls exactly on a substep boundary (Newton's
    start reaches the wall at 0.45 s = 216 substeps exactly), shifted by a few mm/s."""
    v = np.asarray(B.STARTS[start]) + np.array([0.003, 0.007, -0.005])
    check = B.gradient_check(model, v)
    assert check["relative_error"] < 1e-5, check


def test_floor_bounce_is_continuous_across_a_substep_boundary():
    """A bounce at the very end of one substep and at the very start of the next give the same
    motion: the velocity reflected is the one at the impact, gravity's share after it added
    afterwards (it used to jump by 2 g h)."""
    import torch

    from sim.builder import ModelBuilder
    from sim.rollout import rollout

    h = 1.0 / 480.0
    ends = []
    for z0_shift in (-1e-9, 1e-9):
        b = ModelBuilder()
        # free fall from rest reaches z = 0 after exactly 10 substeps (semi-implicit Euler:
        # z_n = z0 - g h^2 n (n + 1) / 2)
        b.add_particle((0.0, 0.0, 9.81 * h * h * 55 + z0_shift), mass=1.0)
        b.add_ground_plane()
        b.set_contact(restitution=1.0, friction=0.0, thickness=0.0)
        res = rollout(b.finalize(), 40, h, 1, particle_qd=torch.zeros((1, 3), dtype=torch.float64))
        ends.append(res.particle_q[-1, 0, 2].item())
    assert abs(ends[0] - ends[1]) < 1e-7, ends


def test_proposed_banks_onto_the_target_from_the_miss(model):
    r = B.optimise(model, B.STARTS["miss"], 300, "proposed")
    assert r["reached_target"], (r["final_distance"], r["wall_bounces"], r["floor_bounces"])
    h = r["history"]
    assert h["wall"][0] == 0 and B.banked({"floor": h["floor"][-1], "wall": h["wall"][-1]})
    # check the claim on a fresh rollout of the final iterate
    _, res = B.simulate(model, h["velocity"][-1])
    assert B.distance(res) < B.TARGET_TOLERANCE and B.banked(B.bounces(res))


def test_baseline_gradient_from_the_miss_turns_away_from_the_wall(model):
    """The distance's gradient alone (what the baseline follows) shortens the throw (v_y falls:
    a direct throw, no wall); the lifted event's pulls v_x towards the wall (x = 1.35 m at the
    wall's plane, beyond its side at x = 1 m) and its loss is positive."""

    x, res = B.simulate(model, B.STARTS["miss"], grad=True)
    B.distance_loss(res).backward()
    assert x.grad[0, 1] > 0.0  # descent lowers v_y
    x, res = B.simulate(model, B.STARTS["miss"], events=B.events_of(model), grad=True)
    loss, _ = B.miss_loss(res)
    loss.backward()
    assert float(loss.detach()) > 0.0 and x.grad[0, 0] > 0.0  # descent lowers v_x: towards the wall


def test_cli_reports_all_methods(tmp_path):
    out = tmp_path / "bank_shot.rrd"
    proc = subprocess.run([sys.executable, "-m", "scenes", "bank_shot", "--out", str(out), "--iters", "2",
                           "--start", "miss"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(summary["methods"]) == {"proposed", "baseline", "cma"}
    for figures in summary["methods"].values():
        assert {"reached_target", "final_loss", "iterations_to_target", "final_distance"} <= set(figures)
        assert figures["rollouts"] <= 3
    assert out.stat().st_size > 0


def test_bad_methods_option_is_rejected():
    from scenes.optim import parse_methods

    with pytest.raises(ValueError, match="--methods"):
        parse_methods("proposed,newton", B.METHODS)
    with pytest.raises(ValueError, match="--methods"):
        parse_methods(" , ", B.METHODS)
    assert parse_methods("cma, proposed", B.METHODS) == ["cma", "proposed"]


def test_inverse_benchmark_bank_shot_smoke(tmp_path):
    """A tiny configuration of the bank_shot part of benchmarks/inverse.py (Newton included), run
    as ``python -m benchmarks.inverse``."""
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "inverse"
    # as a module of the benchmarks package, the way `python -m benchmarks --full` imports it
    # (no benchmarks/ folder on sys.path: a bare `import newton_ball` failed there)
    proc = subprocess.run([sys.executable, "-m", "benchmarks.inverse", "--scenes", "bank_shot",
                           "--bank-iters", "1", "--bank-seeds", "1", "--jobs", "1", "--out", str(out)],
                          capture_output=True, text=True, timeout=900, cwd=root)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "inverse_bank_shot.json").read_text())
    methods = {(r["start"], r["method"]) for r in data["runs"]}
    assert ("miss", "newton (penalty, GD)") in methods and ("newton", "cma") in methods
    assert len(data["gradient_checks"]) == 3
    assert all(np.isfinite(c["relative_error"]) for c in data["gradient_checks"].values())
    text = (tmp_path / "inverse_bank_shot.md").read_text()
    assert "| miss | proposed |" in text and "| seed 0 | baseline |" in text and "Seeded misses" in text
    assert data["profile"]["ccd_events"] >= 1  # Newton's start bounces off the wall
    assert (tmp_path / "inverse_bank_shot.png").stat().st_size > 0


def test_seeded_starts_miss_the_wall_and_repeat(model):
    """``--start seeded``: each seed's start bounces off the floor and passes the wall (the
    rollout's contact record), lies in the stated ranges, and the same seed gives the same start."""
    for seed in (0, 1):
        v = np.asarray(B.seeded_start(model, seed))
        assert B.SEEDED_SIDEWAYS[0] <= abs(v[0]) <= B.SEEDED_SIDEWAYS[1]
        assert B.SEEDED_FORWARD[0] <= v[1] <= B.SEEDED_FORWARD[1] and B.SEEDED_DOWN[0] <= -v[2] <= B.SEEDED_DOWN[1]
        hits = B.bounces(B.simulate(model, v)[1])
        assert hits["floor"] >= 1 and hits["wall"] == 0
        assert tuple(v) == B.seeded_start(model, seed)


def test_rollout_knobs_reach_the_rollout(model):
    """``--substeps 4 --max-derivative 10 --ccd-precision float32`` parse into settings that run
    exactly the rollout called with them directly, and still bank off floor and wall."""
    import argparse

    import torch

    from scenes.sim_common import rollout_settings
    from sim.rollout import rollout

    parser = argparse.ArgumentParser()
    B.add_arguments(parser)
    assert rollout_settings(parser.parse_args([])).substeps == B.SUBSTEPS
    settings = rollout_settings(parser.parse_args(["--substeps", "4", "--max-derivative", "10",
                                                   "--ccd-precision", "float32"]))
    assert (settings.substeps, settings.max_derivative, settings.ccd_options) == (4, 10.0, {"precision": "float32"})
    with pytest.raises(SystemExit):
        parser.parse_args(["--max-derivative", "0"])
    v = torch.tensor([B.STARTS["newton"]], dtype=torch.float64)
    _, res = B.simulate(model, v, settings=settings)
    assert B.bounces(res) == {"floor": 1, "wall": 1}
    direct = rollout(model, B.FRAMES, B.DT, 4, particle_qd=v, max_derivative=10.0,
                     ccd_options={"precision": "float32"})
    np.testing.assert_array_equal(res.particle_q.numpy(), direct.particle_q.numpy())
    assert not np.array_equal(res.particle_q.numpy(), B.simulate(model, v)[1].particle_q.numpy())  # 8 substeps


def test_seeded_start_and_gradient_check_run_with_the_given_settings(model):
    """``seeded_start`` and ``gradient_check`` take the scene's settings: the start drawn with 4
    substeps misses the wall in the 4-substep rollout, and the gradient check at 4 substeps
    differentiates that rollout (its analytic gradient is the 4-substep rollout's, not the
    default 8's, and matches its central differences)."""
    from scenes.sim_common import RolloutSettings

    settings = RolloutSettings(substeps=4)
    v = np.asarray(B.seeded_start(model, 0, settings))
    hits = B.bounces(B.simulate(model, v, settings=settings)[1])
    assert hits["floor"] >= 1 and hits["wall"] == 0
    w = np.asarray(B.STARTS["newton"]) + np.array([0.003, 0.007, -0.005])
    check = B.gradient_check(model, w, settings=settings)
    assert check["relative_error"] < 1e-5, check
    x, res = B.simulate(model, w, grad=True, settings=settings)
    B.distance_loss(res).backward()
    np.testing.assert_array_equal(check["analytic"], x.grad.numpy()[0])
    x8, res8 = B.simulate(model, w, grad=True)
    B.distance_loss(res8).backward()
    assert not np.array_equal(check["analytic"], x8.grad.numpy()[0])
