"""The replayed collision response of one substep (:class:`ReplayedSubstep`): design.md's "decide,
then replay", the decisions off the tape and the smooth map on it."""

from __future__ import annotations

import contextlib
import itertools

import warp as wp

from core.buffers import host, zero
from core.tape import active_tape, paused_tape
from kernels.active_set import (active_set_update_kernel, flags_differ_kernel, friction_share_count_kernel,
                                friction_share_kernel, initial_active_kernel, owner_rows_finish_kernel,
                                owner_rows_kernel, owner_rows_reset_kernel, set_impulses_kernel)
from sim.contact.record import ContactRecord
from sim.contact.tuning import (ACTIVE_SET_COLLIDED_MAX_CONTACTS, ACTIVE_SET_ITERATIONS, ACTIVE_SET_PULLING,
                                APPROACH_EPS, SEPARATION_RATE, SOLVER_TOLERANCE, TOUCHING_RELATIVE)
from sim.contact.zones import ImpactZones
from sim.model import State


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

    def __init__(self, handler, state_in: State, state_pred: State, h: float) -> None:
        self.handler = hd = handler
        self.replay = R = hd.replay
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
        self.contacts = hd.contact_set
        self.contacts.clear()
        self.zones = None
        self.zone_flags = (hd.no_zone_p, hd.no_zone_b)
        # the taped contact geometry of the set (None before its first contact), the velocities
        # and those that move the positions
        self.rows = None
        self.vp, self.vb, self.xp, self.xb = self.vm_p, self.vm_b, self.vm_p, self.vm_b
        self.tolerance = SOLVER_TOLERANCE * SEPARATION_RATE * hd.separation_speed
        self.resting = (*hd.v_start, SEPARATION_RATE * hd.separation_speed)  # contact_geometry_kernel's bounce threshold
        self.launch = hd.launches.launch

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
        kp, kb = hd.staging.empty("owner_key_p", P, wp.int32), hd.staging.empty("owner_key_b", B, wp.int32)
        hd.owner_times(tp, tb, self.zone_flags)
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
        return self.replay.geometry(self.X0, X1, self.L0, rows, H.count, *hd.v_start, self.vm_p, self.vp, self.vm_b,
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
            hd.staging.empty("active_jn", C, wp.float64), repaired, changes])
        return repaired, int(host(changes)[0])

    def solve(self) -> None:
        """Decide the active set by projected Gauss-Seidel on top of the current velocities,
        then replay the exact normal solve and repair the set (drop pulling contacts, add
        violated ones) until it holds; the velocities and the motion that moves the positions
        become the final solve's."""
        hd, R, cs, P, B, mu = self.handler, self.replay, self.contacts, self.P, self.B, self.mu
        C, take, launch = cs.count, R.take, self.launch
        with paused_tape():
            dec = hd.velocities_of(*self.current())
            hd.gauss_seidel(dec, self.L0, self.inv_I)
        # the set's rows as the taped solves read them (one copy while a tape records)
        vertices, kinds = R.frozen(cs.vertices, C), R.frozen(cs.kind, C)
        mobile = hd.staging.empty("mobile_rows", C, wp.int32)
        active = take(C, wp.int32, zero=False, grad=False)
        launch("r_initial_active", initial_active_kernel, C, [
            cs.vertices, cs.weights, cs.normal_impulse, hd.mobile_vertex_w, mobile, active])
        taped = active  # the set whose solve the tape holds (the first trial's)
        tape = active_tape()
        changes = hd.staging.empty("active_changes", 1, wp.int32)
        self.collided_tolerance = (APPROACH_EPS * hd.separation_speed if C <= ACTIVE_SET_COLLIDED_MAX_CONTACTS
                                   else self.tolerance)
        args = (vertices, kinds, C)
        for iteration in range(ACTIVE_SET_ITERATIONS):
            share = self.friction_share(active) if mu > 0 else None
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
        if tape is not None and active is not taped and self.flags_differ(taped, active, C):
            # the replay of the final active set, recorded
            share = self.friction_share(active) if mu > 0 else None
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
            x1_pred = hd.detect.pose("predicted", sp.particle_q, sp.body_q)
            hd.detect.cover(self.X0, x1_pred, self.delta)
            found = hd.detect.proximity_hits(self.X0, x1_pred, self.delta)
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
        self.zone_flags = hd.zone_flags(self.zones)
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
                counts = hd.detect.ccd_detect(self.X0, X1, 1)
            if counts is None or not hd.detect.hits.count:
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
        hd.note_contacts(ContactRecord(self.contacts, self.X0, X1, self.h, hd.vertex_type))
        return State(
            particle_q=X1p if P else sp.particle_q,
            particle_qd=self.vp if P else sp.particle_qd,
            body_q=BQ1 if B else sp.body_q,
            body_qd=self.vb if B else sp.body_qd,
        )

    def friction_share(self, active: wp.array) -> wp.array:
        """Per contact of the set: one over the largest number of active contacts (``active``)
        that any particle or body it moves takes part in (friction impulses of one pass are
        applied together; :mod:`kernels.contact_set`). A fresh array while a tape records."""
        hd = self.handler
        cs, R, P = hd.contact_set, hd.replay, hd.n_particles
        counts = hd.staging.empty("share_counts", P + hd.n_bodies + 1, wp.int32)
        zero(counts)
        share = R.take(cs.count, wp.float64, zero=False, grad=False)
        launch = hd.launches.launch
        launch("share_count", friction_share_count_kernel, cs.count, [
            cs.vertices, cs.weights, active, P, R.vertex_type, R.vertex_owner, counts])
        launch("share", friction_share_kernel, cs.count, [
            cs.vertices, cs.weights, P, R.vertex_type, R.vertex_owner, counts, share])
        return share

    def flags_differ(self, a: wp.array, b: wp.array, count: int) -> bool:
        """Whether the int flags ``a`` and ``b`` differ in one of their first ``count`` entries."""
        hd = self.handler
        counter = hd.staging.empty("flags_differ", 1, wp.int32)
        zero(counter)
        hd.launches.launch("flags_differ", flags_differ_kernel, count, [a, b, counter])
        return bool(host(counter)[0])
