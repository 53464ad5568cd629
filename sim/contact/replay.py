"""The taped half of the collision response: "decide, then replay" (design.md).

:class:`ContactReplay` owns the Warp launches that turn the decisions of
:class:`sim.contact.response.ImpulseCollisionHandler` (which pairs are contacts, from which root
slot, which contacts carry an impulse and whether they stick or slide, which contact comes first
for each particle or body) into the new velocities and positions. Every launch here is recorded on
the active ``wp.Tape`` (if any), so the map ``(x0, v-) -> (x1, v+)`` is differentiable:

* ``t*`` of each CCD contact comes from its coplanarity cubic through :func:`kernels.roots.cubic_roots`
  (mollified implicit derivative, bounded by ``max_derivative``);
* weights and normals at ``t*`` come from the one closest-point definition
  (:func:`kernels.point_triangle.point_triangle_closest`, :func:`kernels.edge_edge.segment_segment_closest`);
* the impulses solve the active set's equations exactly (dense LU in a Warp kernel, refined
  once on its residual); the tape holds the implicit adjoint of each solve (a solve with the
  transposed matrix), never iterations. Coulomb friction: all active contacts sticking (normal
  and tangential impulses in one system) when every impulse lies in its cone, else, when no
  contact could stick, all sliding (``j_n (n - mu s)`` against the slip ``s``) when none stops,
  else a split of sticking and sliding contacts in one system (:class:`FrictionSplit`), else
  each contact's stopping impulse with the normal impulses solved again on top (which regime:
  a decision);
* the push: the separation ``SEPARATION_RATE (delta - d)`` restored by a second solve whose
  velocities move the positions but never reach the velocities;
* time-of-impact integration ``x0 + t* v- + (h - t*) v+`` per particle and body;
* the fail-safe's impact zones (membership decided on the host) as their momentum-conserving
  rigid motion (:meth:`ContactReplay.zone_velocities`).

Arrays are never written after a launch read them (fresh outputs per call), so the tape can be
replayed backwards. Without an active tape nothing is recorded and the same launches give the
forward result: the value and its gradient belong to one function.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.buffers import Arena, RecordedLaunches, upload
from core.tape import active_tape, any_tape, paused_tape
from core.warp_adapter import is_frozen, mark_frozen
from sim.contact.contacts import ContactLimitExceeded
from kernels.contact_geometry import (
    contact_geometry_kernel,
    contact_sides_kernel,
    merge_contacts_kernel,
)
from kernels.decide import (
    push_active_kernel,
    push_overshoot_kernel,
    slip_reversed_kernel,
)
from kernels.dense import lu_factor_kernel, lu_solve_kernel, solve_adjoint_kernel
from kernels.friction import (
    friction_impulses_kernel,
    sliding_friction_half_kernel,
    sliding_impulses_kernel,
    slip_directions_kernel,
)
from kernels.integrate import time_of_impact_kernel
from kernels.pose import pose_positions_kernel, pose_start_kernel
from kernels.response import (
    add_vectors_kernel,
    contact_rhs_kernel,
    contact_velocities_kernel,
    delassus_kernel,
    normal_part_kernel,
    push_rhs_kernel,
)
from kernels.zones import (
    zone_body_velocity_kernel,
    zone_moments_kernel,
    zone_particle_velocity_kernel,
    zone_rigid_motion_kernel,
    zone_select_kernel,
    zone_sums_kernel,
)
from kernels.active_set import active_unknowns_kernel
from sim.contact.friction_split import FrictionSplit
from sim.contact.tuning import (MAX_SOLVE_WORK, PUSH_OVERSHOOT, PUSH_REGULARIZATION, REGULARIZATION, SLIP_REVERSAL,
                                STICKING_MAX_CONTACTS)


class ContactReplay:
    """Device arrays and taped launches of the collision response of one model.

    Args:
        vertex_type, vertex_owner: (V,) int per collidable vertex (0 particle, 1 rigid, 2
            static; owner = particle / body index). One dummy static vertex is appended here (index
            ``V``), the second side of vertex-plane contacts.
        local: (V, 3) body-frame positions of rigid vertices (relative to the centre of mass) and
            world positions of static ones (anything for particles).
        particle_inv_mass, body_inv_mass, body_inv_inertia: the model's arrays (may be empty).
        planes: (K, 4) plane normals and offsets.
        device: Warp device.
        flat_edges, flat_opposites: (K, 2) the flat edges of rigid and static surfaces and the
            third vertices of their two faces (:class:`sim.collision_mesh.CollisionMesh`).
    """

    def __init__(self, vertex_type, vertex_owner, local, particle_inv_mass, body_inv_mass, body_inv_inertia,
                 planes, friction: float, restitution: float, device, flat_edges=None,
                 flat_opposites=None, gravity=(0.0, 0.0, 0.0)):
        self.device = device
        # the constant force per unit mass [m/s^2] whose half substep the contacts' plane law
        # adds to the velocity at t* (contact_geometry_kernel): none under the exact ballistic
        # update (ImpulseCollisionHandler.set_exact_gravity)
        self.gravity = wp.vec3d(*(float(g) for g in np.asarray(gravity, dtype=np.float64).reshape(3)))
        self.no_gravity = wp.vec3d(0.0, 0.0, 0.0)
        self.half_substep_gravity = self.gravity
        self.n_vertices = len(vertex_type)
        # the flat edges (sim.collision_mesh.flat_edges) as sorted keys lo * base + hi, for the
        # contact geometry's look-up (one key that matches no edge when there are none)
        self.flat_key_base = self.n_vertices + 1
        flat = np.zeros((0, 2), np.int64) if flat_edges is None else np.sort(np.asarray(flat_edges, np.int64), axis=1)
        opposite = np.full((len(flat), 2), -1, np.int64) if flat_opposites is None \
            else np.asarray(flat_opposites, np.int64).reshape(-1, 2)
        keys = flat[:, 0] * self.flat_key_base + flat[:, 1]
        order = np.argsort(keys)
        if not len(flat):  # one key that matches no edge
            keys, opposite, order = np.full(1, -1, np.int64), np.full((1, 2), -1, np.int64), np.zeros(1, np.int64)
        self.flat_keys = wp.array(keys[order], dtype=wp.int64, device=device)
        # the third vertices of each flat edge's two faces, in key order (-1: unknown)
        self.flat_opposites = wp.array(opposite[order].astype(np.int32), dtype=wp.vec2i, device=device)
        vt = np.append(np.asarray(vertex_type, dtype=np.int32), 2)  # the dummy is static
        vo = np.append(np.asarray(vertex_owner, dtype=np.int32), 0)
        self.vertex_type = wp.array(vt.astype(np.int32), dtype=wp.int32, device=device)
        self.vertex_owner = wp.array(vo.astype(np.int32), dtype=wp.int32, device=device)
        loc = np.zeros((self.n_vertices + 1, 3))
        loc[: self.n_vertices] = local
        self.local = wp.array(loc, dtype=wp.vec3d, device=device)
        self.particle_inv_mass = particle_inv_mass if particle_inv_mass is not None and particle_inv_mass.shape[0] else wp.zeros(1, dtype=wp.float64, device=device)
        self.body_inv_mass = body_inv_mass if body_inv_mass is not None and body_inv_mass.shape[0] else wp.zeros(1, dtype=wp.float64, device=device)
        self.body_inv_inertia_body = body_inv_inertia
        # zero inverse inertia tensors: impulses applied with them move the bodies' centres only
        n_bodies = body_inv_inertia.shape[0] if body_inv_inertia is not None else 0
        self._translation_only = wp.zeros(max(n_bodies, 1), dtype=wp.mat33d, device=device)
        p = np.zeros((1, 4)) if planes is None or len(planes) == 0 else np.asarray(planes, dtype=np.float64)
        self.planes = wp.array(p, dtype=wp.vec4d, device=device)
        self.friction = float(friction)
        self.restitution = float(restitution)
        # stand-ins for the arrays of a model without particles / bodies (never read)
        self.empty_vec = wp.zeros(1, dtype=wp.vec3d, device=device)
        self.empty_twist = wp.zeros(1, dtype=wp.spatial_vectord, device=device)
        self.empty_pose = wp.array(np.array([[0, 0, 0, 0, 0, 0, 1.0]]), dtype=wp.transformd, device=device)
        self._no_int = wp.zeros(1, dtype=wp.int32, device=device)
        # the row count of a launch whose dimension is the count itself (no thread to skip)
        self.no_row_limit = wp.array([np.iinfo(np.int32).max], dtype=wp.int32, device=device)
        # stand-ins for outputs a launch has no thread for (never read: the stand-ins above are
        # inputs that taped launches read, which no launch may write afterwards)
        self._unused_vec = wp.zeros(1, dtype=wp.vec3d, device=device)
        self._unused_impulses = wp.zeros(1, dtype=wp.vec3d, device=device)
        self._unused_twist = wp.zeros(1, dtype=wp.spatial_vectord, device=device)
        self._unused_pose = wp.zeros(1, dtype=wp.transformd, device=device)
        self._no_inertia = wp.zeros(1, dtype=wp.mat33d, device=device)
        self._no_float = wp.zeros(1, dtype=wp.float64, device=device)
        self.largest_system = 0
        self.solve_work = 0.0  # this substep's (MAX_SOLVE_WORK); the handler resets it per call
        self._arena = Arena(device)  # the arrays of calls without a tape
        self._recorded = RecordedLaunches(device)  # the launches of calls without a tape

    # ------------------------------------------------------------------ helpers
    def launch(self, kernel, dim, inputs=(), outputs=(), device=None) -> None:
        """``wp.launch`` of ``kernel`` on this model's device; while no tape records or is paused,
        through a recorded command (:class:`core.buffers.RecordedLaunches`: Warp's argument
        packing costs more than most of these kernels on a few hundred contacts)."""
        if any_tape():
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device)
        elif dim if isinstance(dim, int) else all(dim):  # an empty launch runs nothing
            self._recorded.launch(kernel, kernel, dim, [*inputs, *outputs])

    def _grad(self) -> bool:
        return active_tape() is not None

    def begin(self) -> None:
        """Starts a response call: the arrays the previous call took from the arena (see
        :meth:`take`) may be handed out again. The caller must have copied that call's results."""
        self._arena.begin()
        self.solve_work = 0.0

    def take(self, shape, dtype, zero: bool = True, grad: bool = True) -> wp.array:
        """An array of ``shape`` (an int or a square ``(n, n)``) / ``dtype``: fresh while a tape
        records or is paused (its backward reads every array it recorded, and a paused trial's
        result may feed a recorded launch; with a gradient array when ``grad`` and recording),
        else the next one of this call from the arena (:class:`core.buffers.Arena`: a
        response without gradients allocates no memory once its largest sizes have been met),
        zeroed unless ``zero`` is False (the caller fills it)."""
        if any_tape():
            if not zero and not (grad and self._grad()):  # a decision the caller fills: no memset
                return wp.empty(shape, dtype=dtype, device=self.device)
            return wp.zeros(shape, dtype=dtype, device=self.device, requires_grad=grad and self._grad())
        return self._arena.take(shape, dtype, zero)

    def zeros(self, n, dtype):
        return self.take(n, dtype)

    def _ints(self, a, dtype=wp.int32):
        a = np.ascontiguousarray(a)
        if a.shape[0] == 0:
            a = np.zeros((1,) + a.shape[1:], dtype=a.dtype)
        return upload(self.take(a.shape[0], dtype, zero=False, grad=False), a.astype(np.int32))

    @staticmethod
    def or_empty(a, empty):
        return a if a is not None and a.shape[0] else empty

    def frozen(self, a: wp.array, n: int) -> wp.array:
        """``a`` for a launch that the tape may record: a fresh copy of its first ``n`` rows
        while a tape records or is paused (``a`` is a buffer of the decisions that a later call
        overwrites, and the tape's backward reads what its launches read), else ``a`` itself."""
        if not any_tape() or is_frozen(a):
            return a
        out = wp.empty(max(n, 1), dtype=a.dtype, device=self.device)
        if n:
            with paused_tape():
                wp.copy(out, a, count=n)
        return mark_frozen(out)  # a copy of its own: frozen() passes it on as it is

    # ------------------------------------------------------------------ stages
    def pose_start(self, particle_q, body_q):
        """World positions and lever arms of all collidable vertices (+ the dummy vertex) and the
        bodies' world inverse inertia tensors (a dummy row when there is no body), in one launch
        (:func:`kernels.pose.pose_start_kernel`)."""
        n = self.n_vertices + 1
        bodies = body_q.shape[0] if body_q is not None else 0
        x = self.zeros(n, wp.vec3d)
        lever = self.zeros(n, wp.vec3d)
        inv_inertia = self.zeros(max(bodies, 1), wp.mat33d)
        self.launch(
            pose_start_kernel, dim=max(n, bodies),
            inputs=[self.or_empty(particle_q, self.empty_vec), self.or_empty(body_q, self.empty_pose), self.vertex_type,
                    self.vertex_owner, self.local, self.or_empty(self.body_inv_inertia_body, self._no_inertia), n, bodies],
            outputs=[x, lever, inv_inertia], device=self.device,
        )
        return x, lever, inv_inertia

    def positions(self, particle_q, body_q):
        """World positions of all collidable vertices (+ the dummy vertex)."""
        n = self.n_vertices + 1
        x = self.zeros(n, wp.vec3d)
        self.launch(
            pose_positions_kernel, dim=n,
            inputs=[self.or_empty(particle_q, self.empty_vec), self.or_empty(body_q, self.empty_pose), self.vertex_type,
                    self.vertex_owner, self.local],
            outputs=[x], device=self.device,
        )
        return x

    def geometry(self, x0, x1, lever, rows, count: int, v0_p, v0_b, vm_p, vc_p, vm_b, vc_b, particle_time, body_time,
                 h, separation, separation_rate, touching_relative, max_derivative, nearest_slot: bool = False):
        """Times of impact [s], weights, normals, targets (restitution alone) and pushes (the
        separation's speed, restored at the position level) of ``count`` new contact rows.

        ``v0_p``, ``v0_b``: the velocities at the start of the substep (the forces' change
        before ``t*`` is reflected, not the change after it). ``rows``: device arrays
        (``vertices`` (vec4i), ``kind``, ``source``, ``detected`` (fraction
        of the substep), ``plane``; :class:`sim.contact.contacts.Hits`). ``particle_time`` /
        ``body_time``: device times of impact already assigned to each owner (inf for none).
        ``nearest_slot``: take the cubic's root nearest the detected fraction rather than the one
        in the ``source`` slot (for a narrow phase other than the float64 one as written, whose
        slots need not match).
        """
        c = count
        toi = self.zeros(c, wp.float64)
        w = self.zeros(c, wp.vec4d)
        n = self.zeros(c, wp.vec3d)
        target = self.zeros(c, wp.float64)
        push = self.zeros(c, wp.float64)
        frozen = self.frozen
        self.launch(
            contact_geometry_kernel, dim=c,
            inputs=[self.no_row_limit, x0, x1, lever, self.vertex_type, self.vertex_owner, frozen(rows["vertices"], c),
                    frozen(rows["kind"], c), frozen(rows["source"], c), frozen(rows["detected"], c),
                    frozen(rows["plane"], c), self.planes,
                    self.or_empty(v0_p, self.empty_vec), self.or_empty(v0_b, self.empty_twist),
                    self.or_empty(vm_p, self.empty_vec), self.or_empty(vc_p, self.empty_vec),
                    self.or_empty(vm_b, self.empty_twist), self.or_empty(vc_b, self.empty_twist),
                    particle_time, body_time, wp.float64(h), wp.float64(separation),
                    wp.float64(self.restitution), wp.float64(separation_rate), wp.float64(touching_relative),
                    wp.float64(max_derivative), int(bool(nearest_slot)), self.flat_keys, self.flat_opposites,
                    wp.int64(self.flat_key_base), 1, self.particle_inv_mass, self.body_inv_mass,
                    self.half_substep_gravity],
            outputs=[toi, w, n, target, push], device=self.device,
        )
        return toi, w, n, target, push

    def merge(self, old, new, new_index, keep_old_toi, keep_old_target, count: int):
        """The grown contact set's (toi, targets, weights, normals, pushes) (``count`` rows): old
        rows (``new_index`` -1) or this round's detections, as decided per row (device int
        arrays, :func:`kernels.contact_set.add_contacts_kernel`'s; fresh while a tape records)."""
        c = count
        out = (self.zeros(c, wp.float64), self.zeros(c, wp.float64), self.zeros(c, wp.vec4d), self.zeros(c, wp.vec3d),
               self.zeros(c, wp.float64))
        old_count = 0 if old is None else old[0].shape[0]
        if old is None:
            old = (self.zeros(1, wp.float64), self.zeros(1, wp.float64), self.zeros(1, wp.vec4d), self.zeros(1, wp.vec3d),
                   self.zeros(1, wp.float64))
        self.launch(
            merge_contacts_kernel, dim=c,
            inputs=[*old[:4], *new[:4], old[4], new[4], new_index, keep_old_toi, keep_old_target, old_count],
            outputs=list(out), device=self.device,
        )
        return out

    def solve(self, contacts, vertices, kinds, count: int, active, lever, inv_inertia_w, vm_p, vm_b, share=None,
              start=None):
        """Exact impulses of an active set (refined once), with Coulomb friction, the velocities
        after them and those that move the positions (with the push).

        Args:
            contacts: (toi, targets, weights, normals, pushes) device arrays of the whole set (C,).
            vertices, kinds: the set's device (C,) vec4i vertex indices and int32 kinds
                (:class:`sim.contact.contacts.Contacts`); ``count`` = C.
            active: device int32 (C,): the contacts whose normal relative velocity must end at
                their target (the others get no impulse; fresh while a tape records).
            lever, inv_inertia_w: start-pose lever arms and world inverse inertia tensors.
            vm_p, vm_b: the velocities before any impulse (``v-``).
            share: device (C,) friction share factors (see
                :func:`kernels.friction.friction_impulses_kernel`); None for no friction.
            start: (particle_qd, body_qd, resting speed [m/s]): the velocities at the substep's
                start and the approach speed below which a contact at ``t* = 0`` rests (its
                sliding friction is a force over the substep,
                :func:`kernels.friction.sliding_friction_half_kernel`); None: every friction
                impulse counts as an impulse.

        Returns:
            (particle_qd, body_qd, normal impulses (C,) vec3, (particle_qd, body_qd) that move
            the positions): device arrays; the normal impulses are the normal parts of the
            accepted solve's (the sticking, sliding or split one, or the last normal pass after
            the friction pass); the last pair adds the push, the separation restored at the
            position level (:func:`kernels.response.push_rhs_kernel`), and for a sliding or
            split solve half the velocity change of its sliding friction on resting contact
            (linear, :func:`kernels.friction.sliding_friction_half_kernel`), which makes a slide
            to rest second order in the substep.
        """
        # without a tape, its dense matrices are scratch: the next solve of the call reuses them
        # (an active set's repairs solve again and again: a cloth resting on a box with a few
        # hundred unknowns kept over a gigabyte of matrices to the end of each call)
        mark = None if any_tape() else self._arena.mark()
        try:
            return self._solve(contacts, vertices, kinds, count, active, lever, inv_inertia_w, vm_p, vm_b, share,
                               start)
        finally:
            if mark is not None:
                self._arena.release_squares(mark)

    def _solve(self, contacts, vertices, kinds, count: int, active, lever, inv_inertia_w, vm_p, vm_b, share=None,
               start=None):
        """:meth:`solve` itself."""
        _, targets, weights, normals, pushes = contacts
        c = count
        pairs_w = self.frozen(vertices, c)
        kinds_w = self.frozen(kinds, c)
        sides = (self.take(c, wp.vec2i, grad=False), self.zeros(c, wp.vec2d), self.zeros(c, wp.vec3d),
                 self.zeros(c, wp.vec3d))
        self.launch(contact_sides_kernel, dim=c,
                  inputs=[pairs_w, kinds_w, weights, self.vertex_type, self.vertex_owner, lever],
                  outputs=list(sides), device=self.device)
        # the active contacts as unknowns, in row order (a decision: off the tape)
        uc = self.take(c, wp.int32, zero=False, grad=False)
        cu = self.take(c, wp.int32, zero=False, grad=False)
        unknown_count = self.take(1, wp.int32, zero=False, grad=False)
        with paused_tape():
            self.launch(active_unknowns_kernel, dim=1, inputs=[c, active], outputs=[uc, cu, unknown_count],
                      device=self.device)
        n_u = int(unknown_count.numpy()[0])
        masses = (self.particle_inv_mass, self.body_inv_mass, inv_inertia_w)

        def pushed(vp, vb):
            return self._pushed(active, c, pushes, pairs_w, weights, normals, sides, masses, lever, vp, vb)

        def frictional(vp, vb, normal, total, slip):
            # the result of a frictional solve: its sliding friction on resting contact moves
            # the positions by half its velocity change (a constant force over the substep)
            if start is None:
                return vp, vb, normal, pushed(vp, vb)
            half = self.zeros(c, wp.vec3d)
            self.launch(sliding_friction_half_kernel, dim=c,
                         inputs=[total, normals, slip, contacts[0], pairs_w, weights, self.vertex_type,
                                 self.vertex_owner, lever, *sides, *masses, self.or_empty(start[0], self.empty_vec),
                                 self.or_empty(start[1], self.empty_twist), wp.float64(start[2])],
                         outputs=[half], device=self.device)
            linear = (masses[0], masses[1], self._translation_only)
            return vp, vb, normal, self._apply(half, pairs_w, weights, sides, linear, *pushed(vp, vb))

        if not n_u:
            return vm_p, vm_b, self.zeros(c, wp.vec3d), pushed(vm_p, vm_b)
        self.largest_system = max(self.largest_system, n_u)
        matrix = self.take((n_u, n_u), wp.float64, zero=False)  # every entry written
        self.launch(delassus_kernel, dim=(n_u, n_u),
                  inputs=[uc, pairs_w, weights, normals, normals, wp.float64(0.0), self.vertex_type, self.vertex_owner,
                          *sides, *masses, wp.float64(REGULARIZATION)],
                  outputs=[matrix], device=self.device)
        factors = self._factor(matrix)

        def normal_pass(vp, vb):
            # normal impulses that bring every active contact's normal velocity to its target
            rhs = self.zeros(n_u, wp.float64)
            self.launch(contact_rhs_kernel, dim=n_u,
                      inputs=[uc, pairs_w, weights, normals, targets, self.vertex_type, self.vertex_owner, lever,
                              self.or_empty(vp, self.empty_vec), self.or_empty(vb, self.empty_twist)],
                      outputs=[rhs], device=self.device)
            solution = self._dense_solve(matrix, rhs, factors)
            normal = self.zeros(c, wp.vec3d)
            return normal, self._apply(None, pairs_w, weights, sides, masses, vp, vb, (cu, solution, normals, normal))

        def refined_pass(vp, vb):
            # a second pass on the first one's residual (iterative refinement): the regularised
            # matrix leaves every target missed by ~REGULARIZATION relative, which redundant
            # contacts (a face resting on four corners) turn into a spin; after the second
            # pass the miss is ~REGULARIZATION^2
            first, (vp, vb) = normal_pass(vp, vb)
            second, (vp, vb) = normal_pass(vp, vb)
            return self._sum(first, second, c), (vp, vb)

        normal, (vp, vb) = refined_pass(vm_p, vm_b)
        if share is not None and self.friction > 0.0 and n_u <= STICKING_MAX_CONTACTS:
            # static friction first: every active contact sticking, its whole relative velocity
            # solved jointly (normal target, no slip); taken when every impulse lies in its
            # friction cone (a decision, like the active set), else all sliding, then a split of
            # the two, else the friction pass below
            split = FrictionSplit(self, uc, cu, c, n_u, contacts, pairs_w, weights, sides, masses, lever, vm_p, vm_b)
            sticking = split.sticking(normal)
            if sticking is not None:
                return (*sticking, pushed(sticking[0], sticking[1]))  # no contact slides
            # then, when no contact could stick, every active contact sliding against its slip
            # after the normal pass, its friction impulse mu j_n in the same solve as j_n
            sliding = None
            if split.outside == n_u:
                sliding = self._sliding(uc, cu, c, n_u, contacts, pairs_w, weights, sides, masses, lever, vm_p, vm_b,
                                        vp, vb)
            if sliding is not None:
                return frictional(*sliding)
            # then some contacts sticking and the others sliding, in one solve
            mixed = split.mixed()
            if mixed is not None:
                return frictional(*mixed, split.last[2], split.last[3])
        if share is not None and self.friction > 0.0:
            # Coulomb friction from the normal impulses, then the normal impulses again on top of
            # the friction (a rigid body's friction impulse changes its normal velocities too)
            friction = self.zeros(c, wp.vec3d)
            self.launch(friction_impulses_kernel, dim=c,
                      inputs=[normal, share, pairs_w, weights, normals, self.vertex_type,
                              self.vertex_owner, lever, *sides, *masses, self.or_empty(vp, self.empty_vec),
                              self.or_empty(vb, self.empty_twist), wp.float64(self.friction)],
                      outputs=[friction], device=self.device)
            vp_f, vb_f = self._apply(friction, pairs_w, weights, sides, masses, vm_p, vm_b)
            normal, (vp, vb) = refined_pass(vp_f, vb_f)
        return vp, vb, normal, pushed(vp, vb)

    def _pushed(self, active, c: int, pushes, pairs_w, weights, normals, sides, masses, lever, vp, vb):
        """The velocities that move the positions: ``vp``, ``vb`` (after the impulses) plus the
        push, the separation restored at the position level. Its unknowns are the active
        contacts and those still short of their push (:func:`kernels.decide.push_active_kernel`,
        a decision); their normal impulses bring each one's normal velocity up to its push
        (:func:`kernels.response.push_rhs_kernel`); they never reach the velocities."""
        flags = self.take(c, wp.int32, zero=False, grad=False)
        uc = self.take(c, wp.int32, zero=False, grad=False)
        cu = self.take(c, wp.int32, zero=False, grad=False)
        count = self.take(1, wp.int32, zero=False, grad=False)
        with paused_tape():
            self.launch(push_active_kernel, dim=c,
                      inputs=[active, pairs_w, weights, normals, pushes, self.vertex_type, self.vertex_owner, lever,
                              self.or_empty(vp, self.empty_vec), self.or_empty(vb, self.empty_twist)],
                      outputs=[flags], device=self.device)
            self.launch(active_unknowns_kernel, dim=1, inputs=[c, flags], outputs=[uc, cu, count], device=self.device)
        n = int(count.numpy()[0])
        if not n:
            return vp, vb
        rhs = self.zeros(n, wp.float64)
        self.launch(push_rhs_kernel, dim=n,
                  inputs=[uc, pairs_w, weights, normals, pushes, self.vertex_type, self.vertex_owner, lever,
                          self.or_empty(vp, self.empty_vec), self.or_empty(vb, self.empty_twist)],
                  outputs=[rhs], device=self.device)
        for regularization in (REGULARIZATION, PUSH_REGULARIZATION):
            matrix = self.take((n, n), wp.float64, zero=False)  # every entry written
            self.launch(delassus_kernel, dim=(n, n),
                      inputs=[uc, pairs_w, weights, normals, normals, wp.float64(0.0), self.vertex_type,
                              self.vertex_owner, *sides, *masses, wp.float64(regularization)],
                      outputs=[matrix], device=self.device)
            solution = self._dense_solve(matrix, rhs)
            overshoot = self.take(1, wp.int32, grad=False)
            with paused_tape():
                self.launch(push_overshoot_kernel, dim=n, inputs=[matrix, rhs, solution, wp.float64(PUSH_OVERSHOOT)],
                             outputs=[overshoot], device=self.device)
            if not int(overshoot.numpy()[0]):
                break
        return self._apply(None, pairs_w, weights, sides, masses, vp, vb, (cu, solution, normals, self.zeros(c, wp.vec3d)))

    def _sliding(self, uc, cu, c: int, n_u: int, contacts, pairs_w, weights, sides, masses, lever, vm_p, vm_b,
                 vp_n, vb_n):
        """Every active contact sliding: one unknown each, the normal impulse ``j_n``, whose
        impulse ``j_n (n - mu s)`` carries Coulomb friction against the slip direction ``s`` of
        the velocities after the normal pass (``vp_n``, ``vb_n``;
        :func:`kernels.friction.slip_directions_kernel`), solved exactly for the normal targets
        (and refined, as the normal passes). Returns ``(particle_qd, body_qd, normal
        impulses)`` as :meth:`solve` followed by the whole impulses and the slip directions, or
        None when a contact pulls or stops slipping (its slip turns back: it sticks)."""
        _, targets, _, normals, _ = contacts
        directions = self.zeros(c, wp.vec3d)
        self.launch(slip_directions_kernel, dim=c,
                  inputs=[pairs_w, weights, normals, self.vertex_type, self.vertex_owner, lever,
                          self.or_empty(vp_n, self.empty_vec), self.or_empty(vb_n, self.empty_twist)],
                  outputs=[directions], device=self.device)
        matrix = self.take((n_u, n_u), wp.float64, zero=False)  # every entry written
        mu = wp.float64(self.friction)
        self.launch(delassus_kernel, dim=(n_u, n_u),
                  inputs=[uc, pairs_w, weights, normals, directions, mu, self.vertex_type, self.vertex_owner, *sides,
                          *masses, wp.float64(REGULARIZATION)],
                  outputs=[matrix], device=self.device)
        vp, vb, total = self.refined_impulses(matrix, n_u, contact_rhs_kernel, sliding_impulses_kernel,
                                               (directions, mu), uc, cu, c, pairs_w, weights, normals, targets, sides,
                                               masses, lever, vm_p, vm_b)
        rejected = self.take(1, wp.int32, grad=False)
        with paused_tape():
            self.launch(slip_reversed_kernel, dim=c,
                      inputs=[total, normals, directions, cu, pairs_w, weights, self.vertex_type, self.vertex_owner,
                              lever, self.or_empty(vp, self.empty_vec), self.or_empty(vb, self.empty_twist),
                              wp.float64(SLIP_REVERSAL)],
                      outputs=[rejected], device=self.device)
        if int(rejected.numpy()[0]):
            return None
        normal = self.zeros(c, wp.vec3d)
        self.launch(normal_part_kernel, dim=c, inputs=[total, normals], outputs=[normal], device=self.device)
        return vp, vb, normal, total, directions

    def refined_impulses(self, matrix, rows: int, rhs_kernel, impulse_kernel, impulse_args, uc, cu, c: int,
                          pairs_w, weights, normals, targets, sides, masses, lever, vp, vb, rhs_args=()):
        """The impulses of a system ``matrix`` (``rows`` equations from ``rhs_kernel``, impulses per contact
        from ``impulse_kernel`` with ``impulse_args`` after the solution and the normals; ``rhs_args``
        follow the velocities in ``rhs_kernel``'s inputs) on top
        of the velocities ``vp``, ``vb``, solved and refined once on the residual (see the
        normal passes of :meth:`_solve`). Returns (particle_qd, body_qd, the summed impulses)."""
        total = None
        factors = self._factor(matrix)
        for _ in range(2):
            rhs = self.zeros(rows, wp.float64)
            self.launch(rhs_kernel, dim=rows,
                      inputs=[uc, pairs_w, weights, normals, targets, self.vertex_type, self.vertex_owner, lever,
                              self.or_empty(vp, self.empty_vec), self.or_empty(vb, self.empty_twist), *rhs_args],
                      outputs=[rhs], device=self.device)
            solution = self._dense_solve(matrix, rhs, factors)
            impulses = self.zeros(c, wp.vec3d)
            self.launch(impulse_kernel, dim=c, inputs=[cu, solution, normals, *impulse_args], outputs=[impulses],
                      device=self.device)
            vp, vb = self._apply(impulses, pairs_w, weights, sides, masses, vp, vb)
            total = impulses if total is None else self._sum(total, impulses, c)
        return vp, vb, total

    def _sum(self, a, b, count: int):
        """``a + b`` of two (count,) vec3 arrays into a fresh one."""
        out = self.zeros(count, wp.vec3d)
        self.launch(add_vectors_kernel, dim=count, inputs=[a, b], outputs=[out], device=self.device)
        return out

    def _apply(self, impulses, pairs_w, weights, sides, masses, vp, vb, solved=None):
        """Velocities after the contact ``impulses`` (C,) (fresh arrays;
        :func:`kernels.response.contact_velocities_kernel`), or with ``solved`` = (contact
        unknowns, solution, normals, normal impulses out) after the solved normal impulses, which
        are written to the last array."""
        p_count = vp.shape[0] if vp is not None else 0
        b_count = vb.shape[0] if vb is not None else 0
        c = impulses.shape[0] if solved is None else solved[3].shape[0]
        out_p = self.zeros(p_count, wp.vec3d) if p_count else self._unused_vec
        out_b = self.zeros(b_count, wp.spatial_vectord) if b_count else self._unused_twist
        unknowns, solution, normals, normal = solved if solved is not None else \
            (self._no_int, self._no_float, self.empty_vec, self._unused_impulses)
        self.launch(contact_velocities_kernel, dim=c + p_count + b_count,
                  inputs=[c, p_count, int(solved is not None), unknowns, solution, normals,
                          impulses if impulses is not None else self.empty_vec, pairs_w, weights, self.vertex_type,
                          self.vertex_owner, *sides, *masses, self.or_empty(vp, self.empty_vec),
                          self.or_empty(vb, self.empty_twist)],
                  outputs=[normal, out_p, out_b], device=self.device)
        return (out_p if p_count else vp), (out_b if b_count else vb)

    def _factor(self, matrix):
        """The LU factors of a square system ``matrix`` (:func:`kernels.dense.lu_factor_kernel`;
        a solve's refinement pass reuses them), with a slot for the factors of its transpose,
        which the backward passes of the solves that share them make once."""
        n = matrix.shape[0]
        work = self.take((n, n), wp.float64, zero=False, grad=False)
        pivots = self.take(n, wp.int32, zero=False, grad=False)
        with paused_tape():  # the solve's implicit adjoint stands for it (:meth:`_dense_solve`)
            self.launch(lu_factor_kernel, dim=1, inputs=[matrix, 0], outputs=[work, pivots], device=self.device)
        return work, pivots, []

    def _dense_solve(self, matrix, rhs, factors=None):
        """``A^-1 b`` with the implicit adjoint recorded on the active tape; ``factors`` from
        :meth:`_factor` of the same ``matrix`` (made here when None)."""
        n = rhs.shape[0]
        self.solve_work += float(n) ** 3
        if self.solve_work > MAX_SOLVE_WORK:
            raise ContactLimitExceeded(
                f"the exact impulse solves of one substep exceed the work limit MAX_SOLVE_WORK = {MAX_SOLVE_WORK:.0e} "
                f"(sum of n^3 over solves of n unknowns; this one has {n}): the substep is far too long for the motion")
        work, pivots, transposed = factors if factors is not None else self._factor(matrix)
        solution = self.zeros(n, wp.float64)
        with paused_tape():  # not differentiated by the tape: the implicit adjoint is recorded below
            self.launch(lu_solve_kernel, dim=1, inputs=[work, pivots, rhs], outputs=[solution], device=self.device)
        tape = active_tape()
        if tape is not None:
            device = self.device

            def backward():
                if not transposed:  # the first of the solves sharing these factors to run backwards
                    transposed.extend((wp.empty((n, n), dtype=wp.float64, device=device),
                                       wp.empty(n, dtype=wp.int32, device=device)))
                    wp.launch(lu_factor_kernel, dim=1, inputs=[matrix, 1], outputs=transposed, device=device)
                adjoint = wp.zeros(n, dtype=wp.float64, device=device)
                wp.launch(lu_solve_kernel, dim=1, inputs=[*transposed, solution.grad], outputs=[adjoint],
                          device=device)
                wp.launch(solve_adjoint_kernel, dim=(n, n), inputs=[adjoint, solution],
                          outputs=[matrix.grad, rhs.grad], device=device)

            tape.record_func(backward, [matrix, rhs, solution])
        return solution

    def zone_moving(self, moving_p, moving_b, zone_p, zone_b, zone_vp, zone_vb):
        """The velocities that move the positions once impact zones formed (fresh arrays, taped):
        members (``zone_p`` / ``zone_b`` device int flags) take their zone's velocities
        ``zone_v*`` (:meth:`zone_velocities`), the others keep ``moving_*`` (their push)."""
        p_count = moving_p.shape[0] if moving_p is not None else 0
        b_count = moving_b.shape[0] if moving_b is not None else 0
        out_p = self.zeros(p_count, wp.vec3d) if p_count else self._unused_vec
        out_b = self.zeros(b_count, wp.spatial_vectord) if b_count else self._unused_twist
        self.launch(zone_select_kernel, dim=p_count + b_count,
                  inputs=[p_count, self.frozen(zone_p, p_count), self.frozen(zone_b, b_count),
                          self.or_empty(moving_p, self.empty_vec), self.or_empty(moving_b, self.empty_twist),
                          self.or_empty(zone_vp, self.empty_vec), self.or_empty(zone_vb, self.empty_twist)],
                  outputs=[out_p, out_b], device=self.device)
        return (out_p if p_count else moving_p), (out_b if b_count else moving_b)

    def zone_velocities(self, vp, vb, particle_zone, body_zone, n_zones: int, particle_q, body_q, body_mass,
                        body_inertia):
        """Velocities after the impact zones' rigid motion (fresh arrays; the inputs when no
        particle / body is in a zone), recorded on the active tape.

        The zones are decisions (host ints per particle / body: -1 none, -2 a zone touching the
        world, at rest; ``0..n_zones-1`` a free zone); the motion is a smooth function of the
        start positions ``particle_q`` / ``body_q``, the velocities ``vp`` / ``vb``, the inverse
        masses and the body masses and inertias: each zone's total mass, linear momentum and, about
        its centre of mass, angular momentum and inertia tensor are summed
        (:func:`kernels.zones.zone_sums_kernel`, :func:`kernels.zones.zone_moments_kernel`),
        ``linear = momentum / mass`` and ``omega = pinv(inertia) angular momentum``
        (:func:`kernels.zones.zone_rigid_motion_kernel`, the pseudo-inverse for zones of
        collinear particles), and each member moves with ``linear + omega x r`` (bodies: that at
        the centre of mass, and ``omega``). Momentum and angular momentum of each zone are kept.
        """
        p_count = vp.shape[0] if vp is not None else 0
        b_count = vb.shape[0] if vb is not None else 0
        particle_zone = np.asarray(particle_zone)[:p_count]
        body_zone = np.asarray(body_zone)[:b_count]
        in_p = p_count and bool(np.any(particle_zone != -1))
        in_b = b_count and bool(np.any(body_zone != -1))
        if not (in_p or in_b):
            return vp, vb
        pz, bz = self._ints(particle_zone), self._ints(body_zone)
        xp = self.or_empty(particle_q, self.empty_vec)
        vp_in = self.or_empty(vp, self.empty_vec)
        bq = self.or_empty(body_q, self.empty_pose)
        vb_in = self.or_empty(vb, self.empty_twist)
        b_mass = self.or_empty(body_mass, self.body_inv_mass)  # any float64 array when there is no body
        b_inertia = self.or_empty(body_inertia, self.zeros(1, wp.mat33d))
        nz = max(int(n_zones), 1)
        centre, linear, omega = self.zeros(nz, wp.vec3d), self.zeros(nz, wp.vec3d), self.zeros(nz, wp.vec3d)
        if n_zones:
            mass, first, momentum = self.zeros(nz, wp.float64), self.zeros(nz, wp.vec3d), self.zeros(nz, wp.vec3d)
            angular, inertia = self.zeros(nz, wp.vec3d), self.zeros(nz, wp.mat33d)
            members = [p_count, pz, bz, xp, vp_in, self.particle_inv_mass, bq, vb_in, b_mass]
            self.launch(zone_sums_kernel, dim=p_count + b_count, inputs=members, outputs=[mass, first, momentum],
                      device=self.device)
            self.launch(zone_moments_kernel, dim=p_count + b_count, inputs=[*members, b_inertia, mass, first],
                      outputs=[angular, inertia], device=self.device)
            self.launch(zone_rigid_motion_kernel, dim=nz, inputs=[mass, first, momentum, angular, inertia],
                      outputs=[centre, linear, omega], device=self.device)
        out_p, out_b = vp, vb
        if in_p:
            out_p = self.zeros(p_count, wp.vec3d)
            self.launch(zone_particle_velocity_kernel, dim=p_count, inputs=[pz, xp, centre, linear, omega, vp],
                      outputs=[out_p], device=self.device)
        if in_b:
            out_b = self.zeros(b_count, wp.spatial_vectord)
            self.launch(zone_body_velocity_kernel, dim=b_count, inputs=[bz, bq, centre, linear, omega, vb],
                      outputs=[out_b], device=self.device)
        return out_p, out_b

    def integrate(self, x0p, x_pred, vm_p, vp, moving_p, bq0, bq_pred, vm_b, vb, moving_b, particle_owner, body_owner,
                  toi, h):
        """Time-of-impact integration of particles and bodies in one launch
        (:func:`kernels.integrate.time_of_impact_kernel`; owner contact rows: device int32 arrays,
        fresh while a tape records; -1: the prediction stays; -2: an impact zone's rigid motion
        over the whole substep): ``v-`` (``vm_*``) until the owner's ``t*``, ``v+`` (``vp``,
        ``vb``) after it, and the push (``moving_* - v+``) as a displacement over the whole
        substep. Returns (particle positions, body poses): fresh arrays, or the predictions of a
        model without particles / bodies."""
        p_count = x0p.shape[0] if x0p is not None else 0
        b_count = bq0.shape[0] if bq0 is not None else 0
        xp = self.zeros(p_count, wp.vec3d) if p_count else None
        bq = self.zeros(b_count, wp.transformd) if b_count else None
        if p_count + b_count:
            self.launch(time_of_impact_kernel, dim=p_count + b_count,
                      inputs=[p_count, self.or_empty(x0p, self.empty_vec), self.or_empty(x_pred, self.empty_vec),
                              self.or_empty(vm_p, self.empty_vec), self.or_empty(vp, self.empty_vec),
                              self.or_empty(moving_p, self.empty_vec), particle_owner,
                              self.or_empty(bq0, self.empty_pose), self.or_empty(bq_pred, self.empty_pose),
                              self.or_empty(vm_b, self.empty_twist), self.or_empty(vb, self.empty_twist),
                              self.or_empty(moving_b, self.empty_twist), body_owner, toi, wp.float64(h)],
                      outputs=[self.or_empty(xp, self._unused_vec), self.or_empty(bq, self._unused_pose)], device=self.device)
        return (xp if p_count else x_pred), (bq if b_count else bq_pred)


