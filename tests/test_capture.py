"""Recorded graphs (:mod:`core.capture`): a stage list replayed as one Warp graph gives the launches'
bits, a changed argument selects another graph, and the integrator's captured substeps end the
simulation scenes in the same state as launching one by one."""

import importlib

import numpy as np
import pytest
import warp as wp

from core.capture import Graphs, Launch, Zero, run_stages
from scenes.sim_common import build_model, default_args, simulate
from sim.builder import ModelBuilder
from sim.integrators.semi_implicit import SemiImplicitIntegrator


@wp.kernel
def _axpy(a: wp.float64, x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64)):
    i = wp.tid()
    y[i] = y[i] + a * x[i]


@wp.kernel
def _scale(a: wp.float64, x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64)):
    i = wp.tid()
    y[i] = a * x[i]


def _stages(a, x, y):
    return [Zero(y), Launch(_axpy, x.shape[0], (a, x), (y,)), Launch(_axpy, x.shape[0], (a, x), (y,))]


def test_a_stage_list_is_recorded_on_its_second_call_and_replayed_after():
    """First call: launch by launch; second: recorded and launched; later: the graph. Every call
    gives y = 2 a x, whatever y held before (the zeroing is in the graph), and the recorded
    graph follows the current contents of its arrays."""
    graphs = Graphs("cpu")
    x = wp.array(np.arange(5.0), dtype=wp.float64)
    y = wp.array(np.full(5, 7.0), dtype=wp.float64)
    for call in range(4):
        y.fill_(-1.0)
        graphs.run(_stages(wp.float64(0.5), x, y))
        np.testing.assert_array_equal(y.numpy(), np.arange(5.0))
        assert (graphs.recorded, graphs.replayed) == ((0, 0) if call == 0 else (1, call))
    x.assign(np.arange(5.0) * 3.0)  # new contents, same array: the same graph reads them
    graphs.run(_stages(wp.float64(0.5), x, y))
    np.testing.assert_array_equal(y.numpy(), np.arange(5.0) * 3.0)
    assert graphs.recorded == 1


@pytest.mark.parametrize("change", ["scalar", "array", "negative zero"])
def test_a_changed_argument_never_replays_a_stale_graph(change):
    """Another scalar value (or -0.0 for 0.0, which a graph tells apart: the products' signs
    differ) or another array is another key: its first call launches one by one and gives its
    own result, bit for bit."""
    graphs = Graphs("cpu")
    x = wp.array(np.array([1.0, -2.0, 3.0]), dtype=wp.float64)
    y = wp.zeros(3, dtype=wp.float64)
    first = 0.0 if change == "negative zero" else 0.25
    for _ in range(3):
        graphs.run([Launch(_scale, 3, (wp.float64(first), x), (y,))])
    if change == "scalar":
        a, x2 = wp.float64(4.0), x
    elif change == "array":
        a, x2 = wp.float64(first), wp.array(np.array([5.0, 6.0, 7.0]), dtype=wp.float64)
    else:
        a, x2 = wp.float64(-0.0), x
    graphs.run([Launch(_scale, 3, (a, x2), (y,))])
    expected = a.value * x2.numpy()
    np.testing.assert_array_equal(y.numpy().view(np.int64), expected.view(np.int64))
    assert graphs.recorded == 1 and graphs.replayed == 2  # the changed call was not a replay


def test_numpy_and_python_floats_key_by_their_bits():
    from core.capture import argument_key

    assert argument_key(np.float64(-0.0)) != argument_key(0.0)
    assert argument_key(np.float64(0.25)) == argument_key(0.25)
    assert argument_key(wp.float64(np.float64(-0.0))) != argument_key(wp.float64(0.0))


def test_an_empty_stage_list_records_nothing():
    graphs = Graphs("cpu")
    for _ in range(3):
        graphs.run([])
    assert (graphs.recorded, graphs.replayed) == (0, 0)


def test_the_graph_limit_drops_the_oldest():
    """With room for two graphs, a third drops the least recently run: running the first list
    again records it anew, the third's (run since) is still replayed."""
    graphs = Graphs("cpu", limit=2)
    x, y = wp.ones(2, dtype=wp.float64), wp.zeros(2, dtype=wp.float64)
    for a in (1.0, 2.0, 3.0):
        for _ in range(2):
            graphs.run(_stages(wp.float64(a), x, y))
        np.testing.assert_array_equal(y.numpy(), [2.0 * a] * 2)
    assert graphs.recorded == 3
    graphs.run(_stages(wp.float64(3.0), x, y))
    assert graphs.recorded == 3  # kept: replayed
    for _ in range(2):  # dropped: seen once more (also dropped from the seen keys), then recorded
        graphs.run(_stages(wp.float64(1.0), x, y))
    np.testing.assert_array_equal(y.numpy(), [2.0, 2.0])
    assert graphs.recorded == 4


def _run(name: str, steps: int, response: str) -> str:
    module = importlib.import_module(f"scenes.{name}")
    summary, _ = simulate(module.build, default_args(steps=steps, response=response), None, name=name,
                          progress=False)
    return summary["state_sha256"]


@pytest.mark.parametrize("name", ["cloth_drop", "rigid_toss", "cloth_rigid"])
def test_captured_substeps_end_the_scenes_in_the_launches_bits(name, monkeypatch):
    """The scenes' default (their integrator's stages replayed as graphs) and the same run
    launched one by one end in the same state, bit for bit, after resting and impact contacts;
    the captured run did replay graphs."""
    steps = {"cloth_drop": 30, "rigid_toss": 30, "cloth_rigid": 40}[name]
    launches = []
    original = wp.capture_launch
    monkeypatch.setattr(wp, "capture_launch", lambda graph, *a, **k: (launches.append(1), original(graph, *a, **k)))
    captured = _run(name, steps, "gauss-seidel")
    substeps = default_args().substeps
    # one graph per substep, but for each key's first two sights (a few keys: the caller's
    # two states and the two alternating scratch ones as the substep's start)
    assert substeps * steps - 16 <= len(launches) <= substeps * steps
    monkeypatch.setattr(Graphs, "run", lambda self, stages: run_stages(stages, self.device))
    launches.clear()
    assert _run(name, steps, "gauss-seidel") == captured
    assert not launches


def test_a_taped_step_launches_one_by_one_and_its_gradient_matches():
    """Under a tape nothing is replayed from a graph (a graph's launches are not on the tape):
    the gradient of a falling cloth's summed final height with respect to its start velocities
    is the uncaptured integrator's, bit for bit, and the free flight's d z / d v_z = t."""
    b = ModelBuilder()
    b.add_cloth_grid((0.0, 0.0, 1.0), None, 3, 3, 0.1, 0.1, density=0.2, stretch_stiffness=200.0,
                     shear_stiffness=50.0, bend_stiffness=5.0, damping=0.5, velocity=(0.0, 0.0, -1.0))
    b.add_ground_plane()
    model = b.finalize()

    def gradient(capture):
        integrator = SemiImplicitIntegrator(model, capture=capture)
        s0 = model.state(requires_grad=True)
        states = [s0] + [model.state(requires_grad=True) for _ in range(10)]
        tape = wp.Tape()
        with tape:
            for k in range(10):
                integrator.step(states[k], states[k + 1], 1.0 / 60.0, 2)
        q = states[-1].particle_q.numpy().copy()
        states[-1].particle_q.grad.assign(np.tile([0.0, 0.0, 1.0], (model.particle_count, 1)))
        tape.backward()
        replayed = integrator.graphs.replayed if integrator.graphs is not None else 0
        return q, s0.particle_qd.grad.numpy().copy(), replayed

    q1, g1, replayed = gradient(True)
    q0, g0, _ = gradient(False)
    assert replayed == 0
    np.testing.assert_array_equal(q1, q0)
    np.testing.assert_array_equal(g1, g0)
    np.testing.assert_allclose(g1[:, 2], 10.0 / 60.0, rtol=1e-9)  # above the plane all along


def _cloth_on_ground():
    b = ModelBuilder()
    b.add_cloth_grid((0.0, 0.0, 0.05), None, 3, 3, 0.1, 0.1, density=0.2, stretch_stiffness=200.0,
                     shear_stiffness=50.0, bend_stiffness=5.0, damping=0.5, velocity=(0.3, 0.0, -1.0))
    b.add_ground_plane()
    return b.finalize()


def _spheres_on_ground():
    b = ModelBuilder()
    b.add_sphere(0.05, mass=0.2, pos=(0.0, 0.0, 0.2), velocity=(1.0, 0.0, -1.0))
    b.add_sphere(0.05, mass=0.2, pos=(0.3, 0.0, 0.05), velocity=(-0.5, 0.0, 0.0))
    b.add_ground_plane()
    return b.finalize()


@pytest.mark.parametrize("case", ["implicit cloth", "spheres"])
def test_captured_steps_match_the_launches_for_the_implicit_integrator_and_spheres(case):
    """The implicit integrator (its bodies' and planes' stages captured, the spring solve not)
    and a model of spheres (stages before and after the sphere stage) end in the launches'
    bits, with graphs replayed, after contacts with the ground. The implicit integrator's
    substeps after the first start from a fresh State each (its refinement may halve them), so
    only its first substep per step is sure to repeat a key: at least one replay per step from
    the third on."""
    from sim.integrators.implicit import ImplicitIntegrator

    model = _cloth_on_ground() if case == "implicit cloth" else _spheres_on_ground()
    make = ImplicitIntegrator if case == "implicit cloth" else SemiImplicitIntegrator

    def run(capture):
        integrator = make(model, capture=capture)
        s0, s1 = model.state(), model.state()
        for _ in range(30):
            integrator.step(s0, s1, 1.0 / 60.0, 4)
            s0, s1 = s1, s0
        replayed = integrator.graphs.replayed if integrator.graphs is not None else 0
        return [getattr(s0, n).numpy().copy() for n in ("particle_q", "particle_qd", "body_q", "body_qd")], replayed

    captured, replayed = run(True)
    launched, _ = run(False)
    assert replayed >= (30 - 2 if case == "implicit cloth" else 30 * 4 - 16)
    for a, b in zip(captured, launched):
        np.testing.assert_array_equal(a, b)
    z = captured[0][:, 2] if case == "implicit cloth" else captured[2][:, 2]
    assert z.min() < 0.06  # on the ground by the end


def test_no_graph_runs_under_a_tape_even_without_gradients():
    """An integrator told to keep no gradients (``requires_grad=False``) still launches one by
    one while a tape records: its launches are on the tape."""
    model = _cloth_on_ground()
    integrator = SemiImplicitIntegrator(model, requires_grad=False, capture=True)
    s0, s1 = model.state(), model.state()
    for _ in range(3):
        integrator.step(s0, s1, 1.0 / 60.0, 4)
    assert integrator.graphs.replayed > 0
    before = integrator.graphs.replayed
    tape = wp.Tape()
    with tape:
        integrator.step(s0, s1, 1.0 / 60.0, 4)
    assert integrator.graphs.replayed == before
    assert len(tape.launches) >= 4 * 3  # springs, particles and the planes' response per substep


@pytest.mark.parametrize("name", ["cloth_drop", "rigid_toss", "cloth_rigid"])
def test_gauss_seidel_rounds_as_graphs_end_in_the_launches_bits(name):
    """``capture_rounds``: each substep's CCD rounds after its first contact recorded as one
    graph (``wp.capture_while`` over the rounds, ``wp.capture_if`` over each round's growth and
    solve) and launched. The scene run ends in the same bits, with the same contacts, as the
    rounds launched one by one on the host, and graphs were launched."""
    from sim.contact.response import ImpulseCollisionHandler

    module = importlib.import_module(f"scenes.{name}")
    steps = 25 if name == "cloth_drop" else 40  # past the first contacts of each scene
    captured, _ = simulate(module.build, default_args(steps=steps, response="gauss-seidel", capture_rounds=True),
                           None, name=name, progress=False)
    plain, _ = simulate(module.build, default_args(steps=steps, response="gauss-seidel"), None, name=name,
                        progress=False)
    assert captured["captured_round_graphs"] > 0
    assert "captured_round_graphs" not in plain
    assert captured["contacts"] == plain["contacts"] > 0
    assert captured["state_sha256"] == plain["state_sha256"]
    with pytest.raises(ValueError, match="capture_rounds=True needs differentiable=False"):
        ImpulseCollisionHandler(build_model(module.build, default_args()), differentiable=True, capture_rounds=True)
