"""Gradients of :func:`sim.rollout.rollout` w.r.t. particle masses and spring stiffnesses.

Ground truth: central finite differences of the *same* rollout's forward along a random direction
(relative steps ``FD_STEP`` of each parameter; each perturbed run re-decides its contacts; the
steps ``FD_STEP`` and ``10 * FD_STEP`` must agree, so the difference quotient has converged), and
one closed form that does not use the code under test: the discrete semi-implicit Euler recurrence
of a spring oscillator, differentiated by sympy. The contact scenes are transversal hits away from
decision boundaries; each asserts that contacts happened and that no impact zone (whose motion is
not taped) formed.
"""

import dataclasses

import numpy as np
import pytest
import sympy as sp
import torch
import warp as wp

from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh
from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE, rollout
from test_rollout import ball_into_hanging_cloth  # the same scene as the velocity-gradient test

DT = 1.0 / 60.0
FD_STEP = 1e-6
"""Relative step of the central differences (of each parameter's own size)."""
GRAD_RTOL = 1e-5
CHECKPOINT_RTOL = 1e-12
"""Checkpointed vs whole-tape gradients: the same launches in the same order, so they differ only
by the summation order of the segments' parameter adjoints (measured ~5e-16)."""


def _hanging_cloth(**extra):
    """A 3x3-cell cloth pinned at two corners of one edge, swinging under gravity."""
    b = ModelBuilder()
    b.add_cloth_grid((0.0, 0.0, 1.0), None, 3, 3, 0.1, 0.1, density=1.0, stretch_stiffness=10.0,
                     shear_stiffness=3.0, bend_stiffness=0.3, damping=0.01, pinned=[0, 3], **extra)
    return b.finalize()


def _cloth_onto_small_box():
    """A 3x3-cell cloth, larger than the box top, thrown onto a slightly rotated box: the box's
    edges and corners hit the cloth's faces and edges, so the impulse solve's matrix (and the
    velocities it gives) depends on the particles' inverse masses."""
    b = ModelBuilder()
    b.add_cloth_grid((-0.15, -0.13, 0.2), None, 3, 3, 0.1, 0.1, density=1.0, stretch_stiffness=10.0,
                     shear_stiffness=3.0, bend_stiffness=0.3, damping=0.01)
    b.add_static_mesh(*box_mesh((0.08, 0.08, 0.1)), rot=(np.sin(0.1), 0.0, 0.0, np.cos(0.1)))
    b.set_contact(restitution=0.0, friction=0.3)
    model = b.finalize()
    v0 = torch.tensor(np.tile([0.1, 0.05, -1.5], (model.particle_count, 1)), dtype=torch.float64)
    return model, v0


def _cloth_onto_ground_plane():
    """A tilted 3x3-cell cloth thrown onto the ground plane (the integrator's particle-plane
    contacts): it lands corner first and ends lying on the plane (at the contact separation)."""
    b = ModelBuilder()
    b.add_cloth_grid((-0.15, -0.13, 0.12), (np.sin(0.1), 0.0, 0.0, np.cos(0.1)), 3, 3, 0.1, 0.1, density=1.0,
                     stretch_stiffness=10.0, shear_stiffness=3.0, bend_stiffness=0.3, damping=0.01)
    b.add_ground_plane()
    b.set_contact(restitution=0.0, friction=0.3)
    model = b.finalize()
    v0 = torch.tensor(np.tile([0.3, 0.05, -1.0], (model.particle_count, 1)), dtype=torch.float64)
    return model, v0


def _params(model):
    return (torch.tensor(model.particle_mass.numpy(), dtype=torch.float64),
            torch.tensor(model.spring_stiffness.numpy(), dtype=torch.float64))


def _loss_fn(model, steps, substeps, seed=0, **kw):
    """A scalar of the final state: random weights on the particles' final positions (+ the
    ball's final centre of mass); returns (loss(mass, stiffness, **more) -> (loss, result))."""
    weights = torch.tensor(np.random.default_rng(seed).normal(size=(model.particle_count, 3)))

    def loss(mass, stiffness, **more):
        res = rollout(model, steps, DT, substeps, particle_mass=mass, spring_stiffness=stiffness, **kw, **more)
        value = (res.particle_q[-1] * weights).sum()
        if res.body_q.shape[1]:
            value = value + res.body_q[-1, 0, :3].sum()
        return value, res

    return loss


def _gradients(loss, mass, stiffness, **more):
    m, k = mass.clone().requires_grad_(), stiffness.clone().requires_grad_()
    value, res = loss(m, k, **more)
    value.backward()
    return m.grad.clone(), k.grad.clone(), res


def _check_directional(loss, mass, stiffness, grad_m, grad_k, seed=1):
    """Directional derivatives along random relative directions (free particles only for the
    masses) against central differences at ``FD_STEP`` (converged: ``10 FD_STEP`` agrees);
    returns the relative errors (mass, stiffness)."""
    rng = np.random.default_rng(seed)
    dm = torch.tensor(rng.uniform(0.5, 1.5, mass.shape) * rng.choice([-1.0, 1.0], mass.shape)) * mass
    dk = torch.tensor(rng.uniform(0.5, 1.5, stiffness.shape) * rng.choice([-1.0, 1.0], stiffness.shape)) * stiffness
    errors = []
    for grad, d, which in ((grad_m, dm, "mass"), (grad_k, dk, "stiffness")):
        analytic = float((grad * d).sum())
        fd = {}
        for eps in (FD_STEP, 10 * FD_STEP):
            if which == "mass":
                hi, lo = loss(mass + eps * d, stiffness)[0], loss(mass - eps * d, stiffness)[0]
            else:
                hi, lo = loss(mass, stiffness + eps * d)[0], loss(mass, stiffness - eps * d)[0]
            fd[eps] = float(hi - lo) / (2 * eps)
        assert abs(fd[FD_STEP] - fd[10 * FD_STEP]) < GRAD_RTOL * abs(fd[FD_STEP]), (which, fd)
        print(f"  {which}: FD steps {FD_STEP:g} vs {10 * FD_STEP:g} differ by "
              f"{abs(fd[FD_STEP] - fd[10 * FD_STEP]) / abs(fd[FD_STEP]):.1e}")
        errors.append(abs(analytic - fd[FD_STEP]) / abs(fd[FD_STEP]))
    return errors


# ------------------------------------------------------------------------------ finite differences


@pytest.mark.parametrize("integrator", ["semi_implicit", "implicit"])
def test_swinging_cloth_gradients_match_finite_differences(integrator):
    """(a) no contact: springs, gravity and the integration; the implicit integrator's gradient
    comes from its solve's implicit adjoint (CG tolerance 1e-13, so the solve's error is far
    below the differences' resolution)."""
    model = _hanging_cloth()
    mass, stiffness = _params(model)
    mass_before, inv_before = model.particle_mass.numpy().copy(), model.particle_inv_mass.numpy().copy()
    options = {"integrator": integrator}
    if integrator == "implicit":
        options["integrator_options"] = {"tolerance": 1e-13}
    loss = _loss_fn(model, 20, 4, **options)
    gm, gk, _ = _gradients(loss, mass, stiffness)
    assert np.all(gm.numpy()[mass.numpy() == 0.0] == 0.0)  # pinned particles: no mass gradient
    err_m, err_k = _check_directional(loss, mass, stiffness, gm, gk)
    print(f"{integrator}: relative errors mass {err_m:.2e} stiffness {err_k:.2e}")
    assert err_m < GRAD_RTOL and err_k < GRAD_RTOL
    # the caller's model is untouched
    np.testing.assert_array_equal(model.particle_mass.numpy(), mass_before)
    np.testing.assert_array_equal(model.particle_inv_mass.numpy(), inv_before)


@pytest.mark.parametrize("scene", ["cloth_onto_box", "ball_into_cloth", "cloth_onto_plane"])
def test_contact_gradients_match_finite_differences(scene):
    """(b) through contacts. Mesh contacts use the replayed collision response: the masses enter
    the impulse solve's matrix and the impulses' velocity changes (without the replay's
    inverse-mass adjoint the mass gradients of "cloth_onto_box" and "ball_into_cloth" are off by
    94 % and 156 %, measured). On the plane the masses act through the springs only."""
    if scene == "cloth_onto_box":
        model, v0 = _cloth_onto_small_box()
        loss = _loss_fn(model, 10, 4, particle_qd=v0, max_derivative=UNMOLLIFIED_MAX_DERIVATIVE)
    elif scene == "ball_into_cloth":
        model, qd0 = ball_into_hanging_cloth()
        loss = _loss_fn(model, 10, 8, body_qd=qd0)
    else:
        model, v0 = _cloth_onto_ground_plane()
        loss = _loss_fn(model, 12, 4, particle_qd=v0)
    mass, stiffness = _params(model)
    gm, gk, res = _gradients(loss, mass, stiffness)
    if scene == "cloth_onto_plane":
        # all resting on the plane at the separation every contact keeps (thickness 0 here:
        # 1e-4 of the scene's size)
        x = model.particle_q.numpy()
        separation = 1e-4 * np.linalg.norm(x.max(0) - x.min(0))
        np.testing.assert_allclose(res.particle_q[-1, :, 2].detach().numpy(), separation, rtol=1e-9)
    else:
        assert res.stats["contact_substeps"] >= 20 and res.stats["failsafe_substeps"] == 0
        assert res.stats["largest_system"] >= 2
    err_m, err_k = _check_directional(loss, mass, stiffness, gm, gk)
    print(f"{scene}: relative errors mass {err_m:.2e} stiffness {err_k:.2e}")
    assert err_m < GRAD_RTOL and err_k < GRAD_RTOL


def test_checkpointed_parameter_gradients_equal_the_full_tape():
    """(c) segments recomputed in the backward sum their parameter adjoints; outputs at several
    steps (not only the last) carry adjoints."""
    model, v0 = _cloth_onto_small_box()
    mass, stiffness = _params(model)
    grads = []
    for every in (None, 3, 4):
        m, k = mass.clone().requires_grad_(), stiffness.clone().requires_grad_()
        v = v0.clone().requires_grad_()
        res = rollout(model, 10, DT, 4, particle_qd=v, particle_mass=m, spring_stiffness=k, checkpoint_every=every)
        (res.particle_q[-1, :, 2].sum() + res.particle_qd[5, 3, 0] + res.particle_q[3, :, 1].sum()).backward()
        assert res.stats["contact_substeps"] > 0
        grads.append((m.grad.numpy().copy(), k.grad.numpy().copy(), v.grad.numpy().copy()))
    for other in grads[1:]:
        for a, b in zip(other, grads[0]):
            np.testing.assert_allclose(a, b, rtol=CHECKPOINT_RTOL, atol=CHECKPOINT_RTOL * np.abs(b).max())


def test_only_requested_parameter_gradients_and_same_values():
    """The model's own values given as tensors reproduce the default rollout exactly; a parameter
    without requires_grad gets no gradient while the others do."""
    model = _hanging_cloth()
    mass, stiffness = _params(model)
    base = rollout(model, 5, DT, 2)
    k = stiffness.clone().requires_grad_()
    res = rollout(model, 5, DT, 2, particle_mass=mass, spring_stiffness=k)
    np.testing.assert_array_equal(res.particle_q.detach().numpy(), base.particle_q.numpy())
    res.particle_q[-1, :, 2].sum().backward()
    assert mass.grad is None and k.grad is not None and float(k.grad.abs().max()) > 0.0


# ------------------------------------------------------------------------------ closed form


def _oscillator(length, stretch, speed, mass):
    """A free particle on a spring (rest ``length``) to a pinned one at the origin, along x,
    started at ``length + stretch`` with velocity ``speed``; no gravity, no damping."""
    b = ModelBuilder()
    b.set_gravity((0.0, 0.0, 0.0))
    b.add_particle((0.0, 0.0, 0.0), pinned=True)
    b.add_particle((length + stretch, 0.0, 0.0), velocity=(speed, 0.0, 0.0), mass=mass)
    model = b.finalize()

    def arr(a, dtype):
        return wp.array(np.asarray(a), dtype=dtype, device=model.device)

    return dataclasses.replace(
        model, spring_count=1, spring_indices=arr([[0, 1]], wp.int32), spring_rest_length=arr([length], wp.float64),
        spring_stiffness=arr([1.0], wp.float64), spring_damping=arr([0.0], wp.float64))


def test_spring_oscillator_matches_the_discrete_closed_form():
    """Semi-implicit Euler of ``y'' = -(k/m) y`` (y the stretch) is ``[y, v]_{n+1} = A [y, v]_n``
    with ``A = [[1 - h^2 w, h], [-h w, 1]]``, ``w = k / m``: det A = 1 and trace A = 2 cos(theta),
    so ``A^N = (sin(N theta) A - sin((N-1) theta) I) / sin(theta)`` (Cayley-Hamilton). sympy
    differentiates ``y_N`` w.r.t. k and m; the rollout's gradients must agree to float64
    round-off over the N = 240 substeps (1e-9 relative). As a check that this is the oscillator,
    the discrete derivatives are within 2 % of the continuous ones
    (``y(T) = y0 cos(wT) + v0/w sin(wT)``, ``w = sqrt(k/m)``): the scheme's error is O(h w),
    h w = 0.024 here."""
    length, stretch, speed, k_val, m_val = 0.5, 0.05, 0.1, 40.0, 0.3
    steps, substeps = 30, 8
    model = _oscillator(length, stretch, speed, 1.0)
    m = torch.tensor([0.0, m_val], dtype=torch.float64, requires_grad=True)
    k = torch.tensor([k_val], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, DT, substeps, particle_mass=m, spring_stiffness=k)
    res.particle_q[-1, 1, 0].backward()

    ks, ms = sp.symbols("k m", positive=True)
    h = sp.Rational(1, 60 * substeps)
    n = steps * substeps
    y0, v0 = sp.Rational(1, 20), sp.Rational(1, 10)
    w = ks / ms
    theta = sp.acos(1 - h**2 * w / 2)
    y_n = (sp.sin(n * theta) * ((1 - h**2 * w) * y0 + h * v0) - sp.sin((n - 1) * theta) * y0) / sp.sin(theta)
    at = {ks: sp.Float(k_val, 40), ms: sp.Float(m_val, 40)}
    expected = [float(y_n.subs(at).evalf(30)) + length,
                float(sp.diff(y_n, ks).subs(at).evalf(30)), float(sp.diff(y_n, ms).subs(at).evalf(30))]
    got = [float(res.particle_q[-1, 1, 0].detach()), float(k.grad[0]), float(m.grad[1])]
    print("oscillator: relative errors", np.abs(np.subtract(got, expected)) / np.abs(expected))
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    assert float(m.grad[0]) == 0.0  # the pinned particle

    omega, t = sp.sqrt(ks / ms), sp.Rational(steps, 60)
    y_t = y0 * sp.cos(omega * t) + v0 / omega * sp.sin(omega * t)
    continuous = [float(sp.diff(y_t, s).subs(at).evalf(30)) for s in (ks, ms)]
    print("oscillator: discrete vs continuous", np.abs(np.subtract(expected[1:], continuous)) / np.abs(continuous))
    np.testing.assert_allclose(expected[1:], continuous, rtol=0.02)


# ------------------------------------------------------------------------------ input checks


def _tensor(values, dtype=torch.float64):
    return torch.tensor(values, dtype=dtype)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"particle_mass": "heavy"}, "particle_mass"),
        ({"particle_mass": np.ones(16)}, "particle_mass"),
        ({"particle_mass": "shape"}, "particle_mass"),
        ({"particle_mass": "float32"}, "particle_mass"),
        ({"particle_mass": "nan"}, "particle_mass"),
        ({"particle_mass": "inf"}, "particle_mass"),
        ({"particle_mass": "negative"}, "particle_mass"),
        ({"particle_mass": "unpin"}, "particle_mass"),
        ({"particle_mass": "pin"}, "particle_mass"),
        ({"spring_stiffness": "shape"}, "spring_stiffness"),
        ({"spring_stiffness": "float32"}, "spring_stiffness"),
        ({"spring_stiffness": "nan"}, "spring_stiffness"),
        ({"spring_stiffness": "negative"}, "spring_stiffness"),
        ({"spring_stiffness": [1.0, 2.0]}, "spring_stiffness"),
    ],
)
def test_bad_parameters_raise_value_error_naming_the_argument(kwargs, name, monkeypatch):
    model = _hanging_cloth()
    mass, stiffness = _params(model)
    base = {"particle_mass": mass, "spring_stiffness": stiffness}[name]
    value = kwargs[name]
    if isinstance(value, str):
        v = base.clone()
        if value == "shape":
            v = torch.cat([v, v[:1]])
        elif value == "float32":
            v = v.float()
        elif value == "nan":
            v[1] = float("nan")
        elif value == "inf":
            v[1] = float("inf")
        elif value == "negative":
            v[1] = -v[1]
        elif value == "unpin":
            v[0] = 0.01  # particle 0 is pinned in the model
        elif value == "pin":
            v[1] = 0.0  # particle 1 is free in the model
        else:
            v = value
        value = v

    import sim.rollout as sr

    def no_run(*a, **k):  # nothing may run before the check
        raise AssertionError("the rollout started")

    monkeypatch.setattr(sr._Runner, "forward", no_run)
    with pytest.raises(ValueError, match=name):
        rollout(model, 2, DT, 1, **{name: value})
