"""Impact zones on the tape: the fail-safe's momentum-conserving rigid motion as Warp kernels.

The zone membership is a decision (host union-find, :class:`sim.contact.zones.ImpactZones`);
the zone's velocities are replayed on the tape (:meth:`sim.contact.replay.ContactReplay.zone_velocities`).
Checked here: the Warp motion equals a numpy reference (``_rigid_velocities``, ``pinv``) to 1e-12;
each zone keeps its linear and angular momentum and moves rigidly (closed form, computed in this
file); a rollout whose substeps form impact zones has gradients equal to central differences;
the tape holds the zone kernels.
"""

import contextlib
import functools

import numpy as np
import pytest
import torch
import warp as wp

import sim.rollout as rollout_module
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, VERTEX_STATIC
from sim.contact.response import ImpulseCollisionHandler
from sim.contact.zones import ImpactZones
from sim.builder import ModelBuilder

# the random zones' bodies may start inside each other: the zones' motion is the point here, not
# finalize's warning about it
pytestmark = pytest.mark.filterwarnings("ignore::sim.penetration.InitialPenetrationWarning")
from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.mesh_io import box_mesh
from core.rotation import quat_to_matrix

wp.init()

DT = 1 / 60
ZONE_KERNELS = {"zone_sums_kernel", "zone_moments_kernel", "zone_rigid_motion_kernel",
                "zone_particle_velocity_kernel", "zone_body_velocity_kernel"}


def _unit_quat(rng):
    q = rng.normal(size=4)
    return tuple(q / np.linalg.norm(q))


def _random_model(seed, n_particles, n_bodies, collinear=False):
    rng = np.random.default_rng(seed)
    b = ModelBuilder()
    a, d = rng.normal(size=3), rng.normal(size=3)
    for _ in range(n_particles):
        x = a + rng.uniform(-1.0, 1.0) * d if collinear else rng.normal(size=3)
        b.add_particle(x, velocity=rng.normal(size=3), mass=rng.uniform(0.1, 1.0))
    b.add_particle((9.0, 9.0, 9.0), pinned=True)  # the last particle is pinned
    for k in range(max(n_bodies, 1)):
        far = k >= n_bodies  # a body far away when the zones hold none (the model needs a surface)
        b.add_rigid_body(*box_mesh(tuple(rng.uniform(0.05, 0.3, 3))), density=rng.uniform(100.0, 1000.0),
                         pos=(20.0, 20.0, 20.0) if far else rng.normal(size=3), rot=_unit_quat(rng),
                         velocity=rng.normal(size=3), angular_velocity=rng.normal(size=3))
    return b.finalize()


def _rows(nodes):
    """(types, owners) rows for :meth:`ImpactZones.merge` from ("p"|"b"|"s", index) nodes."""
    kinds = {"p": VERTEX_PARTICLE, "b": VERTEX_BODY, "s": VERTEX_STATIC}
    return (np.array([[kinds[k] for k, _ in nodes]], dtype=np.int64),
            np.array([[i for _, i in nodes]], dtype=np.int64))


def _zones(handler, groups):
    zones = ImpactZones(handler.n_particles, handler.n_bodies, handler.particle_inv_mass)
    for group in groups:
        zones.merge(*_rows(group))
    return zones


def _rigid_velocities(zones, x0p, vp, bq0, bv, particle_inv_mass, body_mass, body_inertia_w) -> None:
    """The reference (numpy, ``pinv``; independent of the Warp kernels): overwrites the
    velocities of the zone members with their zone's rigid motion (total mass, momentum and,
    about the centre of mass, angular momentum and inertia), in place; a zone that holds the
    world is at rest."""
    members_p = np.flatnonzero(zones.particles)
    members_b = np.flatnonzero(zones.bodies)
    roots_p = np.array([zones._find(int(i)) for i in members_p], dtype=np.int64)
    roots_b = np.array([zones._find(int(zones.P + i)) for i in members_b], dtype=np.int64)
    for root in np.unique(np.concatenate([roots_p, roots_b])):
        zp = members_p[roots_p == root]
        zb = members_b[roots_b == root]
        if root == zones.world:
            vp[zp] = 0.0
            bv[zb] = 0.0
            continue
        mp = np.divide(1.0, particle_inv_mass[zp], out=np.zeros(len(zp)), where=particle_inv_mass[zp] > 0)
        mb = body_mass[zb]
        mass = mp.sum() + mb.sum()
        centre = (mp @ x0p[zp] + mb @ bq0[zb, :3]) / mass
        momentum = mp @ vp[zp] + mb @ bv[zb, 3:6]
        rp = x0p[zp] - centre
        rb = bq0[zb, :3] - centre
        angular = (np.cross(rp, vp[zp]) * mp[:, None]).sum(0) + (np.cross(rb, bv[zb, 3:6]) * mb[:, None]).sum(0)
        angular += np.einsum("bij,bj->i", body_inertia_w[zb], bv[zb, :3])
        eye = np.eye(3)
        inertia = np.einsum("p,pij->ij", mp, (rp * rp).sum(1)[:, None, None] * eye - rp[:, :, None] * rp[:, None, :])
        inertia += body_inertia_w[zb].sum(0)
        inertia += np.einsum("b,bij->ij", mb, (rb * rb).sum(1)[:, None, None] * eye - rb[:, :, None] * rb[:, None, :])
        omega = np.linalg.pinv(inertia) @ angular  # pinv: a zone of collinear particles
        linear = momentum / mass
        vp[zp] = linear + np.cross(omega, rp)
        bv[zb, 3:6] = linear + np.cross(omega, rb)
        bv[zb, :3] = omega


def _host(handler, zones, state):
    vp, bv = state.particle_qd.numpy().copy(), state.body_qd.numpy().copy()
    bq = state.body_q.numpy()
    rot = quat_to_matrix(bq[:, 3:7])
    inertia_w = rot @ handler.model.body_inertia.numpy().reshape(-1, 3, 3) @ np.swapaxes(rot, 1, 2)
    _rigid_velocities(zones, state.particle_q.numpy(), vp, bq, bv, handler.particle_inv_mass,
                      handler.model.body_mass.numpy(), inertia_w)
    return vp, bv


def _warp(handler, zones, state, particle_q=None, particle_qd=None, body_q=None, body_qd=None):
    pz, bz, n = zones.labels()
    m = handler.model
    return handler.replay.zone_velocities(
        particle_qd if particle_qd is not None else state.particle_qd,
        body_qd if body_qd is not None else state.body_qd, pz, bz, n,
        particle_q if particle_q is not None else state.particle_q,
        body_q if body_q is not None else state.body_q, m.body_mass, m.body_inertia)


# zone layouts: lists of merged groups of ("p", particle) / ("b", body) / ("s", static vertex)
CASES = {
    "particles": (6, 0, False, [[("p", 0), ("p", 1), ("p", 2), ("p", 3)], [("p", 4), ("p", 5), ("p", 0)]]),
    "particles_two_zones": (7, 0, False, [[("p", 0), ("p", 1), ("p", 2)], [("p", 3), ("p", 4), ("p", 5), ("p", 6)]]),
    "particles_and_bodies": (6, 3, False, [[("p", 0), ("b", 0), ("b", 0), ("b", 0)], [("p", 1), ("p", 2), ("b", 1)],
                                           [("b", 1), ("b", 2)], [("p", 4), ("p", 5), ("b", 0)]]),
    "bodies_only": (2, 2, False, [[("b", 0), ("b", 1)]]),
    "collinear_pair": (2, 0, True, [[("p", 0), ("p", 1)]]),
    "collinear_four": (4, 0, True, [[("p", 0), ("p", 1), ("p", 2), ("p", 3)]]),
    "with_world": (6, 2, False, [[("p", 0), ("p", 1), ("s", 0)], [("p", 2), ("b", 0), ("p", 6)],
                                 [("p", 3), ("p", 4), ("b", 1)]]),  # particle 6 is pinned
}


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("case", sorted(CASES))
def test_warp_zone_motion_equals_the_host_rigid_velocities(case, seed):
    n_p, n_b, collinear, groups = CASES[case]
    model = _random_model(seed, n_p, n_b, collinear)
    handler = ImpulseCollisionHandler(model, differentiable=True)
    zones = _zones(handler, groups)
    state = model.state()
    vp, bv = _host(handler, zones, state)
    out_p, out_b = _warp(handler, zones, state)
    scale = max(1.0, np.abs(vp).max(), np.abs(bv).max())
    np.testing.assert_allclose(out_p.numpy(), vp, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(out_b.numpy(), bv, rtol=0, atol=1e-12 * scale)
    # members of a zone that touches the world rest; non-members keep their velocities
    pz, bz, _ = zones.labels()
    assert np.all(out_p.numpy()[pz == -2] == 0.0) and np.all(out_b.numpy()[bz == -2] == 0.0)
    np.testing.assert_array_equal(out_p.numpy()[pz == -1], state.particle_qd.numpy()[pz == -1])
    np.testing.assert_array_equal(out_b.numpy()[bz == -1], state.body_qd.numpy()[bz == -1])
    if case == "with_world":
        assert (pz == -2).sum() == 3 and (bz == -2).sum() == 1  # p0, p1 (static), p2 + b0 (pinned p6)


def _quat_matrix(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("case", ["particles", "particles_and_bodies", "collinear_pair", "collinear_four"])
def test_zone_keeps_momentum_and_angular_momentum_and_moves_rigidly(case):
    """Closed form, independent of the code under test: per zone the total linear momentum and the
    angular momentum about the origin (particles ``m x x v``, bodies ``M c x v + R I R^T w``)
    are those before, the members' velocities are one rigid motion (``v_i - v_j = w x (x_i -
    x_j)``, every body turning at ``w``), and the kinetic energy does not grow."""
    n_p, n_b, collinear, groups = CASES[case]
    model = _random_model(7, n_p, n_b, collinear)
    handler = ImpulseCollisionHandler(model, differentiable=True)
    zones = _zones(handler, groups)
    state = model.state()
    out_p, out_b = _warp(handler, zones, state)
    x, bq = state.particle_q.numpy(), state.body_q.numpy()
    m_p = np.array([1.0 / w if w > 0 else 0.0 for w in model.particle_inv_mass.numpy()])
    m_b = model.body_mass.numpy()
    inertia = [_quat_matrix(q[3:]) @ i @ _quat_matrix(q[3:]).T
               for q, i in zip(bq, model.body_inertia.numpy().reshape(-1, 3, 3))]
    pz, bz, n = zones.labels()
    assert n >= 1

    def totals(vp, bv, z):
        p_sel, b_sel = np.flatnonzero(pz == z), np.flatnonzero(bz == z)
        lin = sum(m_p[i] * vp[i] for i in p_sel) + sum(m_b[b] * bv[b, 3:] for b in b_sel)
        ang = sum(m_p[i] * np.cross(x[i], vp[i]) for i in p_sel)
        ang = ang + sum(m_b[b] * np.cross(bq[b, :3], bv[b, 3:]) + inertia[b] @ bv[b, :3] for b in b_sel)
        energy = sum(0.5 * m_p[i] * vp[i] @ vp[i] for i in p_sel)
        energy += sum(0.5 * m_b[b] * bv[b, 3:] @ bv[b, 3:] + 0.5 * bv[b, :3] @ inertia[b] @ bv[b, :3] for b in b_sel)
        return lin, ang, energy, p_sel, b_sel

    vp0, bv0 = state.particle_qd.numpy(), state.body_qd.numpy()
    vp1, bv1 = out_p.numpy(), out_b.numpy()
    for z in range(n):
        lin0, ang0, e0, p_sel, b_sel = totals(vp0, bv0, z)
        lin1, ang1, e1, _, _ = totals(vp1, bv1, z)
        np.testing.assert_allclose(lin1, lin0, rtol=0, atol=1e-12 * max(1.0, np.abs(lin0).max()))
        np.testing.assert_allclose(ang1, ang0, rtol=0, atol=1e-12 * max(1.0, np.abs(ang0).max()))
        assert e1 <= e0 * (1 + 1e-12)
        # rigid: one angular velocity w; w from two members (a body's own, or the particles')
        points = [x[i] for i in p_sel] + [bq[b, :3] for b in b_sel]
        vels = [vp1[i] for i in p_sel] + [bv1[b, 3:] for b in b_sel]
        if len(b_sel):
            w = bv1[b_sel[0], :3]
            for b in b_sel:
                np.testing.assert_allclose(bv1[b, :3], w, rtol=0, atol=1e-12)
        else:  # particles: least squares for w from v_i - v_0 = w x (x_i - x_0)
            a = np.concatenate([-np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
                                for r in (p - points[0] for p in points[1:])])
            w = np.linalg.lstsq(a, np.concatenate([v - vels[0] for v in vels[1:]]), rcond=None)[0]
        for p, v in zip(points, vels):
            np.testing.assert_allclose(v - vels[0], np.cross(w, p - points[0]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("case", ["particles_and_bodies", "collinear_pair", "particles"])
def test_zone_motion_gradient_equals_central_differences(case):
    """The tape's derivative of the zone motion w.r.t. particle positions and velocities, body
    centres and twists (two particles are collinear for every position: the pseudo-inverse's
    constant-rank derivative is the true one)."""
    n_p, n_b, collinear, groups = CASES[case]
    model = _random_model(3, n_p, n_b, collinear)
    handler = ImpulseCollisionHandler(model, differentiable=True)
    zones = _zones(handler, groups)
    state = model.state()
    rng = np.random.default_rng(11)
    x0, v0 = state.particle_q.numpy(), state.particle_qd.numpy()
    q0, t0 = state.body_q.numpy(), state.body_qd.numpy()
    w_p, w_b = rng.normal(size=x0.shape), rng.normal(size=t0.shape)

    def f(x, v, q, t, tape=None):
        arrays = (wp.array(x, dtype=wp.vec3d, requires_grad=True), wp.array(v, dtype=wp.vec3d, requires_grad=True),
                  wp.array(q, dtype=wp.transformd, requires_grad=True),
                  wp.array(t, dtype=wp.spatial_vectord, requires_grad=True))
        with tape if tape is not None else contextlib.nullcontext():
            out_p, out_b = _warp(handler, zones, state, *arrays)
        return arrays, out_p, out_b, float((out_p.numpy() * w_p).sum() + (out_b.numpy() * w_b).sum())

    tape = wp.Tape()
    arrays, out_p, out_b, _ = f(x0, v0, q0, t0, tape)
    out_p.grad = wp.array(w_p, dtype=wp.vec3d)
    out_b.grad = wp.array(w_b, dtype=wp.spatial_vectord)
    tape.backward()
    grads = [a.grad.numpy() for a in arrays]
    base = [x0, v0, q0, t0]
    eps = 1e-6
    for k, g in enumerate(grads):
        cols = 3 if k == 2 else g.shape[1]  # body poses: the centre of mass only
        for i in range(g.shape[0]):
            for j in range(cols):
                plus = [b.copy() for b in base]
                minus = [b.copy() for b in base]
                plus[k][i, j] += eps
                minus[k][i, j] -= eps
                fd = (f(*plus)[3] - f(*minus)[3]) / (2 * eps)
                assert abs(g[i, j] - fd) <= 1e-7 * max(1.0, abs(fd)), (k, i, j, g[i, j], fd)


def _squeeze():
    """Three particles between two boxes flying at each other (no gravity): with the fail-safe
    forced at the first approaching CCD round, box A and the first particle form a zone, then
    the second box and the other particles join it (particles + bodies, turning)."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    for i in range(3):
        b.add_particle((0.01 * i - 0.01, 0.03 * (i - 1) + 0.01, 0.02 * (-1) ** i),
                       velocity=tuple(0.1 * rng.normal(size=3)), mass=0.02 * (i + 1))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    b.add_rigid_body(*box_mesh((0.05, 0.08, 0.07)), density=300.0, pos=(-0.12, 0.02, 0.01),
                     rot=(*(axis * np.sin(0.1)), np.cos(0.1)), velocity=(1.5, 0.1, -0.05),
                     angular_velocity=(0.3, -0.5, 0.8))
    b.add_rigid_body(*box_mesh((0.06, 0.07, 0.09)), density=200.0, pos=(0.13, -0.01, 0.0),
                     velocity=(-1.2, -0.05, 0.1), angular_velocity=(-0.4, 0.2, 0.6))
    b.set_contact(restitution=0.2, friction=0.3)
    return b.finalize()


def test_rollout_through_impact_zones_has_central_difference_gradients(monkeypatch):
    """A rollout whose collisions all end in impact zones (``max_iterations=0``): gradients of a
    loss on the final positions and velocities w.r.t. the initial particle velocities and body
    twists equal central differences (two step sizes: away from any decision boundary)."""
    monkeypatch.setattr(rollout_module, "ImpulseCollisionHandler",
                        functools.partial(ImpulseCollisionHandler, max_iterations=0))
    model = _squeeze()
    steps = 12
    pv0 = torch.tensor(model.particle_qd.numpy(), dtype=torch.float64)
    bv0 = torch.tensor(model.body_qd.numpy(), dtype=torch.float64)
    rng = np.random.default_rng(5)
    w_q = torch.tensor(rng.normal(size=(3, 3)))
    w_b = torch.tensor(rng.normal(size=(2, 7)))
    w_v = torch.tensor(rng.normal(size=(3, 3)))

    def loss(pv, bv):
        res = rollout_module.rollout(model, steps=steps, dt=DT, substeps=4, particle_qd=pv, body_qd=bv)
        value = (res.particle_q[-1] * w_q).sum() + (res.body_q[-1] * w_b).sum()
        value = value + 0.1 * (res.particle_qd[-1] * w_v).sum()
        return value, res

    pv = pv0.clone().requires_grad_(True)
    bv = bv0.clone().requires_grad_(True)
    value, res = loss(pv, bv)
    value.backward()
    assert res.stats["failsafe_substeps"] > 0
    grad = np.concatenate([pv.grad.numpy().ravel(), bv.grad.numpy().ravel()])
    x0 = np.concatenate([pv0.numpy().ravel(), bv0.numpy().ravel()])

    def f(x):
        with torch.no_grad():
            return float(loss(torch.tensor(x[:9].reshape(3, 3)), torch.tensor(x[9:].reshape(2, 6)))[0])

    scale = np.abs(grad).max()
    for eps in (1e-5, 1e-6):
        fd = np.array([(f(x0 + eps * e) - f(x0 - eps * e)) / (2 * eps) for e in np.eye(len(x0))])
        np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-5 * scale)
    assert np.abs(pv.grad.numpy()).max() > 1e-3 * scale  # the particles' velocities matter


def test_tape_holds_the_zone_kernels():
    """The impact zones' rigid motion is recorded on the tape (no host splice)."""
    model = _squeeze()
    integ = SemiImplicitIntegrator(model, requires_grad=True)
    handler = ImpulseCollisionHandler(model, max_iterations=0, differentiable=True)
    integ.collision_handler = handler
    tape = wp.Tape()
    s = model.state(requires_grad=True)
    with tape:
        for _ in range(6):
            s_next = model.state(requires_grad=True)
            integ.step(s, s_next, DT, 4)
            s = s_next
    assert handler.failsafe_count > 0
    kernels = {launch[0].key for launch in tape.launches if not callable(launch)}
    assert ZONE_KERNELS <= kernels


def test_gauss_seidel_failsafe_keeps_momentum_and_never_penetrates():
    """The Gauss-Seidel response's fail-safe (the zones' motion from the same kernels as the
    replay's, off the tape; membership from the device contact set's approaching hits): forced at
    the first approaching round, it acts, nothing interpenetrates on any step, and the total
    linear momentum of the particles and bodies (no gravity, nothing static: every impulse and
    every zone conserves it) stays what it was at the start."""
    from sim.penetration import PenetrationChecker

    model = _squeeze()
    integ = SemiImplicitIntegrator(model)
    handler = ImpulseCollisionHandler(model, max_iterations=0)
    integ.collision_handler = handler
    checker = PenetrationChecker(model)
    mp = 1.0 / model.particle_inv_mass.numpy()
    mb = model.body_mass.numpy()

    def momentum(state):
        return mp @ state.particle_qd.numpy() + mb @ state.body_qd.numpy()[:, 3:6]

    s0, s1 = model.state(), model.state()
    start = momentum(s0)
    scale = (mp[:, None] * np.abs(s0.particle_qd.numpy())).sum() + (mb[:, None] * np.abs(s0.body_qd.numpy()[:, 3:6])).sum()
    for _ in range(12):
        integ.step(s0, s1, DT, 4)
        s0, s1 = s1, s0
        report = checker.check(s0)
        assert report.inside_count == 0 and report.crossing_count == 0, report.summary()
        np.testing.assert_allclose(momentum(s0), start, rtol=0, atol=1e-12 * scale)
    assert handler.failsafe_count > 0
