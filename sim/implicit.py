"""Implicit (backward-Euler) cloth integration: :class:`ImplicitIntegrator`.

The springs of a mass-spring cloth are integrated with one Baraff-Witkin Newton step of backward
Euler per substep (:mod:`kernels.implicit` has the system), so stiff or fine cloth runs at steps
where semi-implicit Euler diverges. The linear system is solved matrix-free by Jacobi-
preconditioned conjugate gradients in Warp kernels on the model's device (a scalar or two read
back per iteration). Rigid bodies, planes and the collision handler run after it exactly as
after :class:`sim.integrator.SemiImplicitIntegrator`.

Differentiable by implicit differentiation: under a ``wp.Tape`` the solve is one recorded
function whose backward solves the same (symmetric) system for the adjoint ``lambda`` of the
velocity change, adds it to the right-hand side's adjoint, and adds ``-d<lambda, A(x) dv>/dx``
(and the model arrays' share) by replaying the operator's kernels on a small tape. No CG
iteration is ever taped, so the gradient is the derivative of the solved step, to the solve's
tolerance.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from collision.replay import active_tape, paused_tape
from kernels.implicit import (
    add_kernel,
    cg_direction_kernel,
    cg_step_kernel,
    dot_kernel,
    implicit_rhs,
    implicit_update,
    jacobi_kernel,
    mass_operator,
    negate_kernel,
    spring_diagonal,
    spring_operator,
)
from sim.integrator import SemiImplicitIntegrator
from sim.model import Model, State

DEFAULT_TOLERANCE = 1.0e-8
"""Relative residual ``|r| / |b|`` at which conjugate gradients stop."""
DEFAULT_MAX_ITERATIONS = 2000


def check_options(tolerance: float = DEFAULT_TOLERANCE, max_iterations: int = DEFAULT_MAX_ITERATIONS) -> None:
    """Raises ``ValueError`` naming the option for a CG tolerance that is not a positive finite
    number or an iteration cap that is not an integer >= 1."""
    if isinstance(tolerance, bool) or not (isinstance(tolerance, (int, float)) and np.isfinite(tolerance)
                                           and tolerance > 0.0):
        raise ValueError(f"tolerance must be a positive finite number, got {tolerance!r}")
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
        raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")


class SolveError(RuntimeError):
    """Conjugate gradients did not reach the tolerance within the iteration cap."""


class ImplicitIntegrator(SemiImplicitIntegrator):
    """Backward-Euler springs + the semi-implicit integrator's bodies, planes and collisions.

    Args:
        model: the finalised Model (float64).
        requires_grad: as for :class:`sim.integrator.SemiImplicitIntegrator`.
        tolerance: CG's relative residual (> 0).
        max_iterations: CG's iteration cap (>= 1); reaching it raises :class:`SolveError`.

    Attributes:
        iterations: CG iterations of the last solve (forward), and their running total in
            ``total_iterations``.
    """

    def __init__(self, model: Model, requires_grad: bool | None = None, tolerance: float = DEFAULT_TOLERANCE,
                 max_iterations: int = DEFAULT_MAX_ITERATIONS):
        super().__init__(model, requires_grad)
        check_options(tolerance, max_iterations)
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.iterations = 0
        self.total_iterations = 0
        n = model.particle_count
        d = self.device
        # CG's work arrays (never taped, reused)
        self._r = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._z = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._p = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._ap = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._diag = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._dot_out = wp.zeros(1, dtype=wp.float64, device=d)
        self._ones = wp.array(np.ones((n, 3)), dtype=wp.vec3d, device=d)

    # ------------------------------------------------------------------ the operator
    def _apply(self, x, p, y, h: float, coef_x: float | None = None, coef_v: float | None = None,
               mass: bool = True) -> None:
        """``y = (M + coef_v Kd + coef_x Kx)(x) p`` (defaults: the system's ``h`` and ``h^2``);
        without ``mass`` the springs' part is added to ``y`` (a fresh zeroed array)."""
        m, d = self.model, self.device
        cx = h * h if coef_x is None else coef_x
        cv = h if coef_v is None else coef_v
        if mass:
            wp.launch(mass_operator, dim=m.particle_count, inputs=[p, m.particle_inv_mass], outputs=[y], device=d)
        if self._spring_indices is not None:
            wp.launch(spring_operator, dim=m.spring_count,
                      inputs=[x, self._spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping,
                              m.particle_inv_mass, wp.float64(cx), wp.float64(cv), p],
                      outputs=[y], device=d)

    def _dot(self, a, b) -> float:
        self._dot_out.zero_()
        wp.launch(dot_kernel, dim=a.shape[0], inputs=[a, b], outputs=[self._dot_out], device=self.device)
        return float(self._dot_out.numpy()[0])

    def solve(self, x, b, out, h: float) -> int:
        """Solves ``A(x) out = b`` by Jacobi-preconditioned CG from ``out = 0``; returns the
        iterations. Raises :class:`SolveError` at the cap and ``ValueError`` on a non-finite
        right-hand side."""
        m, d, n = self.model, self.device, self.model.particle_count
        with paused_tape():  # CG's in-place updates are not replayable; the adjoint is recorded instead
            wp.launch(mass_operator, dim=n, inputs=[self._ones, m.particle_inv_mass], outputs=[self._diag], device=d)
            if self._spring_indices is not None:
                wp.launch(spring_diagonal, dim=m.spring_count,
                          inputs=[x, self._spring_indices, m.spring_rest_length, m.spring_stiffness,
                                  m.spring_damping, m.particle_inv_mass, wp.float64(h * h), wp.float64(h)],
                          outputs=[self._diag], device=d)
            out.zero_()
            wp.copy(self._r, b)
            b_norm = np.sqrt(self._dot(b, b))
            if not np.isfinite(b_norm):
                raise ValueError("implicit step: the right-hand side is not finite (NaN or inf in the state)")
            if b_norm == 0.0:
                return 0
            wp.launch(jacobi_kernel, dim=n, inputs=[self._r, self._diag], outputs=[self._z], device=d)
            wp.copy(self._p, self._z)
            rz = self._dot(self._r, self._z)
            for it in range(1, self.max_iterations + 1):
                self._apply(x, self._p, self._ap, h)
                pap = self._dot(self._p, self._ap)
                if not pap > 0.0:
                    raise SolveError(f"implicit step: the system is not positive definite (p.Ap = {pap:g})")
                alpha = rz / pap
                wp.launch(cg_step_kernel, dim=n, inputs=[wp.float64(alpha), self._p, self._ap], outputs=[out, self._r],
                          device=d)
                if np.sqrt(self._dot(self._r, self._r)) <= self.tolerance * b_norm:
                    return it
                wp.launch(jacobi_kernel, dim=n, inputs=[self._r, self._diag], outputs=[self._z], device=d)
                rz_new = self._dot(self._r, self._z)
                wp.launch(cg_direction_kernel, dim=n, inputs=[wp.float64(rz_new / rz), self._z], outputs=[self._p],
                          device=d)
                rz = rz_new
        raise SolveError(f"implicit step: CG did not reach the relative residual {self.tolerance:g} in "
                         f"{self.max_iterations} iterations (raise max_iterations or the tolerance, or add substeps)")

    # ------------------------------------------------------------------ the step
    def _integrate_particles(self, s_in: State, pred: State, h: float, requires_grad: bool) -> None:
        m, d, n = self.model, self.device, self.model.particle_count
        x0, v0 = s_in.particle_q, s_in.particle_qd
        f = self._spring_forces(s_in, requires_grad)
        stiff_v0 = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        self._apply(x0, v0, stiff_v0, h, coef_x=h * h, coef_v=0.0, mass=False)
        b = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        wp.launch(implicit_rhs, dim=n, inputs=[f, stiff_v0, m.particle_inv_mass, self.gravity, wp.float64(h)],
                  outputs=[b], device=d)
        dv = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        self.iterations = self.solve(x0, b, dv, h)
        self.total_iterations += self.iterations
        tape = active_tape()
        if requires_grad and tape is not None:
            # only arrays with gradients (the input state may have none: model arrays only)
            tape.record_func(backward=lambda: self._solve_adjoint(x0, b, dv, h),
                             arrays=[a for a in (x0, b, dv) if a.requires_grad])
        wp.launch(implicit_update, dim=n, inputs=[x0, v0, dv, m.particle_inv_mass, wp.float64(h)],
                  outputs=[pred.particle_q, pred.particle_qd], device=d)

    def _solve_adjoint(self, x0, b, dv, h: float) -> None:
        """Backward of ``dv = A(x0)^-1 b``: ``lambda = A^-T dv.grad`` (A is symmetric);
        ``b.grad += lambda``; ``x0.grad`` (and the model arrays' grads) ``+= -d<lambda, A(x0) dv>``."""
        n, d = self.model.particle_count, self.device
        lam = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.solve(x0, dv.grad, lam, h)
        wp.launch(add_kernel, dim=n, inputs=[lam], outputs=[b.grad], device=d)
        # replay the operator on a small tape: d<lambda, A(x) dv>/dx with dv held fixed
        dv_fixed = wp.clone(dv, requires_grad=False)
        y = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=True)
        sub = wp.Tape()
        with sub:
            self._apply(x0, dv_fixed, y, h)
        wp.launch(negate_kernel, dim=n, inputs=[lam], outputs=[y.grad], device=d)
        sub.backward()
