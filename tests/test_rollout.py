"""The differentiable rollout (``sim.rollout``): gradients through mesh contacts.

Ground truth: central finite differences of the *same* rollout's forward (each perturbed run
re-decides its contacts), closed-form free flight, and the grazing blow-up of the unmollified
derivative ``-1/p'(t*)``. The contacts in the gradient tests are transversal, so the mollified
derivative equals the exact one there; each test asserts contacts really happened and that the
impact-zone fail-safe (whose motion is not taped) did not.
"""

import numpy as np
import pytest
import torch

from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh, icosphere
from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE, rollout

DT = 1.0 / 60.0
FD_STEP = 1e-6
GRAD_RTOL = 1e-5


def _rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b)))


def _jacobian(model, steps, substeps, start, which, rows, **kw):
    """d (final output[rows]) / d start from the tape, one backward pass per row."""
    name_in = "particle_qd" if which == "particle" else "body_qd"
    out = np.zeros((len(rows), start.shape[1]))
    for i, (index, comp) in enumerate(rows):
        x = start.clone().requires_grad_()
        res = rollout(model, steps, DT, substeps, **{name_in: x}, **kw)
        final = (res.particle_q if which == "particle" else res.body_q)[-1]
        final[index, comp].backward()
        out[i] = x.grad.numpy()[0]
    return out, res


def _fd_jacobian(model, steps, substeps, start, which, rows, **kw):
    name_in = "particle_qd" if which == "particle" else "body_qd"
    out = np.zeros((len(rows), start.shape[1]))
    for j in range(start.shape[1]):
        plus, minus = start.clone(), start.clone()
        plus[0, j] += FD_STEP
        minus[0, j] -= FD_STEP
        finals = []
        for s in (plus, minus):
            res = rollout(model, steps, DT, substeps, **{name_in: s}, **kw)
            finals.append((res.particle_q if which == "particle" else res.body_q)[-1].numpy())
        out[:, j] = [(finals[0][i, c] - finals[1][i, c]) / (2 * FD_STEP) for i, c in rows]
    return out


def _particle_on_tilted_box(friction, velocity, start=(0.05, 0.02, 0.6)):
    b = ModelBuilder()
    b.add_particle(start, velocity=velocity, mass=0.1)
    b.add_static_mesh(*box_mesh((0.3, 0.3, 0.1)), rot=(np.sin(0.15), 0.0, 0.0, np.cos(0.15)))
    b.set_contact(restitution=0.5, friction=friction)
    return b.finalize()


# ------------------------------------------------------------------------------ input checks


def _tiny_model():
    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 1.0))
    b.add_rigid_body(*box_mesh(0.1), density=100.0, pos=(1.0, 0.0, 1.0))
    return b.finalize()


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"steps": 0}, "steps"),
        ({"steps": 2.5}, "steps"),
        ({"dt": 0.0}, "dt"),
        ({"dt": float("nan")}, "dt"),
        ({"substeps": 0}, "substeps"),
        ({"particle_qd": torch.zeros((2, 3), dtype=torch.float64)}, "particle_qd"),
        ({"particle_qd": torch.zeros((1, 3), dtype=torch.float32)}, "particle_qd"),
        ({"particle_qd": torch.tensor([[0.0, float("nan"), 0.0]], dtype=torch.float64)}, "particle_qd"),
        ({"particle_qd": np.zeros((1, 3))}, "particle_qd"),
        ({"body_qd": torch.zeros((1, 3), dtype=torch.float64)}, "body_qd"),
        ({"body_qd": torch.full((1, 6), float("inf"), dtype=torch.float64)}, "body_qd"),
        ({"events": [("vf", 0, 0)]}, "events"),
        ({"checkpoint_every": 0}, "checkpoint_every"),
        ({"dt": "0.1"}, "dt"),
        ({"dt": True}, "dt"),
        ({"max_derivative": None}, "max_derivative"),
        ({"max_derivative": "big"}, "max_derivative"),
        ({"max_derivative": -1.0}, "max_derivative"),
        ({"events": np.zeros((1, 3))}, "events"),
        ({"ccd_options": {"precision": "float16"}}, "precision"),
        ({"ccd_options": {"tolerance_scale": -1.0}}, "tolerance_scale"),
        ({"ccd_options": {"iterations": 3}}, "ccd_options"),
        ({"ccd_options": "float32"}, "ccd_options"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(kwargs, name):
    args = {"steps": 2, "dt": DT, "substeps": 1}
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        rollout(_tiny_model(), **args)


def test_free_flight_jacobian_is_time_times_identity():
    """Without contacts d x(T) / d v0 = T I for particles and the centre of mass (closed form of
    semi-implicit Euler), and positions/velocities keep the initial state at index 0."""
    model = _tiny_model()
    steps = 7
    v = torch.tensor([[0.3, -0.2, 0.5]], dtype=torch.float64, requires_grad=True)
    w = torch.tensor([[0.0, 0.0, 0.0, 0.1, 0.2, 0.3]], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, DT, 3, particle_qd=v, body_qd=w)
    assert res.particle_q.shape == (steps + 1, 1, 3) and res.body_q.shape == (steps + 1, 1, 7)
    np.testing.assert_allclose(res.particle_qd[0].detach().numpy(), v.detach().numpy())
    (res.particle_q[-1, 0, 0] + 2.0 * res.body_q[-1, 0, 1]).backward()
    np.testing.assert_allclose(v.grad.numpy(), [[steps * DT, 0.0, 0.0]], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(w.grad.numpy()[0, 3:], [0.0, 2.0 * steps * DT, 0.0], rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------------------ through contacts


@pytest.mark.parametrize(
    "friction, velocity, start",
    [
        (0.0, (0.3, 0.1, -2.0), (0.05, 0.02, 0.6)),  # frictionless bounce
        (0.4, (0.3, 0.1, -2.0), (0.05, 0.02, 0.6)),  # sticks on impact
        (0.1, (1.0, 0.5, -2.0), (-0.15, -0.05, 0.6)),  # slides on impact
    ],
)
def test_particle_bouncing_off_tilted_box_matches_finite_differences(friction, velocity, start):
    model = _particle_on_tilted_box(friction, velocity, start)
    v0 = torch.tensor([velocity], dtype=torch.float64)
    rows = [(0, 0), (0, 1), (0, 2)]
    jac, res = _jacobian(model, 20, 4, v0, "particle", rows)
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    # one particle meets the box: every CCD event is a vertex-face hit of it, at least the impact
    assert res.stats["ccd_events"] >= 1
    fd = _fd_jacobian(model, 20, 4, v0, "particle", rows)
    assert _rel(jac, fd) < GRAD_RTOL
    # transversal: the mollifier is inactive, the unmollified derivative is the same
    jac_plain, _ = _jacobian(model, 20, 4, v0, "particle", rows, max_derivative=UNMOLLIFIED_MAX_DERIVATIVE)
    assert _rel(jac, jac_plain) < 1e-10
    # and the bounce changed the gradient (a contact that did nothing would give T I)
    assert _rel(jac, 20 * DT * np.eye(3)) > 0.1


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_rigid_box_landing_corner_first_matches_finite_differences(friction):
    """Angular and linear initial velocities of a box tilted so a corner hits a static box first."""
    axis = np.array([1.0, 1.0, 0.3]) / np.linalg.norm([1.0, 1.0, 0.3])
    rot = (*(axis * np.sin(0.25)), np.cos(0.25))
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(0.1), density=400.0, pos=(0.02, -0.03, 0.32), rot=rot)
    b.add_static_mesh(*box_mesh((0.4, 0.4, 0.1)))
    b.set_contact(restitution=0.3, friction=friction)
    model = b.finalize()
    qd0 = torch.tensor([[0.5, -1.0, 0.3, 0.2, 0.1, -2.0]], dtype=torch.float64)
    rows = [(0, c) for c in range(7)]  # centre of mass and quaternion
    # one of the corner's contacts is close to tangential with friction: compare the exact
    # (unmollified) derivative, which the mollified one departs from by ~2% there
    plain = {"max_derivative": UNMOLLIFIED_MAX_DERIVATIVE}
    jac, res = _jacobian(model, 12, 4, qd0, "body", rows, **plain)
    assert res.stats["contact_substeps"] >= 2 and res.stats["failsafe_substeps"] == 0
    fd = _fd_jacobian(model, 12, 4, qd0, "body", rows, **plain)
    assert _rel(jac, fd) < GRAD_RTOL
    assert np.abs(jac[:3, :3]).max() > 1e-3  # the spin reaches the landing position


def _directional(model, steps, substeps, v0, direction, weights, **kw):
    v = v0.clone().requires_grad_()
    res = rollout(model, steps, DT, substeps, particle_qd=v, **kw)
    (res.particle_q[-1] * weights).sum().backward()
    grad = float((v.grad * direction).sum())
    losses = [float((rollout(model, steps, DT, substeps, particle_qd=v0 + s * FD_STEP * direction, **kw).particle_q[-1]
                     * weights).sum()) for s in (1, -1)]
    return grad, (losses[0] - losses[1]) / (2 * FD_STEP), res


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_cloth_thrown_onto_box_matches_finite_differences(friction):
    """A 3x3-cell cloth thrown onto a slightly tilted box: the hit, then resting contact with
    friction for the rest of the run (directional derivatives in two random directions)."""
    b = ModelBuilder()
    b.add_cloth_grid((-0.1, -0.12, 0.25), None, 3, 3, 0.08, 0.08, density=1.0, stretch_stiffness=10.0,
                     shear_stiffness=3.0, bend_stiffness=0.3, damping=0.01)
    b.add_static_mesh(*box_mesh((0.3, 0.3, 0.1)), rot=(np.sin(0.05), 0.0, 0.0, np.cos(0.05)))
    b.set_contact(restitution=0.0, friction=friction)
    model = b.finalize()
    P = model.particle_count
    v0 = torch.tensor(np.tile([0.3, 0.2, -2.0], (P, 1)), dtype=torch.float64)
    v0[:, 0] += torch.linspace(0.0, 0.1, P, dtype=torch.float64)
    rng = np.random.default_rng(1)
    for _ in range(2):
        d = torch.tensor(rng.normal(size=(P, 3)))
        w = torch.tensor(rng.normal(size=(P, 3)))
        grad, fd, res = _directional(model, 12, 4, v0, d, w, max_derivative=UNMOLLIFIED_MAX_DERIVATIVE)
        assert abs(grad - fd) < GRAD_RTOL * abs(fd)
    assert res.stats["contact_substeps"] >= 20 and res.stats["failsafe_substeps"] == 0
    assert float(res.particle_q[-1, :, 2].detach().min()) > 0.08  # resting on the box top (z ~ 0.09-0.1)


def ball_into_hanging_cloth():
    """A rigid ball (mu 0.3) thrown into a 4x4-cell cloth hanging from its two top corners; the
    model and the ball's initial twist (B, 6). Also used by tests/test_rollout_params.py."""
    b = ModelBuilder()
    n, size, s = 4, 0.4, np.sqrt(0.5)
    b.add_cloth_grid((-size / 2, 0.0, 0.6 - size), (s, 0.0, 0.0, s), n, n, size / n, size / n, density=1.0,
                     stretch_stiffness=10.0, shear_stiffness=3.0, bend_stiffness=0.3, damping=0.01,
                     pinned=[n * (n + 1), n * (n + 1) + n])
    b.add_rigid_body(*icosphere(0.06, 1), density=300.0, pos=(0.01, -0.15, 0.42))
    b.set_contact(restitution=0.0, friction=0.3, thickness=0.005)
    return b.finalize(), torch.tensor([[0.0, 0.0, 0.0, 0.0, 3.0, 0.1]], dtype=torch.float64)


def test_rigid_ball_into_hanging_cloth_matches_finite_differences():
    model, qd0 = ball_into_hanging_cloth()
    rows = [(0, 0), (0, 1), (0, 2)]
    jac, res = _jacobian(model, 10, 8, qd0, "body", rows)
    assert res.stats["contact_substeps"] >= 20 and res.stats["failsafe_substeps"] == 0
    assert float(res.body_q[-1, 0, 1].detach()) < 0.35  # the cloth held the ball back (free flight: 0.35 m)
    fd = _fd_jacobian(model, 10, 8, qd0, "body", rows)
    assert _rel(jac, fd) < GRAD_RTOL


def test_checkpointed_backward_equals_the_full_tape():
    model = _particle_on_tilted_box(0.4, (0.3, 0.1, -2.0))
    v0 = torch.tensor([[0.3, 0.1, -2.0]], dtype=torch.float64)
    grads = []
    for every in (None, 3, 7):
        v = v0.clone().requires_grad_()
        res = rollout(model, 20, DT, 4, particle_qd=v, checkpoint_every=every)
        (res.particle_q[-1, 0].sum() + res.particle_qd[11, 0, 2] + res.particle_q[5, 0, 0]).backward()
        grads.append(v.grad.numpy().copy())
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(grads[2], grads[0], rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------------------ grazing
# scenes/grazing.py: a particle grazing a tilting flap, a true double root of the coplanarity cubic


def mollified_bound(m: float) -> float:
    """Stated bound of the mollified gradient over the whole grazing sweep, in units of the
    free-flight gradient: 1.2 M + 2 (measured: plateau 1.16 M for M = 1000 and M = 10, largest
    1161.8 and 12.5 on a 41-point sweep; first-order prediction of the contact's share
    2 M (1 + e) (t_m / h) (T - t_m) / T = 1.125 M, see scenes/grazing.py; the 2 covers the
    unclamped terms, free flight and the bounce)."""
    return 1.2 * m + 2.0

UNMOLLIFIED_OVER_MOLLIFIED = 10.0
"""At the sweep's smallest offset (1e-11) the unmollified gradient exceeds this multiple of the
largest mollified one (measured 65x)."""


@pytest.fixture(scope="module")
def grazing_sweep():
    from scenes.grazing import sweep

    return sweep(other_max_derivatives=(10.0,), fd_steps=(2.5e-4,))


def test_grazing_flap_is_a_true_double_root_of_the_substep_cubic():
    """Independent of the simulator (exact rational arithmetic, sympy): at the threshold aim the
    coplanarity cubic of the substep holding t_m, built from the straight paths of the four
    points from the substep's start to its end as in kernels/ccd_common.py, has p = p' = 0 at
    s = 1/2 and p'' != 0 (a double, not a triple root; zero discriminant), with the particle
    strictly inside the flap there; deeper aims give two roots in that substep, shallower ones
    no root in the whole rollout."""
    import sympy as sp

    from scenes import grazing as g

    s = sp.Symbol("s")
    h = sp.Rational(g.DT) / g.SUBSTEPS
    tm = sp.Rational(g.MEET_TIME)
    j = int(sp.floor(tm / h))
    assert j == 1 and tm / h - j == sp.Rational(1, 2)  # the middle of the second substep

    def points(vz, t):
        pos, vel = g.initial_state(vz)
        return [sp.Matrix([sp.Rational(c) for c in p]) + t * sp.Matrix([sp.Rational(c) for c in v])
                for p, v in zip(pos, vel)]

    def cubic(vz, first, last):
        """(x_t0 - x_p) x (x_t1 - x_p) . (x_t2 - x_p) on the straight paths from time `first` to
        `last`, as a polynomial in the fraction s of that interval."""
        start, end = points(vz, first), points(vz, last)
        x = [a + s * (b - a) for a, b in zip(start, end)]
        p = x[g.PARTICLE]
        return sp.Poly(sp.expand((x[0] - p).cross(x[1] - p).dot(x[2] - p)), s)

    vz = sp.Rational(g.THRESHOLD_VZ)
    p = cubic(vz, j * h, (j + 1) * h)
    assert p.degree() == 3 and p.LC() != 0
    half = sp.Rational(1, 2)
    assert p.eval(half) == 0 and p.diff(s).eval(half) == 0 and p.diff(s).diff(s).eval(half) != 0
    assert sp.discriminant(p) == 0
    # the coplanarity point at t_m: barycentric coordinates of the particle in the flap
    x = points(vz, tm)
    a, b, c, q = x[0], x[1], x[2], x[g.PARTICLE]
    area = (b - a).cross(c - a)
    bary = [(c - b).cross(q - b).dot(area), (a - c).cross(q - c).dot(area), (b - a).cross(q - a).dot(area)]
    bary = [w / area.dot(area) for w in bary]
    assert sum(bary) == 1 and min(bary) > sp.Rational(1, 5)
    # deeper: two roots in the substep; shallower: none anywhere in the rollout
    deeper = cubic(vz * (1 + sp.Rational(1, 10**6)), j * h, (j + 1) * h)
    assert deeper.count_roots(0, 1) == 2
    shallower = cubic(vz * (1 - sp.Rational(1, 10**6)), 0, g.STEPS * sp.Rational(g.DT))
    assert shallower.count_roots(0, 1) == 0


def test_grazing_sweep_hits_misses_and_free_flight(grazing_sweep):
    """The simulator agrees with the design: every aim deeper than the threshold hits (down to a
    relative 1e-11), every shallower one misses with exactly the free-flight gradient T; no
    impact zones."""
    from scenes import grazing as g

    r = grazing_sweep
    t_end = g.STEPS * float(g.DT)
    assert abs(r["free"] - t_end) < 1e-12  # free flight: d z / d v_z = T
    assert np.all(r["contacts"] == 1) and np.all(r["failsafe"] == 0)
    assert np.all(r["miss_contacts"] == 0)
    np.testing.assert_allclose(r["miss_gradients"], r["free"], rtol=1e-12)


def test_grazing_mollified_gradient_is_bounded_over_the_whole_sweep(grazing_sweep):
    """Mollified (M = 1000 and M = 10): finite, within mollified_bound(M) times free flight
    everywhere, and levelled off at the smallest offsets (not growing)."""
    r = grazing_sweep
    free = abs(r["free"])
    for m, grads in ((1000.0, r["mollified"]), (10.0, r["by_max_derivative"][10.0])):
        assert np.all(np.isfinite(grads))
        assert np.abs(grads).max() <= mollified_bound(m) * free
        tail = grads[r["offsets"] <= 1e-9]
        assert len(tail) >= 3 and np.ptp(tail) <= 1e-3 * np.abs(tail).max()


def test_grazing_unmollified_gradient_blows_up_like_offset_to_the_minus_half(grazing_sweep):
    """Unmollified -1/p'(t*): grows like offset^(-1/2) (fitted slope in [-0.55, -0.45]) past
    UNMOLLIFIED_OVER_MOLLIFIED times the largest mollified gradient; it is the exact derivative:
    central differences of the forward agree (1e-3) down to the offset 1e-9, where the mollified
    one is already 6x smaller."""
    r = grazing_sweep
    k, plain = r["offsets"], np.abs(r["unmollified"])
    assert k.min() <= 1e-11
    assert plain[np.argmin(k)] >= UNMOLLIFIED_OVER_MOLLIFIED * np.abs(r["mollified"]).max()
    near = k <= 1e-6
    slope = np.polyfit(np.log(k[near]), np.log(plain[near]), 1)[0]
    assert -0.55 <= slope <= -0.45
    fd_ok = (k <= 1e-7) & (k >= 1e-9)
    assert fd_ok.sum() == 3
    np.testing.assert_allclose(r["unmollified"][fd_ok], r["fd"][0][fd_ok], rtol=1e-3)
    assert np.abs(r["unmollified"][k == 1e-9]) > 5 * np.abs(r["mollified"][k == 1e-9])


def test_grazing_away_from_the_tangency_mollified_equals_unmollified_and_finite_differences(grazing_sweep):
    """At offsets >= 1e-6 the contact is far from the clamp (|p'(t*)| of the unit-scaled cubic
    above 1/M): both derivatives are the same exact one and match central differences (1e-5)."""
    r = grazing_sweep
    far = r["offsets"] >= 1e-6
    assert far.sum() >= 5
    np.testing.assert_allclose(r["mollified"][far], r["unmollified"][far], rtol=1e-10)
    np.testing.assert_allclose(r["mollified"][far], r["fd"][0][far], rtol=1e-5)


@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_particle_plane_rows_of_the_replayed_response_match_finite_differences(friction):
    """A particle sliding inside the separation band of the ground (half the 1 mm thickness
    up; a static box far away, so the collision handler runs): on every substep the handler's
    vertex-plane row lifts it towards the separation while it slides (with friction against
    the row's impulse). The gradient of a weighting of its end position w.r.t. its initial
    velocity through the replayed rows matches central differences (the contact set is the
    same in the whole stencil)."""
    thickness = 1e-3
    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 0.5 * thickness), mass=0.1)
    b.add_static_mesh(*box_mesh((0.1, 0.1, 0.1)), pos=(3.0, 0.0, 0.5))
    b.add_ground_plane()
    b.set_contact(restitution=0.0, friction=friction, thickness=thickness)
    model = b.finalize()
    weights = torch.tensor([0.3, -0.7, 5.0], dtype=torch.float64)

    def loss(v):
        res = rollout(model, steps=6, dt=DT, substeps=4, particle_qd=v)
        return (res.particle_q[-1, 0] * weights).sum(), res

    v0 = torch.tensor([[0.8, 0.4, 0.0]], dtype=torch.float64, requires_grad=True)
    value, res = loss(v0)
    value.backward()
    assert res.stats["contact_substeps"] == 24 and res.stats["failsafe_substeps"] == 0
    z = res.particle_q[:, 0, 2].detach().numpy()
    assert np.all(np.diff(z) > 0) and z[-1] < thickness  # lifted towards the separation, not past it
    eps = 1e-6
    fd = []
    for k in range(3):
        d = torch.zeros(1, 3, dtype=torch.float64)
        d[0, k] = eps
        fd.append((float(loss(v0.detach() + d)[0]) - float(loss(v0.detach() - d)[0])) / (2 * eps))
    fd = np.array(fd)
    np.testing.assert_allclose(v0.grad.numpy()[0], fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def _box_on_plane(friction, **body):
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(0.1), density=400.0, **body)
    b.add_ground_plane()
    b.set_contact(restitution=0.3, friction=friction)
    return b.finalize()


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_rigid_box_corner_on_ground_plane_matches_finite_differences(friction):
    """Vertex-plane contacts of a rigid body (the path that replaced falling through planes)."""
    axis = np.array([1.0, -0.5, 0.2]) / np.linalg.norm([1.0, -0.5, 0.2])
    model = _box_on_plane(friction, pos=(0.0, 0.0, 0.3), rot=(*(axis * np.sin(0.3)), np.cos(0.3)))
    qd0 = torch.tensor([[0.4, 0.8, -0.3, 0.3, -0.2, -1.5]], dtype=torch.float64)
    rows = [(0, c) for c in range(7)]
    plain = {"max_derivative": UNMOLLIFIED_MAX_DERIVATIVE}
    jac, res = _jacobian(model, 10, 4, qd0, "body", rows, **plain)
    assert res.stats["contact_substeps"] >= 2 and res.stats["failsafe_substeps"] == 0
    fd = _fd_jacobian(model, 10, 4, qd0, "body", rows, **plain)
    assert _rel(jac, fd) < GRAD_RTOL


def test_box_at_rest_with_sticking_friction_matches_finite_differences():
    """A box resting face-down on a static box, from exactly zero velocity: every contact sticks
    with a vanishing tangential velocity. Static friction solved jointly with the normal impulses
    stops any small kick in the substep it is given (the proximity contacts act at its start),
    so the end pose does not depend on the start velocity: the replayed gradient and the central
    differences both vanish (an effective mass along ``v_t / |v_t|``, whose direction comes from
    rounding noise at rest, gave gradients of order DT in every direction)."""
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(0.3, 0.0, 0.1))
    b.add_static_mesh(*box_mesh((1.0, 1.0, 0.1)), pos=(0.0, 0.0, -0.1))
    b.set_contact(restitution=0.2, friction=0.4)
    model = b.finalize()
    qd0 = torch.zeros((1, 6), dtype=torch.float64)
    rows = [(0, c) for c in range(7)]
    jac, res = _jacobian(model, 2, 8, qd0, "body", rows)
    assert res.stats["contact_substeps"] == 16 and res.stats["failsafe_substeps"] == 0
    fd = _fd_jacobian(model, 2, 8, qd0, "body", rows)
    # free flight would move the box by 2 DT per unit of start velocity
    assert np.abs(fd).max() < 1e-12 * 2 * DT
    assert np.abs(jac).max() < 1e-12 * 2 * DT


def test_float32_ccd_decisions_keep_the_gradient_exact():
    """The narrow phase's knobs decide contacts only (a forward-only generated variant, off the
    tape): with float32 CCD and a 4-iteration root cap the particle still bounces off the
    tilted box, and the replayed float64 gradient matches the same rollout's central
    differences."""
    model = _particle_on_tilted_box(0.0, (0.3, 0.1, -2.0))
    v0 = torch.tensor([[0.3, 0.1, -2.0]], dtype=torch.float64)
    rows = [(0, c) for c in range(3)]
    knobs = {"ccd_options": {"precision": "float32", "max_iterations": 4}}
    jac, res = _jacobian(model, 20, 4, v0, "particle", rows, **knobs)
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    assert res.particle_qd[:, 0, 2].max() > 0.0  # bounced
    fd = _fd_jacobian(model, 20, 4, v0, "particle", rows, **knobs)
    assert _rel(jac, fd) < GRAD_RTOL
    plain, _ = _jacobian(model, 20, 4, v0, "particle", rows)
    np.testing.assert_allclose(jac, plain, rtol=1e-6)  # the same contact, replayed in float64


def test_checkpointed_backward_with_a_rigid_body_equals_the_full_tape():
    model = _box_on_plane(0.4, pos=(0.0, 0.0, 0.3), rot=(0.2, 0.1, 0.0, float(np.sqrt(0.95))))
    qd0 = torch.tensor([[0.4, 0.8, -0.3, 0.3, -0.2, -1.5]], dtype=torch.float64)
    grads = []
    for every in (None, 4):
        w = qd0.clone().requires_grad_()
        res = rollout(model, 14, DT, 4, body_qd=w, checkpoint_every=every)
        (res.body_q[-1, 0].sum() + res.body_qd[6, 0, 1]).backward()
        grads.append(w.grad.numpy().copy())
    assert res.stats["contact_substeps"] >= 2
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("differentiable", [False, True])
def test_sliding_box_decelerates_at_mu_g(differentiable):
    """Closed-form Coulomb friction: a box sliding flat on a plane slows at mu g until it stops
    (four corner contacts share the load; the friction of each is its own mu j_n)."""
    from sim.contact.response import ImpulseCollisionHandler
    from sim.integrators.semi_implicit import SemiImplicitIntegrator

    mu, g, v0 = 0.5, 9.81, 2.0
    model = _box_on_plane(mu, pos=(0.0, 0.0, 0.1), velocity=(v0, 0.0, 0.0))
    integ = SemiImplicitIntegrator(model)
    integ.collision_handler = ImpulseCollisionHandler(model, differentiable=differentiable)
    s = model.state()
    steps = 18  # 0.3 s, stops after v0 / (mu g) = 0.41 s
    for _ in range(steps):
        s_next = model.state()
        integ.step(s, s_next, DT, 8)
        s = s_next
    v = s.body_qd.numpy()[0, 3]
    expected = v0 - mu * g * steps * DT
    assert abs(v - expected) < 0.03 * (v0 - expected), (v, expected)


def test_tape_holds_the_replay_only_no_decisions_or_iterative_solves():
    """Decide, then replay: after taped substeps with contacts (rigid box on a static box and a
    plane, friction), the tape holds the smooth map (roots, geometry, Delassus matrix, impulses,
    integration) and the implicit adjoint of the solve, never the narrow phase, the Gauss-Seidel
    sweeps or the LU iterations."""
    import warp as wp

    from sim.contact.response import ImpulseCollisionHandler
    from sim.integrators.semi_implicit import SemiImplicitIntegrator

    axis = np.array([1.0, 1.0, 0.3]) / np.linalg.norm([1.0, 1.0, 0.3])
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(0.1), density=400.0, pos=(0.02, -0.03, 0.32), rot=(*(axis * np.sin(0.25)), np.cos(0.25)),
                     velocity=(0.2, 0.1, -2.0), angular_velocity=(0.5, -1.0, 0.3))
    b.add_static_mesh(*box_mesh((0.4, 0.4, 0.1)))
    b.set_contact(restitution=0.3, friction=0.4)
    model = b.finalize()
    integ = SemiImplicitIntegrator(model, requires_grad=True)
    handler = ImpulseCollisionHandler(model, differentiable=True)
    integ.collision_handler = handler
    tape = wp.Tape()
    s = model.state(requires_grad=True)
    with tape:
        for _ in range(8):
            s_next = model.state(requires_grad=True)
            integ.step(s, s_next, DT, 4)
            s = s_next
    kernels = {launch[0].key for launch in tape.launches if not callable(launch)}
    assert {"contact_geometry_kernel", "delassus_kernel", "contact_rhs_kernel", "time_of_impact_kernel",
            "push_rhs_kernel"} <= kernels
    # friction: one of the exact forms (all contacts sticking, all sliding, a split of the two in
    # one system, or the per-contact pass)
    assert kernels & {"sticking_delassus_kernel", "sliding_impulses_kernel", "friction_impulses_kernel"}
    # the solve's implicit adjoint (a transposed solve), recorded as a function
    assert any(callable(launch) and "_dense_solve" in getattr(launch, "__qualname__", "") for launch in tape.launches)
    for decision in ("ccd_kernel", "pair_ccd_kernel", "pair_proximity_kernel", "solve_contacts_kernel",
                     "lu_factor_kernel", "lu_solve_kernel", "outside_cone_kernel", "slip_reversed_kernel",
                     "slip_update_kernel", "push_active_kernel", "tangent_weights_kernel"):
        assert decision not in kernels
