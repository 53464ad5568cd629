"""Scene ``billiards`` (DiffTaichi's billiards with sphere bodies and lifted sphere events).

Ground truth: the rack's layout and the untouched loss in closed form, straight-line geometry of
the cue's path, and the rollout's own trajectory (a ball at rest that nothing hits keeps a zero
velocity exactly)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from scenes import billiards as B


@pytest.fixture(scope="module")
def model():
    return B.build()


def test_rack_is_difftaichis(model):
    rack = B.rack_positions()
    assert rack.shape == (10, 2)
    assert np.allclose(rack[-1], (0.68, 0.617), atol=1e-15)
    # neighbours in a row touch (to rounding), rows do not
    assert abs(np.linalg.norm(rack[1] - rack[2]) - 2 * B.RADIUS) < 1e-15
    assert np.linalg.norm(rack[0] - rack[1]) > 2 * B.RADIUS * 1.05
    assert model.body_count == 11 and model.sphere_count == 11


@pytest.mark.parametrize("start", ["miss-above", "miss-away"])
def test_named_misses_touch_nothing(model, start):
    assert B.cue_path_gap(model, B.STARTS[start]) > 0.0
    _, res = B.simulate(model, B.STARTS[start])
    assert not B.moved(res)[1:].any()
    untouched = (0.68 - 0.9) ** 2 + (0.617 - 0.75) ** 2
    assert abs(float(B.distance_loss(model, res)) - untouched) < 1e-15


def test_seeded_starts_miss(model):
    for seed in range(3):
        shot = B.seeded_start(model, seed)
        _, res = B.simulate(model, shot)
        assert not B.moved(res)[1:].any()


def test_the_push_chain_runs_down_the_diagonal_to_the_apex(model):
    """Pushing the target (0.68, 0.617) at the goal needs a striker where ball 6 (0.62, 0.578)
    is; ball 6, pushed along the line of centres (0.06, 0.039), needs one where ball 3 is, and
    so on to the apex (ball 1), which the cue can reach."""
    centres = model.body_q.numpy()[:, :2]
    head, direction = B.push_chain(centres, B.target_of(model), B.GOAL)
    assert head == 1
    np.testing.assert_allclose(direction, np.array([0.06, 0.039]) / np.hypot(0.06, 0.039), rtol=0, atol=1e-14)
    # a goal whose striking position is free: the target itself, pushed straight at it
    head, direction = B.push_chain(centres, B.target_of(model), (1.0, 0.3))
    assert head == B.target_of(model)
    np.testing.assert_allclose(direction, np.array([0.32, -0.317]) / np.hypot(0.32, -0.317), rtol=0, atol=1e-14)


def test_the_miss_loss_is_the_closest_approach_against_the_striking_point(model):
    """For a miss the lifted roots' real part is the time of closest approach, so the aim term
    equals |d_closest / 2r + u|^2 from straight-line geometry (the time term is 0 here)."""
    from sim.events import sphere_event_roots

    shot = B.STARTS["miss-above"]
    _, res = B.simulate(model, shot)
    event = B.lifted_event(model, res)
    assert (event.body_a, event.body_b, event.window) == (0, 1, (0, B.STEPS))
    roots = sphere_event_roots(model, [event], res.body_q, B.DT)[0]
    assert float(roots[0, 1]) != 0.0  # a miss: a complex pair
    d0 = np.array(shot[:2]) - np.array([0.5, 0.5])
    v = np.array(shot[2:])
    closest = d0 + v * (-(d0 @ v) / (v @ v))
    _, u = B.push_chain(model.body_q.numpy()[:, :2], B.target_of(model), B.GOAL)
    expected = float(np.sum((closest / (2 * B.RADIUS) + u) ** 2))
    assert abs(float(B.miss_loss(model, res, event, roots)) - expected) < 1e-12 * expected


def test_the_miss_loss_slopes_towards_a_ball_abeam_of_the_cue(model):
    """Seeded start 34 passes the apex abeam: its closest approach comes 0.06 s after the start,
    before the contact window. The aim is then taken at the window's start (straight-line
    geometry, to 1e-12), and the loss falls as the heading turns towards the ball (the aim at the
    closest approach itself slopes away from the ball there: a trap)."""
    def loss_at(heading):
        speed = float(np.hypot(*start[2:]))
        shot = (*start[:2], speed * np.cos(heading), speed * np.sin(heading))
        _, _, loss, hit, _ = B.evaluate(model, shot, "proposed", grad=False)
        assert not hit
        return float(loss), shot

    start = B.seeded_start(model, 34)
    heading = float(np.arctan2(start[3], start[2]))
    value, shot = loss_at(heading)
    d0, v = np.array(shot[:2]) - np.array([0.5, 0.5]), np.array(shot[2:])
    tau, duration = -(d0 @ v) / (v @ v), B.STEPS * B.DT
    low = B.CONTACT_WINDOW[0] * duration
    assert 0.0 < tau < low
    _, u = B.push_chain(model.body_q.numpy()[:, :2], B.target_of(model), B.GOAL)
    expected = float(np.sum(((d0 + low * v) / (2 * B.RADIUS) + u) ** 2)) + (low - tau) ** 2 / duration ** 2
    assert abs(value - expected) < 1e-12 * expected
    towards, _ = loss_at(heading - np.radians(5.0))  # the apex lies clockwise of the heading
    away, _ = loss_at(heading + np.radians(5.0))
    assert towards < value < away, (towards, value, away)


def test_a_hit_needs_the_chain_s_head_struck_within_the_cone(model):
    """DiffTaichi's start (the apex struck head-on, 33 degrees off the chain) is a hit; a cue
    that strikes the target itself from the upper right moves it but is not."""
    _, res = B.simulate(model, B.STARTS["default"])
    assert B.good_hit(model, res)
    _, res = B.simulate(model, (0.8, 0.8, -0.3, -0.45))
    assert B.moved(res)[B.target_of(model)] and not B.good_hit(model, res)
    _, res = B.simulate(model, B.STARTS["miss-above"])
    assert not B.good_hit(model, res)
    # the apex struck from below: it leaves 80 degrees above the x axis (47 off the chain) and
    # moves the target, but is not a hit; struck a little further left, it leaves 32 off: a hit
    _, res = B.simulate(model, (0.49, 0.3, 0.0, 0.6))
    assert B.moved(res)[B.target_of(model)] and not B.good_hit(model, res)
    _, res = B.simulate(model, (0.45, 0.3, 0.1, 0.6))
    assert B.good_hit(model, res)


def test_the_proposed_method_reaches_the_goal_from_a_miss(model):
    """From ``miss-above`` (DiffTaichi's gradient: exactly 0) the target ends within 5 mm of
    the goal, checked on the reported shot's own rollout."""
    result = B.optimise(model, B.STARTS["miss-above"], 80, "proposed", "adam")
    assert result["reached_target"] and result["rollouts"] == result["iterations_to_target"] + 1
    _, res = B.simulate(model, result["final_shot"])
    assert B.target_distance(model, res) < B.TARGET_TOLERANCE


def test_a_stalled_hit_phase_plays_the_best_hit_faster_and_reaches_the_goal(model):
    """From a hit where the descent steps keep crossing into a worse branch (a shot where seed
    14's run once stopped 6.4 cm from the goal), the guarded step shrinks below ``STALL_STEP``; the next
    shot is the best hit so far with the same position and heading, ``STALL_SPEEDUP`` faster,
    and the run then reaches the goal."""
    stalled = (0.375829038721194, 0.3790784145999505, 0.2016820246452815, 0.18453948584739724)
    result = B.optimise(model, stalled, 40, "proposed", "adam")
    history = result["history"]
    assert result["restarts"], "the hit phase never stalled"
    k = result["restarts"][0]
    # the guarded step from the history (the start is a hit: the phase starts there): each
    # rejected iterate halves it, each accepted one grows it; the replay follows the first
    # iterate that leaves it below STALL_STEP of its largest
    step, steps = B.HIT_LEARNING_RATE, []
    for taken in history["accepted"][1:k]:
        step = min(step * B.HIT_GROWTH, B.HIT_LEARNING_RATE) if taken else step * 0.5
        steps.append(step)
    threshold = B.HIT_LEARNING_RATE * B.STALL_STEP
    assert steps[-1] < threshold and all(s >= threshold for s in steps[:-1]), steps
    best = min((i for i in range(k) if history["accepted"][i] and history["hit"][i]), key=lambda i: history["loss"][i])
    before, after = history["shot"][best], history["shot"][k]
    np.testing.assert_array_equal(after[:2], before[:2])
    np.testing.assert_allclose(after[2:], before[2:] * B.STALL_SPEEDUP, rtol=1e-15)
    assert result["reached_target"]
    _, res = B.simulate(model, result["final_shot"])
    assert B.target_distance(model, res) < B.TARGET_TOLERANCE


def test_the_default_start_hits_and_its_gradient_equals_central_differences(model):
    _, res = B.simulate(model, B.STARTS["default"])
    assert B.moved(res)[B.target_of(model)]
    check = B.gradient_check(model, B.STARTS["default"])
    assert check["relative_error"] < 1e-6, check


def test_cli_from_a_miss(tmp_path):
    """The baseline's gradient is exactly zero from a miss (it stops at once with DiffTaichi's
    untouched loss); the proposed method's lifted loss falls."""
    out = tmp_path / "b.rrd"
    proc = subprocess.run([sys.executable, "-m", "scenes", "billiards", "--out", str(out), "--start", "miss-above",
                           "--iters", "4", "--methods", "baseline,proposed", "--plot", str(tmp_path / "l.png")],
                          capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    base, proposed = summary["methods"]["baseline"], summary["methods"]["proposed"]
    assert base["zero_gradient_at"] == 0 and not base["reached_target"] and base["rollouts"] == 1
    assert abs(base["final_loss"] - 0.066089) < 1e-12
    assert abs(base["target_distance"] - np.hypot(0.22, 0.133)) < 1e-12
    assert proposed["rollouts"] == 5  # --iters 4: four steps, the start and every step's shot played
    assert set(proposed) >= {"reached_target", "final_loss", "iterations_to_target", "target_distance"}
    assert out.exists() and out.stat().st_size > 0
    assert (tmp_path / "l.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("argv,message", [
    (["--cue-pos", "0.1", "0.5"], "--cue-pos and --cue-vel go together"),
    (["--methods", "foo"], "--methods must be"),
    (["--cue-pos", "0.1", "nan", "--cue-vel", "0.3", "0"], "finite"),
    (["--plot", "x.txt"], "--plot must name a .png file"),
])
def test_cli_usage_errors(tmp_path, argv, message):
    proc = subprocess.run([sys.executable, "-m", "scenes", "billiards", "--out", str(tmp_path / "x.rrd")] + argv,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and message in proc.stderr
    assert not (tmp_path / "x.rrd").exists()


def test_shots_inside_the_rack_are_projected_out():
    rack = B.rack_positions()
    shot = B.outside_the_rack((rack[3, 0] + 0.01, rack[3, 1], 0.3, 0.0))
    gaps = np.linalg.norm(rack - np.asarray(shot[:2])[None], axis=1) - 2 * B.RADIUS
    assert gaps.min() >= 0.0 and gaps.min() < 1e-9 and shot[2:] == (0.3, 0.0)
    assert B.outside_the_rack(B.STARTS["default"]) == B.STARTS["default"]
    # wedged between two touching balls of a row: pushing out of one pushes into the other
    wedged = B.outside_the_rack((*(0.5 * (rack[1] + rack[2]) + (0.001, 0.0)), 0.3, 0.0))
    assert (np.linalg.norm(rack - np.asarray(wedged[:2])[None], axis=1) - 2 * B.RADIUS).min() >= 0.0


def test_the_miss_phase_polar_variables_and_their_gradient():
    """(speed, heading / HEADING_SCALE) round-trips to the shot's velocity, and the chain rule of
    ``polar_gradient`` equals autograd through ``from_polar``."""
    import torch

    from scenes.optim import from_polar, polar_gradient, to_polar

    velocity = (-0.37, -0.24)
    polar = torch.tensor(to_polar(velocity, B.HEADING_SCALE), dtype=torch.float64, requires_grad=True)
    back = from_polar(polar, B.HEADING_SCALE)
    np.testing.assert_allclose(back.detach().numpy(), velocity, rtol=0, atol=1e-15)
    weights = torch.tensor([2.0, 0.7], dtype=torch.float64)
    (back * weights).sum().backward()
    np.testing.assert_allclose(polar_gradient(polar.detach(), weights, B.HEADING_SCALE).numpy(),
                               polar.grad.numpy(), rtol=1e-14, atol=1e-15)
