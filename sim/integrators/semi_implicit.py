"""Semi-implicit Euler stepper: forces + integration, plane contacts, and the collision hook.

One substep of length ``h = dt / substeps`` maps ``s -> s_next``:

1. particles: spring forces into a fresh force array, then ``v- = v + h (f / m + g)`` and the
   predicted positions ``x0 + h v-`` (pinned particles stay put); bodies: semi-implicit Euler of
   the centre of mass and the angular-momentum update (``kernels.integrate``). This *predicted*
   State is a fresh one;
2. if ``model.plane_count > 0``: particle-vs-plane contact with time-of-impact integration
   (``kernels.integrate.respond_plane_contacts``), into fresh particle arrays, keeping
   :meth:`SemiImplicitIntegrator.plane_separation` (the collision handler's separation when it
   has surfaces, which also holds the particles at the planes in its own solve);
3. if ``self.collision_handler`` (a :class:`sim.contact.stage.CollisionStage`, or any callable
   of that signature) is set, it is called as ``collision_handler(state_in, state_out, h)`` where ``state_in`` is the State at the start of
   the substep and ``state_out`` the predicted end of substep (after the plane contacts): its
   ``particle_qd`` / ``body_qd`` are the predicted velocities ``v-`` and its positions the
   predicted positions. The handler must not write into either State's arrays (a tape may have
   read them); it returns a State of fresh arrays that replaces ``state_out`` (it may reuse
   arrays it leaves unchanged), or None to keep the prediction;
4. the result is ``s_next`` (the caller's ``state_out`` on the last substep; copies are tape
   recorded).

Every intermediate State (and force / contact-index array) is allocated per substep when the input
State requires gradients (or ``requires_grad=True``), so a ``wp.Tape`` around
:meth:`SemiImplicitIntegrator.step` can be back-propagated; without gradients two scratch States
are reused. Kernels are launched only for what the model has: no particle
kernels when ``particle_count == 0``, no spring kernel without springs, no body kernel when
``body_count == 0``, no plane kernels without planes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import warp as wp

from core.buffers import host
from core.capture import Graphs, Launch, Zero, run_stages
from core.tape import active_tape, any_tape
from kernels.forces import eval_springs
from kernels.integrate import (
    find_plane_contacts,
    integrate_bodies,
    integrate_particles,
    respond_plane_contacts,
)
from sim.contact.spheres import SphereContacts
from sim.contact.stage import CollisionStage
from sim.model import Model, State
from sim.stability import DivergenceGuard, SimulationDiverged

CollisionHandler = Callable[[State, State, float], "State | None"]


def copy_state(src: State, dst: State, names=("particle_q", "particle_qd", "body_q", "body_qd"),
               taped: bool = True) -> None:
    """Copies the arrays ``names`` of ``src`` into ``dst`` (shared or empty arrays skipped):
    taped copies, or with ``taped=False`` on the CPU through the arrays' numpy views (a few
    microseconds less per array: a stepping loop without gradients copies four per substep)."""
    for name in names:
        a, b = getattr(src, name), getattr(dst, name)
        if a is not b and a.shape[0] > 0:
            if not taped and a.device.is_cpu and b.device.is_cpu and a.shape == b.shape and a.dtype == b.dtype \
                    and active_tape() is None:
                host(b)[:] = host(a)
            else:
                wp.copy(b, a)


def shares_arrays(a: State, b: State) -> bool:
    """Whether two States share a non-empty array (a step must not write the State it reads)."""
    return a is b or any(getattr(a, n) is getattr(b, n) and getattr(a, n).shape[0] > 0
                         for n in ("particle_q", "particle_qd", "body_q", "body_qd"))


def requires_grad_of(state: State) -> bool:
    """Whether a step from ``state`` must keep every intermediate array: its arrays require
    gradients, or a ``wp.Tape`` is recording (it may differentiate w.r.t. model arrays only, and
    reused scratch arrays would be overwritten before its backward reads them)."""
    return active_tape() is not None or any(
        a is not None and a.requires_grad for a in (state.particle_q, state.particle_qd, state.body_q, state.body_qd))


class SemiImplicitIntegrator:
    """Forces + semi-implicit Euler integration of a :class:`sim.model.Model`.

    Attributes:
        model: the Model stepped.
        collision_handler: optional ``(state_in, state_out, dt) -> State | None`` called per
            substep after the predicted velocities (see the module docstring); None by default.
        requires_grad: None (default) allocates fresh intermediate States per substep when the
            input State requires gradients and reuses scratch States otherwise; True always
            allocates (e.g. to differentiate w.r.t. model arrays only), False never does.
        divergence_guard: optional :class:`sim.stability.DivergenceGuard`; with one, every
            substep ends with its check and raises :class:`sim.stability.SimulationDiverged`
            when a value is non-finite or a position left the scene's bounds.
        substeps_done: substeps taken over the integrator's life.
        exact_gravity: False (default): semi-implicit Euler, ``x1 = x0 + h v1``, first order in
            free flight; True: the exact ballistic update, ``x1 = x0 + h v1 - h^2 g / 2`` (the
            springs' kick, then the exact flow of free flight under gravity: symplectic, and
            exact to rounding for ballistic motion). Plane contacts follow it (a bounce is
            second order); the collision handler's mesh contacts follow the same plane law
            but keep the semi-implicit time-of-impact positions (first order within a contact
            substep). With particle
            drag (``Model.particle_drag``) the flight is no longer ballistic and the update is
            first order again.
        graphs: the :class:`core.capture.Graphs` that replay a substep's stages up to the
            collision stage (forces, integration, particle-plane contacts; with spheres, the
            stages before and after the sphere stage) as recorded graphs when the step keeps no
            gradients and no tape records, or None (constructor argument ``capture``: None, the
            default, captures on the CPU; True on any device; False never). A graph gives the
            same bits as the launches.
    """

    def __init__(self, model: Model, requires_grad: bool | None = None, exact_gravity: bool = False,
                 capture: bool | None = None):
        if not isinstance(exact_gravity, bool):
            raise ValueError(f"exact_gravity must be True or False, got {exact_gravity!r}")
        if exact_gravity and model.sphere_count:
            raise ValueError("exact_gravity is not available for models with spheres (their contacts use the "
                             "semi-implicit positions)")
        drag = model.particle_drag
        if not (isinstance(drag, (int, float)) and np.isfinite(drag) and drag >= 0.0):
            raise ValueError(f"model.particle_drag must be a finite rate >= 0 [1/s], got {drag!r}")
        self.model = model
        self.requires_grad = requires_grad
        self.exact_gravity = exact_gravity
        self.device = model.device
        self.collision_handler: CollisionHandler | None = None
        self.sphere_contacts = SphereContacts(model) if model.sphere_count else None
        self.gravity = wp.vec3d(*(float(g) for g in np.asarray(model.gravity, dtype=np.float64)))

        self._spring_indices = None
        if model.particle_count > 0 and model.spring_count > 0:
            idx = model.spring_indices
            # the kernel reads a flat (2 S,) view of the (S, 2) pairs (a flat array is accepted too)
            self._spring_indices = idx if idx.ndim == 1 else idx.flatten()
        self._body_f = None
        if model.body_count > 0:
            # no external body wrenches yet: a constant zero array (never written)
            self._body_f = wp.zeros(model.body_count, dtype=wp.spatial_vectord, device=self.device)
        self._scratch: list[State] = []
        self._empty: dict = {}
        self._stages: dict[str, State] = {}
        self._scratch_forces = None
        self._scratch_plane_index = None
        self.divergence_guard: DivergenceGuard | None = None
        self.substeps_done = 0
        if capture is not None and not isinstance(capture, bool):
            raise ValueError(f"capture must be None, True or False, got {capture!r}")
        if capture is None:  # on the CPU the replayed graph is measured faster (benchmarks/sim.py)
            capture = wp.get_device(self.device).is_cpu
        self.graphs = Graphs(self.device) if capture else None

    # ------------------------------------------------------------------ allocation
    def new_state(self, requires_grad: bool) -> State:
        """A State of zeros (fresh arrays; the empty arrays of a model without particles or
        bodies are shared: nothing ever writes or reads them)."""
        m, d = self.model, self.device

        def zeros(count, dtype):
            if count == 0:
                key = (dtype, requires_grad)
                if key not in self._empty:
                    self._empty[key] = wp.zeros(0, dtype=dtype, device=d, requires_grad=requires_grad)
                return self._empty[key]
            return wp.zeros(count, dtype=dtype, device=d, requires_grad=requires_grad)

        return State(particle_q=zeros(m.particle_count, wp.vec3d), particle_qd=zeros(m.particle_count, wp.vec3d),
                     body_q=zeros(m.body_count, wp.transformd), body_qd=zeros(m.body_count, wp.spatial_vectord))

    def _scratch_state(self, k: int) -> State:
        while len(self._scratch) <= k:
            self._scratch.append(self.new_state(False))
        return self._scratch[k]

    def _stage_state(self, name: str, requires_grad: bool, bodies: State | None = None) -> State:
        """A State for an intermediate stage of a substep: fresh under a tape (the tape needs
        every stage's arrays), else one kept per ``name`` and reused (no allocation per
        substep). ``bodies``: take the body arrays from this State instead."""
        if requires_grad:
            s = self.new_state(True)
        else:
            s = self._stages.get(name)
            if s is None:
                s = self._stages[name] = self.new_state(False)
        if bodies is not None:
            s = State(particle_q=s.particle_q, particle_qd=s.particle_qd, body_q=bodies.body_q, body_qd=bodies.body_qd)
        return s

    def _plane_index(self, requires_grad: bool):
        m = self.model
        if requires_grad or self._scratch_plane_index is None:
            idx = wp.empty(m.particle_count, dtype=wp.int32, device=self.device)
            if not requires_grad:
                self._scratch_plane_index = idx
            return idx
        return self._scratch_plane_index

    # ------------------------------------------------------------------ stepping
    def step(self, state_in: State, state_out: State, dt: float, substeps: int = 1) -> State:
        """Advances ``state_in`` by ``dt`` in ``substeps`` equal substeps into ``state_out``.

        ``state_out`` must be distinct from ``state_in`` (arrays of matching sizes, e.g.
        ``model.state(requires_grad=...)``). Returns ``state_out``.
        """
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if shares_arrays(state_in, state_out):
            raise ValueError("state_out must not alias state_in (the tape needs both)")
        h = float(dt) / substeps
        requires_grad = requires_grad_of(state_in) if self.requires_grad is None else bool(self.requires_grad)
        s = state_in
        for k in range(substeps):
            if k == substeps - 1:
                s_next = state_out
            elif requires_grad:
                s_next = self.new_state(True)
            else:
                s_next = self._scratch_state(k % 2)
            self._substep(s, s_next, h, requires_grad)
            s = s_next
        return state_out

    def _substep(self, s_in: State, s_out: State, h: float, requires_grad: bool) -> None:
        self._advance(s_in, s_out, h, requires_grad)
        self.substeps_done += 1
        guard = self.divergence_guard
        if guard is not None and guard.exceeded(s_out):
            raise SimulationDiverged(f"{guard.message()} (substep {self.substeps_done}, h = {h:.3g} s)")

    def _advance(self, s_in: State, s_out: State, h: float, requires_grad: bool) -> None:
        m = self.model
        planes = m.particle_count > 0 and m.plane_count > 0
        handler = self.collision_handler

        spheres = self.sphere_contacts
        # where the prediction goes: straight into s_out unless a collision stage follows (the
        # sphere stage returns fresh arrays when a contact changes the prediction)
        if handler is None and not planes:
            pred = s_out
        elif handler is None and spheres is None:  # planes only touch particles: bodies go straight to s_out
            pred = self._stage_state("pred", requires_grad, bodies=s_out)
        else:
            pred = self._stage_state("pred", requires_grad)

        # the stages up to the collision stage, launched together (one graph when captured)
        stages = []
        if m.particle_count > 0:
            stages += self._integrate_particles(s_in, pred, h, requires_grad)
        if m.body_count > 0:
            stages.append(Launch(integrate_bodies, m.body_count, (
                s_in.body_q, s_in.body_qd, self._body_f, m.body_inv_mass, m.body_inertia, m.body_inv_inertia,
                self.gravity, wp.float64(h), self._drift(h)), (pred.body_q, pred.body_qd)))
        cur = pred
        if spheres is not None:
            self._run(stages, requires_grad)
            stages = []
            body_q, body_qd = spheres(s_in, pred, h, requires_grad)
            cur = State(particle_q=pred.particle_q, particle_qd=pred.particle_qd, body_q=body_q, body_qd=body_qd)
            if pred is s_out and body_q is not s_out.body_q:
                if requires_grad:  # fresh arrays: s_out takes them (nothing to copy)
                    s_out.body_q, s_out.body_qd = body_q, body_qd
                else:
                    copy_state(cur, s_out, names=("body_q", "body_qd"), taped=False)
        if pred is s_out:
            self._run(stages, requires_grad)
            return
        if planes:
            if handler is None:
                out = s_out
            else:
                out = self._stage_state("planes", requires_grad, bodies=cur)
            stages += self.plane_stages(s_in.particle_q, s_in.particle_qd, pred.particle_qd, out.particle_q,
                                        out.particle_qd, h, requires_grad, self.plane_separation())
            cur = out
        self._run(stages, requires_grad)
        if handler is not None:
            if isinstance(handler, CollisionStage):
                handler.set_exact_gravity(self.exact_gravity)
            result = handler(s_in, cur, h)
            if result is not None:
                cur = result
        copy_state(cur, s_out, taped=requires_grad)

    def _run(self, stages: list, requires_grad: bool) -> None:
        """Runs a substep's stages: as a recorded graph (:class:`core.capture.Graphs`) when
        capture is on and nothing is taped, else launch by launch."""
        if self.graphs is not None and not requires_grad and not any_tape():
            self.graphs.run(stages)
        else:
            run_stages(stages, self.device)

    def _spring_stages(self, s_in: State, requires_grad: bool) -> tuple[wp.array, list]:
        """The springs' forces at the substep's start: (the force array (a fresh one, or a
        scratch one zeroed by the first stage), the stages that fill it)."""
        m = self.model
        if requires_grad:
            f = wp.zeros(m.particle_count, dtype=wp.vec3d, device=self.device, requires_grad=True)
            stages = []
        else:
            if self._scratch_forces is None:
                self._scratch_forces = wp.zeros(m.particle_count, dtype=wp.vec3d, device=self.device)
            f = self._scratch_forces
            stages = [Zero(f)]
        if self._spring_indices is not None:
            stages.append(Launch(eval_springs, m.spring_count, (
                s_in.particle_q, s_in.particle_qd, self._spring_indices, m.spring_rest_length, m.spring_stiffness,
                m.spring_damping), (f,)))
        return f, stages

    def _spring_forces(self, s_in: State, requires_grad: bool):
        """The springs' forces at the substep's start, evaluated now (a fresh or zeroed scratch
        array)."""
        f, stages = self._spring_stages(s_in, requires_grad)
        run_stages(stages, self.device)
        return f

    def _drift(self, h: float) -> wp.vec3d:
        """The position correction of the exact ballistic update (zero without it)."""
        c = -0.5 * h * h if self.exact_gravity else 0.0
        return wp.vec3d(*(c * float(g) for g in self.gravity))

    def _integrate_particles(self, s_in: State, pred: State, h: float, requires_grad: bool) -> list:
        """The stages of spring forces and semi-implicit Euler of the particles into ``pred``
        (run by the caller with the substep's other stages)."""
        m = self.model
        f, stages = self._spring_stages(s_in, requires_grad)
        stages.append(Launch(integrate_particles, m.particle_count, (
            s_in.particle_q, s_in.particle_qd, f, m.particle_inv_mass, self.gravity, wp.float64(h), self._drift(h),
            wp.float64(m.particle_drag)), (pred.particle_q, pred.particle_qd)))
        return stages

    def plane_separation(self) -> float:
        """The distance [m] particles keep from the planes: the collision stage's
        :attr:`~sim.contact.stage.CollisionStage.surface_separation` when it acts on surfaces
        (every contact keeps it, and its vertex-plane rows hold the particles there), else the
        model's thickness (no stage, a stage without surfaces, or a hook that declares none)."""
        separation = getattr(self.collision_handler, "surface_separation", None)
        return float(self.model.thickness) if separation is None else float(separation)

    def plane_stages(self, x0, v_start, v, x_out, v_out, h: float, requires_grad: bool = True,
                     separation: float | None = None) -> list:
        """The stages of particle-vs-plane time-of-impact integration over one substep ``h``:
        from start positions ``x0``, start velocities ``v_start`` and predicted velocities ``v``
        (after the forces) into ``x_out``, ``v_out`` (fresh arrays), stopping ``separation`` [m]
        (default: the model's thickness) in front of the planes.
        Which plane each particle hits is chosen outside the tape; under a tape the response is
        recorded."""
        m = self.model
        idx = self._plane_index(requires_grad)
        hd = wp.float64(h)
        thickness = wp.float64(m.thickness if separation is None else separation)
        return [
            Launch(find_plane_contacts, m.particle_count,
                   (x0, v, m.particle_inv_mass, m.planes, int(m.plane_count), thickness, hd), (idx,),
                   record_tape=False),
            Launch(respond_plane_contacts, m.particle_count,
                   (x0, v_start, v, m.particle_inv_mass, m.planes, idx, wp.float64(m.restitution),
                    wp.float64(m.friction), thickness, self.gravity, hd, self._drift(h)), (x_out, v_out)),
        ]
