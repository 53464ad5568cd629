"""Rollout gradients against closed-form physics (no finite differences, no code under test).

* Elastic head-on collision of two equal rigid boxes (no gravity, no friction): the velocities
  swap at ``t*``, so along the line ``x_A(T) = x_A0 + v_A t* + v_B (T - t*)`` with
  ``t* = gap / (v_A - v_B)``. Differentiating (``t*`` moves with the velocities) gives exactly
  ``d(x_A, x_B)(T) / d(v_A, v_B) = [[0, T], [T, 0]]``. A simulator that treats the time of impact
  as a constant (Liang et al. 2019, Qiao et al. 2020) gets ``[[t*, T - t*], [T - t*, t*]]``.
* An elastic bounce off a static face without gravity: ``x(T)`` is the mirror image of the free
  flight, so ``d x(T) / d v0 = T (I - 2 n n^T)``: ``-T`` across the face, ``T`` along it.

The contacts are small (a 1 cm step onto a 20 cm face) on purpose: the mollifier's bound ``M``
must not clamp a transversal contact whatever the scene's length scale.
"""

import numpy as np
import pytest
import torch

from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh
from sim.rollout import rollout

DT = 1.0 / 60.0
STEPS = 30
T = STEPS * DT
# the impulse solve's Tikhonov term (sim.contact.tuning.REGULARIZATION = 1e-8) perturbs an
# elastic swap at that level; nothing else in the closed form is approximate
ATOL = 1e-7


def _corner_first_rotation():
    """The quaternion turning the body diagonal (1, 1, 1) onto +x: a box then meets a face
    corner first, on the line through both centres of mass (no torque)."""
    angle = np.arccos(1.0 / np.sqrt(3.0))
    axis = np.array([0.0, 1.0, -1.0]) / np.sqrt(2.0)
    return (*(axis * np.sin(angle / 2.0)), np.cos(angle / 2.0))


def _swap_time(v_a, v_b):
    corner = 0.1 * np.sqrt(3.0)  # body diagonal half length of box A (it leads with a corner)
    gap = (0.5 - 0.1) - (-0.5 + corner)
    return gap / (v_a - v_b)


@pytest.mark.parametrize("substeps", [1, 2])
def test_elastic_head_on_boxes_swap_and_jacobian_is_0_T_T_0(substeps):
    b = ModelBuilder(gravity=0.0)
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(-0.5, 0.0, 0.0), rot=_corner_first_rotation())
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(0.5, 0.0, 0.0))
    b.set_contact(restitution=1.0, friction=0.0, thickness=0.0)
    model = b.finalize()
    v_a, v_b = 1.5, -0.5
    t_star = _swap_time(v_a, v_b)
    assert 0.0 < t_star < T
    jac = np.zeros((2, 2))
    for row in range(2):
        twist = torch.tensor([[0, 0, 0, v_a, 0, 0], [0, 0, 0, v_b, 0, 0]], dtype=torch.float64, requires_grad=True)
        res = rollout(model, STEPS, DT, substeps, body_qd=twist)
        res.body_q[-1, row, 0].backward()
        jac[row] = twist.grad[:, 3].numpy()
    assert res.stats["contact_substeps"] >= 1 and res.stats["failsafe_substeps"] == 0
    # the physics first: the velocities swapped and the positions are the closed form's
    np.testing.assert_allclose(res.body_qd[-1, :, 3].detach().numpy(), [v_b, v_a], atol=ATOL)
    x_a0, x_b0 = -0.5, 0.5
    expected = [x_a0 + v_a * t_star + v_b * (T - t_star), x_b0 + v_b * t_star + v_a * (T - t_star)]
    np.testing.assert_allclose(res.body_q[-1, :, 0].detach().numpy(), expected, atol=ATOL)
    np.testing.assert_allclose(jac, [[0.0, T], [T, 0.0]], atol=ATOL)
    # and not the constant-time-of-impact answer
    assert abs(jac[0, 0] - t_star) > 0.1


@pytest.mark.parametrize("normal_axis", [0, 2])
def test_elastic_bounce_off_a_static_face_mirrors_the_jacobian(normal_axis):
    start = np.array([0.513, 0.521, 0.517])
    start[normal_axis] = 0.7537  # not a whole number of substeps from the face
    velocity = np.array([0.2, -0.1, 0.15])
    velocity[normal_axis] = -1.5
    b = ModelBuilder(gravity=0.0)
    b.add_particle(start, mass=0.1)
    b.add_static_mesh(*box_mesh(0.1), pos=(0.5, 0.5, 0.5))
    b.set_contact(restitution=1.0, friction=0.0, thickness=0.0)
    model = b.finalize()
    jac = np.zeros((3, 3))
    for row in range(3):
        v = torch.tensor(velocity[None], dtype=torch.float64, requires_grad=True)
        res = rollout(model, STEPS, DT, 2, particle_qd=v)
        res.particle_q[-1, 0, row].backward()
        jac[row] = v.grad.numpy()[0]
    assert res.stats["contact_substeps"] == 1 and res.stats["failsafe_substeps"] == 0
    n = np.zeros(3)
    n[normal_axis] = 1.0
    mirror = np.eye(3) - 2.0 * np.outer(n, n)
    free = start + T * velocity
    plane = 0.6
    expected = free.copy()
    expected[normal_axis] = 2.0 * plane - free[normal_axis]
    np.testing.assert_allclose(res.particle_q[-1, 0].detach().numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(jac, T * mirror, atol=1e-10)


def _wall(gap: float):
    b = ModelBuilder(gravity=0.0)
    b.add_particle((0.0, 1.75 - gap, 1.0), mass=1.0)
    b.add_static_mesh(*box_mesh(np.array([1.0, 0.25, 1.0])), pos=(0.0, 2.0, 1.0))
    b.set_contact(restitution=1.0, friction=0.0, thickness=0.0)
    return b.finalize()


def _wall_bounce(gap: float, speed: float = 5.0, steps: int = 4, h: float = 0.05):
    """A particle ``gap`` [m] in front of a static wall (face at y = 1.75), moving at ``speed``
    into it, no gravity, elastic: (final y, d final y / d v_y, rollout result)."""
    v = torch.tensor([[0.0, speed, 0.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(_wall(gap), steps, h, 1, particle_qd=v)
    res.particle_q[-1, 0, 1].backward()
    return float(res.particle_q[-1, 0, 1].detach()), float(v.grad[0, 1]), res


def test_contact_at_the_very_end_of_a_substep_bounces_instead_of_freezing():
    """The particle reaches the wall exactly at the end of the first step (gap = v h): it must
    bounce (velocity -v, no impact-zone fail-safe), where it used to be frozen by the fail-safe."""
    y, _, res = _wall_bounce(0.25)
    assert res.stats["failsafe_substeps"] == 0
    np.testing.assert_allclose(res.particle_qd[-1, 0, 1].detach().numpy(), -5.0, rtol=1e-6)
    np.testing.assert_allclose(y, 2 * 1.75 - (1.5 + 1.0), atol=1e-6)


@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_tangential_gradient_of_a_head_on_plane_impact(friction):
    """A particle falls straight onto the ground plane (no tangential velocity at all) and rests
    there. Without friction its horizontal motion is free: d x_T / d v_x = T exactly, also where
    the tangential velocity is exactly zero. With friction a small horizontal velocity sticks at
    the impact (the normal impulse stops it), so the derivative is the time before the impact."""
    b = ModelBuilder()
    b.friction = friction
    b.add_particle((0.0, 0.0, 0.3))
    b.add_ground_plane()
    model = b.finalize()
    steps = 30
    v = torch.zeros((1, 3), dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps, DT, 8, particle_qd=v)
    res.particle_q[-1, 0, 0].backward()
    z = res.particle_q[:, 0, 2].detach().numpy()
    assert z[-1] < 1e-3  # it landed and rests
    expected = steps * DT if friction == 0.0 else np.sqrt(2 * 0.3 / 9.81)  # free, or until the impact
    tol = 1e-12 if friction == 0.0 else DT / 8  # the impact's substep
    assert abs(float(v.grad[0, 0]) - expected) <= tol, (float(v.grad[0, 0]), expected)


def _drop_height_and_gradient(floor: str, restitution: float, substeps: int = 8, exact_gravity: bool = False):
    """A particle dropped at 1 m/s from 0.5 m above a floor under gravity: its height after
    0.5 s and the height's derivative with respect to its initial vertical velocity. The floor
    is a ground plane (the integrator's plane stage) or the top face of a static box (the
    collision handler's mesh contacts)."""
    b = ModelBuilder()
    if floor == "plane":
        b.add_particle((0.0, 0.0, 0.5), mass=0.1)
        b.add_ground_plane()
        base = 0.0
    else:
        b.add_particle((0.0, 0.0, 0.6), mass=0.1)
        b.add_static_mesh(*box_mesh((0.3, 0.3, 0.1)))  # its top face at z = 0.1 m
        base = 0.1
    b.set_contact(restitution=restitution, friction=0.0)
    model = b.finalize()
    v0 = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(model, steps=STEPS, dt=DT, substeps=substeps, particle_qd=v0,
                  integrator_options={"exact_gravity": True} if exact_gravity else None)
    height = res.particle_q[-1, 0, 2]
    height.backward()
    return height.item() - base, float(v0.grad[0, 2])


def _drop_closed_form(restitution: float, speed: float = 1.0, drop: float = 0.5, g: float = 9.81):
    """Height above the floor after ``T`` and its derivative with respect to the initial
    vertical velocity ``-speed`` (one bounce, the time of impact moving with the speed)."""
    def height(u):
        t_hit = (-u + np.sqrt(u * u + 2.0 * g * drop)) / g
        rest = T - t_hit
        return restitution * (u + g * t_hit) * rest - 0.5 * g * rest * rest

    step = 1e-6
    return height(speed), -(height(speed + step) - height(speed - step)) / (2.0 * step)


@pytest.mark.parametrize("restitution,exact_gravity", [(0.5, False), (1.0, False), (0.5, True)])
def test_a_bounce_off_a_mesh_floor_follows_the_plane_law(restitution, exact_gravity):
    """Mesh contacts and ground planes share one contact law (the rebound at ``t*``, then
    gravity over the rest of the substep): the same drop bounces to the same height, with the
    same gradient, whichever floor it lands on, and both follow the closed form (the gradient
    to 5 %, the height to 2 mm at 8 substeps of 1/60 s: semi-implicit Euler's first-order
    flight, 1.3 mm for ``e = 1``). Reflecting the velocity alone made the
    height a sawtooth of the initial speed whose slope missed ``g (h - t*) dt*/dv``: the
    gradient came out -0.157 instead of +0.028 for ``e = 0.5``. Under the exact ballistic
    update (whose stored velocity is the substep's end one) the law takes no half substep of
    gravity into the velocity at ``t*``, for the plane and the mesh alike (the mesh contact's
    positions within the contact substep stay semi-implicit: a few 1e-5 m)."""
    height, gradient = _drop_closed_form(restitution)
    plane = _drop_height_and_gradient("plane", restitution, exact_gravity=exact_gravity)
    mesh = _drop_height_and_gradient("mesh", restitution, exact_gravity=exact_gravity)
    if exact_gravity:
        # the mesh contact's time-of-impact positions stay semi-implicit (no drift within the
        # contact substep): 2.7e-5 m and 0.8 % of the gradient here
        assert abs(mesh[0] - plane[0]) < 1e-4 and abs(mesh[1] - plane[1]) < 0.02 * abs(plane[1])
    else:
        assert abs(mesh[0] - plane[0]) < 1e-6 and abs(mesh[1] - plane[1]) < 1e-6 * max(1.0, abs(plane[1]))
    assert abs(mesh[0] - height) < 2e-3
    assert abs(mesh[1] - gradient) < 0.05 * abs(gradient) + 1e-3
