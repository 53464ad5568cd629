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
   start offset (a rigid body's face: outwards, so a vertex crossing it from behind, leaving the
   body, separates), the target ``-e v_n`` (``v_n`` the velocity at ``t*``: the start velocity plus
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
and the plan read that set where it is. The counts stay on the device too, in one array
(:attr:`sim.contact.detect.ContactDetection.counts`): the kernels launch over a bound and read
them there, and a CCD round's detection, whose broad-phase cover is tested by a kernel as well,
brings them to the host in one read (for Gauss-Seidel the whole round, the loop's continue test;
``benchmarks/host_reads.py`` counts the reads). The host also sees the per-vertex positions of
the substep's start (the cover and the proximity pass), the replayed response's approaching and
contact counts, the sizes of its exact solves and their decisions, and in the rare fail-safe the
approaching hits that join impact zones.

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

import weakref

import numpy as np
import warp as wp

from collision.broad_phase import BroadPhase
from collision.roots import DEFAULT_MAX_DERIVATIVE
from core.buffers import RecordedLaunches, Staging, copy_rows, host
from kernels.active_set import owner_times_kernel, owner_times_reset_kernel
from kernels.decide import solve_contacts_kernel
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, VERTEX_STATIC
from kernels.variants import check_settings as check_ccd_settings
from sim.collision_mesh import CollisionMesh
from sim.contact.contacts import Contacts
from sim.contact.detect import ContactDetection
from sim.contact.gauss_seidel import GaussSeidelSubstep
from sim.contact.record import NO_CONTACTS, ContactRecord
from sim.contact.replay import ContactReplay
from sim.contact.replayed import ReplayedSubstep
from sim.contact.stage import CollisionStage
from sim.contact.tuning import DEFAULT_SEPARATION_RELATIVE, SEPARATION_RATE, SOLVER_ITERATIONS, SOLVER_TOLERANCE
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


class ImpulseCollisionHandler(CollisionStage):
    """Proximity + CCD + impulse response at the time of impact (see the module docstring).

    Args:
        model: the finalised model (its surfaces, masses, restitution, friction, thickness).
        max_iterations: CCD/response rounds before the fail-safe.
        differentiable: the decide-then-replay response (:class:`sim.contact.replayed.ReplayedSubstep`, the default),
            which a ``wp.Tape`` can record and which passes the physics validation suite
            (``benchmarks/physics.py``); False: projected Gauss-Seidel impulses, 3-4x cheaper
            per step, which fail the suite's flat drops, slopes, rest, stacks and restitution.
        max_derivative: the robust-division bound ``M`` of the replayed times of impact.
        ccd_options: the narrow phase's knobs that decide the CCD contacts, a dict of
            ``precision`` ("float64" / "float32"), ``tolerance_scale``, ``max_iterations`` and
            ``tolerance`` (:class:`collision.narrow_phase.CandidateNarrowPhase`); None: the float64
            kernels as written. The replay recomputes each contact's ``t*`` with the float64
            root solver (and its mollified derivative) either way.
        capture_rounds: with ``differentiable=False``, run each substep's CCD rounds after its
            first contact as one recorded Warp graph (``wp.capture_while``;
            :meth:`sim.contact.gauss_seidel.GaussSeidelSubstep.device_rounds`): the same bits, one
            host read for all the rounds instead of one per round. Off by default: on the CPU the
            recording costs more than it saves (``benchmarks/capture.py``).

    Attributes (of the last call, for logging and tests):
        last_contacts: (C, 3) contact points [m] (side A's closest point at ``t*``) of the
            contacts that received an impulse.
        last_normals: (C, 3) their unit normals.
        last_times: (C,) their times of impact from the start of the substep [s].
        last_contact_count: C (cheap: the three above are worked out when first read).
        last_body_particles: the particles that touched a rigid body's vertex in the last call.
        failsafe_count: substeps (over the handler's life) in which the fail-safe froze something.
        active_set_repairs: exact solves redone because the active set changed.
        unsettled_active_sets: solves whose active set still changed after
            :data:`ACTIVE_SET_ITERATIONS` repairs (the last trial's set is used).
        separation: the separation ``delta`` [m] the proximity pass keeps.
    """

    def __init__(self, model: Model, max_iterations: int = 8, differentiable: bool = True,
                 max_derivative: float = DEFAULT_MAX_DERIVATIVE, ccd_options: dict | None = None,
                 capture_rounds: bool = False):
        if not isinstance(capture_rounds, bool):
            raise ValueError(f"capture_rounds must be True or False, got {capture_rounds!r}")
        if capture_rounds and differentiable:
            raise ValueError("capture_rounds=True needs differentiable=False: the replayed response's rounds "
                             "decide on the host")
        self.model = model
        self.capture_rounds = capture_rounds
        self.captured_round_graphs = 0  # graphs of CCD rounds recorded and launched (capture_rounds)
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
        self.staging = Staging(model.device)  # the Gauss-Seidel path's reused arrays
        self.no_time = wp.zeros(1, dtype=wp.float64, device=model.device)  # an unread time array
        self.launches = RecordedLaunches(model.device)  # and its replayed kernel launches
        self._sweeps = None  # the last Gauss-Seidel solve's sweep count (device)
        self.particle_inv_mass = m.particle_inv_mass.numpy() if self.n_particles else np.zeros(0)
        # vertices an impulse can move: rigid ones and unpinned particles
        inv_mass = np.zeros(len(self.vertex_type))
        is_particle = self.vertex_type == VERTEX_PARTICLE
        inv_mass[is_particle] = self.particle_inv_mass[self.vertex_owner[is_particle]]
        self._mobile_vertex = (self.vertex_type == VERTEX_BODY) | (inv_mass > 0)
        self.n_bodies = int(m.body_count) if self.n_shape else 0
        self.body_inv_mass = m.body_inv_mass.numpy() if self.n_bodies else np.zeros(0)
        self._particle_inv_mass_w = self.staging.put("inv_mp", self.particle_inv_mass, wp.float64)
        self._body_inv_mass_w = self.staging.put("inv_mb", self.body_inv_mass, wp.float64)
        self.separation = contact_separation(model, mesh)
        self._last = self._last_call = NO_CONTACTS  # the last call's contacts (restorable / not)
        self.failsafe_count = 0
        self.ccd_events = 0  # approaching CCD hits (contacts added by a CCD round) over the handler's life
        self.active_set_repairs = 0
        self.unsettled_active_sets = 0
        # the replay's stages (differentiable=True) and its device copies of the mesh (vertex
        # kinds, owners, local positions, planes), which the Gauss-Seidel path's kernels read too
        self.replay = ContactReplay(
            mesh.vertex_type, mesh.vertex_owner, mesh.local,
            m.particle_inv_mass if self.n_particles else None,
            m.body_inv_mass if self.n_bodies else None,
            m.body_inv_inertia if self.n_bodies else None,
            self.planes, m.friction, m.restitution, m.device, mesh.flat_edges, mesh.flat_opposites, m.gravity,
        )
        # the device contact set (kernels.contact_set), and the detection stage that fills it
        dev = model.device
        self.contact_set = Contacts(dev)
        self.detect = ContactDetection(model, mesh, self.planes, self.n_bodies, self.replay, self.contact_set,
                                       self.staging, self.launches, self.separation, self.max_derivative,
                                       self.ccd_options, self.differentiable)
        self._records = weakref.WeakSet()  # the calls' contact records that still read the buffers
        P, B = max(self.n_particles, 1), max(self.n_bodies, 1)
        self.particle_time_w = wp.zeros(P, dtype=wp.float64, device=dev)
        self.body_time_w = wp.zeros(B, dtype=wp.float64, device=dev)
        # no impact zone (read only)
        self.no_zone_p = wp.zeros(P, dtype=wp.int32, device=dev)
        self.no_zone_b = wp.zeros(B, dtype=wp.int32, device=dev)
        # the result's arrays (the plan's ends and the velocities after the impulses: the model's
        # shapes, so the integrator copies them as they are)
        self.result = model.state()
        self.mobile_vertex_w = wp.array(self._mobile_vertex.astype(np.int32), dtype=wp.int32, device=dev)

    def set_exact_gravity(self, exact: bool) -> None:
        """The contacts' plane law takes gravity's half substep into the velocity at ``t*``
        for semi-implicit Euler's stored velocities, not for the exact ballistic update's
        (:func:`kernels.integrate.plane_rebound`'s rule; :class:`sim.contact.stage.CollisionStage`)."""
        self.replay.half_substep_gravity = self.replay.no_gravity if exact else self.replay.gravity

    @property
    def broad_phase(self) -> BroadPhase | None:
        """The detection stage's broad phase (None when the model has no collidable surface)."""
        return self.detect.broad_phase

    @property
    def surface_separation(self) -> float | None:
        """:attr:`separation` when the handler acts on collidable surfaces (it has a broad phase),
        else None (:class:`sim.contact.stage.CollisionStage`)."""
        return self.separation if self.detect.broad_phase is not None else None

    # ------------------------------------------------------------------------------------------
    # geometry


    # ------------------------------------------------------------------------------------------

    _COUNTERS = ("failsafe_count", "ccd_events", "active_set_repairs", "unsettled_active_sets",
                 "captured_round_graphs")

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
        stats["largest_system"] = self.replay.largest_system
        return stats

    def restore_stats(self, stats: dict) -> None:
        """Puts back the statistics of :meth:`save_stats`."""
        for c, v in stats.items():
            if c == "largest_system":
                self.replay.largest_system = v
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

    def note_contacts(self, record: ContactRecord) -> None:
        """Makes ``record`` the last call's contacts (:attr:`last_contacts`, ...)."""
        self._last = self._last_call = record
        if record.reads_buffers:
            self._records.add(record)

    def __call__(self, state_in: State, state_pred: State, h: float) -> State | None:
        self.note_contacts(NO_CONTACTS)
        if self.broad_phase is None:
            return None
        self._check_states(state_in, state_pred)
        R = self.replay
        # the start velocities: an impact reflects the velocity at its time, not the forces'
        # change after it (contact_geometry_kernel)
        self.v_start = (state_in.particle_qd if self.n_particles else R.empty_vec,
                         state_in.body_qd if self.n_bodies else R.empty_twist)
        self.separation_speed = self.separation / h
        self.detect.begin(self.v_start, self.separation_speed)
        # the buffers of earlier calls are about to be reused: the records still kept (saved
        # statistics) take host copies of what they read
        for record in list(self._records):
            record.materialize()
        self._records.clear()
        if self.differentiable:
            return ReplayedSubstep(self, state_in, state_pred, h).run()
        return GaussSeidelSubstep(self, state_in, state_pred, h).run()

    # ------------------------------------------------------------------------------------------
    # decisions both responses take (the replayed one decides its active set by Gauss-Seidel)

    def velocities(self, state_pred: State):
        """The device buffers (particle velocities (P,), body twists (B,)) that the impulses
        update, holding the predicted velocities ``v-`` (:meth:`velocities_of`)."""
        return self.velocities_of(state_pred.particle_qd, state_pred.body_qd)

    def velocities_of(self, particle_qd, body_qd):
        """The device buffers that the Gauss-Seidel impulses update (the result's velocity
        arrays), holding ``particle_qd`` (P,) and ``body_qd`` (B,) (a model without particles /
        bodies gets the replay's stand-ins, which no contact writes)."""
        P, B, R = self.n_particles, self.n_bodies, self.replay
        vp = copy_rows(self.result.particle_qd, particle_qd, P) if P else R.empty_vec
        bv = copy_rows(self.result.body_qd, body_qd, B) if B else R.empty_twist
        return vp, bv

    def gauss_seidel(self, vel, lever: wp.array, inv_inertia_w: wp.array) -> None:
        """Projected Gauss-Seidel on the contact set (:func:`kernels.decide.solve_contacts_kernel`):
        updates the velocities ``vel`` (device buffers) and the set's accumulated impulses in
        place. ``lever`` (V + 1,) and ``inv_inertia_w`` (B,) (at least one row): the vertices'
        lever arms and the bodies' world inverse inertia tensors at the start pose."""
        cs, R = self.contact_set, self.replay
        tol = SOLVER_TOLERANCE * SEPARATION_RATE * self.separation_speed
        *scratch, sweeps = self.reserve_solve()
        self._sweeps = sweeps
        # without particles (bodies) no contact has a particle (rigid) vertex, so the kernel
        # never writes the shared stand-in passed for their velocities
        self.launches.launch("solve", solve_contacts_kernel, 1, [
            cs.counter, cs.vertices, cs.weights, cs.normals, cs.targets, cs.kind, R.vertex_type, R.vertex_owner,
            lever, 0,  # indexed by vertex
            self._particle_inv_mass_w, self._body_inv_mass_w, inv_inertia_w,
            float(self.model.friction), int(SOLVER_ITERATIONS), float(tol),
            *scratch, vel[0], vel[1], cs.normal_impulse, cs.friction_impulse, sweeps,
        ])

    def reserve_solve(self) -> tuple:
        """The scratch arrays of :meth:`gauss_seidel` for the contact set's capacity (its count
        may be on the device only, after a CCD round's growth): the contacts' constants over the
        sweeps (mass, particles, bodies, body weights, lever arms) and the sweep counter."""
        rows, empty = self.contact_set.capacity, self.staging.empty
        return (empty("contact_mass", rows, wp.float64), empty("contact_particles", rows, wp.vec4i),
                empty("contact_bodies", rows, wp.vec2i), empty("contact_body_weight", rows, wp.vec2d),
                empty("contact_lever", 2 * rows, wp.vec3d), empty("sweeps", 1, wp.int32))

    @property
    def last_sweeps(self) -> int:
        """Sweeps the last Gauss-Seidel solve ran (read from the device when asked)."""
        return int(host(self._sweeps)[0]) if self._sweeps is not None else 0


    def owner_times(self, particle_time: wp.array, body_time: wp.array, zone_flags) -> None:
        """Each particle's / body's earliest contact time [s] in the contact set into
        ``particle_time`` (P,) / ``body_time`` (B,): inf without one, 0 for the members of impact
        zones (``zone_flags``: (P,), (B,) int32 device arrays), which move rigidly over the whole
        substep (:func:`kernels.active_set.owner_times_kernel`)."""
        cs, R, P = self.contact_set, self.replay, self.n_particles
        self.launches.launch("owner_reset", owner_times_reset_kernel, P + self.n_bodies,
                              [P, *zone_flags, particle_time, body_time])
        # over the set's capacity: its count may be on the device only
        self.launches.launch("owner_times", owner_times_kernel, cs.capacity, [
            cs.counter, cs.vertices, cs.weights, cs.toi, R.vertex_type, R.vertex_owner, particle_time, body_time])


    def zone_flags(self, zones: ImpactZones):
        """The impact zones' members per particle / body (device int32 arrays, 1 in a zone)."""
        put = self.staging.put
        return (put("zone_p", zones.particles.astype(np.int32), wp.int32) if self.n_particles else self.no_zone_p,
                put("zone_b", zones.bodies.astype(np.int32), wp.int32) if self.n_bodies else self.no_zone_b)
