"""Semi-implicit Euler stepper (sim.integrators.semi_implicit): gradients through a plane bounce, closed-form
physics, determinism.

Models are built here by filling :class:`sim.model.Model` with Warp arrays directly (no builder),
so these tests only depend on the stepper and its kernels.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.model import Model, State

wp.init()

G = np.array([0.0, 0.0, -9.81])

# Central finite differences of the float64 rollout: truncation O(h^2 |x'''|) and rounding
# O(eps |x| / h) ~ 1e-10 at h = 1e-6, so 1e-6 relative agreement (the bar) has margin.
FD_STEP = 1e-6
FD_RTOL = 1e-6


# ----------------------------------------------------------------------------- model helpers
def _quat_from_axis_angle(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([axis * math.sin(angle / 2), [math.cos(angle / 2)]])


def _rotation(q):
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def make_model(
    q=None,
    qd=None,
    mass=None,
    springs=None,
    rest=None,
    stiffness=0.0,
    damping=0.0,
    planes=None,
    gravity=G,
    restitution=0.0,
    friction=0.0,
    bodies=None,
) -> Model:
    """A Model from numpy data. ``bodies``: list of dicts (p, rot, w, v, mass, inertia)."""
    m = Model(device="cpu", gravity=np.asarray(gravity, dtype=np.float64), restitution=restitution, friction=friction)
    if q is not None:
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n = len(q)
        qd = np.zeros_like(q) if qd is None else np.atleast_2d(np.asarray(qd, dtype=np.float64))
        mass = np.ones(n) if mass is None else np.asarray(mass, dtype=np.float64)
        inv = np.where(mass > 0, 1.0 / np.where(mass > 0, mass, 1.0), 0.0)
        m.particle_count = n
        m.particle_q = wp.array(q, dtype=wp.vec3d)
        m.particle_qd = wp.array(qd, dtype=wp.vec3d)
        m.particle_mass = wp.array(mass, dtype=wp.float64)
        m.particle_inv_mass = wp.array(inv, dtype=wp.float64)
        m.components = frozenset({"cloth"})
    if springs is not None and len(springs):
        springs = np.asarray(springs, dtype=np.int32).reshape(-1, 2)
        s = len(springs)
        if rest is None:
            rest = np.linalg.norm(q[springs[:, 0]] - q[springs[:, 1]], axis=1)
        m.spring_count = s
        m.spring_indices = wp.array(springs, dtype=wp.int32)
        m.spring_rest_length = wp.array(np.broadcast_to(rest, (s,)).astype(np.float64), dtype=wp.float64)
        m.spring_stiffness = wp.array(np.full(s, stiffness, dtype=np.float64), dtype=wp.float64)
        m.spring_damping = wp.array(np.full(s, damping, dtype=np.float64), dtype=wp.float64)
    if planes is not None and len(planes):
        planes = np.atleast_2d(np.asarray(planes, dtype=np.float64))
        m.plane_count = len(planes)
        m.planes = wp.array(planes, dtype=wp.vec4d)
        m.components = m.components | {"static"}
    if bodies:
        poses = np.array([np.concatenate([b["p"], b.get("rot", [0, 0, 0, 1])]) for b in bodies], dtype=np.float64)
        twists = np.array([np.concatenate([b.get("w", np.zeros(3)), b.get("v", np.zeros(3))]) for b in bodies])
        masses = np.array([b["mass"] for b in bodies], dtype=np.float64)
        inertia = np.array([b["inertia"] for b in bodies], dtype=np.float64)
        m.body_count = len(bodies)
        m.body_q = wp.array(poses, dtype=wp.transformd)
        m.body_qd = wp.array(twists, dtype=wp.spatial_vectord)
        m.body_mass = wp.array(masses, dtype=wp.float64)
        m.body_inv_mass = wp.array(1.0 / masses, dtype=wp.float64)
        m.body_inertia = wp.array(inertia, dtype=wp.mat33d)
        m.body_inv_inertia = wp.array(np.linalg.inv(inertia), dtype=wp.mat33d)
        m.components = m.components | {"rigid"}
    return m


def rollout(model, steps, dt, substeps=1, qd0=None, requires_grad=False, handler=None):
    """Runs ``steps`` steps; returns (integrator, list of States)."""
    integ = SemiImplicitIntegrator(model)
    integ.collision_handler = handler
    s0 = model.state(requires_grad=requires_grad)
    if qd0 is not None:
        s0.particle_qd = wp.array(np.atleast_2d(qd0), dtype=wp.vec3d, requires_grad=requires_grad)
    states = [s0]
    for _ in range(steps):
        s1 = model.state(requires_grad=requires_grad)
        integ.step(states[-1], s1, dt, substeps)
        states.append(s1)
    return integ, states


# ----------------------------------------------------------------------------- (a) bounce gradients
GROUND = [0.0, 0.0, 1.0, 0.0]  # z >= 0 is outside


def _bounce_model(x0, restitution=0.5, friction=0.0):
    return make_model(q=[x0], planes=[GROUND], restitution=restitution, friction=friction)


def _final_position(model, v0, steps, dt, substeps):
    _, states = rollout(model, steps, dt, substeps, qd0=v0)
    return states[-1].particle_q.numpy()[0]


def _tape_jacobian(model, v0, steps, dt, substeps):
    """d x_final / d v0 (3x3) from wp.Tape, one backward pass per output component."""
    tape = wp.Tape()
    with tape:
        _, states = rollout(model, steps, dt, substeps, qd0=v0, requires_grad=True)
    out = states[-1].particle_q
    jac = np.zeros((3, 3))
    for i in range(3):
        seed = np.zeros((1, 3))
        seed[0, i] = 1.0
        tape.backward(grads={out: wp.array(seed, dtype=wp.vec3d)})
        jac[i] = states[0].particle_qd.grad.numpy()[0]
        tape.zero()
    return jac, states


def _fd_jacobian(model, v0, steps, dt, substeps, h=FD_STEP):
    jac = np.zeros((3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        xp = _final_position(model, v0 + e, steps, dt, substeps)
        xm = _final_position(model, v0 - e, steps, dt, substeps)
        jac[:, j] = (xp - xm) / (2 * h)
    return jac


def _count_bounces(states):
    vz = np.array([s.particle_qd.numpy()[0, 2] for s in states])
    return int(np.sum((vz[:-1] < 0) & (vz[1:] > 0)))


def _rel_err(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("friction", [0.0, 0.2])
def test_bounce_gradient_matches_finite_differences(friction):
    """The issue's test: a particle thrown at the ground bounces once (e = 0.5); d x(T) / d v0
    from the tape over 20 steps x 4 substeps equals central finite differences of the whole
    rollout. ``t*`` depends on ``v0``, so the time-of-impact path must carry it (treating
    ``t*`` as a constant would change ``d z / d vz`` by order 1)."""
    model = _bounce_model([0.0, 0.0, 1.0], friction=friction)
    v0 = np.array([1.0, 0.5, -3.0])
    steps, dt, substeps = 20, 1.0 / 60.0, 4
    jac, states = _tape_jacobian(model, v0, steps, dt, substeps)
    assert _count_bounces(states) == 1
    assert states[-1].particle_q.numpy()[0, 2] > 0.0
    fd = _fd_jacobian(model, v0, steps, dt, substeps)
    assert np.all(np.isfinite(jac))
    assert _rel_err(jac, fd) < FD_RTOL, (jac, fd)
    # the impact makes d z / d vz differ from the free-flight value T: the bounce is in the gradient
    assert abs(jac[2, 2] - steps * dt) > 0.05


def _mid_substep_start_height(vz0, h, k_hit):
    """Start height so that the (0-based) substep ``k_hit`` crosses z = 0 at exactly h/2
    (semi-implicit Euler: ``v_k = vz0 + (k+1) g h``, ``z_{k+1} = z_k + h v_k``)."""
    vs = vz0 + (np.arange(k_hit + 1) + 1) * G[2] * h
    return -(h * np.sum(vs[:k_hit]) + 0.5 * h * vs[k_hit])


def test_bounce_exactly_mid_substep_gradient():
    steps, substeps = 12, 4
    h = 1.0 / 256.0  # substep, a power of two
    dt = h * substeps
    k_hit = 21  # 6th step, 2nd substep
    v0 = np.array([0.75, -0.25, -2.0])
    z0 = _mid_substep_start_height(v0[2], h, k_hit)
    model = _bounce_model([0.0, 0.0, z0])

    # check the construction: substep k_hit starts above the ground and its predicted motion
    # reaches it at half the substep
    _, sub = rollout(model, steps * substeps, h, 1, qd0=v0)
    z_k = sub[k_hit].particle_q.numpy()[0, 2]
    vz_k = sub[k_hit].particle_qd.numpy()[0, 2] + G[2] * h
    assert z_k > 0.0
    assert abs(-z_k / vz_k / h - 0.5) < 1e-12
    assert _count_bounces(sub) == 1

    jac, states = _tape_jacobian(model, v0, steps, dt, substeps)
    fd = _fd_jacobian(model, v0, steps, dt, substeps)
    # substeps inside step() and single-substep steps are the same arithmetic
    np.testing.assert_array_equal(states[-1].particle_q.numpy(), sub[-1].particle_q.numpy())
    assert _rel_err(jac, fd) < FD_RTOL, (jac, fd)


def test_plane_toi_position_closed_form():
    """One substep through the plane: x = x0 + t* v + (dt - t*) v+, v+ = v - (1+e)(n.v) n."""
    e = 0.5
    x0 = np.array([0.1, 0.2, 0.05])
    v = np.array([0.3, -0.1, -1.0])
    model = _bounce_model(x0, restitution=e)
    model.gravity = np.zeros(3)
    _, states = rollout(model, 1, 0.1, 1, qd0=v)
    t = 0.05 / 1.0
    vp = v.copy()
    vp[2] = e * 1.0
    np.testing.assert_allclose(states[-1].particle_q.numpy()[0], x0 + t * v + (0.1 - t) * vp, rtol=0, atol=1e-15)
    np.testing.assert_allclose(states[-1].particle_qd.numpy()[0], vp, rtol=0, atol=1e-15)


# ----------------------------------------------------------------------------- (b) physics
def test_free_fall_matches_recurrence_exactly_and_converges_first_order():
    x0 = np.array([0.5, -1.0, 2.0])
    v0 = np.array([1.0, 0.25, 3.0])
    T = 0.5
    errors = []
    for n in (50, 100, 200):
        h = T / n
        model = make_model(q=[x0], qd=[v0])
        _, states = rollout(model, n // 10, h * 10, 10)
        x, v = x0.copy(), v0.copy()
        for _ in range(n):
            v = v + (np.zeros(3) * 1.0 + G) * h
            x = x + v * h
        np.testing.assert_array_equal(states[-1].particle_q.numpy()[0], x)
        np.testing.assert_array_equal(states[-1].particle_qd.numpy()[0], v)
        exact = x0 + v0 * T + 0.5 * G * T**2
        # semi-implicit Euler's error is exactly g T h / 2
        np.testing.assert_allclose(x - exact, 0.5 * G * T * h, rtol=1e-9, atol=1e-13)
        errors.append(np.linalg.norm(x - exact))
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=1e-6)
    assert errors[1] / errors[2] == pytest.approx(2.0, rel=1e-6)


def test_spring_oscillator_period():
    m_, k = 0.5, 200.0  # omega = 20 rad/s
    period = 2 * math.pi * math.sqrt(m_ / k)
    rest, amp = 1.0, 0.1
    model = make_model(
        q=[[0, 0, 0], [rest + amp, 0, 0]],
        mass=[0.0, m_],
        springs=[[0, 1]],
        rest=rest,
        stiffness=k,
        gravity=np.zeros(3),
    )
    h = 1e-4
    n = int(2.2 * period / h)
    integ = SemiImplicitIntegrator(model)
    s0, s1 = model.state(), model.state()
    # 20 substeps per step() call, positions read once per call
    every = 20
    xs = [s0.particle_q.numpy()[1, 0]]
    for _ in range(n // every):
        integ.step(s0, s1, h * every, every)
        s0, s1 = s1, s0
        xs.append(s0.particle_q.numpy()[1, 0])
    d = np.array(xs) - rest
    t = np.arange(len(d)) * h * every
    # upward zero crossings, linearly interpolated
    idx = np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]
    crossings = t[idx] - d[idx] * (t[idx + 1] - t[idx]) / (d[idx + 1] - d[idx])
    assert len(crossings) >= 2
    measured = crossings[1] - crossings[0]
    # symplectic Euler's period is 2 pi / ((2/h) asin(omega h / 2)): relative error -(omega h)^2 / 24
    # ~ -1.7e-7 (measured -1.5e-7); the linear interpolation of the crossings (samples every
    # 2 ms) adds O((omega dt_sample)^3) since the displacement's curvature vanishes there
    assert measured == pytest.approx(period, rel=1e-6)
    # amplitude bounded (no energy growth): symplectic
    assert np.max(np.abs(d)) < amp * 1.001


def _cloth(n=6, pinned=(0,), planes=None, restitution=0.0, friction=0.0):
    xs, ys = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    q = np.stack([xs.ravel() * 0.1, ys.ravel() * 0.1, np.full(n * n, 0.5)], axis=1)
    mass = np.full(n * n, 0.1)
    mass[list(pinned)] = 0.0
    springs = []
    idx = lambda i, j: i * n + j  # noqa: E731
    for i in range(n):
        for j in range(n):
            for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1), (2, 0), (0, 2)):
                if 0 <= i + di < n and 0 <= j + dj < n:
                    springs.append((idx(i, j), idx(i + di, j + dj)))
    return make_model(
        q=q,
        qd=np.tile([0.0, 0.0, -1.0], (n * n, 1)),
        mass=mass,
        springs=springs,
        stiffness=500.0,
        damping=1.0,
        planes=planes,
        restitution=restitution,
        friction=friction,
    )


def test_pinned_particles_never_move():
    n = 6
    pinned = (0, n - 1)
    model = _cloth(n, pinned=pinned, planes=[GROUND, [0.0, 1.0, 0.0, 0.1]], restitution=0.3, friction=0.3)
    q0 = model.particle_q.numpy()
    _, states = rollout(model, 30, 1.0 / 60.0, 8)
    for s in states[1:]:
        q = s.particle_q.numpy()
        np.testing.assert_array_equal(q[list(pinned)], q0[list(pinned)])
        np.testing.assert_array_equal(s.particle_qd.numpy()[list(pinned)], 0.0)
    # everything else fell and stays above the ground
    q = states[-1].particle_q.numpy()
    free = np.setdiff1d(np.arange(n * n), pinned)
    assert np.all(q[free, 2] < 0.5)
    assert np.all(q[:, 2] >= -1e-12)


def _top(w_body, rot, dt, steps, gravity=np.zeros(3), inertia=(1.0, 1.0, 2.0)):
    q = _quat_from_axis_angle(*rot)
    w = _rotation(q) @ np.asarray(w_body, dtype=np.float64)
    body = dict(p=np.array([0.0, 0.0, 1.0]), rot=q, w=w, v=np.zeros(3), mass=2.0, inertia=np.diag(inertia))
    model = make_model(bodies=[body], gravity=gravity)
    integ = SemiImplicitIntegrator(model)
    s0, s1 = model.state(), model.state()
    poses, twists = [s0.body_q.numpy()[0].copy()], [s0.body_qd.numpy()[0].copy()]
    for _ in range(steps):
        integ.step(s0, s1, dt)
        s0, s1 = s1, s0
        poses.append(s0.body_q.numpy()[0].copy())
        twists.append(s0.body_qd.numpy()[0].copy())
    return np.array(poses), np.array(twists), np.diag(inertia)


def _angular_momentum(pose, twist, inertia):
    R = _rotation(pose[3:])
    return R @ inertia @ R.T @ twist[:3]


@pytest.mark.parametrize("dt", [1e-3, 1.0 / 60.0])
def test_symmetric_top_conserves_angular_momentum(dt):
    """Torque-free symmetric top spinning off its symmetry axis (it precesses: w changes, L must
    not): relative drift of L < 1e-6 over 1000 steps, unit quaternion."""
    poses, twists, inertia = _top([0.3, 0.0, 2.0], ([1.0, -2.0, 0.5], 0.7), dt, 1000)
    L0 = _angular_momentum(poses[0], twists[0], inertia)
    drift = max(np.linalg.norm(_angular_momentum(p, t, inertia) - L0) for p, t in zip(poses, twists))
    assert drift / np.linalg.norm(L0) < 1e-6
    assert np.max(np.abs(np.linalg.norm(poses[:, 3:], axis=1) - 1.0)) < 1e-14
    # it really precesses: the world angular velocity moved by far more than the tolerance
    assert np.max(np.linalg.norm(twists[:, :3] - twists[0, :3], axis=1)) > 1e-2
    # and it rotates (orientation changed)
    assert np.abs(poses[-1, 3:] - poses[0, 3:]).max() > 0.1


def test_free_rigid_body_falls_with_g():
    v0 = np.array([0.5, 0.0, 1.0])
    body = dict(
        p=np.array([0.0, 0.0, 3.0]), rot=[0, 0, 0, 1], w=np.array([0.1, 0.2, 0.3]), v=v0, mass=3.0,
        inertia=np.diag([1.0, 2.0, 3.0]),
    )
    particle = [[0.0, 0.0, 3.0]]
    model = make_model(q=particle, qd=[v0], bodies=[body])
    h, n = 1e-3, 400
    _, states = rollout(model, n // 10, h * 10, 10)
    p = states[-1].body_q.numpy()[0, :3]
    v = states[-1].body_qd.numpy()[0, 3:]
    # the centre of mass follows the same semi-implicit Euler recurrence as a particle, bit for bit
    np.testing.assert_array_equal(p, states[-1].particle_q.numpy()[0])
    np.testing.assert_array_equal(v, states[-1].particle_qd.numpy()[0])
    T = n * h
    np.testing.assert_allclose(v, v0 + G * T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(p, body["p"] + v0 * T + 0.5 * G * T**2 + 0.5 * G * T * h, rtol=0, atol=1e-12)


def test_rigid_body_gradient_through_rotation():
    """The unrolled angular update is differentiable: d(orientation, position)/d(w0) from the tape
    against central finite differences."""
    q = _quat_from_axis_angle([0.2, 1.0, -0.3], 0.4)
    w0 = np.array([0.4, -1.0, 2.5])
    steps, dt = 30, 1.0 / 60.0

    def run(w, requires_grad):
        body = dict(p=np.zeros(3), rot=q, w=w, v=np.array([0.1, 0.0, 0.0]), mass=1.0, inertia=np.diag([0.5, 1.0, 1.5]))
        model = make_model(bodies=[body])
        integ = SemiImplicitIntegrator(model)
        states = [model.state(requires_grad=requires_grad)]
        for _ in range(steps):
            s = model.state(requires_grad=requires_grad)
            integ.step(states[-1], s, dt, 2)
            states.append(s)
        return states

    tape = wp.Tape()
    with tape:
        states = run(w0, True)
    jac = np.zeros((7, 3))
    for i in range(7):
        seed = np.zeros((1, 7))
        seed[0, i] = 1.0
        tape.backward(grads={states[-1].body_q: wp.array(seed, dtype=wp.transformd)})
        jac[i] = states[0].body_qd.grad.numpy()[0, :3]
        tape.zero()
    fd = np.zeros((7, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = FD_STEP
        fd[:, j] = (run(w0 + e, False)[-1].body_q.numpy()[0] - run(w0 - e, False)[-1].body_q.numpy()[0]) / (2 * FD_STEP)
    assert _rel_err(jac, fd) < FD_RTOL, (jac, fd)


def test_cloth_directional_gradient_springs_and_planes():
    """Springs (stiffness, damping), pinned particles and plane contacts together: the tape's
    directional derivative of a random weighting of the final positions, along random directions
    of the spring stiffnesses and of the initial velocities, against central finite differences.
    Stiffness lives in the Model, so ``requires_grad=True`` forces per-substep States."""
    rng = np.random.default_rng(7)
    steps, dt, substeps = 10, 1.0 / 60.0, 4

    def build(ke_delta, v_delta, requires_grad):
        model = _cloth(4, pinned=(0,), planes=[[0.0, 0.0, 1.0, 0.45]], restitution=0.5, friction=0.2)
        ke = model.spring_stiffness.numpy() + ke_delta
        model.spring_stiffness = wp.array(ke, dtype=wp.float64, requires_grad=requires_grad)
        model.particle_qd = wp.array(model.particle_qd.numpy() + v_delta, dtype=wp.vec3d, requires_grad=requires_grad)
        return model

    def run(model, requires_grad):
        integ = SemiImplicitIntegrator(model, requires_grad=requires_grad)
        states = [model.state(requires_grad=requires_grad)]
        for _ in range(steps):
            s = model.state(requires_grad=requires_grad)
            integ.step(states[-1], s, dt, substeps)
            states.append(s)
        return states

    model = build(0.0, 0.0, True)
    w = rng.normal(size=(model.particle_count, 3))
    d_ke = rng.normal(size=model.spring_count) * 1.0e4  # large enough that FD rounding stays ~1e-10 relative
    d_v = rng.normal(size=(model.particle_count, 3))
    tape = wp.Tape()
    with tape:
        states = run(model, True)
    tape.backward(grads={states[-1].particle_q: wp.array(w, dtype=wp.vec3d)})
    grad_ke = model.spring_stiffness.grad.numpy()
    # model.state() inside the tape is a recorded clone: the gradient lands in the Model's array
    grad_v = model.particle_qd.grad.numpy()
    lowest = min(s.particle_q.numpy()[:, 2].min() for s in states)
    assert lowest < 0.46  # some particles reached the plane (at 0.45) and bounced

    def loss(eps_ke, eps_v):
        final = run(build(eps_ke * d_ke, eps_v * d_v, False), False)[-1].particle_q.numpy()
        return float(np.sum(w * final))

    for name, tape_dd, (a, b) in (
        ("stiffness", float(grad_ke @ d_ke), (1.0, 0.0)),
        ("velocity", float(np.sum(grad_v * d_v)), (0.0, 1.0)),
    ):
        h = FD_STEP
        fd = (loss(a * h, b * h) - loss(-a * h, -b * h)) / (2 * h)
        assert abs(tape_dd - fd) <= FD_RTOL * abs(fd), (name, tape_dd, fd)


def test_launches_only_what_the_model_has():
    """Particle-only and body-only models step with the other arrays left None."""
    model = make_model(q=[[0.0, 0.0, 1.0]], planes=[GROUND])
    assert model.body_q is None and model.spring_indices is None
    _, states = rollout(model, 2, 0.01, 2)
    assert states[-1].body_q.shape == (0,)
    body = dict(p=np.zeros(3), mass=1.0, inertia=np.eye(3))
    model = make_model(bodies=[body], planes=[GROUND])
    assert model.particle_q is None and model.particle_inv_mass is None
    _, states = rollout(model, 2, 0.01, 2)
    assert states[-1].particle_q.shape == (0,)


def test_collision_handler_hook():
    """Called once per substep with (start-of-substep state, predicted state, h); a returned
    State replaces the prediction, None keeps it."""
    model = _bounce_model([0.0, 0.0, 1.0])
    calls = []

    def observe(s_in, s_pred, h):
        calls.append(
            (
                s_in.particle_q.numpy()[0].copy(),
                s_pred.particle_q.numpy()[0].copy(),
                s_pred.particle_qd.numpy()[0].copy(),
                h,
            )
        )
        return None

    _, ref = rollout(model, 3, 0.03, 3)
    _, got = rollout(model, 3, 0.03, 3, handler=observe)
    assert len(calls) == 9
    np.testing.assert_array_equal(got[-1].particle_q.numpy(), ref[-1].particle_q.numpy())
    x0, xp, vp, h = calls[0]
    assert h == pytest.approx(0.01)
    np.testing.assert_array_equal(xp, x0 + vp * h)

    def freeze(s_in, s_pred, h):
        return State(particle_q=wp.clone(s_in.particle_q), particle_qd=wp.zeros_like(s_pred.particle_qd), body_q=s_pred.body_q, body_qd=s_pred.body_qd)

    _, frozen = rollout(model, 3, 0.03, 3, handler=freeze)
    np.testing.assert_array_equal(frozen[-1].particle_q.numpy(), model.particle_q.numpy())


# ----------------------------------------------------------------------------- (c) determinism
def test_bit_identical_runs():
    def run(requires_grad):
        model = _cloth(8, pinned=(0, 7), planes=[[0.0, 0.0, 1.0, 0.3]], restitution=0.5, friction=0.3)
        _, states = rollout(model, 20, 1.0 / 60.0, 4, requires_grad=requires_grad)
        return states[-1].numpy()

    a, b, c = run(False), run(False), run(True)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
        # the tape-ready path (fresh arrays per substep) computes the same bits
        np.testing.assert_array_equal(a[key], c[key])
    assert np.min(a["particle_q"][:, 2]) < 0.31  # the plane was reached


def test_taped_step_from_plain_states_keeps_every_intermediate_array():
    """Under a recording tape a step keeps fresh arrays for every substep and stage even when
    its input State does not require gradients (only a model array does): reused scratch
    arrays would be overwritten before the backward reads them. The stiffness gradient of a
    4-substep step from a plain State equals the one from a gradient-requiring State, and both
    equal central differences."""
    rng = np.random.default_rng(3)
    dt, substeps = 1.0 / 60.0, 4

    def build(ke_delta):
        model = _cloth(4, pinned=(0,), planes=[[0.0, 0.0, 1.0, 0.45]], restitution=0.5, friction=0.2)
        model.spring_stiffness = wp.array(model.spring_stiffness.numpy() + ke_delta, dtype=wp.float64,
                                          requires_grad=True)
        return model

    model = build(0.0)
    w = rng.normal(size=(model.particle_count, 3))
    d_ke = rng.normal(size=model.spring_count) * 1.0e4
    grads = []
    for plain in (True, False):
        model.spring_stiffness.grad.zero_()
        s0 = model.state(requires_grad=not plain)
        s1 = model.state(requires_grad=True)
        tape = wp.Tape()
        with tape:
            SemiImplicitIntegrator(model).step(s0, s1, dt, substeps)
        tape.backward(grads={s1.particle_q: wp.array(w, dtype=wp.vec3d)})
        grads.append(float(model.spring_stiffness.grad.numpy() @ d_ke))

    def loss(eps):
        m = build(eps * d_ke)
        s0, s1 = m.state(), m.state()
        SemiImplicitIntegrator(m).step(s0, s1, dt, substeps)
        return float(np.sum(w * s1.particle_q.numpy()))

    fd = (loss(FD_STEP) - loss(-FD_STEP)) / (2 * FD_STEP)
    assert grads[0] == pytest.approx(grads[1], rel=1e-12)
    assert abs(grads[0] - fd) <= FD_RTOL * abs(fd), (grads, fd)


# ----------------------------------------------------------------------------- particle drag
def test_particle_drag_reaches_the_terminal_velocity_and_converges_first_order():
    """Linear air drag ``c``: ``dv/dt = g - c v``, whose exact solution from rest is
    ``v(t) = (g / c)(1 - exp(-c t))``. The implicit update ``v1 = (v0 + h g) / (1 + h c)`` has
    the terminal velocity ``g / c`` as its fixed point (exact to rounding after 1600 substeps at
    ``c h = 1/48``: the distance shrinks by ``(1 + c h)^-1`` each), and its error at
    ``t = 0.5 s`` halves with the substep (first order); in both integrators."""
    from sim.integrators import make_integrator

    c = 10.0
    for kind in ("semi_implicit", "implicit"):
        model = make_model(q=[[0.0, 0.0, 0.0]])
        model.particle_drag = c
        integ = make_integrator(model, kind)
        s0, s1 = model.state(), model.state()
        for _ in range(200):
            integ.step(s0, s1, 1.0 / 60.0, 8)
            s0, s1 = s1, s0
        np.testing.assert_allclose(s0.particle_qd.numpy()[0], G / c, rtol=1e-12, atol=1e-15, err_msg=kind)

    c, T = 2.0, 0.5
    exact = G / c * (1.0 - math.exp(-c * T))
    errors = []
    for n in (100, 200, 400):
        model = make_model(q=[[0.0, 0.0, 0.0]])
        model.particle_drag = c
        _, states = rollout(model, n // 10, T / n * 10, 10)
        errors.append(np.linalg.norm(states[-1].particle_qd.numpy()[0] - exact))
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.02)
    assert errors[1] / errors[2] == pytest.approx(2.0, rel=0.02)


def test_particle_drag_gradient_is_the_closed_form():
    """``d v_N / d v_0 = (1 + c h)^-N`` for a particle under drag (gravity adds a constant)."""
    c, dt, substeps, steps = 3.0, 1.0 / 60.0, 4, 10
    model = make_model(q=[[0.0, 0.0, 1.0]])
    model.particle_drag = c
    integ = SemiImplicitIntegrator(model)
    s0 = model.state(requires_grad=True)
    s0.particle_qd = wp.array([[0.5, 0.0, 0.0]], dtype=wp.vec3d, requires_grad=True)
    tape = wp.Tape()
    with tape:
        states = [s0]
        for _ in range(steps):
            s1 = model.state(requires_grad=True)
            integ.step(states[-1], s1, dt, substeps)
            states.append(s1)
    out = states[-1].particle_qd
    out.grad = wp.array([[1.0, 0.0, 0.0]], dtype=wp.vec3d)
    tape.backward()
    expected = (1.0 + c * dt / substeps) ** -(steps * substeps)
    assert s0.particle_qd.grad.numpy()[0, 0] == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_builder_refuses_a_bad_particle_drag_naming_it(bad):
    from sim.builder import ModelBuilder

    b = ModelBuilder()
    with pytest.raises(ValueError, match="particle_drag"):
        b.particle_drag = bad
    b.particle_drag = 0.5
    b.add_particle((0.0, 0.0, 0.0))
    assert b.finalize().particle_drag == 0.5
    assert b.finalize().scaled(1e-3).particle_drag == 0.5  # a rate [1/s]: lengths do not change it
