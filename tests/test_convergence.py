"""Convergence on closed forms (small versions of ``benchmarks/convergence.py``).

Ground truth is closed-form mechanics (or, for the swinging strip, a DOP853 integration of its
equations of motion): free flight ``x0 + v0 t + g t^2 / 2``; the piecewise
parabola of a restitution bounce with impact times in closed form; Newton's elastic impact on
a free rigid body through its effective mass at the contact point.
"""

from __future__ import annotations

import math

import pytest

from benchmarks import convergence


@pytest.mark.parametrize("check", ["ballistic", "bounce"])
def test_first_order_in_the_substep(check):
    """Semi-implicit Euler's position error halves as the substeps double (first order): the
    ratio of the errors at 8 and 16 substeps is 2 within 5 %, and the error at 8 substeps is
    below 1 cm."""
    function = convergence.CHECKS[check][1]
    e8, e16 = function(8), function(16)
    assert e8 < 1e-2
    assert e8 / e16 == pytest.approx(2.0, rel=0.05)
    assert convergence.fitted_order([8, 16], [e8, e16]) == pytest.approx(1.0, abs=0.05)


def test_elastic_hit_on_a_free_box_is_exact():
    """The particle's velocity after an elastic hit off the box's centre matches
    ``(m_e - m1) / (m1 + m_e) v`` to rounding at 8 substeps (the impact is resolved at its time
    of impact, whatever the substep)."""
    assert convergence.elastic_hit(8) < 1e-12


def test_fitted_order():
    assert convergence.fitted_order([4, 8, 16], [1e-2, 2.5e-3, 6.25e-4]) == pytest.approx(2.0)
    assert convergence.fitted_order([4, 8], [1e-17, 1e-18]) == math.inf
    assert convergence.fitted_order([4, 8], [1e-3, 1e-18]) is None


def test_exact_ballistic_update():
    """``exact_gravity=True``: free flight under gravity is exact to rounding at 8 substeps, and
    a restitution bounce on a plane is second order (its impact time is taken on the substep's
    straight path): the error at 8 substeps is below 2e-5 m and falls at least 3.5x at 16."""
    assert convergence.ballistic_exact(8) < 1e-12
    e8, e16 = convergence.bounce_exact(8), convergence.bounce_exact(16)
    assert e8 < 2e-5 and e8 / e16 > 3.5


def test_exact_ballistic_update_in_a_rollout_is_exact_and_differentiable():
    """Through ``rollout(integrator_options={"exact_gravity": True})`` a thrown particle lands
    on ``x0 + v0 t + g t^2 / 2`` to rounding, and the gradient of its final height w.r.t. the
    initial vertical velocity is ``t`` exactly."""
    import torch

    from sim.builder import ModelBuilder
    from sim.rollout import rollout

    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 1.0), mass=1.0)
    model = b.finalize("cpu")
    v0 = torch.tensor([[1.0, 0.0, 3.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(model, 30, 1.0 / 60.0, 4, particle_qd=v0, integrator_options={"exact_gravity": True})
    t = 0.5
    z = res.particle_q[-1, 0, 2]
    assert abs(float(z.detach()) - (1.0 + 3.0 * t - 0.5 * 9.81 * t * t)) < 1e-12
    z.backward()
    assert abs(float(v0.grad[0, 2]) - t) < 1e-12
    with pytest.raises(ValueError, match="exact_gravity"):
        rollout(model, 1, 1.0 / 60.0, 1, integrator_options={"exact_gravity": 1})


def test_exact_ballistic_update_leaves_pinned_particles_alone():
    """A pinned particle above a ground plane stays exactly where it is under the exact
    ballistic update (the drift moves free particles only), beside a free one that falls."""
    from sim.builder import ModelBuilder
    from sim.integrators import make_integrator

    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 0.5), mass=1.0, pinned=True)
    b.add_particle((1.0, 0.0, 0.5), mass=1.0)
    b.add_ground_plane()
    model = b.finalize("cpu")
    integ = make_integrator(model, exact_gravity=True)
    s, nxt = model.state(), model.state()
    for _ in range(30):
        integ.step(s, nxt, 1.0 / 60.0, 8)
        s, nxt = nxt, s
    x = s.particle_q.numpy()
    assert x[0].tolist() == [0.0, 0.0, 0.5]
    assert x[1, 2] < 0.5 - 0.1


def test_swinging_strip_converges_first_order_to_an_independent_reference():
    """A cloth strip pinned at one edge swings down under gravity: its largest position error
    at 0.5 s against a DOP853 integration (rtol 1e-12) of the same equations of motion, written
    in numpy from the model's arrays, is below 2 mm at 8 substeps and halves at 16 (first order;
    measured 1.66e-3 / 8.05e-4 m)."""
    e8, e16 = convergence.strip(8), convergence.strip(16)
    assert e8 < 2e-3
    assert e8 / e16 == pytest.approx(2.0, rel=0.1)
