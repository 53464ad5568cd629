"""The physics validation checks of ``benchmarks/physics.py``, one small setting each (8 substeps,
the replayed response unless a test says otherwise, short runs), asserting that every row of the
check passes its tolerance. The tolerances are the targets the physics must meet; the sliding
check also asserts its order of convergence. Gradients through an impact (closed form) and
through a landing held by static friction (central differences) close the file.

Also: the measuring helpers (yaw from the quaternion, pass/fail of a record) and the command.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks import physics as P

RESPONSE = "replayed"
SUBSTEPS = 8


def _assert_passed(rows: list[P.Record]) -> None:
    assert rows, "the check returned no rows"
    bad = [f"{r.label} ({r.response} x{r.substeps}): measured {r.measured:.6g}, expected {r.expected} "
           f"(tolerance {r.tolerance:g}{' rel' if r.mode == 'rel' else ''}) {r.details.get('error', '')}"
           for r in rows if not r.passed]
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------------------------------------
# the measuring helpers


def test_twist_and_rotation_angles():
    qz = P._quat_axis_angle((0, 0, 1), 0.3)
    qx = P._quat_axis_angle((1, 0, 0), 0.2)
    q0 = P._quat_axis_angle((0, 1, 0), 0.7)  # an arbitrary start: angles are relative to it
    assert P.twist_angle(np.array(qz), np.array([0, 0, 0, 1.0])) == pytest.approx(0.3, abs=1e-15)
    assert abs(P.twist_angle(np.array(qx), np.array([0, 0, 0, 1.0]))) < 1e-16
    # z-rotation applied after q0 (world frame): the yaw relative to q0 is its angle
    q = P._quat_mul(np.array(qz), np.array(q0))
    assert P.twist_angle(q, np.array(q0)) == pytest.approx(0.3, abs=1e-14)
    assert P.rotation_angle(q, np.array(q0)) == pytest.approx(0.3, abs=1e-14)
    # -q is the same rotation; a tiny yaw keeps its digits
    assert P.twist_angle(-q, np.array(q0)) == pytest.approx(0.3, abs=1e-14)
    tiny = P._quat_axis_angle((0, 0, 1), 1e-12)
    assert P.twist_angle(np.array(tiny), np.array([0, 0, 0, 1.0])) == pytest.approx(1e-12, rel=1e-9)


def test_record_pass_modes():
    r = P._record("x", "replayed", 8, "q", 1.0005, expected_value=1.0, tolerance=1e-3, mode="rel", expected="1",
                  reference="r")
    assert r.passed and r.error == pytest.approx(5e-4)
    r = P._record("x", "replayed", 8, "q", 2e-9, tolerance=1e-9, expected="0", reference="r")
    assert not r.passed
    r = P._record("x", "replayed", 8, "q", math.nan, tolerance=1.0, expected="0", reference="r")
    assert not r.passed
    r = P._record("x", "replayed", 8, "q", 0, tolerance=0.0, expected="0", reference="r")
    assert r.passed


def test_command_writes_table_and_json(tmp_path):
    records = P.main(["--only", "sphere_bounce", "--responses", "replayed", "--substeps", "8",
                      "--out-dir", str(tmp_path)])
    assert len(records) == 1
    data = json.loads((tmp_path / "physics.json").read_text())
    row = data["checks"][0]
    for key in ("name", "response", "substeps", "expected", "expected_value", "measured", "tolerance", "passed",
                "reference"):
        assert key in row
    assert row["name"] == "sphere_bounce" and row["response"] == "replayed" and row["substeps"] == 8
    md = (tmp_path / "physics.md").read_text()
    assert "| check | response | substeps | reference/expected | measured | tolerance | result |" in md
    with pytest.raises(SystemExit):
        P.main(["--only", "nope", "--out-dir", str(tmp_path)])


def test_suite_names_every_check():
    assert list(P.CHECKS) == [
        "flat_drop_plane", "flat_drop_static_box", "flat_drop_rigid_box", "slope_static", "slope_sliding",
        "rest_plane", "rest_box", "stack", "restitution_sweep", "head_on", "free_rotation", "cloth_flat_box",
        "cloth_hanging", "cloth_on_sphere", "sliding_friction", "sphere_bounce", "ball_bounce", "ball_roll",
        "ball_head_on"]


# ------------------------------------------------------------------------------------------------
# the checks, one setting each


def test_flat_drop_plane():
    _assert_passed(P.check_flat_drop_plane(response=RESPONSE, substeps=SUBSTEPS, friction=0.3, seconds=1.0))


def test_flat_drop_static_box():
    _assert_passed(P.check_flat_drop_static_box(response=RESPONSE, substeps=SUBSTEPS, seconds=1.0))


def test_flat_drop_rigid_box():
    _assert_passed(P.check_flat_drop_rigid_box(response=RESPONSE, substeps=SUBSTEPS, seconds=1.0))


def test_slope_static():
    _assert_passed(P.check_slope_static(response=RESPONSE, substeps=SUBSTEPS, mu=0.5, seconds=2.0))


def test_slope_sliding():
    _assert_passed(P.check_slope_sliding(response=RESPONSE, substeps=SUBSTEPS, seconds=1.0))


def test_rest_plane():
    _assert_passed(P.check_rest_plane(response=RESPONSE, substeps=SUBSTEPS, seconds=2.0))


def test_rest_box():
    _assert_passed(P.check_rest_box(response=RESPONSE, substeps=SUBSTEPS, seconds=2.0))


def test_stack():
    _assert_passed(P.check_stack(response=RESPONSE, substeps=SUBSTEPS, boxes=3, seconds=2.0))


def test_stack_of_five():
    # equal boxes: every corner rests on a corner (one constraint found by several faces)
    _assert_passed(P.check_stack(response=RESPONSE, substeps=SUBSTEPS, boxes=5, seconds=2.0))


def test_restitution_sweep():
    _assert_passed(P.check_restitution_sweep(response=RESPONSE, substeps=SUBSTEPS, restitution=0.5))


def test_head_on():
    _assert_passed(P.check_head_on(response=RESPONSE, substeps=SUBSTEPS, gap=0.05))


def test_free_rotation():
    # 3.5 s holds two flips (1.05 s and 3.21 s): one flip interval
    _assert_passed(P.check_free_rotation(response=RESPONSE, substeps=SUBSTEPS, seconds=3.5))


def test_cloth_flat_box():
    _assert_passed(P.check_cloth_flat_box(response=RESPONSE, substeps=SUBSTEPS, count=5))


def test_cloth_hanging():
    _assert_passed(P.check_cloth_hanging(response=RESPONSE, substeps=SUBSTEPS, seconds=6.0))


def test_cloth_on_sphere_comes_to_rest():
    """The draped cloth (with air drag, so that its free corners stop swinging) rests: its
    centre, on top of the sphere, moves < 1e-6 m over the sixth second (the check's tolerance;
    measured 5e-8 m). Its contacts mix sticking and sliding ones in one solve; a load-bearing
    contact that rounding put a hair beyond the separation stays in the proximity set (it
    dropped its load for a substep, which kicked the cloth: 2.6e-5 m over the last second of
    10 s, and 6.0e-4 m with the contacts' stopping impulses shared instead)."""
    (row,) = P.check_cloth_on_sphere(response=RESPONSE, substeps=SUBSTEPS, seconds=6.0, window=1.0)
    _assert_passed([row])


def _relative_error(rows: list[P.Record]) -> float:
    (row,) = rows
    return (row.measured - row.expected_value) / row.expected_value


def test_sliding_friction_stopping_distance_is_second_order():
    """The stopping distance ``v^2 / (2 mu g)`` within the check's 0.2 % at 8 substeps, and short
    of it by at most ``mu g h^2 / 2`` at 8 and 16 (measured 2.5e-7 m): sliding friction on
    resting contact moves the positions by half its velocity change (a constant force over the
    substep: exact while it slides), and only the last substep, where the box sticks with a
    speed below ``mu g h``, misses the distance ``v^2 / (2 mu g)`` it would still slide. Moved by
    the velocities after the friction, the box stopped short by ``v0 h / 2`` (2.1e-3 m at 8
    substeps, first order), as it still does at 4 substeps, where the friction's change of
    velocity per substep exceeds the bound of a force over the substep
    (``kernels.friction.SLIDING_HALF_STEP_LIMIT``)."""
    _assert_passed(P.check_sliding_friction(response=RESPONSE, substeps=SUBSTEPS))
    for substeps in (SUBSTEPS, 16):
        (row,) = P.check_sliding_friction(response=RESPONSE, substeps=substeps)
        h = P.DT / substeps
        bound = 0.5 * 0.3 * P.GRAVITY * h * h
        assert -bound - 1e-12 <= row.measured - row.expected_value <= 1e-12, (substeps, row.measured, bound)


def test_sphere_bounce_apex_ratio_at_every_substep_count():
    """The apex ratio of a particle's bounce is ``e^2`` to the check's 0.1 % at 4, 8 and 32
    substeps: the plane stage reflects the velocity of the exact parabola at ``t*`` (the stored
    velocity is half a substep behind), so the error is no longer O(h) (it was -1.4 % at 8)."""
    for substeps in (4, SUBSTEPS, 32):
        _assert_passed(P.check_sphere_bounce(response=RESPONSE, substeps=substeps))
    assert abs(_relative_error(P.check_sphere_bounce(response=RESPONSE, substeps=SUBSTEPS))) < 1e-4


def test_sphere_bodies():
    """The sphere rows: a sphere body bounces to e^2 of its height (the particles' plane law),
    slides into rolling at 5/7 of its speed, and swaps velocities head on."""
    _assert_passed(P.check_ball_bounce(response=RESPONSE, substeps=SUBSTEPS))
    _assert_passed(P.check_ball_roll(response=RESPONSE, substeps=SUBSTEPS))
    _assert_passed(P.check_ball_head_on(response=RESPONSE, substeps=SUBSTEPS))


@pytest.mark.parametrize("restitution", [0.0, 1.0])
def test_restitution_at_a_substep_boundary_and_mid_substep(restitution):
    """e = 0 (no rebound, the separation restored at the position level) and e = 1, with the
    impact exactly at the end of a substep (gap 0.05 m at 1 m/s, 8 substeps) and inside one."""
    _assert_passed(P.check_restitution_sweep(response=RESPONSE, substeps=SUBSTEPS, restitution=restitution,
                                             gaps=(0.05, 0.0505)))


# ------------------------------------------------------------------------------------------------
# gradients through the fixed physics: the rollout's against closed forms and central differences


def _box_toward_static_box(restitution: float, gap: float):
    """A box moving along x towards a larger static box (its corners well inside the face hit)."""
    from sim.builder import ModelBuilder
    from sim.mesh_io import box_mesh

    b = ModelBuilder()
    b.set_gravity((0.0, 0.0, 0.0))
    b.add_rigid_body(*box_mesh(P.BOX_HALF), density=P.DENSITY, pos=(-2 * P.BOX_HALF - gap, 0.0, 0.0))
    b.add_static_mesh(*box_mesh((P.BOX_HALF, 2 * P.BOX_HALF, 2 * P.BOX_HALF)))
    b.set_contact(restitution=restitution, friction=0.0, thickness=P.THICKNESS)
    return b.finalize()


@pytest.mark.parametrize("gap", [0.0515, 0.0535])
def test_gradient_through_an_impact_equals_the_closed_form(gap):
    """A box at speed v hits a static box after ``gap / v`` and leaves at ``-e v``: its position at
    T is ``x0 + gap (1 + e) - e v T``, so ``dx/dv = -e T`` (and ``dy/dv_y = T``), at two phases
    of the impact in its substep. (A substep that starts closer than the thickness bounces at
    its start, as a proximity contact: gap 0.0505 m bounces 0.5 mm early, and there
    ``dx/dv = t_start - e (T - t_start)``; an impact exactly at a substep's end, gap 0.05 m, is
    the kink between the two.)"""
    import torch

    from sim.rollout import rollout

    e, steps = 0.5, 12
    model = _box_toward_static_box(e, gap)
    qd = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, P.DT, SUBSTEPS, body_qd=qd)
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    T = steps * P.DT
    (res.body_q[-1, 0, 0] + res.body_q[-1, 0, 1]).backward()
    grad = qd.grad.numpy()[0]
    np.testing.assert_allclose(grad[3], -e * T, rtol=1e-9)
    np.testing.assert_allclose(grad[4], T, rtol=1e-9)
    np.testing.assert_allclose(res.body_q[-1, 0, 0].item(), -2 * P.BOX_HALF - gap + gap * (1 + e) - e * T,
                               rtol=0, atol=1e-12)


def test_gradient_through_a_landing_held_by_static_friction_matches_central_differences():
    """A box dropped onto a 20 degree slope (mu 0.5 > tan 20) lands and sticks: the replayed
    gradient of its final position w.r.t. its start velocity (the landing point) equals central
    differences of the same rollout."""
    import torch

    from sim.builder import ModelBuilder
    from sim.mesh_io import box_mesh
    from sim.rollout import rollout

    angle = math.radians(20.0)
    n = np.array([math.sin(angle), 0.0, math.cos(angle)])
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(P.BOX_HALF), density=P.DENSITY, pos=tuple(n * (P.BOX_HALF + 0.004)),
                     rot=(0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2)))
    b.add_ground_plane(normal=tuple(n), offset=0.0)
    b.set_contact(restitution=0.0, friction=0.5, thickness=P.THICKNESS)
    model = b.finalize()
    steps, start = 10, np.array([0.0, 0.0, 0.0, 0.05, 0.02, -0.3])

    def final(v):
        res = rollout(model, steps, P.DT, SUBSTEPS, body_qd=torch.tensor(v[None], dtype=torch.float64))
        return res, res.body_q[-1, 0, :3].numpy()

    qd = torch.tensor(start[None], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, P.DT, SUBSTEPS, body_qd=qd)
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    res.body_q[-1, 0, :3].sum().backward()
    grad = qd.grad.numpy()[0]
    step = 1e-6
    for j in (3, 4, 5):
        plus, minus = start.copy(), start.copy()
        plus[j] += step
        minus[j] -= step
        fd = (final(plus)[1].sum() - final(minus)[1].sum()) / (2 * step)
        assert abs(grad[j] - fd) <= 1e-5 * max(abs(fd), 1e-3), (j, grad[j], fd)
    # static friction held it: the box has stopped on the slope
    assert np.abs(res.body_qd[-1, 0].detach().numpy()).max() < 1e-9


def test_gradient_through_a_slide_is_the_closed_form():
    """A box sliding flat on the ground (mu 0.3) with the start velocity ``v0`` in the plane
    moves along ``v0 / |v0|`` by ``|v0| T - mu g T^2 / 2`` until it stops (the slide's friction
    a force over each substep: exact while sliding). After 0.2 s (it slides 0.68 s) the replayed
    rollout's position and its Jacobian w.r.t. ``v0`` equal the closed form
    ``T I - (mu g T^2 / 2)(I - u u^T) / |v0|`` (``u = v0 / |v0|``; the friction's direction
    turns with ``v0``, which the half step of the positions carries)."""
    import torch

    from sim.rollout import rollout

    mu, steps = 0.3, 12
    b = P.scene_builder(friction=mu)
    P.add_box(b, P.BOX_HALF, (0.0, 0.0, P.BOX_HALF + P.THICKNESS))
    b.add_ground_plane()
    model = b.finalize()
    v0 = np.array([1.5, 0.5])
    qd = torch.tensor([[0.0, 0.0, 0.0, v0[0], v0[1], 0.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, P.DT, SUBSTEPS, body_qd=qd)
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    T = steps * P.DT
    speed = np.linalg.norm(v0)
    u = v0 / speed
    x = res.body_q[-1, 0, :2]
    np.testing.assert_allclose(x.detach().numpy(), u * (speed * T - 0.5 * mu * P.GRAVITY * T * T), rtol=0, atol=1e-12)
    jacobian = np.stack([torch.autograd.grad(x[i], qd, retain_graph=True)[0].numpy()[0, 3:5] for i in range(2)])
    expected = T * np.eye(2) - 0.5 * mu * P.GRAVITY * T * T * (np.eye(2) - np.outer(u, u)) / speed
    np.testing.assert_allclose(jacobian, expected, rtol=0, atol=1e-10)
