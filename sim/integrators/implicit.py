"""Implicit (backward-Euler) cloth integration: :class:`ImplicitIntegrator`.

The springs of a mass-spring cloth are integrated with one Baraff-Witkin Newton step of backward
Euler per substep (:mod:`kernels.implicit` has the system), so stiff or fine cloth runs at steps
where semi-implicit Euler diverges. The linear system is solved matrix-free by Jacobi-
preconditioned conjugate gradients in Warp kernels on the model's device (two scalars read
back per iteration). Rigid bodies, planes and the collision handler run after it as after
:class:`sim.integrators.semi_implicit.SemiImplicitIntegrator`, with two additions for large steps with contacts
(both decided off the tape, then replayed on it): particles the collision stage moved are held
in a constrained re-solve (``contact_passes``, :meth:`ImplicitIntegrator._substep`), and a
substep whose springs' strain grows too fast is halved (``max_strain_step``,
:meth:`ImplicitIntegrator.step`).

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

from core.buffers import upload
from core.tape import active_tape, paused_tape
from kernels.implicit import (
    add_kernel,
    cg_direction_kernel,
    cg_update_kernel,
    collided_particles,
    constrained_rhs,
    constrained_velocity_change,
    dot_kernel,
    held_velocity,
    implicit_rhs,
    implicit_update,
    jacobi_kernel,
    mass_operator,
    negate_kernel,
    spring_block_operator,
    spring_blocks,
    spring_diagonal,
    strain_growth,
    sum_kernel,
)
from sim.integrators.semi_implicit import SemiImplicitIntegrator, copy_state, requires_grad_of, shares_arrays
from sim.model import Model, State

DEFAULT_TOLERANCE = 1.0e-8
"""Relative residual ``|r| / |b|`` at which conjugate gradients stop."""
DEFAULT_MAX_ITERATIONS = 2000
DEFAULT_CONTACT_PASSES = 1
"""Constrained re-solves per substep at most (see :meth:`ImplicitIntegrator._substep`)."""
DEFAULT_MAX_STRAIN_STEP = 0.1
"""Largest increase of a spring's strain in one substep before the substep is halved (see
:meth:`ImplicitIntegrator.step`)."""
DEFAULT_MAX_REFINEMENTS = 4
"""Halvings of a substep at most (a substep is split into at most ``2**4 = 16``)."""


OPTIONS = ("tolerance", "max_iterations", "contact_passes", "max_strain_step", "max_refinements")
"""The implicit integrator's options (keyword arguments of :class:`ImplicitIntegrator`)."""


def check_options(tolerance: float = DEFAULT_TOLERANCE, max_iterations: int = DEFAULT_MAX_ITERATIONS,
                  contact_passes: int = DEFAULT_CONTACT_PASSES, max_strain_step: float | None = DEFAULT_MAX_STRAIN_STEP,
                  max_refinements: int = DEFAULT_MAX_REFINEMENTS) -> None:
    """Raises ``ValueError`` naming the option for a CG tolerance that is not a positive finite
    number, an iteration cap that is not an integer >= 1, ``contact_passes`` or
    ``max_refinements`` that is not an integer >= 0, or a ``max_strain_step`` that is neither None
    (no refinement) nor a positive finite number."""
    if isinstance(tolerance, bool) or not (isinstance(tolerance, (int, float)) and np.isfinite(tolerance)
                                           and tolerance > 0.0):
        raise ValueError(f"tolerance must be a positive finite number, got {tolerance!r}")
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
        raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    for name, value in (("contact_passes", contact_passes), ("max_refinements", max_refinements)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    if max_strain_step is not None and (isinstance(max_strain_step, bool) or not (
            isinstance(max_strain_step, (int, float)) and np.isfinite(max_strain_step) and max_strain_step > 0.0)):
        raise ValueError(f"max_strain_step must be None or a positive finite number, got {max_strain_step!r}")


def _save_stats(handler):
    """The collision handler's statistics (None when it keeps none)."""
    return handler.save_stats() if handler is not None and hasattr(handler, "save_stats") else None


def _restore_stats(handler, stats) -> None:
    if stats is not None:
        handler.restore_stats(stats)


class SolveError(RuntimeError):
    """Conjugate gradients did not reach the tolerance within the iteration cap."""


class ImplicitIntegrator(SemiImplicitIntegrator):
    """Backward-Euler springs + the semi-implicit integrator's bodies, planes and collisions.

    Args:
        model: the finalised Model (float64).
        requires_grad: as for :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator`.
        tolerance: CG's relative residual (> 0).
        max_iterations: CG's iteration cap (>= 1); reaching it raises :class:`SolveError`.
        contact_passes: constrained re-solves per substep for the particles in contact (>= 0;
            0: the collision stage only corrects the solve's prediction, as after the explicit
            step).
        max_strain_step: a substep in which some spring's strain grows by more than this is
            halved (None: never).
        max_refinements: halvings of one substep at most (>= 0).
        capture: as for :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator` (the
            bodies' and planes' stages; the spring solve is launched one by one).

    Attributes:
        iterations: CG iterations of the last solve; ``total_iterations``: all CG iterations
            run (work done: rejected attempts and a taped step's decision run included).
        constrained: particles held in the last substep's re-solves; ``total_constrained``:
            their running total over the kept substeps.
        refinements: substeps added by halving, over the integrator's life.
    """

    def __init__(self, model: Model, requires_grad: bool | None = None, tolerance: float = DEFAULT_TOLERANCE,
                 max_iterations: int = DEFAULT_MAX_ITERATIONS, contact_passes: int = DEFAULT_CONTACT_PASSES,
                 max_strain_step: float | None = DEFAULT_MAX_STRAIN_STEP,
                 max_refinements: int = DEFAULT_MAX_REFINEMENTS, capture: bool | None = None):
        if model.sphere_count:
            raise ValueError("the implicit integrator steps cloth; a model with spheres takes the semi-implicit one")
        super().__init__(model, requires_grad, capture=capture)
        check_options(tolerance, max_iterations, contact_passes, max_strain_step, max_refinements)
        self.max_strain_step = None if max_strain_step is None else float(max_strain_step)
        self.max_refinements = int(max_refinements)
        self.refinements = 0
        self._growth = wp.zeros(1, dtype=wp.float64, device=model.device)
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.contact_passes = int(contact_passes)
        self.iterations = 0
        self.total_iterations = 0
        self.constrained = 0
        self.total_constrained = 0
        n = model.particle_count
        d = self.device
        # the second solve's constraint (set by _substep between its two passes)
        self._fixed = None
        self._x_target = None
        self._last_pred = None
        self._no_fixed = wp.zeros(n, dtype=wp.int32, device=d)
        self._body_touch = wp.zeros(n, dtype=wp.int32, device=d)  # a decision mask, refilled per trial (never taped)
        self._count = wp.zeros(1, dtype=wp.int32, device=d)
        # CG's work arrays (never taped, reused)
        self._r = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._z = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._p = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._ap = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._diag = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._dot_out = wp.zeros(1, dtype=wp.float64, device=d)
        self._dots = wp.zeros(2, dtype=wp.float64, device=d)
        springs = max(model.spring_count, 1)
        self._direction = wp.zeros(springs, dtype=wp.vec3d, device=d)
        self._along = wp.zeros(springs, dtype=wp.float64, device=d)
        self._across = wp.zeros(springs, dtype=wp.float64, device=d)
        self._ones = wp.array(np.ones((n, 3)), dtype=wp.vec3d, device=d)

    # ------------------------------------------------------------------ the operator
    def _apply(self, x, p, y, h: float, coef_x: float | None = None, coef_v: float | None = None,
               mass: bool = True, fixed=None) -> None:
        """``y = (M + coef_v Kd + coef_x Kx)(x) p`` (defaults: the system's ``h`` and ``h^2``);
        without ``mass`` the springs' part is added to ``y`` (a fresh zeroed array). ``fixed``
        (int32 (N,), default none) particles get identity rows and no columns, like pinned ones."""
        m, d = self.model, self.device
        cx = h * h if coef_x is None else coef_x
        cv = h if coef_v is None else coef_v
        fixed = self._no_fixed if fixed is None else fixed
        if mass:
            wp.launch(mass_operator, dim=m.particle_count, inputs=[p, m.particle_inv_mass, fixed], outputs=[y],
                      device=d)
        if self._spring_indices is not None:
            # fresh blocks: a taped product is differentiated through them (x, stiffness, damping)
            grad = active_tape() is not None
            blocks = (wp.zeros(m.spring_count, dtype=wp.vec3d, device=d, requires_grad=grad),
                      wp.zeros(m.spring_count, dtype=wp.float64, device=d, requires_grad=grad),
                      wp.zeros(m.spring_count, dtype=wp.float64, device=d, requires_grad=grad))
            self._blocks(x, cx, cv, blocks)
            wp.launch(spring_block_operator, dim=m.spring_count,
                      inputs=[self._spring_indices, *blocks, m.particle_inv_mass, fixed, p], outputs=[y], device=d)

    def _blocks(self, x, coef_x: float, coef_v: float, out) -> None:
        """The springs' blocks of ``coef_x Kx + coef_v Kd`` at ``x`` into ``out`` (direction,
        along, across)."""
        m = self.model
        wp.launch(spring_blocks, dim=m.spring_count,
                  inputs=[x, self._spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping,
                          wp.float64(coef_x), wp.float64(coef_v)],
                  outputs=list(out), device=self.device)

    def _dot(self, a, b) -> float:
        self._dot_out.zero_()
        wp.launch(dot_kernel, dim=a.shape[0], inputs=[a, b], outputs=[self._dot_out], device=self.device)
        return float(self._dot_out.numpy()[0])

    def solve(self, x, b, out, h: float, fixed=None) -> int:
        """Solves ``A(x) out = b`` by Jacobi-preconditioned CG from ``out = 0``; returns the
        iterations. ``fixed`` particles (int32 (N,)) have identity rows and no columns (their
        ``out`` is their ``b``). Raises :class:`SolveError` at the cap and ``ValueError`` on a non-finite
        right-hand side."""
        m, d, n = self.model, self.device, self.model.particle_count
        fixed = self._no_fixed if fixed is None else fixed
        with paused_tape():  # CG's in-place updates are not replayable; the adjoint is recorded instead
            wp.launch(mass_operator, dim=n, inputs=[self._ones, m.particle_inv_mass, fixed], outputs=[self._diag],
                      device=d)
            springs = self._spring_indices is not None
            if springs:
                self._blocks(x, h * h, h, (self._direction, self._along, self._across))
                wp.launch(spring_diagonal, dim=m.spring_count,
                          inputs=[self._spring_indices, self._direction, self._along, self._across,
                                  m.particle_inv_mass, fixed],
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
            dots = self._dots
            for it in range(1, self.max_iterations + 1):
                wp.launch(mass_operator, dim=n, inputs=[self._p, m.particle_inv_mass, fixed], outputs=[self._ap],
                          device=d)
                if springs:
                    wp.launch(spring_block_operator, dim=m.spring_count,
                              inputs=[self._spring_indices, self._direction, self._along, self._across,
                                      m.particle_inv_mass, fixed, self._p],
                              outputs=[self._ap], device=d)
                pap = self._dot(self._p, self._ap)
                if not pap > 0.0:
                    raise SolveError(f"implicit step: the system is not positive definite (p.Ap = {pap:g})")
                dots.zero_()
                wp.launch(cg_update_kernel, dim=n, inputs=[wp.float64(rz / pap), self._p, self._ap, self._diag],
                          outputs=[out, self._r, self._z, dots], device=d)
                rr, rz_new = dots.numpy()
                if np.sqrt(rr) <= self.tolerance * b_norm:
                    return it
                wp.launch(cg_direction_kernel, dim=n, inputs=[wp.float64(rz_new / rz), self._z], outputs=[self._p],
                          device=d)
                rz = rz_new
        raise SolveError(f"implicit step: CG did not reach the relative residual {self.tolerance:g} in "
                         f"{self.max_iterations} iterations (raise max_iterations or the tolerance, or add substeps)")

    # ------------------------------------------------------------------ the step
    def step(self, state_in: State, state_out: State, dt: float, substeps: int = 1) -> State:
        """Advances ``state_in`` by ``dt`` in ``substeps`` substeps into ``state_out``, halving a
        substep (up to ``max_refinements`` times) whose springs' strain grows by more than
        ``max_strain_step`` (a fast impact at a large step: stopped particles, neighbours falling
        on). The halvings are decided off the tape; under an active tape the decided substeps
        are then replayed on it (decide, then replay), so a taped step costs the decision run
        besides. ``refinements`` counts the substeps added (over the integrator's life)."""
        if not (isinstance(dt, (int, float, np.floating)) and np.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
        if self.max_strain_step is None or self.max_refinements == 0 or self._spring_indices is None:
            return super().step(state_in, state_out, dt, substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if shares_arrays(state_in, state_out):
            raise ValueError("state_out must not alias state_in (the tape needs both)")
        h = float(dt) / substeps
        handler = self.collision_handler
        stats = _save_stats(handler)
        constrained = self.total_constrained
        schedule: list[float] = []
        s = state_in
        with paused_tape():
            for _ in range(substeps):
                s = self._refined(s, h, 0, schedule)
        self.refinements += len(schedule) - substeps
        requires_grad = requires_grad_of(state_in) if self.requires_grad is None else bool(self.requires_grad)
        if requires_grad and active_tape() is not None:
            _restore_stats(handler, stats)  # the replay's collision stages count instead
            self.total_constrained = constrained
            s = state_in
            for k, hk in enumerate(schedule):
                s_next = state_out if k == len(schedule) - 1 else self.new_state(True)
                self._substep(s, s_next, hk, True)
                s = s_next
            return state_out
        copy_state(s, state_out)
        return state_out

    def _refined(self, s: State, h: float, depth: int, schedule: list) -> State:
        """``s`` advanced by ``h`` (off the tape), in halves while the strain grows too fast;
        appends the substeps taken to ``schedule``."""
        m, handler = self.model, self.collision_handler
        out = self.new_state(False)
        stats = _save_stats(handler)
        constrained = self.total_constrained
        self._substep(s, out, h, False)
        if depth < self.max_refinements:
            self._growth.zero_()
            wp.launch(strain_growth, dim=m.spring_count,
                      inputs=[s.particle_q, out.particle_q, self._spring_indices, m.spring_rest_length],
                      outputs=[self._growth], device=self.device, record_tape=False)
            if float(self._growth.numpy()[0]) > self.max_strain_step:
                _restore_stats(handler, stats)
                self.total_constrained = constrained
                mid = self._refined(s, 0.5 * h, depth + 1, schedule)
                return self._refined(mid, 0.5 * h, depth + 1, schedule)
        schedule.append(h)
        return out

    def _substep(self, s_in: State, s_out: State, h: float, requires_grad: bool) -> None:
        """One substep; with ``contact_passes`` > 0 and a collision stage, in up to
        ``contact_passes + 1`` passes.

        Each pass but the last is a trial: it solves and runs the collision stage as the explicit
        integrator does. The free particles a trial's collision stage moved are *decided* (off
        the tape) to be in contact and join the fixed set; the next pass solves again with the
        fixed particles' velocity change prescribed to end the substep where the trial's
        collision stage put them (Baraff-Witkin's constrained particles). Their neighbours thus
        feel the contact through the springs within the substep instead of falling on for a
        whole substep and overstretching the springs. A trial that fixes no new particle is the
        substep; after ``contact_passes`` re-solves the last pass is kept as it is. The collision
        stage always runs last, on the kept pass's prediction, so its guarantees are the
        result's; a held particle it leaves alone ends with the velocity the trial's collision
        stage gave it (its restitution and friction), not the mean velocity that carried it to
        its target. Every pass is on the tape: the prescribed velocities are a smooth function
        of the previous pass's output.
        """
        m, handler = self.model, self.collision_handler
        planes = m.particle_count > 0 and m.plane_count > 0
        self.constrained = 0
        if self.contact_passes == 0 or self._spring_indices is None or (handler is None and not planes):
            super()._substep(s_in, s_out, h, requires_grad)
            return
        n, d = m.particle_count, self.device
        fixed, target, target_v = None, None, None
        try:
            for _ in range(self.contact_passes):
                self._fixed, self._x_target = fixed, target
                trial = self.new_state(requires_grad) if requires_grad else self._scratch_state(2 + (_ % 2))
                stats = _save_stats(handler)
                super()._substep(s_in, trial, h, requires_grad)
                pred = self._last_pred
                grown = wp.zeros(n, dtype=wp.int32, device=d)  # fresh: a taped pass's adjoint keeps its mask
                self._count.zero_()
                # a particle that touched a rigid body is left to the collision stage: holding it
                # where the trial put it would push the cloth without the body feeling the
                # reaction (energy created; measured 3x on cloth_rigid before this)
                body_touch = getattr(self.collision_handler, "last_body_particles", None)
                excluded = self._no_fixed
                if body_touch is not None and len(body_touch):
                    mask = np.zeros(n, dtype=np.int32)
                    mask[body_touch[body_touch < n]] = 1
                    excluded = upload(self._body_touch, mask)
                wp.launch(collided_particles, dim=n,
                          inputs=[pred.particle_q, pred.particle_qd, trial.particle_q, trial.particle_qd,
                                  m.particle_inv_mass, self._no_fixed if fixed is None else fixed, excluded],
                          outputs=[grown, self._count], device=d, record_tape=False)
                added = int(self._count.numpy()[0])
                if added == 0:
                    # nothing new in contact: this trial is the substep (its collision stage counts)
                    copy_state(trial, s_out)
                    return
                _restore_stats(handler, stats)  # the trial's collision stage is redone
                self.constrained += added
                self.total_constrained += added
                fixed, target, target_v = grown, trial.particle_q, trial.particle_qd
            self._fixed, self._x_target = fixed, target
            final = self.new_state(requires_grad) if requires_grad else self._scratch_state(4)
            super()._substep(s_in, final, h, requires_grad)
            pred = self._last_pred
            wp.launch(held_velocity, dim=n,
                      inputs=[fixed, pred.particle_q, pred.particle_qd, final.particle_q, final.particle_qd, target_v],
                      outputs=[s_out.particle_qd], device=d)
            copy_state(final, s_out, ("particle_q", "body_q", "body_qd"))
        finally:
            self._fixed = self._x_target = None

    def _integrate_particles(self, s_in: State, pred: State, h: float, requires_grad: bool) -> list:
        """The backward-Euler solve of the particles into ``pred``, run now (an iterative solve
        that reads its residual on the host, so no stage is left for the caller: returns [])."""
        m, d, n = self.model, self.device, self.model.particle_count
        x0, v0 = s_in.particle_q, s_in.particle_qd
        f = self._spring_forces(s_in, requires_grad)
        stiff_v0 = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        self._apply(x0, v0, stiff_v0, h, coef_x=h * h, coef_v=0.0, mass=False)
        b = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        wp.launch(implicit_rhs, dim=n, inputs=[f, stiff_v0, m.particle_inv_mass, self.gravity, wp.float64(h)],
                  outputs=[b], device=d)
        fixed = self._fixed
        if fixed is None:
            dv = self._solve_taped(x0, b, h, requires_grad, None)
        else:
            # prescribed velocity changes g of the contact particles: dv = g + delta with
            # A_S delta = S (b - A g) (S drops the fixed rows and columns)
            g = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
            wp.launch(constrained_velocity_change, dim=n,
                      inputs=[x0, v0, self._x_target, fixed, wp.float64(h), wp.float64(m.particle_drag)],
                      outputs=[g], device=d)
            a_g = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
            self._apply(x0, g, a_g, h)
            rhs = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
            wp.launch(constrained_rhs, dim=n, inputs=[b, a_g, fixed], outputs=[rhs], device=d)
            delta = self._solve_taped(x0, rhs, h, requires_grad, fixed)
            dv = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
            wp.launch(sum_kernel, dim=n, inputs=[delta, g], outputs=[dv], device=d)
        wp.launch(implicit_update, dim=n, inputs=[x0, v0, dv, m.particle_inv_mass, wp.float64(h),
                                                  wp.float64(m.particle_drag)],
                  outputs=[pred.particle_q, pred.particle_qd], device=d)
        self._last_pred = pred
        return []

    def _solve_taped(self, x0, b, h: float, requires_grad: bool, fixed):
        """``A_S(x0)^-1 b`` into a fresh array, with its adjoint recorded on the active tape."""
        n, d = self.model.particle_count, self.device
        dv = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        self.iterations = self.solve(x0, b, dv, h, fixed)
        self.total_iterations += self.iterations
        tape = active_tape()
        if requires_grad and tape is not None:
            # only arrays with gradients (the input state may have none: model arrays only)
            tape.record_func(backward=lambda: self._solve_adjoint(x0, b, dv, h, fixed),
                             arrays=[a for a in (x0, b, dv) if a.requires_grad])
        return dv

    def _solve_adjoint(self, x0, b, dv, h: float, fixed=None) -> None:
        """Backward of ``dv = A_S(x0)^-1 b``: ``lambda = A_S^-T dv.grad`` (A_S is symmetric);
        ``b.grad += lambda``; ``x0.grad`` (and the model arrays' grads) ``+= -d<lambda, A_S(x0) dv>``.
        The fixed rows of ``lambda`` multiply rows of ``A_S`` that do not depend on ``x0``."""
        n, d = self.model.particle_count, self.device
        lam = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.solve(x0, dv.grad, lam, h, fixed)
        wp.launch(add_kernel, dim=n, inputs=[lam], outputs=[b.grad], device=d)
        # replay the operator on a small tape: d<lambda, A(x) dv>/dx with dv held fixed
        dv_fixed = wp.clone(dv, requires_grad=False)
        y = wp.zeros(n, dtype=wp.vec3d, device=d, requires_grad=True)
        sub = wp.Tape()
        with sub:
            self._apply(x0, dv_fixed, y, h, fixed=fixed)
        wp.launch(negate_kernel, dim=n, inputs=[lam], outputs=[y.grad], device=d)
        sub.backward()
