"""A simulation rollout as one differentiable torch function.

:func:`rollout` steps a :class:`sim.model.Model` with :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator`
and the collision response of :class:`sim.contact.response.ImpulseCollisionHandler` in its replayed
form (``differentiable=True``: decisions on the host, the response's smooth map as taped Warp
launches; design.md "Differentiating collision response: decide, then replay"). Its outputs are
torch tensors inside one ``torch.autograd.Function`` whose backward runs the ``wp.Tape``, so
``torch.optim`` can optimise initial particle velocities and body twists through contacts, and
(optionally) particle masses and spring stiffnesses: given as tensors, they replace the model's
arrays in a shallow copy of the Model (the caller's Model is never changed), the inverse masses
are computed from them by a taped kernel, and their gradients come from every launch that reads
them (springs, integration, the replayed impulse solve).

Memory: a taped step keeps every substep's arrays. ``checkpoint_every=K`` keeps only the state
at the start of each segment of K steps in the forward and re-runs each segment under a tape in
the backward (segments in reverse, the adjoint of a segment's last state carried to the one
before), so the taped memory is one segment's instead of the whole rollout's, for about one more
forward pass of compute. A good K is about sqrt(steps) (Warp's ``example_fluid_checkpoint``).

Example (gradient of a particle's final height w.r.t. its initial velocity, through a bounce)::

    res = rollout(model, steps=60, dt=1 / 60, substeps=8, particle_qd=v0.requires_grad_())
    res.particle_q[-1, 0, 2].backward()
    v0.grad
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from sim.contact.contacts import ContactLimitExceeded
from sim.contact.response import ImpulseCollisionHandler, check_ccd_options
from sim.contact.stage import StageObserver
from collision.roots import DEFAULT_MAX_DERIVATIVE, DERIVATIVES
from kernels.integrate import inverse_masses
from sim.events import SphereEvent, event_outputs, sphere_event_roots
from sim.rollout_args import check_args, check_parameters, check_poses
from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.integrators import check_integrator, make_integrator
from sim.model import Model, State
from sim.stability import DivergenceGuard, SimulationDiverged

UNMOLLIFIED_MAX_DERIVATIVE = 1e300
"""``max_derivative`` that turns the robust division off: the plain implicit derivative
``-1/p'(t*)`` of the time of impact (what differentiable simulators without mollification use),
for comparisons; it grows without bound at grazing contacts."""


@dataclass
class RolloutResult:
    """Trajectories of a :func:`rollout` (torch float64 on the CPU), index 0 the initial state.

    Attributes:
        particle_q: positions [m], (N+1, P, 3).
        particle_qd: velocities [m/s], (N+1, P, 3).
        body_q: poses (centre of mass [m], quaternion x y z w), (N+1, B, 7).
        body_qd: twists (angular [rad/s], linear [m/s]) in world frame, (N+1, B, 6).
        event_roots: the lifted events' roots (E, 3, 2): slots (t-, tM, t+), (Re, Im) [s from
            the window's start] (:mod:`sim.events`).
        event_coords: closest-point coordinates at each root's real part (E, 3, 3): barycentric
            (w1, w2, w3) of the triangle for vertex-face events, (s_a, s_b, 0) for edge-edge.
        sphere_event_roots: the lifted sphere events' roots (Es, 2, 2): slots (t-, t+), (Re, Im)
            [s from the window's start], in the order the :class:`sim.events.SphereEvent` s
            appear in ``events`` (:func:`sim.events.sphere_event_roots`).
        stats: counts of the forward pass: ``contact_substeps`` (substeps with a mesh contact),
            ``refined_substeps`` and ``contact_constrained`` (the implicit integrator's halved
            substeps and particles held in its constrained re-solves),
            ``ccd_events`` (approaching CCD hits that became contacts, over all rounds and substeps),
            ``failsafe_substeps`` (impact zones formed; their rigid motion is taped),
            ``largest_system`` (most unknowns
            of one impulse solve), ``unsettled_active_sets`` (impulse solves whose active set did
            not settle within the repair budget); with spheres, ``unresolved_sphere_substeps``
            (substeps whose sphere pairs still acted after the stage's last pass).
    """

    particle_q: torch.Tensor
    particle_qd: torch.Tensor
    body_q: torch.Tensor
    body_qd: torch.Tensor
    event_roots: torch.Tensor
    event_coords: torch.Tensor = None
    sphere_event_roots: torch.Tensor = None
    stats: dict = field(default_factory=dict)


class _CountingHandler(StageObserver):
    """The collision handler, counting the substeps it changed in ``stats["contact_substeps"]``;
    its statistics can be saved and restored around calls an integrator discards (see
    ``ImpulseCollisionHandler.save_stats``)."""

    def __init__(self, handler, stats: dict):
        super().__init__(handler)
        self.stats = stats

    def __call__(self, state_in, state_pred, h):
        out = self.handler(state_in, state_pred, h)
        if out is not None:
            self.stats["contact_substeps"] += 1
        return out

    def save_stats(self):
        return self.handler.save_stats(), self.stats["contact_substeps"]

    def restore_stats(self, saved) -> None:
        self.handler.restore_stats(saved[0])
        self.stats["contact_substeps"] = saved[1]


class _Runner:
    """Steps the model and replays taped segments backwards (one instance per rollout call)."""

    def __init__(self, model: Model, steps: int, dt: float, substeps: int, checkpoint_every, collisions: bool,
                 max_derivative: float, integrator: str = "semi_implicit", integrator_options=None,
                 ccd_options=None, on_divergence: str = "raise"):
        self.model = model
        self.on_divergence = on_divergence
        self.guard: DivergenceGuard | None = None
        self.ccd_options = ccd_options
        self.integrator = integrator
        self.integrator_options = dict(integrator_options or {})
        self.steps, self.dt, self.substeps = steps, dt, substeps
        self.checkpoint_every = checkpoint_every
        self.collisions = collisions
        self.max_derivative = max_derivative
        self.handler = None
        self.spheres = None  # the sphere stage (models with spheres)
        self.tape = None
        self.param_tape = None  # the inverse masses from the masses (when their gradient is wanted)
        self.params: dict[str, wp.array] = {}  # the parameter arrays whose gradients are wanted
        self.states: list[State] = []
        self.stats = {"contact_substeps": 0, "failsafe_substeps": 0, "largest_system": 0,
                      "unsettled_active_sets": 0, "ccd_events": 0, "refined_substeps": 0, "contact_constrained": 0,
                      "diverged": False, "diverged_step": None,
                      "divergence_message": None}

    def _integrator(self, requires_grad: bool) -> SemiImplicitIntegrator:
        integ = make_integrator(self.model, self.integrator, requires_grad=requires_grad, **self.integrator_options)
        integ.divergence_guard = self.guard
        if integ.sphere_contacts is not None:
            # one stage per rollout: its counters run over the forward's substeps
            if self.spheres is None:
                self.spheres = integ.sphere_contacts
            integ.sphere_contacts = self.spheres
            self.spheres.max_derivative = self.max_derivative
        if self.collisions:
            if self.handler is None:
                self.handler = ImpulseCollisionHandler(self.model, differentiable=True, max_derivative=self.max_derivative,
                                                       ccd_options=self.ccd_options)
            if self.handler.broad_phase is not None:
                integ.collision_handler = self._counting(self.handler)
        return integ

    def _counting(self, handler):
        return _CountingHandler(handler, self.stats)

    def _set_parameters(self, particle_mass, spring_stiffness, mass_grad: bool, stiffness_grad: bool) -> None:
        """Replaces ``self.model`` by a shallow copy whose ``particle_mass``, ``particle_inv_mass``
        and ``spring_stiffness`` are fresh arrays from the tensors given (None keeps the model's);
        the inverse masses come from the masses by a launch on ``self.param_tape`` when the
        masses' gradient is wanted. Must run before the collision handler is built (it takes
        the inverse-mass array)."""
        if particle_mass is None and spring_stiffness is None:
            return
        m, d = self.model, self.model.device
        changes = {}
        if particle_mass is not None:
            mass = wp.array(particle_mass.detach().cpu().numpy(), dtype=wp.float64, device=d, requires_grad=mass_grad)
            inv = wp.zeros(m.particle_count, dtype=wp.float64, device=d, requires_grad=mass_grad)
            if mass_grad:
                self.param_tape = wp.Tape()
            with self.param_tape if mass_grad else contextlib.nullcontext():
                if m.particle_count:
                    wp.launch(inverse_masses, dim=m.particle_count, inputs=[mass], outputs=[inv], device=d)
            changes.update(particle_mass=mass, particle_inv_mass=inv)
            if mass_grad:
                self.params.update(particle_mass=mass, particle_inv_mass=inv)
        if spring_stiffness is not None:
            k = wp.array(spring_stiffness.detach().cpu().numpy(), dtype=wp.float64, device=d,
                         requires_grad=stiffness_grad)
            changes["spring_stiffness"] = k
            if stiffness_grad:
                self.params["spring_stiffness"] = k
        self.model = dataclasses.replace(m, **changes)

    def _initial_state(self, particle_qd, body_qd, requires_grad: bool, body_q=None) -> State:
        s = self.model.state(requires_grad=requires_grad)
        d = self.model.device
        if particle_qd is not None:
            s.particle_qd = wp.array(particle_qd.detach().cpu().numpy(), dtype=wp.vec3d, device=d, requires_grad=requires_grad)
        if body_qd is not None:
            s.body_qd = wp.array(body_qd.detach().cpu().numpy(), dtype=wp.spatial_vectord, device=d, requires_grad=requires_grad)
        if body_q is not None:
            s.body_q = wp.array(body_q.detach().cpu().numpy(), dtype=wp.transformd, device=d, requires_grad=requires_grad)
        return s

    @staticmethod
    def _state_from(arrays: dict, like: Model, requires_grad: bool) -> State:
        d = like.device
        return State(
            particle_q=wp.array(arrays["particle_q"], dtype=wp.vec3d, device=d, requires_grad=requires_grad),
            particle_qd=wp.array(arrays["particle_qd"], dtype=wp.vec3d, device=d, requires_grad=requires_grad),
            body_q=wp.array(arrays["body_q"], dtype=wp.transformd, device=d, requires_grad=requires_grad),
            body_qd=wp.array(arrays["body_qd"], dtype=wp.spatial_vectord, device=d, requires_grad=requires_grad),
        )

    def _run(self, start: State, first: int, last: int, requires_grad: bool, record: list | None):
        """Steps ``first..last-1`` from ``start``; appends host copies to ``record`` and returns
        the States (all of them when ``requires_grad``; otherwise the last)."""
        integ = self._integrator(requires_grad)
        states = [start]
        s = start
        spare = None if requires_grad else self.model.state()
        for k in range(first, last):
            if requires_grad:
                # zeros, not model.state(): a clone would be recorded on the tape as a copy
                s_next = integ.new_state(True)
            else:
                s_next = spare
            try:
                integ.step(s, s_next, self.dt, self.substeps)
            except (SimulationDiverged, ContactLimitExceeded) as exc:
                implicit = "" if self.integrator == "implicit" else " or integrator='implicit'"
                raise SimulationDiverged(
                    f"rollout: step {k + 1} of {self.steps}: {exc}; use more substeps, a shorter dt{implicit} "
                    f"(on_divergence='return' returns instead)") from None
            if record is not None:
                record.append(s_next.numpy())
            if requires_grad:
                states.append(s_next)
            else:
                spare = s
            s = s_next
        if record is not None:  # the forward's (a backward recompute repeats the same work)
            self.stats["refined_substeps"] += int(getattr(integ, "refinements", 0))
            self.stats["contact_constrained"] += int(getattr(integ, "total_constrained", 0))
        return states if requires_grad else [s]

    def forward(self, particle_qd, body_qd, requires_grad: bool, particle_mass=None, spring_stiffness=None,
                mass_grad: bool = False, stiffness_grad: bool = False, body_q=None):
        self._set_parameters(particle_mass, spring_stiffness, mass_grad and requires_grad,
                             stiffness_grad and requires_grad)
        start = self._initial_state(particle_qd, body_qd, requires_grad and self.checkpoint_every is None, body_q)
        self.guard = DivergenceGuard(self.model, start, self.steps * self.dt)
        record = [start.numpy()]
        self.segment_starts = {0: record[0]}
        try:
            self._forward_steps(start, record, requires_grad)
        except SimulationDiverged as exc:
            if self.on_divergence != "return":
                raise
            # the frames from the diverged step on hold the last completed one; no gradient
            self.stats["diverged"] = True
            self.stats["diverged_step"] = len(record)
            self.stats["divergence_message"] = str(exc)
            self.tape, self.states = None, []
            record.extend([record[-1]] * (self.steps + 1 - len(record)))
        if self.spheres is not None:
            self.stats["unresolved_sphere_substeps"] = self.spheres.unresolved_substeps
        if self.handler is not None:
            self.stats["failsafe_substeps"] = self.handler.failsafe_count
            self.stats["ccd_events"] = self.handler.ccd_events
            self.stats["unsettled_active_sets"] = self.handler.unsettled_active_sets
            if self.handler.differentiable:
                self.stats["largest_system"] = self.handler.replay.largest_system
        return {name: np.stack([r[name] for r in record]) for name in ("particle_q", "particle_qd", "body_q", "body_qd")}

    def _forward_steps(self, start: State, record: list, requires_grad: bool) -> None:
        """Steps the whole rollout from ``start``, appending each step's host copy to ``record``
        (taped, or in checkpointed segments whose starts are kept)."""
        if requires_grad and self.checkpoint_every is None:
            self.tape = wp.Tape()
            with self.tape:
                self.states = self._run(start, 0, self.steps, True, record)
        else:
            k = self.checkpoint_every or self.steps
            s = start
            for a in range(0, self.steps, k):
                b = min(a + k, self.steps)
                if requires_grad:
                    self.segment_starts[a] = record[a]
                s = self._run(s, a, b, False, record)[0]
                if not requires_grad:
                    continue
                # a fresh State for the next segment (the scratch ones are reused)
                s = self._state_from(record[b], self.model, False)

    @staticmethod
    def _seed(arr: wp.array, grad: np.ndarray) -> None:
        if arr.shape[0] == 0:
            return
        arr.grad.assign(wp.array(arr.grad.numpy() + grad, dtype=arr.dtype, device=arr.device))

    def backward(self, grads: dict):
        """Adjoints of the initial velocities (particles (P, 3), bodies (B, 6)), of the initial
        body poses (B, 7) and of the
        parameters (``{"particle_mass": (P,), "spring_stiffness": (S,)}``, those whose gradient
        was asked for) for the output adjoints ``grads[name]`` of shape (N+1, ...).

        The parameters are shared by all segments: their adjoints are read after each
        segment's backward pass and summed (each segment's tape is zeroed before the next)."""
        if self.stats["diverged"]:
            raise RuntimeError(f"rollout diverged at step {self.stats['diverged_step']} (on_divergence='return'): "
                               f"it has no gradient")
        names = ("particle_q", "particle_qd", "body_q", "body_qd")
        for arr in self.params.values():
            if arr.shape[0]:
                arr.grad.zero_()
        param_sum = {name: np.zeros(a.shape[0]) for name, a in self.params.items()}
        carry = {name: grads[name][self.steps].copy() for name in names}
        if self.checkpoint_every is None:
            segments = [(0, self.steps, self.tape, self.states)]
        else:
            k = self.checkpoint_every
            segments = [(a, min(a + k, self.steps), None, None) for a in range(0, self.steps, k)]
        for a, b, tape, states in reversed(segments):
            if tape is None:
                start = self._state_from(self.segment_starts[a], self.model, True)
                tape = wp.Tape()
                with tape:
                    states = self._run(start, a, b, True, None)
            for step in range(a + 1, b + 1):
                s = states[step - a]
                for name in names:
                    self._seed(getattr(s, name), carry[name] if step == b else grads[name][step])
            tape.backward()
            for name, arr in self.params.items():
                if arr.shape[0]:
                    param_sum[name] += arr.grad.numpy()
                    arr.grad.zero_()
            s0 = states[0]
            carry = {name: (getattr(s0, name).grad.numpy() if getattr(s0, name).shape[0] else np.zeros_like(grads[name][a]))
                     + grads[name][a] for name in names}
            tape.zero()
        self.tape = None
        self.states = []
        params = {}
        if "particle_mass" in self.params:
            mass, inv = self.params["particle_mass"], self.params["particle_inv_mass"]
            params["particle_mass"] = param_sum["particle_mass"]
            if mass.shape[0]:
                # through the taped inverse masses: d inv / d m
                inv.grad.assign(wp.array(param_sum["particle_inv_mass"], dtype=wp.float64, device=inv.device))
                self.param_tape.backward()
                params["particle_mass"] = param_sum["particle_mass"] + mass.grad.numpy()
                self.param_tape.zero()
        if "spring_stiffness" in self.params:
            params["spring_stiffness"] = param_sum["spring_stiffness"]
        return carry["particle_qd"], carry["body_qd"], carry["body_q"], params


class _RolloutFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, particle_qd, body_qd, particle_mass, spring_stiffness, body_q, runner, has_particle, has_body,
                has_mass, has_stiffness, has_pose):
        needs = any(ctx.needs_input_grad[:5])
        out = runner.forward(particle_qd if has_particle else None, body_qd if has_body else None, needs,
                             particle_mass if has_mass else None, spring_stiffness if has_stiffness else None,
                             mass_grad=has_mass and ctx.needs_input_grad[2],
                             stiffness_grad=has_stiffness and ctx.needs_input_grad[3],
                             body_q=body_q if has_pose else None)
        ctx.runner = runner
        ctx.input_devices = (particle_qd.device, body_qd.device, particle_mass.device, spring_stiffness.device,
                             body_q.device)
        ctx.shapes = {k: v.shape for k, v in out.items()}
        return tuple(torch.from_numpy(np.ascontiguousarray(out[k])) for k in ("particle_q", "particle_qd", "body_q", "body_qd"))

    @staticmethod
    def backward(ctx, g_q, g_qd, g_bq, g_bqd):
        def arr(g, name):
            return np.zeros(ctx.shapes[name]) if g is None else g.detach().cpu().numpy().astype(np.float64)

        gp, gb, gpose, params = ctx.runner.backward({
            "particle_q": arr(g_q, "particle_q"), "particle_qd": arr(g_qd, "particle_qd"),
            "body_q": arr(g_bq, "body_q"), "body_qd": arr(g_bqd, "body_qd"),
        })
        # gradients on the inputs' devices (the rollout itself computes on the model's device)
        gp = torch.from_numpy(np.ascontiguousarray(gp)).to(ctx.input_devices[0])
        gb = torch.from_numpy(np.ascontiguousarray(gb)).to(ctx.input_devices[1])
        gpose = torch.from_numpy(np.ascontiguousarray(gpose)).to(ctx.input_devices[4])
        gm, gk = (None if name not in params else torch.from_numpy(np.ascontiguousarray(params[name])).to(device)
                  for name, device in (("particle_mass", ctx.input_devices[2]),
                                       ("spring_stiffness", ctx.input_devices[3])))
        return gp, gb, gm, gk, gpose, None, None, None, None, None, None


def rollout(
    model: Model,
    steps: int,
    dt: float,
    substeps: int = 1,
    particle_qd: torch.Tensor | None = None,
    body_qd: torch.Tensor | None = None,
    events=(),
    *,
    collisions: bool = True,
    max_derivative: float = DEFAULT_MAX_DERIVATIVE,
    checkpoint_every: int | None = None,
    event_derivative: str = "mollified",
    integrator: str = "semi_implicit",
    integrator_options: dict | None = None,
    particle_mass: torch.Tensor | None = None,
    spring_stiffness: torch.Tensor | None = None,
    ccd_options: dict | None = None,
    on_divergence: str = "raise",
    body_q: torch.Tensor | None = None,
) -> RolloutResult:
    """Simulates ``steps`` steps of ``dt`` [s] (each split into ``substeps``) from the model's
    initial state, differentiably.

    Args:
        model: the finalised :class:`sim.model.Model` (float64).
        steps: number of steps N (>= 1).
        dt: step length [s] (> 0).
        substeps: substeps per step (>= 1).
        particle_qd: initial particle velocities [m/s], torch float64 (P, 3); None = the model's.
        body_qd: initial body twists (angular [rad/s], linear [m/s]) in world frame, torch
            float64 (B, 6); None = the model's.
        events: lifted events, a sequence of :class:`sim.events.Event` (designated vertex-face
            or edge-edge pairs and a window of steps): their roots and closest-point
            coordinates come back in ``event_roots`` / ``event_coords``, differentiable with the
            mollified derivative bounded by ``max_derivative``; and of
            :class:`sim.events.SphereEvent` (two sphere bodies and a window), whose quadratic's
            roots come back in ``sphere_event_roots``.
        collisions: mesh collisions (cloth, rigid, static, vertex-plane) as the scenes handle
            them; the integrator's particle-plane stage is always on (with collisions it keeps
            the handler's separation, without them the model's thickness).
        max_derivative: the robust-division bound ``M`` of the time-of-impact derivative
            (:data:`UNMOLLIFIED_MAX_DERIVATIVE` for the unmollified ``-1/p'(t*)``).
        checkpoint_every: None keeps the whole rollout's tape; K recomputes segments of K steps
            in the backward (memory of one segment).
        event_derivative: the event roots' derivative: "mollified" (robust division bounded by
            ``max_derivative``) or "orthogonal" (real roots' exact derivative with only the part
            that merges or separates a pair clamped to ``max_derivative``, eq.
            ``orthogonal_clamping_real_side``; see :func:`collision.roots.orthogonal_clamped_jacobian`).
        integrator: "semi_implicit" (explicit springs) or "implicit" (backward Euler, CG solve
            differentiated implicitly: :class:`sim.integrators.implicit.ImplicitIntegrator`).
        integrator_options: the implicit integrator's options (:data:`sim.integrators.implicit.OPTIONS`:
            ``tolerance``, ``max_iterations``, ``contact_passes``, ``max_strain_step``,
            ``max_refinements``).
        particle_mass: particle masses [kg], torch float64 (P,), finite and >= 0; None = the
            model's. The model's pinned particles (mass 0) must have mass 0 here and every other
            particle a positive mass (pinning cannot change). The inverse masses used by the
            integrator and the collision response are computed from it (1/m, 0 for pinned).
        spring_stiffness: spring stiffnesses [N/m], torch float64 (S,), finite and >= 0; None =
            the model's.
        ccd_options: the knobs of the narrow phase that decides the CCD contacts
            (``precision`` "float64"/"float32", ``tolerance_scale``, ``max_iterations``,
            ``tolerance``; see :class:`sim.contact.response.ImpulseCollisionHandler`); None: the
            float64 kernels as written. Decisions only: the replayed ``t*`` and its derivative
            come from the float64 root solver either way.
        body_q: initial body poses (centre of mass [m], unit quaternion x y z w), torch float64
            (B, 7); None = the model's. Its gradient is the pose's adjoint as stored (the
            quaternion's four components, not projected onto rotations).
        on_divergence: what a diverged rollout does (a position or velocity not finite, or a
            position farther than :data:`sim.stability.BOUNDS_FACTOR` times the scene's reach
            from its centre, checked every substep; or a substep past the contact limits,
            :class:`sim.contact.contacts.ContactLimitExceeded`): "raise" (default) raises
            :class:`sim.stability.SimulationDiverged` naming the step; "return" stops there and
            returns with ``stats["diverged"] = True``, ``stats["diverged_step"]`` (the first
            step not completed) and ``stats["divergence_message"]``, every later frame holding
            the last completed one; such a result has no gradient (its backward raises).

    Either parameter replaces the model's array in a shallow copy of ``model`` (``model``
    itself is not changed). When it requires gradients, they flow through everything the
    rollout does with it: spring forces, the integration (semi-implicit, or the implicit
    integrator's solve through its implicit adjoint), the particle-plane contacts and the
    replayed impulse solve (whose matrix holds the inverse masses). With ``checkpoint_every``
    the parameters' gradients are summed over the recomputed segments (impact zones' rigid
    motion included: it is taped); pinned particles get a zero mass gradient.

    Returns:
        :class:`RolloutResult`; its tensors are differentiable w.r.t. ``particle_qd``,
        ``body_qd``, ``body_q``, ``particle_mass`` and ``spring_stiffness`` when those require
        gradients.

    Raises:
        ValueError: naming the argument, for wrong types, shapes, dtypes, non-finite values,
            negative masses or stiffnesses, masses that change which particles are pinned,
            ``steps < 1``, ``substeps < 1`` or ``dt <= 0``; before anything runs.
        sim.stability.SimulationDiverged: when the rollout diverges (see ``on_divergence``).
    """
    steps, dt, substeps, particle_qd, body_qd, events = check_args(
        model, steps, dt, substeps, particle_qd, body_qd, events, checkpoint_every, max_derivative)
    if event_derivative not in DERIVATIVES:
        raise ValueError(f"event_derivative must be one of {DERIVATIVES}, got {event_derivative!r}")
    check_integrator(integrator, integrator_options)
    ccd_options = check_ccd_options(ccd_options)
    particle_mass, spring_stiffness = check_parameters(model, particle_mass, spring_stiffness)
    body_q = check_poses(body_q, model)
    if on_divergence not in ("raise", "return"):
        raise ValueError(f"on_divergence must be 'raise' or 'return', got {on_divergence!r}")
    runner = _Runner(model, steps, dt, substeps, checkpoint_every, collisions, float(max_derivative), integrator,
                     integrator_options, ccd_options, on_divergence)
    has_p, has_b = particle_qd is not None, body_qd is not None
    has_m, has_k = particle_mass is not None, spring_stiffness is not None
    p_in = particle_qd if has_p else torch.zeros((model.particle_count, 3), dtype=torch.float64)
    b_in = body_qd if has_b else torch.zeros((model.body_count, 6), dtype=torch.float64)
    m_in = particle_mass if has_m else torch.zeros(model.particle_count, dtype=torch.float64)
    k_in = spring_stiffness if has_k else torch.zeros(model.spring_count, dtype=torch.float64)
    has_pose = body_q is not None
    pose_in = body_q if has_pose else torch.zeros((model.body_count, 7), dtype=torch.float64)
    q, qd, bq, bqd = _RolloutFunction.apply(p_in, b_in, m_in, k_in, pose_in, runner, has_p, has_b, has_m, has_k,
                                            has_pose)
    mesh_events = [ev for ev in events if not isinstance(ev, SphereEvent)]
    sphere_events = [ev for ev in events if isinstance(ev, SphereEvent)]
    roots, coords = event_outputs(model, mesh_events, q, bq, dt, float(max_derivative), event_derivative)
    sphere_roots = sphere_event_roots(model, sphere_events, bq, dt, float(max_derivative), event_derivative)
    return RolloutResult(
        particle_q=q, particle_qd=qd, body_q=bq, body_qd=bqd,
        event_roots=roots, event_coords=coords, sphere_event_roots=sphere_roots, stats=dict(runner.stats),
    )
