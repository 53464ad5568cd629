"""Sphere bodies: closed-form physics of their contacts, their gradients and lifted sphere events.

Ground truth is closed-form mechanics (impulses along the line of centres, the time of impact
from the quadratic solved in mpmath at 50 digits) and central finite differences of the same
forward, never the code under test.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import torch

from sim.builder import ModelBuilder
from sim.events import SphereEvent, sphere_event_roots
from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.rollout import rollout

R = 0.03


def _model(balls, restitution=1.0, friction=0.0, gravity=0.0, plane=False, thickness=0.0):
    b = ModelBuilder(gravity=gravity)
    b.set_contact(restitution=restitution, friction=friction, thickness=thickness)
    for pos, vel, *mass in balls:
        b.add_sphere(R, mass=mass[0] if mass else 1.0, pos=pos, velocity=vel)
    if plane:
        b.add_ground_plane()
    return b.finalize()


def _run(model, steps, dt, substeps=1):
    integ = SemiImplicitIntegrator(model)
    s0, s1 = model.state(), model.state()
    for _ in range(steps):
        integ.step(s0, s1, dt, substeps)
        s0, s1 = s1, s0
    return s0, integ


def test_equal_masses_elastic_head_on_swap_velocities():
    m = _model([((0, 0, 0), (1.0, 0, 0)), ((0.2, 0, 0), (0, 0, 0))])
    s, _ = _run(m, 100, 0.003)
    qd = s.body_qd.numpy()
    assert np.allclose(qd[0], 0.0, atol=1e-15) and np.allclose(qd[1], [0, 0, 0, 1.0, 0, 0], atol=1e-15)
    # the cue stops where it touches (0.14 m) and the struck ball travels the rest of the 0.3 s
    assert abs(s.body_q.numpy()[0, 0] - 0.14) < 1e-14 and abs(s.body_q.numpy()[1, 0] - 0.36) < 1e-14


@pytest.mark.parametrize("restitution", [0.0, 0.5, 1.0])
def test_oblique_impact_closed_form(restitution):
    """One substep with an oblique impact: the time of impact of the quadratic, the normal
    relative velocity times -e, the tangential one kept, momentum kept, and the
    time-of-impact positions, against mpmath."""
    h = 0.01
    x_a, v_a, x_b = np.array([0.0, 0, 0]), np.array([5.0, 0.5, 0]), np.array([0.08, 0.02, 0])
    m = _model([(x_a, v_a, 1.0), (x_b, (0, 0, 0), 3.0)], restitution=restitution)
    s, _ = _run(m, 1, h)
    mpmath.mp.dps = 50
    d0 = [mpmath.mpf(float(a)) - mpmath.mpf(float(b)) for a, b in zip(x_a, x_b)]
    dv = [mpmath.mpf(float(c)) for c in v_a]
    a = sum(c * c for c in dv)
    b = 2 * sum(p * q for p, q in zip(d0, dv))
    c = sum(p * p for p in d0) - mpmath.mpf(2 * R) ** 2
    toi = (-b - mpmath.sqrt(b * b - 4 * a * c)) / (2 * a)
    n = np.array([float((p + toi * q) / (2 * R)) for p, q in zip(d0, dv)])
    vn = float(np.dot(n, v_a))
    j = -(1 + restitution) * vn / (1.0 + 1.0 / 3.0)
    va_after, vb_after = v_a + j * n, -j * n / 3.0
    qd = s.body_qd.numpy()
    assert np.allclose(qd[0, 3:], va_after, rtol=0, atol=1e-14) and np.allclose(qd[1, 3:], vb_after, atol=1e-14)
    rel_before, rel_after = v_a, qd[0, 3:] - qd[1, 3:]
    assert abs(np.dot(n, rel_after) + restitution * np.dot(n, rel_before)) < 1e-13
    assert np.allclose(rel_after - np.dot(n, rel_after) * n, rel_before - np.dot(n, rel_before) * n, atol=1e-14)
    assert np.allclose(qd[0, 3:] * 1.0 + qd[1, 3:] * 3.0, v_a, atol=1e-15)
    rest = h - float(toi)
    q = s.body_q.numpy()
    assert np.allclose(q[0, :3], x_a + h * v_a + rest * (va_after - v_a), atol=1e-15)
    assert np.allclose(q[1, :3], x_b + rest * vb_after, atol=1e-15)


@pytest.mark.parametrize("restitution,friction", [(0.0, 0.5), (0.5, 0.5), (0.8, 0.0)])
def test_ball_resting_on_a_plane_stays_put(restitution, friction):
    m = _model([((0.2, 0.1, R), (0, 0, 0))], restitution=restitution, friction=friction, gravity=-9.81, plane=True)
    s, _ = _run(m, 120, 1 / 60, 8)
    q, qd = s.body_q.numpy()[0], s.body_qd.numpy()[0]
    assert abs(q[2] - R) < 1e-12 and np.allclose(q[:2], (0.2, 0.1), atol=0) and np.abs(qd).max() < 1e-12


def test_dropped_ball_bounces_to_e_squared_of_its_height():
    """A ball dropped from 1 m with restitution 0.5 rises to 0.25 m (exact bounce law of the
    particles' plane model; the semi-implicit positions are first order, 8 substeps of 1/60 s)."""
    e = 0.5
    m = _model([((0, 0, 1.0 + R), (0, 0, 0))], restitution=e, friction=0.0, gravity=-9.81, plane=True)
    integ = SemiImplicitIntegrator(m)
    s0, s1 = m.state(), m.state()
    heights, rising = [], []
    for _ in range(60):
        integ.step(s0, s1, 1 / 60, 8)
        s0, s1 = s1, s0
        heights.append(s0.body_q.numpy()[0, 2] - R)
        rising.append(s0.body_qd.numpy()[0, 5] > 0.0)
    bounce = rising.index(True)
    apex = max(heights[bounce:bounce + 30])  # the first flight after the bounce (0.45 s up)
    assert abs(apex / 1.0 - e * e) < 0.02


def test_sliding_ball_on_a_rough_plane_starts_rolling():
    """A ball sliding at v0 without spin on a plane with friction ends rolling at 5/7 v0 (the
    angular momentum about the contact point is kept)."""
    m = _model([((0, 0, R), (1.0, 0, 0))], restitution=0.0, friction=0.3, gravity=-9.81, plane=True)
    s, _ = _run(m, 60, 1 / 60, 8)
    qd = s.body_qd.numpy()[0]
    assert abs(qd[3] - 5.0 / 7.0) < 1e-9
    assert abs(qd[1] * R - qd[3]) < 1e-9  # rolling: w_y r = v_x


def test_break_keeps_momentum_and_no_interpenetration():
    """A sample of the random breaks of benchmarks/billiards.py: momentum to rounding, and no
    pair overlaps beyond rounding at any step."""
    from scenes import billiards as B

    model = B.build()
    rng = np.random.default_rng(7)
    shots = []
    for _ in range(2):
        y, speed = rng.uniform(0.45, 0.55), rng.uniform(1.0, 3.0)
        angle = math.atan2(0.55 - y, 0.5) + rng.uniform(-0.05, 0.05)  # at the rack
        shots.append((0.1, y, speed * math.cos(angle), speed * math.sin(angle)))
    # a break in which two balls' contacts with others shifted them into each other while they
    # separated (9.7e-5 m deep at step 112 before such pairs were pushed apart)
    shots.append((0.1, 0.5160664771973701, 1.240239814019412, 0.12714817841606138))
    for shot in shots:
        _, res = B.simulate(model, shot)
        q, qd = res.body_q.numpy()[:, :, :2], res.body_qd.numpy()[:, :, 3:5]
        gaps = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1) - 2 * R
        gaps[:, np.arange(11), np.arange(11)] = np.inf
        assert gaps.min() > -1e-12
        momentum = qd.sum(axis=1)
        assert np.abs(momentum - momentum[0]).max() < 1e-14
        assert np.any(qd[-1, 1:] != 0.0)  # the break happened


def _shot_loss(model, shot, steps, target=1):
    bq = torch.from_numpy(model.body_q.numpy().copy())
    bqd = torch.from_numpy(model.body_qd.numpy().copy())
    z = shot
    zero = torch.zeros(1, dtype=torch.float64)
    body_q = torch.cat([torch.cat([z[:2], zero, bq[0, 3:]])[None], bq[1:]])
    body_qd = torch.cat([torch.cat([zero, zero, zero, z[2:], zero])[None], bqd[1:]])
    res = rollout(model, steps, 0.003, 1, body_q=body_q, body_qd=body_qd)
    return ((res.body_q[-1, target, :2] - torch.tensor([0.9, 0.75], dtype=torch.float64)) ** 2).sum()


def test_gradient_through_a_hit_equals_central_differences():
    """The cue's initial position and velocity -> a struck ball's final distance to a goal,
    through an oblique impact and a second one: rollout backward against central differences
    (step 1e-6) to 1e-6 relative."""
    model = _model([((0.1, 0.5, 0), (0.3, 0, 0)), ((0.4, 0.52, 0), (0, 0, 0)), ((0.6, 0.56, 0), (0, 0, 0))],
                   restitution=0.8)
    start = torch.tensor([0.1, 0.5, 0.3, 0.0], dtype=torch.float64)
    z = start.clone().requires_grad_()
    loss = _shot_loss(model, z, 1000, target=2)
    loss.backward()
    numeric = np.zeros(4)
    for k in range(4):
        e = torch.zeros(4, dtype=torch.float64)
        e[k] = 1e-6
        with torch.no_grad():
            numeric[k] = float(_shot_loss(model, start + e, 1000, 2) - _shot_loss(model, start - e, 1000, 2)) / 2e-6
    assert np.all(numeric != 0.0)  # both impacts happen: every component matters
    assert np.linalg.norm(z.grad.numpy() - numeric) / np.linalg.norm(numeric) < 1e-6


def test_grazing_sweep_gradient_is_finite():
    """Closest approaches from 0.9 to 1.1 x 2 r: the struck ball's final position's gradient is
    finite everywhere (bounded by the mollified derivative at the grazing contact)."""
    for offset in np.linspace(0.9, 1.1, 9) * 2 * R:
        model = _model([((0.0, 0.0, 0), (1.0, 0, 0)), ((0.2, offset, 0), (0, 0, 0))])
        bqd = torch.from_numpy(model.body_qd.numpy().copy()).requires_grad_()
        res = rollout(model, 100, 0.003, 1, body_qd=bqd)
        res.body_q[-1, 1, :2].sum().backward()
        assert torch.isfinite(bqd.grad).all()


def _mp_quadratic_roots(a, b, c):
    a, b, c = (mpmath.mpf(float(x)) for x in (a, b, c))
    disc = b * b - 4 * a * c
    s = mpmath.sqrt(disc) if disc >= 0 else mpmath.sqrt(-disc) * 1j
    return sorted([(-b - s) / (2 * a), (-b + s) / (2 * a)], key=lambda r: (mpmath.re(r), mpmath.im(r)))


@pytest.mark.parametrize("vy,tolerance", [(0.1, 1e-12), (0.0, 1e-12), (-0.25, 1e-12)])
def test_lifted_sphere_event_roots_equal_the_closed_form(vy, tolerance):
    """The event's roots against the quadratic of the same window positions in mpmath (50 digits)."""
    mpmath.mp.dps = 50
    model = _model([((0.1, 0.5, 0), (0.3, vy, 0)), ((0.5, 0.5, 0), (0, 0, 0))])
    res = rollout(model, 100, 0.003, 1, events=[SphereEvent(0, 1, (0, 100))])
    q = res.body_q.numpy()
    d_first = [mpmath.mpf(float(x)) for x in q[0, 0, :3] - q[0, 1, :3]]
    d_last = [mpmath.mpf(float(x)) for x in q[100, 0, :3] - q[100, 1, :3]]
    delta = [p - f for p, f in zip(d_last, d_first)]
    a = sum(x * x for x in delta)
    b = 2 * sum(x * y for x, y in zip(d_first, delta))
    c = sum(x * x for x in d_first) - mpmath.mpf(2 * R) ** 2
    roots = [mpmath.mpc(r) * mpmath.mpf(0.3) for r in _mp_quadratic_roots(a, b, c)]
    got = res.sphere_event_roots[0].numpy()
    for slot, exact in enumerate(sorted(roots, key=lambda r: float(mpmath.im(r)))):
        scale = float(abs(exact))
        assert abs(got[slot, 0] - float(mpmath.re(exact))) <= tolerance * scale
        assert abs(got[slot, 1] - float(mpmath.im(exact))) <= tolerance * scale


def test_lifted_sphere_event_roots_near_a_double_root():
    """A path whose closest approach is within 1e-6 of touching (nearly a double root): the roots
    equal the closed form to 1e-8 relative."""
    mpmath.mp.dps = 50
    model = _model([((0.1, 0.5, 0), (0.3, 0, 0)), ((0.5, 0.5 + 2 * R * (1 + 1e-6), 0), (0, 0, 0))])
    q = torch.from_numpy(np.stack([model.body_q.numpy(), model.body_q.numpy()]))
    q[1, 0, 0] += 0.3
    roots = sphere_event_roots(model, [SphereEvent(0, 1, (0, 1))], q, 1.0)[0].numpy()
    d0 = q[0, 0, :3].numpy() - q[0, 1, :3].numpy()
    a, b = 0.09, 2 * 0.3 * mpmath.mpf(float(d0[0]))
    c = mpmath.mpf(float(d0[0])) ** 2 + mpmath.mpf(float(d0[1])) ** 2 - mpmath.mpf(2 * R) ** 2
    exact = _mp_quadratic_roots(a, b, c)
    for slot in range(2):
        assert abs(complex(exact[slot]) - complex(*roots[slot])) <= 1e-8 * abs(complex(exact[slot]))


def test_lifted_sphere_event_pulls_a_miss_together():
    """From a miss the event's imaginary part has a gradient w.r.t. the cue's velocity that
    closes the gap (the real contacts' gradient is exactly zero there)."""
    model = _model([((0.1, 0.5, 0), (0.3, 0.1, 0)), ((0.5, 0.5, 0), (0, 0, 0))])
    bqd = torch.from_numpy(model.body_qd.numpy().copy()).requires_grad_()
    res = rollout(model, 100, 0.003, 1, body_qd=bqd, events=[SphereEvent(0, 1, (0, 100))])
    im = res.sphere_event_roots[0, 1, 1]
    assert float(im.detach()) > 0.0
    im.backward()
    assert float(bqd.grad[0, 4]) > 0.0  # less upward velocity: nearer the ball
    bqd.grad = None
    res = rollout(model, 100, 0.003, 1, body_qd=bqd)
    res.body_q[-1, 1, 0].backward()
    assert float(bqd.grad[0].abs().sum()) == 0.0  # the miss: no gradient w.r.t. the cue


def test_rollout_differentiates_the_initial_poses():
    model = _model([((0.0, 0.0, 0), (0.5, 0.2, 0))])
    bq = torch.from_numpy(model.body_q.numpy().copy()).requires_grad_()
    res = rollout(model, 10, 0.01, 1, body_q=bq)
    res.body_q[-1, 0, :3].sum().backward()
    assert np.allclose(bq.grad.numpy()[0], [1, 1, 1, 0, 0, 0, 0])


def test_rollout_checks_the_initial_poses():
    model = _model([((0.0, 0.0, 0), (0.5, 0.2, 0))])
    with pytest.raises(ValueError, match="body_q.*unit quaternion"):
        rollout(model, 2, 0.01, body_q=torch.tensor([[0, 0, 0, 0, 0, 0, 2.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="body_q must have shape"):
        rollout(model, 2, 0.01, body_q=torch.zeros((2, 7), dtype=torch.float64))


def test_sphere_events_are_checked():
    model = _model([((0.0, 0.0, 0), (0.5, 0.2, 0)), ((0.5, 0, 0), (0, 0, 0))])
    with pytest.raises(ValueError, match=r"events\[0\].body_b must be the body index of a sphere"):
        rollout(model, 2, 0.01, events=[SphereEvent(0, 5, (0, 2))])
    with pytest.raises(ValueError, match="two different spheres"):
        rollout(model, 2, 0.01, events=[SphereEvent(1, 1, (0, 2))])
    with pytest.raises(ValueError, match="window"):
        rollout(model, 2, 0.01, events=[SphereEvent(0, 1, (0, 3))])


def test_builder_validates_spheres():
    b = ModelBuilder()
    with pytest.raises(ValueError, match="radius"):
        b.add_sphere(0.0, mass=1.0)
    with pytest.raises(ValueError, match="exactly one of density"):
        b.add_sphere(0.1, mass=1.0, density=2.0)
    with pytest.raises(ValueError, match="exactly one of density"):
        b.add_sphere(0.1)
    with pytest.raises(ValueError, match="velocity"):
        b.add_sphere(0.1, mass=1.0, velocity=(np.nan, 0, 0))
    b.add_sphere(0.1, mass=1.0)
    b.add_sphere(0.1, mass=1.0, pos=(0.15, 0, 0))
    with pytest.raises(ValueError, match="spheres 0 and 1 overlap by 0.05 m"):
        b.finalize()
    from sim.mesh_io import box_mesh

    c = ModelBuilder()
    c.add_sphere(0.1, density=1000.0)
    c.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(1, 0, 0))
    with pytest.raises(ValueError, match="spheres collide with each other, ground planes and static meshes only.*rigid meshes"):
        c.finalize()
    d = ModelBuilder()
    d.add_sphere(0.1, density=1000.0)
    model = d.finalize()
    assert abs(model.body_mass.numpy()[0] - 1000.0 * 4 / 3 * math.pi * 1e-3) < 1e-12
    assert np.allclose(model.body_inertia.numpy()[0], np.eye(3) * 0.4 * model.body_mass.numpy()[0] * 0.01)
    assert np.allclose(model.scaled(2.0).sphere_radius.numpy(), [0.2])


def test_implicit_integrator_refuses_spheres():
    from sim.integrators.implicit import ImplicitIntegrator

    with pytest.raises(ValueError, match="spheres"):
        ImplicitIntegrator(_model([((0, 0, 0), (0, 0, 0))]))


def _box_run(pos, vel, gravity=0.0, restitution=1.0, friction=0.0, steps=60):
    from sim.mesh_io import box_mesh

    b = ModelBuilder(gravity=gravity)
    b.set_contact(restitution=restitution, friction=friction, thickness=0.0)
    b.add_sphere(0.05, mass=1.0, pos=pos, velocity=vel)
    b.add_static_mesh(*box_mesh((0.2, 0.2, 0.2)))
    s, _ = _run(b.finalize(), steps, 1 / 60, 8)
    return s.body_q.numpy()[0, :3], s.body_qd.numpy()[0]


@pytest.mark.parametrize("feature,direction", [("face", (1, 0, 0)), ("edge", (1, 1, 0)), ("corner", (1, 1, 1))])
def test_sphere_bounces_off_a_static_box_feature(feature, direction):
    """A sphere (r 0.05 m) at 1 m/s per axis towards a static box (half extent 0.2 m) hits its
    face, an edge or a corner head on and is reflected along that feature's normal: the end
    position after 1 s in closed form (contact when the centre is r from the feature)."""
    d = np.asarray(direction, dtype=np.float64)
    k = d.sum()  # axes moving
    start = -0.5 * d
    q, qd = _box_run(start, d)
    t_hit = 0.3 - 0.05 / math.sqrt(k)  # the centre's distance from the feature is sqrt(k) (0.3 - t)
    expected = (-0.2 - 0.05 / math.sqrt(k)) * d - (1.0 - t_hit) * d
    assert np.allclose(q, expected, atol=1e-12) and np.allclose(qd[3:], -d, atol=1e-12)
    assert np.allclose(qd[:3], 0.0)


def test_sphere_rests_on_a_static_box():
    q, qd = _box_run((0.05, -0.03, 0.25), (0, 0, 0), gravity=-9.81, restitution=0.5, friction=0.5)
    assert np.allclose(q, (0.05, -0.03, 0.25), atol=1e-12) and np.abs(qd).max() < 1e-12


def test_gradient_through_an_edge_hit_equals_central_differences():
    from sim.mesh_io import box_mesh

    b = ModelBuilder(gravity=0.0)
    b.set_contact(restitution=0.7, friction=0.0, thickness=0.0)
    b.add_sphere(0.05, mass=1.0, pos=(-0.5, -0.47, 0.01), velocity=(1.0, 0.9, 0.0))
    b.add_static_mesh(*box_mesh((0.2, 0.2, 0.2)))
    model = b.finalize()

    def end(v):
        bqd = torch.zeros((1, 6), dtype=torch.float64)
        bqd = bqd + torch.nn.functional.pad(v, (3, 0))[None]
        return rollout(model, 40, 1 / 60, 4, body_qd=bqd).body_q[-1, 0, :3].sum()

    v0 = torch.tensor([1.0, 0.9, 0.1], dtype=torch.float64)
    v = v0.clone().requires_grad_()
    end(v).backward()
    numeric = np.array([float(end(v0 + e) - end(v0 - e)) / 2e-6 for e in torch.eye(3, dtype=torch.float64) * 1e-6])
    assert np.linalg.norm(v.grad.numpy() - numeric) / np.linalg.norm(numeric) < 1e-6


@pytest.mark.parametrize("restitution", [0.0, 0.8, 1.0])
def test_glancing_impact_is_one_impulse(restitution):
    """A grazing hit (closest approach 0.99999 x 2 r): the struck ball's velocity in closed form
    (a single impulse along the normal at contact), in one pass per substep."""
    off = 0.99999 * 2 * R
    m = _model([((0, 0, 0), (0.3, 0, 0)), ((0.2, off, 0), (0, 0, 0))], restitution=restitution)
    s, integ = _run(m, 300, 0.003)
    n = np.array([-math.sqrt(4 * R * R - off * off), -off, 0.0]) / (2 * R)
    j = -(1 + restitution) * float(n @ np.array([0.3, 0, 0])) / 2.0
    assert np.allclose(s.body_qd.numpy()[1, 3:], -j * n, rtol=1e-9, atol=1e-18)
    assert integ.sphere_contacts.unresolved_substeps == 0


def test_elastic_cradle_passes_the_momentum_down_the_row():
    """A ball at 1 m/s into a row of 10 touching balls, e = 1: the last ball leaves at 1 m/s
    and the others stop (the contacts resolved pass by pass down the row, no overlap)."""
    m = _model([((0, 0, 0), (1.0, 0, 0))] + [((0.2 + 2 * R * k, 0, 0), (0, 0, 0)) for k in range(10)])
    s, integ = _run(m, 300, 0.003)
    qd = s.body_qd.numpy()[:, 3]
    assert np.allclose(qd[:-1], 0.0, atol=1e-12) and abs(qd[-1] - 1.0) < 1e-12
    assert np.diff(s.body_q.numpy()[:, 0]).min() - 2 * R > -1e-12
    assert integ.sphere_contacts.unresolved_substeps == 0
