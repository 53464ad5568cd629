"""Lifted events (``sim.events``, ``rollout(..., events=...)``).

Ground truth: mpmath at 50 digits — the roots of the coplanarity cubic built from the event's
vertex positions at the window's ends, and central finite differences of those roots (step
1e-20) w.r.t. the particle's initial velocity (free flight, no gravity: its position at a step is
exactly ``x0 + v t``; the body's vertices do not depend on it).
"""

import mpmath as mp
import numpy as np
import pytest
import torch

from collision.roots import cubic_roots
from sim.builder import ModelBuilder
from sim.events import BranchTracker, Event, body_vertex, particle, root_loss
from sim.mesh_io import box_mesh
from sim.rollout import rollout

DT = 1.0 / 60.0
STEPS = 20


def _model():
    b = ModelBuilder(gravity=0.0)
    b.add_particle((0.05, -0.6, 0.3), mass=0.01)
    b.add_rigid_body(*box_mesh(0.2), density=100.0, angular_velocity=(0.3, 0.2, 2.0))
    return b.finalize()


def _face_event(model, window=(0, STEPS)):
    face = model.shape_faces.numpy().reshape(-1, 3)[0]
    return Event("vertex_face", (particle(0),) + tuple(body_vertex(0, int(k)) for k in face), window)


def _mp_roots(xa, xb):
    """Roots in fractions of the window (mpmath, 50 digits) of the cubic of x(s) = xa + s (xb - xa)."""
    xa = [[c if isinstance(c, mp.mpf) else mp.mpf(float(c)) for c in row] for row in xa]
    xb = [[c if isinstance(c, mp.mpf) else mp.mpf(float(c)) for c in row] for row in xb]

    def volume(s):
        p = [[xa[i][k] + s * (xb[i][k] - xa[i][k]) for k in range(3)] for i in range(4)]
        d = [[p[j][k] - p[0][k] for k in range(3)] for j in (1, 2, 3)]
        return mp.det(mp.matrix(d))

    # the cubic through four samples (exact: it is a cubic)
    s = [mp.mpf(k) for k in (0, 1, 2, 3)]
    v = [volume(x) for x in s]
    coeffs = mp.lu_solve(mp.matrix([[x**3, x**2, x, 1] for x in s]), mp.matrix(v))
    return mp.polyroots([coeffs[0], coeffs[1], coeffs[2], coeffs[3]], maxsteps=200, extraprec=200)


def test_event_roots_match_mpmath_roots_of_the_linearised_cubic():
    mp.mp.dps = 50
    model = _model()
    event = _face_event(model)
    v = torch.tensor([[0.0, 1.0, -0.2]], dtype=torch.float64)
    res = rollout(model, STEPS, DT, 1, particle_qd=v, events=[event])
    from sim.events import event_positions

    xa, xb = event_positions(model, [event], res.particle_q, res.body_q)
    expected = sorted((complex(r) for r in _mp_roots(xa[0].numpy(), xb[0].numpy())), key=lambda z: (z.real, z.imag))
    got = res.event_roots[0].numpy() / (STEPS * DT)
    got = sorted((complex(re, im) for re, im in got), key=lambda z: (z.real, z.imag))
    assert any(abs(g.imag) > 0 for g in got)  # this aim misses: a complex pair
    for g, e in zip(got, expected):
        assert abs(g - e) <= 1e-12 * max(1.0, abs(e))


def test_event_root_gradient_matches_high_precision_finite_differences():
    mp.mp.dps = 50
    model = _model()
    event = _face_event(model)
    v0 = np.array([0.0, 1.0, -0.2])
    v = torch.tensor(v0[None], dtype=torch.float64, requires_grad=True)
    res = rollout(model, STEPS, DT, 1, particle_qd=v, events=[event])
    from sim.events import event_positions

    xa, xb = event_positions(model, [event], res.particle_q, res.body_q)
    xa, xb = xa[0].detach().numpy(), xb[0].detach().numpy()
    T = STEPS * DT
    # the complex root with positive imaginary part, as (re, im) [s]
    slot = int(np.argmax(res.event_roots[0, :, 1].detach().numpy()))
    (res.event_roots[0, slot, 0] + 0.5 * res.event_roots[0, slot, 1]).backward()
    h = mp.mpf(10) ** -20
    fd = []
    for j in range(3):
        vals = []
        for sign in (1, -1):
            b = [[mp.mpf(float(c)) for c in row] for row in xb]
            b[0][j] += sign * h * T  # x_particle(T) = x0 + v T
            roots = _mp_roots(xa, b)
            r = max(roots, key=lambda z: mp.im(z))
            vals.append((mp.re(r) + mp.im(r) / 2) * T)
        fd.append(float((vals[0] - vals[1]) / (2 * h)))
    np.testing.assert_allclose(v.grad.numpy()[0], fd, rtol=1e-8, atol=1e-12)


def test_merging_roots_gradient_stays_bounded_by_M_times_the_coefficient_chain():
    """At (near) a double root the exact derivative blows up; the event's stays within
    ``M * max(1, |t|)^3 * sum_k |d p_k / d v|`` for the unit-scaled cubic."""
    p = torch.tensor([1.0, -2.0, 1.0 - 1e-14, 0.0], dtype=torch.float64, requires_grad=True)  # roots ~ 0, 1, 1
    roots = cubic_roots(p, max_derivative=1000.0)
    slot = int(torch.argmax(roots[:, 0]))
    roots[slot, 0].backward()
    assert torch.isfinite(p.grad).all()
    assert float(p.grad.abs().max()) <= 1000.0 * 1.0 + 1e-9
    p2 = p.detach().clone().requires_grad_()
    exact = cubic_roots(p2, max_derivative=1e300)
    exact[slot, 0].backward()
    assert float(p2.grad.abs().max()) > 1e5  # what the bound protects against


def test_branch_tracker_drives_the_bad_q_example_to_the_target():
    """Subsection "Examples" of the cubic: start t^2 - 1 = 0 ([q, a, b, c] = [0, 1, 0, -1]) whose
    escaping root is at -t_max, target t+ = 0.5, Adam (lr 0.1, M = 1000): converges."""
    p = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([p], lr=0.1)
    tracker = BranchTracker(2)
    for _ in range(300):
        opt.zero_grad()
        roots = cubic_roots(p, max_derivative=1000.0)
        root_loss(roots[tracker.update(roots)], (0.5, 0.0)).backward()
        opt.step()
    roots = cubic_roots(p.detach(), max_derivative=1000.0)
    slot = tracker.update(roots)
    assert abs(float(roots[slot, 0]) - 0.5) < 1e-6 and float(roots[slot, 1]) == 0.0


def test_branch_tracker_merge_split_and_escaping_sign_flip():
    # two real roots merge: the larger goes on as +Im, the smaller as -Im
    for slot, sign in ((2, 1.0), (1, -1.0)):
        tracker = BranchTracker(slot)
        tracker.update(np.array([[-1.0, 0.0], [0.30, 0.0], [0.35, 0.0]]))
        s = tracker.update(np.array([[-1.0, 0.0], [0.325, -0.01], [0.325, 0.01]]))
        assert np.sign([-0.01, 0.01][s - 1]) == sign
        # and the pair splits back: +Im -> the larger real root
        s = tracker.update(np.array([[-1.0, 0.0], [0.31, 0.0], [0.34, 0.0]]))
        assert s == slot
    # with a target time, a splitting pair goes on as the real root nearer the target
    for target, expected in ((0.0, 1), (1.0, 2)):
        tracker = BranchTracker(2)
        tracker.update(np.array([[-1.0, 0.0], [0.325, -0.01], [0.325, 0.01]]))
        assert tracker.update(np.array([[-1.0, 0.0], [0.31, 0.0], [0.34, 0.0]]), target=target) == expected
    # the escaping root changes sign (q crosses 0): followed into the other slot
    tracker = BranchTracker(2)
    tracker.update(np.array([[0.2, 0.0], [0.5, 0.0], [1e150, 0.0]]))
    assert tracker.update(np.array([[-1e150, 0.0], [0.2, 0.0], [0.5, 0.0]])) == 0
    with pytest.raises(ValueError, match="slot"):
        BranchTracker(3)


@pytest.mark.parametrize(
    "events, match",
    [
        ([("vf", 0, 0)], "events\\[0\\] must be a sim.events.Event"),
        ([Event("point_face", (particle(0),) * 4, (0, 1))], "kind"),
        ([Event("vertex_face", (particle(0), body_vertex(0, 0), body_vertex(0, 1), body_vertex(0, 99)), (0, 1))], "not a vertex"),
        ([Event("vertex_face", (particle(0), body_vertex(0, 0), body_vertex(0, 1), body_vertex(0, 2)), (3, 3))], "window"),
        ([Event("vertex_face", (particle(0), body_vertex(0, 0), body_vertex(0, 1), body_vertex(0, 2)), (0, STEPS + 1))], "window"),
    ],
)
def test_bad_events_raise_value_error_naming_the_event(events, match):
    with pytest.raises(ValueError, match=match):
        rollout(_model(), STEPS, DT, 1, events=events)


def test_orthogonal_event_derivative_in_the_rollout():
    """``rollout(..., event_derivative="orthogonal")``: the same roots; a complex root's
    gradient is the mollified one (the clamp is for real roots); an unknown name is refused."""
    model = _model()
    event = _face_event(model)
    grads, roots = [], []
    for derivative in ("mollified", "orthogonal"):
        v = torch.tensor([[0.0, 1.0, -0.2]], dtype=torch.float64, requires_grad=True)
        res = rollout(model, STEPS, DT, 1, particle_qd=v, events=[event], event_derivative=derivative)
        slot = int(np.argmax(res.event_roots[0, :, 1].detach().numpy()))
        res.event_roots[0, slot, 1].backward()
        grads.append(v.grad.numpy().copy())
        roots.append(res.event_roots.detach().numpy())
    np.testing.assert_allclose(roots[1], roots[0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-10, atol=1e-14)
    with pytest.raises(ValueError, match="event_derivative"):
        rollout(model, STEPS, DT, 1, events=[event], event_derivative="clamped")


def test_branch_tracker_keeps_a_real_root_real_while_no_pair_merges():
    """A real root running off towards infinity (q -> 0) is nearer the complex pair than its own
    next value; with the count of real roots unchanged it cannot have joined the pair."""
    tracker = BranchTracker(2)
    tracker.update(np.array([[-0.066, -0.875], [-0.066, 0.875], [7.10, 0.0]]))
    assert tracker.update(np.array([[-0.062, -0.888], [-0.062, 0.888], [56.6, 0.0]])) == 2
    # a real pair merging into a complex one is still followed (the count changes)
    tracker = BranchTracker(2)
    tracker.update(np.array([[-1.0, 0.0], [0.9, 0.0], [1.1, 0.0]]))
    assert tracker.update(np.array([[-1.0, 0.0], [1.0, -0.05], [1.0, 0.05]])) == 2


def test_branch_tracker_follows_a_real_root_past_the_escaping_bound():
    """The only real root runs past 1e100 (q -> 0) while a complex pair stays: still the real root."""
    tracker = BranchTracker(2)
    tracker.update(np.array([[-0.06, -0.9], [-0.06, 0.9], [1e90, 0.0]]))
    assert tracker.update(np.array([[-0.06, -0.9], [-0.06, 0.9], [2e100, 0.0]])) == 2
