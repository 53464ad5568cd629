"""Collision handling for the stepper: proximity impulses, CCD, impulses at the time of impact.

:class:`ImpulseCollisionHandler` is plugged into :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator`
as its ``collision_handler``. Per substep of length ``h`` it receives the start State and the
predicted end State (velocities ``v-`` after forces) and works on one set of collidable vertices:
cloth particles, rigid-body surface vertices (body frame -> world) and static mesh vertices; the
model's components decide which groups exist and which may touch (cloth with itself only with
``"self_collision"``, a rigid body never with itself, static meshes never with each other).

1. **Proximity** (resting and sliding contact, after Bridson et al. 2002): vertex-face and
   edge-edge pairs closer than the separation ``delta`` (or up to ``PROXIMITY_HYSTERESIS``
   beyond it, allowed to approach until they reach it) at the start of the substep become
   contacts at ``t* = 0`` with the normal of their exact closest points (a vertex over a face,
   or over its coplanar neighbours, takes the face's normal; edges between coplanar faces of a
   rigid or static surface are no features at all, :func:`sim.collision_mesh.flat_edges`; a
   touching pair whose closest points give no direction joins no set). Their impulses keep the
   normal relative velocity at least ``-e v_n`` (restitution ``e``, when they approach faster
   than the separation speed; ``v_n`` at the start) and restore ``SEPARATION_RATE`` of the
   missing gap ``delta - d`` per substep: as a velocity target in the Gauss-Seidel response, as
   a push of the positions alone in the replayed one (no velocity outlives it: an inelastic
   impact does not rebound; the push is a displacement over the whole substep, so a contact
   that CCD finds at the very end of the substep still ends separated).
2. **Continuous collision detection**: the planned motion (linear per vertex from the start to
   the planned end positions) goes through :class:`collision.broad_phase.BroadPhase` and the
   vertex-face / edge-edge narrow phase of :mod:`kernels.ccd` at zero thickness (the coplanarity
   cubic and its robust roots: the exact first contact time ``t*``). Every hit whose primitives
   still approach at ``t*`` joins the contact set, with the normal at ``t*`` oriented by the
   start offset, the target ``-e v_n`` (``v_n`` the velocity at ``t*``: the start velocity plus
   the forces' change up to ``t*``) and the separation ``SEPARATION_RATE delta`` restored as in 1.
3. **Impulses** for the whole contact set: projected Gauss-Seidel sweeps in a Warp kernel
   (:func:`kernels.decide.solve_contacts_kernel`, sequential, deterministic), accumulated normal
   impulses clamped to ``>= 0`` and Coulomb friction clamped to the cone ``|j_t| <= mu j_n``. Cloth impulses split by the barycentric / segment weights and the
   inverse masses; rigid ones change the linear and the angular velocity (world inverse inertia).
4. **Time-of-impact integration**: every particle or body whose velocity changed moves with its
   old velocity until its earliest contact ``t*`` and with the new one after,
   ``x(h) = x0 + t* v- + (h - t*) v+`` (bodies: the centre of mass the same way, the orientation
   turned by ``w-`` for ``t*`` and then by ``w+``).
5. 2-4 repeat until the planned motion is collision free or ``max_iterations`` rounds are done;
   then the fail-safe forms **rigid impact zones** (Provot 1997; Bridson et al. 2002): the
   particles and bodies joined by a still-approaching contact move as one rigid body over the
   whole substep with their total linear and angular momentum (at rest when the zone holds a
   static vertex or a pinned particle), and the zones grow until CCD finds no approaching
   contact. A zone's straight vertex paths are an invertible affine motion, so nothing inside it
   can collide, and the start of a substep is collision free: this terminates without
   interpenetration.

Everything per contact happens on the model's device: the narrow phase and the proximity test
read the broad phase's candidate pairs where it left them and append their hits through
counters; the hits are put in pair order (the same contacts in the same order whatever the
thread schedule or the candidates' order), matched to the contact set, given their geometry,
tested for approach and added to a fixed-capacity device contact set
(:class:`sim.contact.contacts.Contacts`) by the kernels of :mod:`kernels.contact_set`; the solve
and the plan read that set where it is. The host sees only counts (hits, approaching hits,
contacts, Gauss-Seidel sweeps, the active set's changes), the per-vertex positions of the
broad-phase cover's box tests (views of the device arrays on the CPU) and, in the rare
fail-safe, the approaching hits that join impact zones.

Two forms share the detection: with ``differentiable=False`` the one above (projected
Gauss-Seidel impulses; it reuses its buffers, so stepping allocates no Warp array, and its cost
is measured per scene in ``benchmarks/sim.py``), and by default the replayed one (design.md
"Differentiating collision response: decide, then replay"): the same decisions off the tape,
then ``t*`` through the mollified roots, the exact impulse solve, the time-of-impact integration
and the impact zones' rigid motion as taped Warp launches (:mod:`sim.contact.replay`). Its
friction is exact for the two common regimes: every contact sticking (one joint solve of the
normal and tangential impulses: a box stays put on a slope steeper than it would be without
friction) or every contact sliding (Coulomb's ``mu j_n`` against the slip in the same solve as
``j_n``); mixed sets of up to 48 contacts solve a split of sticking and sliding contacts in one
system, and larger or unsettled ones take each contact's stopping impulse, shared.
"""

from __future__ import annotations

import contextlib
import itertools
import weakref

import numpy as np
import warp as wp

from collision.broad_phase import BroadPhase
from collision.roots import DEFAULT_MAX_DERIVATIVE
from core.buffers import RecordedLaunches, Staging, copy_rows, host, zero
from core.tape import active_tape, paused_tape
from kernels.active_set import (active_set_update_kernel, flags_differ_kernel, friction_share_count_kernel,
                                friction_share_kernel, initial_active_kernel, owner_rows_finish_kernel,
                                owner_rows_kernel, owner_rows_reset_kernel, owner_times_kernel,
                                owner_times_reset_kernel, set_impulses_kernel)
from kernels.decide import solve_contacts_kernel
from kernels.integrate import planned_substep_kernel
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, VERTEX_STATIC
from kernels.variants import check_settings as check_ccd_settings
from sim.collision_mesh import CollisionMesh
from sim.contact.contacts import Contacts
from sim.contact.detect import ContactDetection
from sim.contact.record import NO_CONTACTS, ContactRecord
from sim.contact.replay import ContactReplay
from sim.contact.tuning import (ACTIVE_SET_COLLIDED_MAX_CONTACTS, ACTIVE_SET_ITERATIONS, ACTIVE_SET_PULLING,
                                APPROACH_EPS, DEFAULT_SEPARATION_RELATIVE, SEPARATION_RATE, SOLVER_ITERATIONS,
                                SOLVER_TOLERANCE, TOUCHING_RELATIVE)
from sim.contact.zones import ImpactZones
from sim.model import Model, State

CCD_OPTIONS = ("precision", "tolerance_scale", "max_iterations", "tolerance")
"""Keys of ``ImpulseCollisionHandler(ccd_options=...)``: the narrow phase's knobs."""


def check_ccd_options(ccd_options) -> dict:
    """``ccd_options`` validated (a dict with keys of :data:`CCD_OPTIONS`, values as
    :func:`kernels.variants.check_settings` takes them; None: {}), as a new dict.

    Raises:
        ValueError: naming ``ccd_options`` or the bad key.
    """
    if ccd_options is None:
        return {}
    if not isinstance(ccd_options, dict):
        raise ValueError(f"ccd_options must be a dict or None, got {type(ccd_options).__name__}")
    unknown = set(ccd_options) - set(CCD_OPTIONS)
    if unknown:
        raise ValueError(f"ccd_options: unknown keys {sorted(map(repr, unknown))}; expected some of {CCD_OPTIONS}")
    try:
        check_ccd_settings(**ccd_options)
    except ValueError as exc:
        raise ValueError(f"ccd_options: {exc}") from None
    return dict(ccd_options)


def contact_separation(model: Model, mesh: CollisionMesh | None = None) -> float:
    """The separation ``delta`` [m] every contact keeps (:attr:`ImpulseCollisionHandler.separation`;
    the integrator's particle-plane stage keeps it too while a handler runs): the model's
    thickness, or when that is 0, :data:`DEFAULT_SEPARATION_RELATIVE` of the diagonal of the
    collidable vertices' bounding box at the model's start (1e-6 m without vertices)."""
    if float(model.thickness) > 0.0:
        return float(model.thickness)
    mesh = model.collision_mesh if mesh is None else mesh
    if not mesh.vertex_count:
        return 1e-6
    x = mesh.positions(model.particle_q.numpy()[: mesh.particle_count] if mesh.particle_count else np.zeros((0, 3)),
                       model.body_q.numpy() if model.body_count else np.zeros((0, 7)))
    diag = float(np.linalg.norm(x.max(0) - x.min(0)))
    return DEFAULT_SEPARATION_RELATIVE * diag if diag > 0 else 1e-6


class ImpulseCollisionHandler:
    """Proximity + CCD + impulse response at the time of impact (see the module docstring).

    Args:
        model: the finalised model (its surfaces, masses, restitution, friction, thickness).
        max_iterations: CCD/response rounds before the fail-safe.
        differentiable: the decide-then-replay response (:meth:`_call_replayed`, the default),
            which a ``wp.Tape`` can record and which passes the physics validation suite
            (``benchmarks/physics.py``); False: projected Gauss-Seidel impulses, 3-4x cheaper
            per step, which fail the suite's flat drops, slopes, rest, stacks and restitution.
        max_derivative: the robust-division bound ``M`` of the replayed times of impact.
        ccd_options: the narrow phase's knobs that decide the CCD contacts, a dict of
            ``precision`` ("float64" / "float32"), ``tolerance_scale``, ``max_iterations`` and
            ``tolerance`` (:class:`collision.narrow_phase.CandidateNarrowPhase`); None: the float64
            kernels as written. The replay recomputes each contact's ``t*`` with the float64
            root solver (and its mollified derivative) either way.

    Attributes (of the last call, for logging and tests):
        last_contacts: (C, 3) contact points [m] (side A's closest point at ``t*``) of the
            contacts that received an impulse.
        last_normals: (C, 3) their unit normals.
        last_times: (C,) their times of impact from the start of the substep [s].
        last_contact_count: C (cheap: the three above are worked out when first read).
        last_body_particles: the particles that touched a rigid body's vertex in the last call.
        failsafe_count: substeps (over the handler's life) in which the fail-safe froze something.
        untaped_substeps: substeps (``differentiable=True``) whose response carries no
            derivative; always 0 since the impact zones' motion is taped (kept for
            compatibility).
        active_set_repairs: exact solves redone because the active set changed.
        unsettled_active_sets: solves whose active set still changed after
            :data:`ACTIVE_SET_ITERATIONS` repairs (the last trial's set is used).
        separation: the separation ``delta`` [m] the proximity pass keeps.
    """

    def __init__(self, model: Model, max_iterations: int = 8, differentiable: bool = True,
                 max_derivative: float = DEFAULT_MAX_DERIVATIVE, ccd_options: dict | None = None):
        self.model = model
        self.ccd_options = check_ccd_options(ccd_options)
        self.max_iterations = int(max_iterations)
        self.differentiable = bool(differentiable)
        self.max_derivative = float(max_derivative)
        m = model
        mesh = self.mesh = model.collision_mesh
        self.n_particles = mesh.particle_count
        self.shape_offset = mesh.shape_offset
        self.n_shape = mesh.shape_count
        self.static_offset = mesh.static_offset
        self.shape_vertices = mesh.shape_local
        self.shape_body = mesh.shape_body
        self.static_vertices = mesh.static_vertices
        self.n_vertices = mesh.vertex_count
        self.faces, self.edges = mesh.faces, mesh.feature_edges
        # one dummy static vertex (index n_vertices, at the origin): the second side of
        # vertex-plane contacts
        self.vertex_type = np.append(mesh.vertex_type, VERTEX_STATIC).astype(np.int64)
        self.vertex_owner = np.append(mesh.vertex_owner, 0).astype(np.int64)
        self.planes = m.planes.numpy().reshape(-1, 4) if m.plane_count else np.zeros((0, 4))
        self._staging = Staging(model.device)  # the Gauss-Seidel path's reused arrays
        self._no_time = wp.zeros(1, dtype=wp.float64, device=model.device)  # an unread time array
        self._launches = RecordedLaunches(model.device)  # and its replayed kernel launches
        self.last_sweeps = 0
        self.particle_inv_mass = m.particle_inv_mass.numpy() if self.n_particles else np.zeros(0)
        # vertices an impulse can move: rigid ones and unpinned particles
        inv_mass = np.zeros(len(self.vertex_type))
        is_particle = self.vertex_type == VERTEX_PARTICLE
        inv_mass[is_particle] = self.particle_inv_mass[self.vertex_owner[is_particle]]
        self._mobile_vertex = (self.vertex_type == VERTEX_BODY) | (inv_mass > 0)
        self.n_bodies = int(m.body_count) if self.n_shape else 0
        self.body_inv_mass = m.body_inv_mass.numpy() if self.n_bodies else np.zeros(0)
        self._particle_inv_mass_w = self._staging.put("inv_mp", self.particle_inv_mass, wp.float64)
        self._body_inv_mass_w = self._staging.put("inv_mb", self.body_inv_mass, wp.float64)
        self.separation = contact_separation(model, mesh)
        self._last = self._last_call = NO_CONTACTS  # the last call's contacts (restorable / not)
        self.failsafe_count = 0
        self.ccd_events = 0  # approaching CCD hits (contacts added by a CCD round) over the handler's life
        self.untaped_substeps = 0
        self.active_set_repairs = 0
        self.unsettled_active_sets = 0
        # the replay's stages (differentiable=True) and its device copies of the mesh (vertex
        # kinds, owners, local positions, planes), which the Gauss-Seidel path's kernels read too
        self._replay = ContactReplay(
            mesh.vertex_type, mesh.vertex_owner, mesh.local,
            m.particle_inv_mass if self.n_particles else None,
            m.body_inv_mass if self.n_bodies else None,
            m.body_inv_inertia if self.n_bodies else None,
            self.planes, m.friction, m.restitution, m.device, mesh.flat_edges, mesh.flat_opposites,
        )
        # the device contact set (kernels.contact_set), and the detection stage that fills it
        dev = model.device
        self._contacts = Contacts(dev)
        self.detect = ContactDetection(model, mesh, self.planes, self.n_bodies, self._replay, self._contacts,
                                       self._staging, self._launches, self.separation, self.max_derivative,
                                       self.ccd_options, self.differentiable)
        self._records = weakref.WeakSet()  # the calls' contact records that still read the buffers
        P, B = max(self.n_particles, 1), max(self.n_bodies, 1)
        self._particle_time_w = wp.zeros(P, dtype=wp.float64, device=dev)
        self._body_time_w = wp.zeros(B, dtype=wp.float64, device=dev)
        # no impact zone (read only)
        self._no_zone_p = wp.zeros(P, dtype=wp.int32, device=dev)
        self._no_zone_b = wp.zeros(B, dtype=wp.int32, device=dev)
        # the result's arrays (the plan's ends and the velocities after the impulses: the model's
        # shapes, so the integrator copies them as they are)
        self._result = model.state()
        self._mobile_vertex_w = wp.array(self._mobile_vertex.astype(np.int32), dtype=wp.int32, device=dev)

    @property
    def broad_phase(self) -> BroadPhase | None:
        """The detection stage's broad phase (None when the model has no collidable surface)."""
        return self.detect.broad_phase

    # ------------------------------------------------------------------------------------------
    # geometry




    # ------------------------------------------------------------------------------------------

    _COUNTERS = ("failsafe_count", "ccd_events", "untaped_substeps", "active_set_repairs", "unsettled_active_sets")

    @property
    def last_contacts(self) -> np.ndarray:
        """(C, 3) contact points [m] of the last call (see the class docstring)."""
        return self._last.contacts()[0]

    @property
    def last_normals(self) -> np.ndarray:
        """(C, 3) unit normals of the last call's contacts."""
        return self._last.contacts()[1]

    @property
    def last_times(self) -> np.ndarray:
        """(C,) times of impact [s] of the last call's contacts, from the start of its substep."""
        return self._last.contacts()[2]

    @property
    def last_contact_count(self) -> int:
        """How many contacts received an impulse in the last call (``len(last_times)``, without
        working out the contact points)."""
        return self._last.count

    @property
    def last_body_particles(self) -> np.ndarray:
        """(K,) the particles that shared a contact with a rigid body's vertex in the last call
        (the implicit integrator must not prescribe their motion in a re-solve: the body would not
        feel the reaction). Not put back by :meth:`restore_stats`."""
        return self._last_call.body_particles()

    def save_stats(self) -> dict:
        """The statistics (life counters, last call's contacts), for :meth:`restore_stats` after
        calls whose result an integrator discards (a trial pass, a rejected substep)."""
        stats = {c: getattr(self, c) for c in self._COUNTERS + ("_last",)}
        stats["largest_system"] = self._replay.largest_system
        return stats

    def restore_stats(self, stats: dict) -> None:
        """Puts back the statistics of :meth:`save_stats`."""
        for c, v in stats.items():
            if c == "largest_system":
                self._replay.largest_system = v
            else:
                setattr(self, c, v)

    def _check_states(self, state_in: State, state_pred: State) -> None:
        """Raises a ValueError naming the array of ``state_in`` / ``state_pred`` with fewer rows
        than the model's particles / bodies (the kernels would read past its end)."""
        for label, state in (("state_in", state_in), ("state_pred", state_pred)):
            for name, count in (("particle_q", self.n_particles), ("particle_qd", self.n_particles),
                                ("body_q", self.n_bodies), ("body_qd", self.n_bodies)):
                if count and (getattr(state, name) is None or getattr(state, name).shape[0] < count):
                    have = 0 if getattr(state, name) is None else getattr(state, name).shape[0]
                    raise ValueError(f"{label}.{name}: {have} rows, the model has {count}")

    def _note_contacts(self, record: ContactRecord) -> None:
        """Makes ``record`` the last call's contacts (:attr:`last_contacts`, ...)."""
        self._last = self._last_call = record
        if record.reads_buffers:
            self._records.add(record)

    def __call__(self, state_in: State, state_pred: State, h: float) -> State | None:
        self._note_contacts(NO_CONTACTS)
        if self.broad_phase is None:
            return None
        self._check_states(state_in, state_pred)
        R = self._replay
        # the start velocities: an impact reflects the velocity at its time, not the forces'
        # change after it (contact_geometry_kernel)
        self._v_start = (state_in.particle_qd if self.n_particles else R.empty_vec,
                         state_in.body_qd if self.n_bodies else R.empty_twist)
        self._sep_speed = self.separation / h
        self.detect.begin(self._v_start, self._sep_speed)
        # the buffers of earlier calls are about to be reused: the records still kept (saved
        # statistics) take host copies of what they read
        for record in list(self._records):
            record.materialize()
        self._records.clear()
        if self.differentiable:
            return self._call_replayed(state_in, state_pred, h)
        P, B = self.n_particles, self.n_bodies
        R = self._replay
        # the vertices at the start (with the rigid ones' lever arms) and the predicted end;
        # host views for the broad-phase cover's box tests (per vertex, not per contact)
        x0, x0_w, lever0_w, x1_pred, inv_inertia_w = self.detect.pose_substep(state_in, state_pred)
        delta = self.separation
        cs = self._contacts
        cs.clear()
        vm = (state_pred.particle_qd if P else R.empty_vec, state_pred.body_qd if B else R.empty_twist)
        vel = None  # the velocities after the impulses (device buffers), made at the first contact
        zones = None  # the fail-safe's impact zones, made when it first acts (rare)
        zone_flags = None  # their members per particle / body (device), for the contact times
        # one broad-phase query for the proximity pass and the CCD rounds while their motion
        # stays within the margin of the predicted one (CandidateNarrowPhase.cover)
        self.detect.cover(x0[:-1], x1_pred[:-1], delta)
        # 1. proximity contacts at the start of the substep: the mesh and the plane ones, added
        # and solved together
        if self.detect.proximity(x0, x1_pred, x0_w, lever0_w, vm, h, delta):
            vel = self._velocities(state_pred)
            self._solve(vel, lever0_w, inv_inertia_w)

        # 2-5. CCD rounds on the planned motion; the result is the last round's plan: every exit
        # follows a plan with nothing changed after it (no contact added, no velocity solved,
        # no zone grown)
        failsafe = False
        planned = None
        for iteration in itertools.count():
            if cs.count or zones is not None:
                planned = self._plan(state_in, state_pred, vel, zone_flags, h)
                x1, x1_w, times = planned[2], planned[3], planned[4]
            else:  # nothing changed the prediction
                x1, x1_w, times = x1_pred, self.detect.x1_pred_w, None
            approaching = self.detect.ccd_round(x0, x1, x0_w, x1_w, lever0_w, vm, vel, times, h)
            if not approaching:
                break
            if iteration >= self.max_iterations:
                # fail-safe: rigid impact zones (Provot 1997, Bridson et al. 2002): everything
                # joined by a still-approaching contact moves as one rigid body (momentum kept;
                # at rest when the zone holds a static or pinned vertex) over the whole substep
                failsafe = True
                if zones is None:
                    zones = ImpactZones(P, B, self.particle_inv_mass)
                idx = self.detect.hits.host("vertices")[self.detect.hits.host("approaching") != 0]
                if not zones.merge(self.vertex_type[idx], self.vertex_owner[idx]):
                    break  # only contacts inside rigidly moving zones remain (rounding)
                vel = vel if vel is not None else self._velocities(state_pred)
                zone_flags = self._zone_motion(zones, state_in, vel)
                continue
            self.ccd_events += approaching
            vel = vel if vel is not None else self._velocities(state_pred)
            self.detect.add_hits(False, approaching)
            self._solve(vel, lever0_w, inv_inertia_w)
        if failsafe:
            self.failsafe_count += 1
        if planned is None:  # nothing changed the prediction (no contact, no zone grew)
            return None
        x1p_w, bq1_w, _, x1_w, _ = planned
        self._note_contacts(ContactRecord(cs, x0_w, x1_w, h, self.vertex_type))
        return State(
            particle_q=x1p_w if P else state_pred.particle_q,
            particle_qd=vel[0] if P else state_pred.particle_qd,
            body_q=bq1_w if B else state_pred.body_q,
            body_qd=vel[1] if B else state_pred.body_qd,
        )

    # ------------------------------------------------------------------------------------------
    # the Gauss-Seidel response's stages on the device (per-contact arrays stay there)

    def _velocities(self, state_pred: State):
        """The device buffers (particle velocities (P,), body twists (B,)) that the impulses
        update, holding the predicted velocities ``v-`` (:meth:`_velocities_of`)."""
        return self._velocities_of(state_pred.particle_qd, state_pred.body_qd)

    def _velocities_of(self, particle_qd, body_qd):
        """The device buffers that the Gauss-Seidel impulses update (the result's velocity
        arrays), holding ``particle_qd`` (P,) and ``body_qd`` (B,) (a model without particles /
        bodies gets the replay's stand-ins, which no contact writes)."""
        P, B, R = self.n_particles, self.n_bodies, self._replay
        vp = copy_rows(self._result.particle_qd, particle_qd, P) if P else R.empty_vec
        bv = copy_rows(self._result.body_qd, body_qd, B) if B else R.empty_twist
        return vp, bv










    def _solve(self, vel, lever: wp.array, inv_inertia_w: wp.array) -> None:
        """Projected Gauss-Seidel on the contact set (:func:`kernels.decide.solve_contacts_kernel`):
        updates the velocities ``vel`` (device buffers) and the set's accumulated impulses in
        place. ``lever`` (V + 1,) and ``inv_inertia_w`` (B,) (at least one row): the vertices'
        lever arms and the bodies' world inverse inertia tensors at the start pose."""
        cs, staging, R, count = self._contacts, self._staging, self._replay, self._contacts.count
        tol = SOLVER_TOLERANCE * SEPARATION_RATE * self._sep_speed
        sweeps = staging.empty("sweeps", 1, wp.int32)
        # without particles (bodies) no contact has a particle (rigid) vertex, so the kernel
        # never writes the shared stand-in passed for their velocities
        self._launches.launch("solve", solve_contacts_kernel, 1, [
            count, cs.vertices, cs.weights, cs.normals, cs.targets, cs.kind, R.vertex_type, R.vertex_owner,
            lever, 0,  # indexed by vertex
            self._particle_inv_mass_w, self._body_inv_mass_w, inv_inertia_w,
            float(self.model.friction), int(SOLVER_ITERATIONS), float(tol),
            # scratch: the contacts' constants over the sweeps
            staging.empty("contact_mass", count, wp.float64), staging.empty("contact_particles", count, wp.vec4i),
            staging.empty("contact_bodies", count, wp.vec2i), staging.empty("contact_body_weight", count, wp.vec2d),
            staging.empty("contact_lever", 2 * count, wp.vec3d),
            vel[0], vel[1], cs.normal_impulse, cs.friction_impulse, sweeps,
        ])
        self.last_sweeps = int(host(sweeps)[0])

    def _plan(self, state_in: State, state_pred: State, vel, zone_flags, h: float):
        """End positions of the substep ``h`` [s] for the contact set's earliest contact time per
        particle / body (:func:`kernels.active_set.owner_times_kernel`; 0 for the members of
        impact zones, ``zone_flags`` (P,), (B,) int32 device arrays or None) and the velocities
        after the impulses ``vel``: the replay's time-of-impact integration
        (:func:`kernels.integrate.time_of_impact_position`, ``time_of_impact_pose``), then the
        vertices' positions (:meth:`_pose`).

        Returns:
            (particle positions (P,), body poses (B,), vertex positions (V + 1, 3) on the host
            (a view on the CPU), their device array, (particle times, body times) [s] device
            arrays): the handler's buffers (the next plan overwrites them).
        """
        empty, R, launch = self._staging.empty, self._replay, self._launches.launch
        P, B, n = self.n_particles, self.n_bodies, self.n_vertices + 1
        tp, tb = self._particle_time_w, self._body_time_w
        self._owner_times(tp, tb, zone_flags if zone_flags is not None else (self._no_zone_p, self._no_zone_b))
        x1p, bq1 = self._result.particle_q, self._result.body_q
        x1 = empty("x_planned", n, wp.vec3d)
        particles = [state_in.particle_q, state_pred.particle_q, state_pred.particle_qd, vel[0], tp] if P else \
            [R.empty_vec] * 4 + [self._no_time]
        bodies = [state_in.body_q, state_pred.body_q, state_pred.body_qd, vel[1], tb] if B else \
            [R.empty_pose, R.empty_pose, R.empty_twist, R.empty_twist, self._no_time]
        # with bodies the vertices are posed by a second launch from the planned poses: in the
        # fused one every rigid vertex would integrate its body's pose again (a body of a few
        # hundred vertices made the plan 4x dearer); the same functions, so the same values
        launch("plan", planned_substep_kernel, P + B + (0 if B else n), [
            *particles, *bodies, float(h), R.vertex_type, R.vertex_owner, R.local, P, B, x1p, bq1, x1])
        if B:
            x1 = self.detect.pose("planned", x1p if P else None, bq1)
        return x1p, bq1, host(x1)[:n], x1, (tp, tb)

    def _owner_times(self, particle_time: wp.array, body_time: wp.array, zone_flags) -> None:
        """Each particle's / body's earliest contact time [s] in the contact set into
        ``particle_time`` (P,) / ``body_time`` (B,): inf without one, 0 for the members of impact
        zones (``zone_flags``: (P,), (B,) int32 device arrays), which move rigidly over the whole
        substep (:func:`kernels.active_set.owner_times_kernel`)."""
        cs, R, P = self._contacts, self._replay, self.n_particles
        self._launches.launch("owner_reset", owner_times_reset_kernel, P + self.n_bodies,
                              [P, *zone_flags, particle_time, body_time])
        if cs.count:
            self._launches.launch("owner_times", owner_times_kernel, cs.count, [
                cs.vertices, cs.weights, cs.toi, R.vertex_type, R.vertex_owner, particle_time, body_time])

    def _zone_motion(self, zones: "ImpactZones", state_in: State, vel):
        """Sets the velocities ``vel`` of the impact zones' members to their zone's
        momentum-conserving rigid motion (the replay's kernels,
        :meth:`sim.contact.replay.ContactReplay.zone_velocities`, off the tape) and returns the
        zones' member flags per particle / body (device int32 arrays)."""
        P, B, R, m = self.n_particles, self.n_bodies, self._replay, self.model
        particle_zone, body_zone, n_zones = zones.labels()
        R.begin()  # its arena: nothing of this call lives there
        with paused_tape():
            vp, vb = R.zone_velocities(vel[0] if P else None, vel[1] if B else None, particle_zone, body_zone,
                                       n_zones, state_in.particle_q if P else None, state_in.body_q if B else None,
                                       m.body_mass if B else None, m.body_inertia if B else None)
        if P and vp is not vel[0]:  # the input itself when no particle is in a zone
            copy_rows(vel[0], vp, P)
        if B and vb is not vel[1]:
            copy_rows(vel[1], vb, B)
        return self._zone_flags(zones)

    def _zone_flags(self, zones: "ImpactZones"):
        """The impact zones' members per particle / body (device int32 arrays, 1 in a zone)."""
        put = self._staging.put
        return (put("zone_p", zones.particles.astype(np.int32), wp.int32) if self.n_particles else self._no_zone_p,
                put("zone_b", zones.bodies.astype(np.int32), wp.int32) if self.n_bodies else self._no_zone_b)

    def _call_replayed(self, state_in: State, state_pred: State, h: float) -> State | None:
        """The response as decisions and a taped replay, both on the device: one
        :class:`ReplayedSubstep` (see there)."""
        return ReplayedSubstep(self, state_in, state_pred, h).run()

    def _friction_share(self, active: wp.array) -> wp.array:
        """Per contact of the set: one over the largest number of active contacts (``active``)
        that any particle or body it moves takes part in (friction impulses of one pass are
        applied together; :mod:`kernels.contact_set`). A fresh array while a tape records."""
        cs, R, P = self._contacts, self._replay, self.n_particles
        counts = self._staging.empty("share_counts", P + self.n_bodies + 1, wp.int32)
        zero(counts)
        share = R.take(cs.count, wp.float64, zero=False, grad=False)
        launch = self._launches.launch
        launch("share_count", friction_share_count_kernel, cs.count, [
            cs.vertices, cs.weights, active, P, R.vertex_type, R.vertex_owner, counts])
        launch("share", friction_share_kernel, cs.count, [
            cs.vertices, cs.weights, P, R.vertex_type, R.vertex_owner, counts, share])
        return share

    def _flags_differ(self, a: wp.array, b: wp.array, count: int) -> bool:
        """Whether the int flags ``a`` and ``b`` differ in one of their first ``count`` entries."""
        counter = self._staging.empty("flags_differ", 1, wp.int32)
        zero(counter)
        self._launches.launch("flags_differ", flags_differ_kernel, count, [a, b, counter])
        return bool(host(counter)[0])


class ReplayedSubstep:
    """One substep of the replayed response (design.md "Differentiating collision response:
    decide, then replay"), as named stages on the device (:class:`sim.contact.replay.ContactReplay`).

    The result is the replay's, exact for the decided contact set (impulses from the active set's
    equations, not Gauss-Seidel sweeps), and differentiable when a ``wp.Tape`` is recording. The
    decisions (the contact set, the root slots, the active set and its repairs, the earliest
    contact per owner) are made by the kernels of :mod:`kernels.contact_set` off the tape; the
    launches that depend smoothly on the state are recorded. The fail-safe's impact zones are
    taped too: their membership is decided on the host from the approaching hits (rare), their
    momentum-conserving rigid motion is replayed
    (:meth:`sim.contact.replay.ContactReplay.zone_velocities`), so every substep is taped.

    Stages, in order (:meth:`run`): :meth:`proximity` (contacts at the start of the substep and
    their :meth:`solve`), then CCD rounds on the :meth:`plan` until nothing approaches, each
    adding its approaching hits (:meth:`geometry`, :meth:`add`) and solving again; after
    ``max_iterations`` rounds the fail-safe's :meth:`grow_zones`.

    Args:
        handler: the :class:`ImpulseCollisionHandler` whose buffers and decisions the substep uses.
        state_in: the start State; state_pred: the predicted end State (velocities ``v-``).
        h: the substep [s].
    """

    def __init__(self, handler: "ImpulseCollisionHandler", state_in: State, state_pred: State, h: float) -> None:
        self.handler = hd = handler
        self.replay = R = hd._replay
        R.begin()  # the previous call's results were copied by the integrator: its arrays are free
        self.P, self.B = P, B = hd.n_particles, hd.n_bodies
        self.state_in, self.state_pred, self.h = state_in, state_pred, h
        self.xq0 = state_in.particle_q if P else None
        self.bq0_w = state_in.body_q if B else None
        self.vm_p = state_pred.particle_qd if P else None
        self.vm_b = state_pred.body_qd if B else None
        self.vm = (self.vm_p if P else R.empty_vec, self.vm_b if B else R.empty_twist)
        self.X0, self.L0, self.inv_I = R.pose_start(self.xq0, self.bq0_w)
        self.delta = hd.separation
        self.mu = float(hd.model.friction)
        self.contacts = hd._contacts
        self.contacts.clear()
        self.zones = None
        self.zone_flags = (hd._no_zone_p, hd._no_zone_b)
        # the taped contact geometry of the set (None before its first contact), the velocities
        # and those that move the positions
        self.rows = None
        self.vp, self.vb, self.xp, self.xb = self.vm_p, self.vm_b, self.vm_p, self.vm_b
        self.tolerance = SOLVER_TOLERANCE * SEPARATION_RATE * hd._sep_speed
        self.resting = (*hd._v_start, SEPARATION_RATE * hd._sep_speed)  # contact_geometry_kernel's bounce threshold
        self.launch = hd._launches.launch

    def current(self):
        """The velocities after the impulses so far (particles, bodies)."""
        R = self.replay
        return (self.vp if self.P else R.empty_vec, self.vb if self.B else R.empty_twist)

    def owners(self):
        """Each owner's earliest contact time and its row (decisions: fresh arrays while a
        tape records, which the taped geometry and integration read). A member of an impact
        zone has time 0 and row -2: it moves with the zone's rigid velocity over the whole
        substep, so later hits see that velocity at any ``t*`` (as in the Gauss-Seidel
        response)."""
        hd, R, cs, P, B, launch = self.handler, self.replay, self.contacts, self.P, self.B, self.launch
        take = R.take
        tp, tb = take(max(P, 1), wp.float64, zero=False, grad=False), take(max(B, 1), wp.float64, zero=False, grad=False)
        po, bo = take(max(P, 1), wp.int32, zero=False, grad=False), take(max(B, 1), wp.int32, zero=False, grad=False)
        kp, kb = hd._staging.empty("owner_key_p", P, wp.int32), hd._staging.empty("owner_key_b", B, wp.int32)
        hd._owner_times(tp, tb, self.zone_flags)
        launch("r_owner_key_reset", owner_rows_reset_kernel, P + B, [P, kp, kb])
        if cs.count:
            launch("r_owner_rows", owner_rows_kernel, cs.count, [
                cs.vertices, cs.weights, cs.toi, cs.timed, R.vertex_type, R.vertex_owner, tp, tb, kp, kb])
        launch("r_owner_finish", owner_rows_finish_kernel, P + B, [P, kp, kb, *self.zone_flags, po, bo])
        return po, bo, tp, tb

    def plan(self):
        """The planned end positions (particles, body poses) and the owners' contact times: the
        positions move with the velocities plus the push (the separation restored), each owner
        from its earliest contact time (taped)."""
        R, P, B, sp = self.replay, self.P, self.B, self.state_pred
        po, bo, tp, tb = self.owners()
        toi = self.rows[0] if self.rows is not None else R.take(1, wp.float64, grad=False)
        X1p, BQ1 = R.integrate(self.xq0, sp.particle_q if P else None, self.vm_p, self.vp, self.xp, self.bq0_w,
                               sp.body_q if B else None, self.vm_b, self.vb, self.xb, po, bo, toi, self.h)
        return X1p, BQ1, tp, tb

    def geometry(self, X1, tp, tb):
        """The taped geometry (time, normal, weights, targets) of the detection pass's hits on
        the motion from the start to ``X1`` (:meth:`sim.contact.replay.ContactReplay.geometry`)."""
        hd, H = self.handler, self.handler.detect.hits
        rows = {"vertices": H.vertices, "kind": H.kind, "source": H.source, "detected": H.detected, "plane": H.plane}
        return self.replay.geometry(self.X0, X1, self.L0, rows, H.count, *hd._v_start, self.vm_p, self.vp, self.vm_b,
                                    self.vb, tp, tb, self.h, self.delta, SEPARATION_RATE, TOUCHING_RELATIVE,
                                    hd.max_derivative,
                                    bool(hd.ccd_options))  # a generated narrow phase numbers roots its own way

    def add(self, out, all_new: bool, approaching: int) -> None:
        """Adds the pass's hits (all, or the ``approaching`` ones) to the contact set and merges
        their taped geometry ``out`` into the set's rows."""
        hd, R, cs = self.handler, self.replay, self.contacts
        take, c = R.take, cs.count + (hd.detect.hits.count if all_new else approaching)
        merge = (take(c, wp.int32, zero=False, grad=False), take(c, wp.int32, zero=False, grad=False),
                 take(c, wp.int32, zero=False, grad=False))
        hd.detect.add_hits(all_new, approaching, out, merge)
        if cs.count:  # touching pairs with no defined normal join no set: it may stay empty
            self.rows = R.merge(self.rows, (out[0], out[3], out[1], out[2], out[4]), *merge, cs.count)

    def repair(self, solved, active, mobile, changes):
        """The repaired set after the trial ``solved`` of ``active`` and how many contacts it
        changes (:func:`kernels.active_set.active_set_update_kernel`)."""
        hd, R, cs, P, B = self.handler, self.replay, self.contacts, self.P, self.B
        C = cs.count
        vp_t, vb_t, normal_t = solved[:3]
        repaired = R.take(C, wp.int32, zero=False, grad=False)
        self.launch("r_active_update", active_set_update_kernel, 1, [
            C, cs.vertices, cs.weights, cs.normals, cs.targets, cs.collided, mobile, active, normal_t,
            R.vertex_type, R.vertex_owner, self.L0, vp_t if P else R.empty_vec, vb_t if B else R.empty_twist,
            float(self.tolerance), float(self.collided_tolerance), float(ACTIVE_SET_PULLING),
            hd._staging.empty("active_jn", C, wp.float64), repaired, changes])
        return repaired, int(host(changes)[0])

    def solve(self) -> None:
        """Decide the active set by projected Gauss-Seidel on top of the current velocities,
        then replay the exact normal solve and repair the set (drop pulling contacts, add
        violated ones) until it holds; the velocities and the motion that moves the positions
        become the final solve's."""
        hd, R, cs, P, B, mu = self.handler, self.replay, self.contacts, self.P, self.B, self.mu
        C, take, launch = cs.count, R.take, self.launch
        with paused_tape():
            dec = hd._velocities_of(*self.current())
            hd._solve(dec, self.L0, self.inv_I)
        # the set's rows as the taped solves read them (one copy while a tape records)
        vertices, kinds = R.frozen(cs.vertices, C), R.frozen(cs.kind, C)
        mobile = hd._staging.empty("mobile_rows", C, wp.int32)
        active = take(C, wp.int32, zero=False, grad=False)
        launch("r_initial_active", initial_active_kernel, C, [
            cs.vertices, cs.weights, cs.normal_impulse, hd._mobile_vertex_w, mobile, active])
        taped = active  # the set whose solve the tape holds (the first trial's)
        tape = active_tape()
        changes = hd._staging.empty("active_changes", 1, wp.int32)
        self.collided_tolerance = (APPROACH_EPS * hd._sep_speed if C <= ACTIVE_SET_COLLIDED_MAX_CONTACTS
                                   else self.tolerance)
        args = (vertices, kinds, C)
        for iteration in range(ACTIVE_SET_ITERATIONS):
            share = hd._friction_share(active) if mu > 0 else None
            # the first trial is recorded (usually it is the final one); repair trials stay off
            # the tape (their O(n^2) matrices would be kept to the end)
            with (contextlib.nullcontext() if iteration == 0 else paused_tape()):
                solved = R.solve(self.rows, *args, active, self.L0, self.inv_I, self.vm_p, self.vm_b, share,
                                 self.resting)
            if iteration == 0:
                recorded = solved
            repaired, n_changes = self.repair(solved, active, mobile, changes)
            if not n_changes:
                break
            if iteration == ACTIVE_SET_ITERATIONS - 1:
                hd.unsettled_active_sets += 1
                break  # the last trial's set stands, taped or not: one forward function
            active = repaired
            hd.active_set_repairs += 1
        vp_d, vb_d, normal, moving = solved
        if tape is not None and active is not taped and hd._flags_differ(taped, active, C):
            # the replay of the final active set, recorded
            share = hd._friction_share(active) if mu > 0 else None
            vp_d, vb_d, normal, moving = R.solve(self.rows, *args, active, self.L0, self.inv_I, self.vm_p, self.vm_b,
                                                 share, self.resting)
        elif tape is not None:
            # the repairs came back to the first trial's set: its recorded solve (the same
            # values) is the one the tape continues from, not the last, unrecorded trial
            vp_d, vb_d, normal, moving = recorded
        if P:
            self.vp, self.xp = vp_d, moving[0]
        if B:
            self.vb, self.xb = vb_d, moving[1]
        launch("r_set_impulses", set_impulses_kernel, C, [
            active, normal, cs.normals, cs.normal_impulse, cs.friction_impulse])

    def proximity(self) -> None:
        """Proximity contacts at the start of the substep, and their solve. Also the substep's
        one broad-phase query while the rounds' motion stays near the predicted one."""
        hd, sp = self.handler, self.state_pred
        with paused_tape():  # decisions: off the tape
            self.x0 = host(self.X0)
            x1_pred = host(hd.detect.pose("predicted", sp.particle_q, sp.body_q))[: hd.n_vertices + 1]
            hd.detect.cover(self.x0[:hd.n_vertices], x1_pred[:hd.n_vertices], self.delta)
            found = hd.detect.proximity_hits(self.x0, x1_pred, self.X0, self.delta)
        if found:
            self.add(self.geometry(self.X0, hd.detect.inf_time_p, hd.detect.inf_time_b), True, 0)  # no contact time yet
            if self.contacts.count:
                self.solve()

    def grow_zones(self) -> bool:
        """The fail-safe: the approaching hits join impact zones (membership decided on the
        host), which move rigidly with their momentum (taped). False when no zone grew."""
        hd, R, P, B = self.handler, self.replay, self.P, self.B
        if self.zones is None:
            self.zones = ImpactZones(P, B, hd.particle_inv_mass)
        idx = hd.detect.hits.host("vertices")[hd.detect.hits.host("approaching") != 0]
        if not self.zones.merge(hd.vertex_type[idx], hd.vertex_owner[idx]):
            return False
        m = hd.model
        particle_zone, body_zone, n_zones = self.zones.labels()
        self.vp, self.vb = R.zone_velocities(self.vp, self.vb, particle_zone, body_zone, n_zones, self.xq0,
                                             self.bq0_w, m.body_mass if B else None, m.body_inertia if B else None)
        self.zone_flags = hd._zone_flags(self.zones)
        self.xp, self.xb = R.zone_moving(self.xp, self.xb, *self.zone_flags, self.vp, self.vb)
        return True

    def run(self) -> State | None:
        """The substep's stages; the new State, or None when nothing touched."""
        hd, R, P, B, sp = self.handler, self.replay, self.P, self.B, self.state_pred
        # 1. proximity contacts at the start of the substep
        self.proximity()
        # 2-5. CCD rounds on the planned motion; the result is the last round's plan: every exit
        # follows a plan with nothing changed after it
        failsafe = False
        for iteration in itertools.count():
            X1p, BQ1, tp, tb = self.plan()
            X1 = R.positions(X1p if P else None, BQ1 if B else None)
            with paused_tape():  # decisions: off the tape
                count = hd.detect.ccd_hits(self.x0, host(X1), X1, 1)
            if not count:
                break
            out = self.geometry(X1, tp, tb)
            with paused_tape():
                approaching = hd.detect.approach(self.X0, X1, self.L0, out[:3], self.vm, self.current(), (tp, tb), self.h)
            if not approaching:
                break
            if iteration >= hd.max_iterations:
                failsafe = True
                if not self.grow_zones():
                    break
                continue
            hd.ccd_events += approaching
            self.add(out, False, approaching)
            self.solve()
        if failsafe:
            hd.failsafe_count += 1
        if self.contacts.count == 0 and not failsafe:
            return None
        hd._note_contacts(ContactRecord(self.contacts, self.X0, X1, self.h, hd.vertex_type))
        return State(
            particle_q=X1p if P else sp.particle_q,
            particle_qd=self.vp if P else sp.particle_qd,
            body_q=BQ1 if B else sp.body_q,
            body_qd=self.vb if B else sp.body_qd,
        )
