"""The detection stage of the collision response: which primitive pairs are hits in a pass (the
proximity pairs at the start of a substep, or one CCD round's crossings), in pair order, with
their geometry and whether they approach, and the contact set they join
(:class:`ContactDetection`). Every decision here is made off the tape, on the model's device."""

from __future__ import annotations

import numpy as np
import warp as wp

from collision.broad_phase import BroadPhase
from collision.narrow_phase import CandidateNarrowPhase
from core.buffers import host, peek, upload, zero
from kernels.contact_geometry import contact_geometry_kernel
from kernels.contact_set import (add_contacts_kernel, approach_kernel, gather_hits_kernel, hit_keys_kernel,
                                 match_contacts_kernel, plane_crossing_kernel, plane_proximity_kernel,
                                 round_control_kernel, sort_hit_keys_kernel)
from kernels.pose import pose_positions_kernel, pose_substep_kernel
from sim.contact.contacts import ContactLimitExceeded, Hits
from sim.model import State
from sim.contact.tuning import (APPROACH_EPS, CCD_REACH_MIN_CANDIDATES, CCD_REACH_SLACK, COVER_AHEAD,
                                COVER_AHEAD_LIMIT, COVER_DENSE_CANDIDATES, COVER_MARGIN, COVER_SCALES, COVER_SLACK,
                                COVER_SPARSE_CANDIDATES, DEVICE_SORT_MIN, END_OF_SUBSTEP, MAX_HITS_MIN,
                                MAX_HITS_PER_VERTEX, PLANE_ROUNDING_SLACK, PROXIMITY_HYSTERESIS, SEPARATION_RATE,
                                TOUCHING_RELATIVE)


COUNT_SLOTS = ("mesh", "plane", "kept", "repeated", "approaching", "contacts", "uncovered", "beyond_reach",
               "round", "events", "go", "cover_outside", "reach_vf", "reach_ee", "unbounded")
"""The slots of :attr:`ContactDetection.counts`: the narrow phase's hits, the vertex-plane hits,
the hits kept in pair order, the pairs found twice, the approaching hits, the contact set's
rows, the vertices whose motion left the broad-phase cover's room or their reach radius
(:meth:`collision.narrow_phase.CandidateNarrowPhase.ccd_count_device`), the state of CCD
rounds run on the device (:func:`kernels.contact_set.round_control_kernel`): the round, the
approaching hits added so far, and whether the next round runs; then the substep's start: the
vertices whose motion left the kept cover's slack (:meth:`ContactDetection.cover`), the pairs
the proximity pass kept for the rounds (vertex-face, edge-edge) and the motion radii that are
not finite."""
(_MESH, _PLANE, _KEPT, _REPEATED, _APPROACHING, _CONTACTS, _UNCOVERED, _BEYOND_REACH, ROUND, EVENTS,
 _GO, _COVER_OUTSIDE, _REACH_VF, _REACH_EE, _UNBOUNDED) = range(len(COUNT_SLOTS))


class ContactDetection:
    """Hits of the collidable vertices, faces, edges and planes of one model, and the contact set
    they join.

    The broad phase's candidates (one query kept while the motion stays inside its cover,
    :meth:`cover`) go through the narrow phase of :class:`collision.narrow_phase.CandidateNarrowPhase`
    (proximity at the start, or CCD of the straight paths at zero thickness) and the
    vertex-plane tests; the hits are put into one canonical pair order (:meth:`sorted_hits`),
    given their geometry (:meth:`hit_geometry`), tested for approach (:meth:`approach`) and added
    to the contact set (:meth:`add_hits`), all by device kernels; the host sees counts.

    Args:
        model: the :class:`sim.model.Model`; mesh: its :class:`sim.collision_mesh.CollisionMesh`.
        planes: (K, 4) the planes' normals and offsets.
        n_bodies: the bodies with collidable vertices.
        replay: the response's :class:`sim.contact.replay.ContactReplay` (its device copies of the
            vertex kinds, owners, local positions and planes).
        contacts: the device contact set (:class:`sim.contact.contacts.Contacts`).
        staging, launches: the response's reused arrays and recorded launches.
        separation: the separation ``delta`` [m] every contact keeps.
        max_derivative: ``M`` of the contact times' mollified derivatives.
        ccd_options: the narrow phase's options.
        differentiable: whether the replayed response (not Gauss-Seidel) follows.
    """

    def __init__(self, model, mesh, planes: np.ndarray, n_bodies: int, replay, contacts, staging, launches,
                 separation: float, max_derivative: float, ccd_options: dict, differentiable: bool) -> None:
        m, dev = model, model.device
        self.model = model
        self.replay, self.contacts, self.staging, self.launches = replay, contacts, staging, launches
        self.separation, self.max_derivative, self.differentiable = separation, max_derivative, differentiable
        self.n_particles, self.n_bodies, self.n_vertices = mesh.particle_count, n_bodies, mesh.vertex_count
        self.planes = planes
        self.max_hits = max(MAX_HITS_MIN, MAX_HITS_PER_VERTEX * (self.n_vertices + int(m.plane_count) * self.n_particles))
        faces, edges = mesh.faces, mesh.feature_edges
        # broad-phase groups: the particles (self-collision only with "self_collision"), each
        # body (never with itself), the static meshes (never with each other)
        groups, self_collision, static = [], [], []
        if self.n_particles:
            groups.append(np.zeros(self.n_particles, dtype=np.int64))
            self_collision.append("self_collision" in model.components)
            static.append(False)
        if mesh.shape_count:
            groups.append(len(self_collision) + mesh.shape_body)
            self_collision.extend([False] * m.body_count)
            static.extend([False] * m.body_count)
        if len(mesh.static_vertices):
            groups.append(np.full(len(mesh.static_vertices), len(self_collision), dtype=np.int64))
            self_collision.append(False)
            static.append(True)
        # one pass's counts in one device array, so that a CCD round brings them to the host in
        # one read (read_counts); each kernel gets the one-element view of its count
        self.counts = wp.zeros(len(COUNT_SLOTS), dtype=wp.int32, device=dev)
        (self._mesh_counter, self._plane_counter, self._kept_counter, self._repeated_counter,
         self._approach_counter, contacts.counter, self._uncovered, self._beyond_reach, _, _, self.go,
         self._cover_outside, _, _, self._unbounded) = (self.counts[i:i + 1] for i in range(len(COUNT_SLOTS)))
        self._cover_pending = None  # (x0, x1, delta, slack) of a cover test not read yet (cover())
        self.bound = 0  # the last sorted pass's bound on its hits (the launches' dimension)
        self.host_tested_rounds = 0  # CCD rounds whose cover was tested on the host (statistics)
        self.broad_phase = None
        # static meshes alone (a model of spheres and walls) have nothing to collide with
        if self.n_vertices and len(faces) and (self.n_particles or mesh.shape_count):
            self.broad_phase = BroadPhase(
                faces, edges, num_vertices=self.n_vertices,
                groups=np.concatenate(groups), self_collision=np.array(self_collision, dtype=bool),
                static=np.array(static, dtype=bool), device=dev,
            )
            self.narrow = CandidateNarrowPhase(self.broad_phase, counter=self._mesh_counter,
                                               reach_counter=self.counts[_REACH_VF:_REACH_EE + 1], **ccd_options)
        self.cover_scale = 0  # index into COVER_SCALES
        # the vertices the vertex-plane tests cover (movable particles and the rigid surface
        # vertices) and the planes' normals / offsets. The integrator's plane stage has already
        # stopped the particles at the planes when the handler runs, but a mesh contact's
        # impulse can push a particle back through (cloth pressed into the ground by a body):
        # as rows of the same solve the plane holds it
        particle_inv_mass = m.particle_inv_mass.numpy() if mesh.particle_count else np.zeros(0)
        movable_particles = np.flatnonzero(particle_inv_mass > 0)
        self.plane_vertex_ids = ids = np.concatenate([movable_particles,
                                                      np.arange(mesh.shape_offset, mesh.static_offset)])
        threshold = np.concatenate([np.full(len(movable_particles), 1.0 - PLANE_ROUNDING_SLACK),
                                    np.full(mesh.shape_count, 1.0 + PROXIMITY_HYSTERESIS)])  # x delta
        n_vertex_rows = mesh.vertex_count + 1  # with the dummy static vertex of vertex-plane contacts
        self.key_base = max(n_vertex_rows, len(faces), len(edges), len(planes)) + 1
        self._no_inertia = wp.zeros(1, dtype=wp.mat33d, device=dev)  # an unread inertia array
        # one detection pass's hits, the plane tests' vertices, distances and hits, the counters
        self.hits = Hits(dev)
        self._plane_ids_w = wp.array(np.append(ids, 0).astype(np.int32), dtype=wp.int32, device=dev)
        self._plane_threshold_w = wp.array(np.append(threshold, 1.0), dtype=wp.float64, device=dev)
        rows = max(len(ids) * len(planes), 1)
        self._plane_d0_w = wp.zeros(rows, dtype=wp.float64, device=dev)
        self._plane_pairs_w = wp.zeros(rows, dtype=wp.vec2i, device=dev)
        self._plane_time_w = wp.zeros(rows, dtype=wp.float64, device=dev)
        P, B = max(self.n_particles, 1), max(self.n_bodies, 1)
        # no contact time yet (inf)
        self.inf_time_p = wp.array(np.full(P, np.inf), dtype=wp.float64, device=dev)
        self.inf_time_b = wp.array(np.full(B, np.inf), dtype=wp.float64, device=dev)
        self._no_merge = wp.zeros(1, dtype=wp.int32, device=dev)  # the merge decisions' stand-in (not written)
        self.v_start = None
        self.separation_speed = 0.0
        self.x1_pred_w = None

    def begin(self, v_start, separation_speed: float) -> None:
        """Starts a substep: the start velocities (particles, bodies: device arrays), which an
        impact reflects, and the separation speed ``delta / h`` [m/s]."""
        self.v_start, self.separation_speed = v_start, separation_speed

    def pose(self, name: str, particle_q: wp.array | None, body_q: wp.array | None) -> wp.array:
        """World positions (V + 1, 3) [m] of the collidable vertices and the dummy vertex at the
        origin for the device arrays ``particle_q`` (P,) and ``body_q`` (B,)
        (:func:`kernels.pose.pose_positions_kernel`), in the handler's device buffer ``name``
        (overwritten by the next pose into ``name``)."""
        n, R = self.n_vertices + 1, self.replay
        x = self.staging.empty("posed_" + name, n, wp.vec3d)  # not the substep pose's buffers
        self.launches.launch(("pose", name), pose_positions_kernel, n, [
            particle_q if self.n_particles else R.empty_vec, body_q if self.n_bodies else R.empty_pose,
            R.vertex_type, R.vertex_owner, R.local, x])
        return x

    def pose_substep(self, state_in: State, state_pred: State):
        """:meth:`pose` of ``state_in`` and of ``state_pred`` and the bodies' world inverse
        inertia tensors at ``state_in`` (``R I^-1 R^T``), in one launch
        (:func:`kernels.pose.pose_substep_kernel`).

        Returns:
            (the start positions' and lever arms' device arrays, the predicted positions' device
            array (also kept in ``x1_pred_w``), the inverse inertia device array).
        """
        n, R, B = self.n_vertices + 1, self.replay, self.n_bodies
        empty = self.staging.empty
        x0, lever0 = empty("x_start", n, wp.vec3d), empty("lever_start", n, wp.vec3d)
        x1 = empty("x_predicted", n, wp.vec3d)
        inv_inertia_w = empty("inv_inertia_w", max(B, 1), wp.mat33d)
        P = self.n_particles
        self.launches.launch("pose_substep", pose_substep_kernel, max(n, B), [
            state_in.particle_q if P else R.empty_vec, state_in.body_q if B else R.empty_pose,
            state_pred.particle_q if P else R.empty_vec, state_pred.body_q if B else R.empty_pose,
            R.vertex_type, R.vertex_owner, R.local, self.model.body_inv_inertia if B else self._no_inertia,
            n, B, x0, lever0, x1, inv_inertia_w])
        self.x1_pred_w = x1
        return x0, lever0, x1, inv_inertia_w

    def cover(self, x0_w: wp.array, x1_pred_w: wp.array, delta: float) -> None:
        """The substep's broad-phase cover (:meth:`CandidateNarrowPhase.cover`) of the motion
        ``x0_w -> x1_pred_w`` (device arrays of V + 1 rows, the dummy vertex last) at the current
        scale (:data:`COVER_SCALES`), which a fresh query then moves a step towards its candidate
        budget. Whether the kept cover still holds the motion is tested on the device
        (:meth:`CandidateNarrowPhase.cover_test_device`); where its count cannot be peeked at
        (a GPU) the pass that follows assumes it does, and its one read settles it
        (:meth:`cover_failed`). Only a fresh query reads the positions."""
        scale = COVER_SCALES[self.cover_scale]
        margin, slack = COVER_MARGIN * scale * delta, COVER_SLACK * scale * delta
        self._cover_pending = None
        if self.narrow.cover_test_device(x0_w, x1_pred_w, margin, slack, self._cover_outside):
            peeked = peek(self._cover_outside)
            if peeked is None:
                self._cover_pending = (x0_w, x1_pred_w, delta, slack)
                self.narrow.assume_kept(slack)
                return
            if not peeked[0]:
                self.narrow.keep_cover(slack)
                return
        self._fresh_cover(x0_w, x1_pred_w, delta)

    def _fresh_cover(self, x0_w: wp.array, x1_pred_w: wp.array, delta: float) -> None:
        """:meth:`cover`'s fresh broad-phase query (the positions read), and the scale's step."""
        n = self.n_vertices
        scale = COVER_SCALES[self.cover_scale]
        self.narrow.query_cover(host(x0_w)[:n], host(x1_pred_w)[:n], COVER_MARGIN * scale * delta, COVER_AHEAD,
                                COVER_AHEAD_LIMIT * scale * delta)
        found = self.narrow.covered_candidates()
        if found < COVER_SPARSE_CANDIDATES:
            self.cover_scale = min(self.cover_scale + 1, len(COVER_SCALES) - 1)
        elif found > COVER_DENSE_CANDIDATES:
            self.cover_scale = max(self.cover_scale - 1, 0)

    def cover_failed(self, counts: np.ndarray) -> bool:
        """After the first pass of a substep whose cover test was left on the device
        (:meth:`cover`), with that pass's counts: whether the kept cover failed (it then queries
        afresh, and the pass must run again); else the cover is kept."""
        pending, self._cover_pending = self._cover_pending, None
        if pending is None:
            return False
        x0_w, x1_pred_w, delta, slack = pending
        if not counts[_COVER_OUTSIDE]:
            self.narrow.keep_cover(slack)
            return False
        self.narrow.discard_pass()
        self._fresh_cover(x0_w, x1_pred_w, delta)
        return True

    def sorted_hits(self, mesh_count: int, plane_count: int, time_mode: int, max_distance: float = -1.0) -> None:
        """Puts the narrow phase's hits (:attr:`CandidateNarrowPhase.hits`) and the vertex-plane
        ones into :attr:`hits` in ascending pair order (the order of the contacts is then the same
        whatever the broad phase's candidate order or the device's thread schedule);
        ``max_distance >= 0`` drops mesh pairs not nearer than it (the proximity pass),
        ``time_mode`` as :func:`kernels.contact_set.gather_hits_kernel`'s. ``mesh_count`` and
        ``plane_count`` bound their hits (their numbers are in the device counters): the launches
        run over :attr:`bound` rows and read the counts on the device, where the number of hits kept
        stays (:meth:`read_counts` brings it to the host)."""
        H, nb, launch = self.hits, self.narrow.hits, self.launches.launch
        bound = self.bound = mesh_count + plane_count
        H.reserve(bound)
        zero(self._kept_counter)
        zero(self._repeated_counter)
        launch("hit_keys", hit_keys_kernel, bound, [
            self._mesh_counter, self._plane_counter, nb["kind"], nb["pairs"], nb["offset"], float(max_distance),
            self._plane_pairs_w, self.key_base, H.keys, H.order, self._kept_counter])
        if self.hits.device.is_cpu or bound <= DEVICE_SORT_MIN:
            launch("sort", sort_hit_keys_kernel, 1, [self._mesh_counter, self._plane_counter, H.keys, H.order])
        else:  # the rows past the hits hold KEY_NONE, which sorts last
            wp.utils.radix_sort_pairs(H.keys, H.order, bound)
        launch("gather", gather_hits_kernel, bound, [
            H.keys, H.order, self._kept_counter, self._mesh_counter, nb["kind"], nb["pairs"], nb["vertices"],
            nb["time"], nb["source"], self._plane_pairs_w, self._plane_time_w, time_mode, self.n_vertices,
            H.kind, H.pair, H.vertices, H.detected, H.source, H.plane, H.row, self._repeated_counter])

    def _exact(self, mesh_bound: int, plane_bound: int) -> tuple[int, int]:
        """The pass's mesh and plane hits where the counts can be peeked at without a
        synchronisation (:func:`core.buffers.peek`: the CPU; the launches then run over the
        hits, an empty pass launches nothing), else the bounds ``mesh_bound``, ``plane_bound``
        (the kernels read the counts on the device)."""
        counts = peek(self.counts)
        if counts is None:
            return mesh_bound, plane_bound
        return int(counts[_MESH]), int(counts[_PLANE])

    def read_counts(self) -> np.ndarray:
        """The device counts (:data:`COUNT_SLOTS`) in one host read, kept as the hits' and the
        contact set's counts, checked: a pair found twice in one pass, or more hits than
        :attr:`max_hits`, raise."""
        return self.accept_counts(np.array(host(self.counts)))

    def accept_counts(self, counts: np.ndarray) -> np.ndarray:
        """:meth:`read_counts` of the counts ``counts`` already read."""
        if counts[_REPEATED]:
            raise RuntimeError("collision detection returned a primitive pair twice in one pass "
                               "(the broad phase's candidates must be distinct pairs)")
        kept = int(counts[_KEPT])
        if kept > self.max_hits:
            raise ContactLimitExceeded(
                f"{kept} contacts in one collision round of a substep, more than the limit of {self.max_hits} "
                f"({MAX_HITS_PER_VERTEX} per collision vertex): the substep is far too long for the motion")
        self.hits.count = kept
        self.contacts.count = int(counts[_CONTACTS])
        self.contacts.fresh = True
        return counts

    def hit_geometry(self, x0_w, x1_w, lever_w, vm, vel, times, h: float) -> None:
        """Times [s], weights, normals and targets of :attr:`hits` on the paths ``x0_w -> x1_w``
        (:func:`kernels.contact_geometry.contact_geometry_kernel`, the replay's definition), with the
        velocities ``v-`` (``vm``) before each owner's contact time (``times``: particle and body
        device arrays; None: no contact yet) and ``vel`` after it (None: still ``v-``)."""
        H, R = self.hits, self.replay
        vc = vm if vel is None else vel
        tp, tb = times if times is not None else (self.inf_time_p, self.inf_time_b)
        self.launches.launch("hit_geometry", contact_geometry_kernel, self.bound, [
            self._kept_counter, x0_w, x1_w, lever_w, R.vertex_type, R.vertex_owner, H.vertices, H.kind, H.source, H.detected,
            H.plane, R.planes, *self.v_start, vm[0], vc[0], vm[1], vc[1], tp, tb, float(h), float(self.separation),
            float(self.model.restitution), float(SEPARATION_RATE), float(TOUCHING_RELATIVE),
            float(self.max_derivative), 0, R.flat_keys, R.flat_opposites, R.flat_key_base, 0, R.particle_inv_mass,
            R.body_inv_mass, R.half_substep_gravity, H.toi, H.weights, H.normals, H.targets,
            self._push_scratch(self.bound)])

    def add_hits(self, all_new: bool, approaching: int, geometry=None, merge=None, read: bool = True) -> None:
        """Grows the contact set by :attr:`hits` (``all_new``: every hit, into the empty set;
        else the ``approaching`` ones, :func:`kernels.contact_set.add_contacts_kernel`) with the
        hits' geometry (``geometry``: (toi, weights, normals, targets) device arrays; default
        the hits' own) and, with ``merge`` ((hit, keep toi, keep target) int32 arrays of the
        grown set's rows), the decisions the taped replay's merge repeats. With ``read=False``
        the set's new count stays on the device (``contacts.fresh`` is False until the next
        :meth:`read_counts`)."""
        cs, H = self.contacts, self.hits
        toi, w, n, target = geometry[:4] if geometry is not None else (H.toi, H.weights, H.normals, H.targets)
        cs.reserve(cs.count + (H.count if all_new else approaching))
        record = merge is not None
        merge = merge if record else (self._no_merge,) * 3
        self.launches.launch("add", add_contacts_kernel, 1, [
            self._kept_counter, int(all_new), H.approaching, H.row, H.kind, H.pair, H.vertices, H.source, toi, w, n,
            target, self.replay.vertex_type, int(record), cs.kind, cs.pair, cs.vertices, cs.toi, cs.weights,
            cs.normals, cs.targets, cs.timed, cs.collided, cs.normal_impulse, cs.friction_impulse, cs.counter,
            *merge])
        if read:
            cs.count = int(host(cs.counter)[0])
        else:
            cs.fresh = False

    def plane_hits(self, x_w, delta: float | None) -> int:
        """Vertex-plane hits into the plane buffers: with ``delta``, the proximity pairs at the
        start positions ``x_w`` (which also keeps their plane distances); else the crossings of
        the paths from the start to ``x_w`` (:mod:`kernels.contact_set`). Their number stays in the
        device counter; returns a bound on it."""
        n = len(self.plane_vertex_ids)
        zero(self._plane_counter)
        if not (n and len(self.planes)):
            return 0
        if delta is not None:
            self.launches.launch("plane_proximity", plane_proximity_kernel, n, [
                x_w, self._plane_ids_w, self._plane_threshold_w, self.replay.planes, len(self.planes), float(delta),
                self._plane_d0_w, self._plane_counter, self._plane_pairs_w])
        else:
            self.launches.launch("plane_crossing", plane_crossing_kernel, n, [
                x_w, self._plane_ids_w, self.replay.planes, len(self.planes), self._plane_d0_w,
                self._plane_counter, self._plane_pairs_w, self._plane_time_w])
        return n * len(self.planes)

    def proximity(self, x0_w, x1_pred_w, lever0_w, vm, h: float, delta: float) -> int:
        """The proximity contacts at the start of the substep (device positions ``x0_w`` (V + 1,))
        into the empty contact set: pairs of primitives whose exact
        closest points are nearer than ``delta`` [m] (up to :data:`PROXIMITY_HYSTERESIS` beyond
        it), then movable vertices nearer than ``delta`` to a plane (rigid ones up to the same
        band), with the start geometry (:meth:`hit_geometry` at ``t* = 0``: the offset's
        direction, or the face's normal over a face, or for touching pairs as
        :data:`TOUCHING_RELATIVE` says; target and push as
        :func:`kernels.contact_geometry.contact_geometry_kernel` says).

        The same pass keeps the pairs that the CCD rounds can hit while every vertex ends within
        ``CCD_REACH_SLACK delta`` of its predicted distance from ``x0_w`` (``x1_pred_w`` (V +
        1,)), which is then all those rounds test (:meth:`CandidateNarrowPhase.near`). Returns
        the number of contacts (the pass's counts, the cover's test of :meth:`cover` with them,
        come to the host in one read)."""
        while True:
            if not self.proximity_hits(x0_w, x1_pred_w, delta, read=False):
                return 0
            self.hit_geometry(x0_w, x0_w, lever0_w, vm, None, None, h)
            self.hits.count = self.bound  # a bound on the rows the set grows by (the set is empty)
            self.add_hits(True, 0, read=False)
            counts = self.read_proximity_counts()
            if counts is not None:
                return int(counts[_CONTACTS])
            self.contacts.clear()  # the kept cover failed its test: the pass runs again on a fresh one

    def proximity_hits(self, x0_w, x1_pred_w, delta: float, read: bool = True) -> int:
        """:meth:`proximity`'s detection: the pairs nearer than ``(1 + PROXIMITY_HYSTERESIS)
        delta`` at the start ``x0_w`` into :attr:`hits` (sorted); returns their number (the
        pass's counts come to the host in one read), or with ``read=False`` a bound on it (0:
        none; :meth:`read_proximity_counts` then reads them)."""
        while True:
            # motion radii from x0_w to x1_pred_w where the candidates are many enough
            x1 = x1_pred_w if self.narrow.covered_candidates() >= CCD_REACH_MIN_CANDIDATES else None
            reach = delta * (1.0 + PROXIMITY_HYSTERESIS)
            # slack: the exact test follows
            mesh = self.narrow.near_count_covered(x0_w, reach * (1.0 + 1e-9), x1, CCD_REACH_SLACK * delta,
                                                  self._unbounded, read=False)
            planes = self.plane_hits(x0_w, delta)
            mesh, planes = self._exact(mesh, planes)
            if not mesh + planes:
                peeked = peek(self.counts)
                if self._cover_pending is not None:  # no pass to read its test with: read it alone
                    zero(self._kept_counter)
                    zero(self._repeated_counter)
                    if self.read_proximity_counts() is None:
                        continue  # the pass runs again on a fresh cover
                elif peeked is not None:  # the CPU's exact counts (a bound of 0 keeps no pair)
                    self._settle_reach(peeked)
                return 0
            self.sorted_hits(mesh, planes, 0, reach)
            if not read:
                return self.bound
            counts = self.read_proximity_counts()
            if counts is not None:
                return int(counts[_KEPT])

    def read_proximity_counts(self) -> np.ndarray | None:
        """:meth:`read_counts` after a substep's proximity pass, which also settle its cover
        (:meth:`cover_failed`: None when it failed, the pass to run again) and the pairs it kept
        for the rounds (dropped when a motion radius is not finite)."""
        counts = np.array(host(self.counts))
        if self.cover_failed(counts):
            return None
        self._settle_reach(counts)
        return self.accept_counts(counts)

    def _settle_reach(self, counts: np.ndarray) -> None:
        """The pairs the proximity pass kept for the rounds, from the pass's ``counts``: dropped
        when a motion radius was not finite, else their counts noted."""
        if counts[_UNBOUNDED]:
            self.narrow.drop_reach()
        else:
            self.narrow.note_reach_counts(counts[_REACH_VF:_REACH_EE + 1])

    def ccd_round(self, x0_w, x1_w, lever0_w, vm, vel, times, h: float) -> int:
        """One Gauss-Seidel CCD round of the straight paths from the start positions ``x0_w`` (V +
        1,) (the positions of this substep's :meth:`proximity`) to the device positions ``x1_w``: the hits (:meth:`ccd_detect`), their
        geometry at their detected times and whether they approach, with the counts kept on the
        device until the round's one read. Returns the number of approaching hits."""
        counts = self.ccd_detect(x0_w, x1_w, 2,
                                 lambda: self._round_decisions(x0_w, x1_w, lever0_w, vm, vel, times, h))
        return 0 if counts is None else int(counts[_APPROACHING])

    def ccd_detect(self, x0_w, x1_w, time_mode: int, decide=None) -> np.ndarray | None:
        """The hits of the straight paths from the start positions ``x0_w`` (V + 1,) (the
        positions of this substep's proximity pass) to the device positions ``x1_w`` (:meth:`ccd_hits`; ``time_mode`` as there), then ``decide()`` (launches
        on the hits that leave their counts on the device), all brought to the host in one read
        (:meth:`read_counts`). The broad-phase cover is tested on the device: a round whose
        vertices moved farther than the proximity pass's reach radii runs again over the cover's
        candidates (a second read), and the rare round whose motion left the cover runs again with
        the host's test (the end positions read; a fresh broad-phase query). Returns the counts
        (:data:`COUNT_SLOTS`), or None when the pass found no hit without reading the counts (on
        the CPU, where they are peeked at; :attr:`hits` ``.count`` is then not updated)."""
        for same_start in (True, False):
            mesh = self.narrow.ccd_count_device(x0_w, x1_w, same_start, self._uncovered, self._beyond_reach)
            if mesh is None:  # no cover to test on the device
                break
            planes = self.plane_hits(x1_w, None)
            peeked = peek(self.counts)
            if peeked is not None:
                if peeked[_UNCOVERED]:
                    break
                if peeked[_BEYOND_REACH]:
                    continue
                mesh, planes = int(peeked[_MESH]), int(peeked[_PLANE])
                if not mesh + planes:
                    return None
            self._match_and_decide(mesh, planes, time_mode, decide)
            counts = self.read_counts()
            if counts[_UNCOVERED]:
                break
            if not counts[_BEYOND_REACH]:
                return counts
        return self._host_tested_round(x0_w, x1_w, time_mode, decide)

    def _match_and_decide(self, mesh: int, planes: int, time_mode: int, decide) -> None:
        """:meth:`sort_and_match` of a pass with ``mesh`` and ``planes`` bounds on its hits, then
        ``decide()``; without a candidate, the counts of no hit (all left on the device)."""
        if mesh + planes:
            self.sort_and_match(mesh, planes, time_mode)
            if decide is not None:
                decide()
        else:
            zero(self._kept_counter)
            zero(self._repeated_counter)
            zero(self._approach_counter)

    def device_round_bound(self) -> int | None:
        """A bound on the hits of one CCD round detected on the device (:meth:`device_round`),
        with the buffers they fill grown to it (so that a graph capture of rounds allocates
        nothing), or None when no broad-phase cover serves such a round."""
        mesh = self.narrow.device_bound(True)
        if mesh is None:
            return None
        self.narrow.reserve(mesh)
        bound = mesh + len(self.plane_vertex_ids) * len(self.planes)  # plane_hits' bound
        self.hits.reserve(bound)
        self._push_scratch(bound)
        return bound

    def _push_scratch(self, rows: int) -> wp.array:
        """The scratch of :meth:`hit_geometry`'s pushes for ``rows`` hits."""
        return self.staging.empty("hit_push", max(rows, 1), wp.float64)

    def start_rounds(self, round_index: int) -> None:
        """Sets the device rounds' state (:func:`kernels.contact_set.round_control_kernel`): round ``round_index``, no
        approaching hit added yet, the next round runs."""
        state = np.array([round_index, 0, 1], dtype=np.int32)
        upload(self.counts[ROUND:], state)

    def device_round(self, x0_w, x1_w, lever0_w, vm, vel, times, h: float, max_iterations: int) -> None:
        """One Gauss-Seidel CCD round wholly on the device (no host read, so a graph capture can
        record it): :meth:`ccd_round`'s detection and decisions over the pairs the proximity pass
        kept for the rounds (else the broad-phase cover's candidates), whose test stays on the
        device, then the continue test (:func:`kernels.contact_set.round_control_kernel`) with
        the ``max_iterations`` rounds the response allows."""
        mesh = self.narrow.ccd_count_device(x0_w, x1_w, True, self._uncovered, self._beyond_reach)
        self._match_and_decide(mesh, self.plane_hits(x1_w, None), 2,
                               lambda: self._round_decisions(x0_w, x1_w, lever0_w, vm, vel, times, h))
        self.launches.launch("round_control", round_control_kernel, 1, [
            self.counts, _KEPT, _REPEATED, _APPROACHING, _UNCOVERED, _BEYOND_REACH, ROUND, EVENTS, _GO,
            self.max_hits, int(max_iterations)])

    def round_outcome(self) -> tuple[np.ndarray, bool]:
        """After device rounds: their counts (one read) and whether the last round ended the
        substep's rounds (its cover's test held and nothing approaches); else that round is to be
        run again on the host (which tests the cover first, as :meth:`ccd_detect` does, then
        checks the counts). A round whose cover's test held is checked here
        (:meth:`accept_counts`: it raises for a pair found twice or too many hits)."""
        counts = np.array(host(self.counts))
        if counts[_UNCOVERED] or counts[_BEYOND_REACH]:
            return counts, False
        self.accept_counts(counts)
        return counts, not counts[_APPROACHING]

    def _host_tested_round(self, x0_w, x1_w, time_mode: int, decide) -> np.ndarray | None:
        """:meth:`ccd_detect` with the cover tested on the host (the positions read)."""
        self.host_tested_rounds += 1
        x0, x1 = host(x0_w)[: self.n_vertices + 1], host(x1_w)[: self.n_vertices + 1]
        if not self.ccd_hits(x0, x1, x1_w, time_mode):
            return None
        if decide is not None:
            decide()
        return self.read_counts()

    def _round_decisions(self, x0_w, x1_w, lever0_w, vm, vel, times, h: float) -> None:
        """A Gauss-Seidel CCD round's sorted hits: their geometry at their detected times and
        whether they approach, the counts left on the device."""
        self.hit_geometry(x0_w, x1_w, lever0_w, vm, vel, times, h)
        H = self.hits
        self.approach(x0_w, x1_w, lever0_w, (H.toi, H.weights, H.normals), vm, vel, times, h, read=False)

    def ccd_hits(self, x0, x1, x1_w, time_mode: int) -> int:
        """The hits of the straight paths ``x0 -> x1`` (V + 1, 3) (``x1_w`` its device array):
        vertex-face, edge-edge (broad + narrow phase at zero thickness) and vertex-plane (a
        movable vertex ends behind a plane, moving inwards) into :attr:`hits` in pair order
        (``time_mode``: :func:`kernels.contact_set.gather_hits_kernel`'s), each matched to its row
        in the contact set. Returns a bound on their number (0: none; the counts stay on the
        device)."""
        n = self.n_vertices
        mesh = self.narrow.ccd_count(x0[:n], x1[:n], 0.0, read=False)
        mesh, planes = self._exact(mesh, self.plane_hits(x1_w, None))
        if not mesh + planes:
            return 0
        self.sort_and_match(mesh, planes, time_mode)
        return self.bound

    def sort_and_match(self, mesh: int, planes: int, time_mode: int) -> None:
        """:meth:`sorted_hits` of a CCD pass (``mesh``, ``planes``: bounds on its hits), each hit
        matched to its row in the contact set (:func:`kernels.contact_set.match_contacts_kernel`,
        over the set's capacity: its count may be on the device only); the counts stay on the
        device."""
        cs, H = self.contacts, self.hits
        self.sorted_hits(mesh, planes, time_mode)
        self.launches.launch("match", match_contacts_kernel, cs.capacity,
                              [cs.counter, cs.kind, cs.pair, self.key_base, H.keys, self._kept_counter, H.row])

    def approach(self, x0_w, x1_w, lever_w, geometry, vm, vel, times, h: float, read: bool = True) -> int | None:
        """Whether each of :attr:`hits` approaches (``geometry``: its (toi [s], weights, normals)
        device arrays; :func:`kernels.contact_set.approach_kernel`, into the hits'
        ``approaching``), with the velocities ``v-`` (``vm``) before each owner's contact time
        (``times``; None: no contact yet) and ``vel`` after it. Returns how many approach (None
        with ``read=False``: the count stays on the device)."""
        H, R = self.hits, self.replay
        vc = vm if vel is None else vel
        tp, tb = times if times is not None else (self.inf_time_p, self.inf_time_b)
        zero(self._approach_counter)
        self.launches.launch("approach", approach_kernel, self.bound, [
            self._kept_counter, x0_w, x1_w, lever_w, R.vertex_type, R.vertex_owner, H.vertices, *geometry, H.row,
            self.contacts.toi, vm[0], vc[0], vm[1], vc[1], tp, tb, float(h), float(self.separation_speed),
            # a contact at the very end leaves once it no longer approaches (the replay pushes
            # the separation at the position level) or, in the Gauss-Seidel response, once it
            # leaves at its separation speed
            0.0 if self.differentiable else float(self.separation_speed),
            float(APPROACH_EPS), float(END_OF_SUBSTEP), self._approach_counter, H.approaching])
        return int(host(self._approach_counter)[0]) if read else None
