"""The Gauss-Seidel collision response of one substep (:class:`GaussSeidelSubstep`): projected
Gauss-Seidel impulses on the device contact set, off the tape, reusing the handler's buffers (a
stepping loop allocates no Warp array)."""

from __future__ import annotations

import warp as wp

from core.buffers import copy_rows
from core.tape import paused_tape
from kernels.integrate import planned_substep_kernel
from sim.contact.detect import EVENTS, ROUND
from sim.contact.record import ContactRecord
from sim.contact.zones import ImpactZones
from sim.model import State


class GaussSeidelSubstep:
    """One substep of the Gauss-Seidel response (``differentiable=False``), as stages of its
    :class:`sim.contact.response.ImpulseCollisionHandler`: proximity contacts at the start and
    their impulses, then CCD rounds on the :meth:`plan` until nothing approaches (each adding its
    approaching hits and solving again), after ``max_iterations`` rounds the fail-safe's impact
    zones (:meth:`zone_motion`).

    Args:
        handler: the handler whose buffers and decisions the substep uses.
        state_in: the start State; state_pred: the predicted end State (velocities ``v-``).
        h: the substep [s].
    """

    def __init__(self, handler, state_in: State, state_pred: State, h: float) -> None:
        self.handler = handler
        self.state_in, self.state_pred, self.h = state_in, state_pred, h

    def run(self) -> State | None:
        """The substep's stages; the new State, or None when nothing changed the prediction."""
        hd, state_in, state_pred, h = self.handler, self.state_in, self.state_pred, self.h
        P, B = hd.n_particles, hd.n_bodies
        R = hd.replay
        # the vertices at the start (with the rigid ones' lever arms) and the predicted end
        x0_w, lever0_w, x1_pred_w, inv_inertia_w = hd.detect.pose_substep(state_in, state_pred)
        delta = hd.separation
        cs = hd.contact_set
        cs.clear()
        vm = (state_pred.particle_qd if P else R.empty_vec, state_pred.body_qd if B else R.empty_twist)
        vel = None  # the velocities after the impulses (device buffers), made at the first contact
        zones = None  # the fail-safe's impact zones, made when it first acts (rare)
        zone_flags = None  # their members per particle / body (device), for the contact times
        # one broad-phase query for the proximity pass and the CCD rounds while their motion
        # stays within the margin of the predicted one (CandidateNarrowPhase.cover)
        hd.detect.cover(x0_w, x1_pred_w, delta)
        # 1. proximity contacts at the start of the substep: the mesh and the plane ones, added
        # and solved together
        if hd.detect.proximity(x0_w, x1_pred_w, lever0_w, vm, h, delta):
            vel = hd.velocities(state_pred)
            hd.gauss_seidel(vel, lever0_w, inv_inertia_w)

        # 2-5. CCD rounds on the planned motion; the result is the last round's plan: every exit
        # follows a plan with nothing changed after it (no contact added, no velocity solved,
        # no zone grown)
        failsafe = False
        planned = None
        device_rounds = hd.capture_rounds  # until a graph of rounds leaves a round to the host
        iteration = -1
        while True:
            iteration += 1
            if vel is not None and zones is None and device_rounds:
                iteration, planned = self.device_rounds(iteration, x0_w, lever0_w, vm, vel, inv_inertia_w)
                if planned is not None:
                    break
                device_rounds = False  # that round runs again here, tested on the host
            if vel is not None:  # a contact or a zone changed the prediction
                planned = self.plan(state_in, state_pred, vel, zone_flags, h)
                x1_w, times = planned[2], planned[3]
            else:  # nothing changed the prediction
                x1_w, times = hd.detect.x1_pred_w, None
            approaching = hd.detect.ccd_round(x0_w, x1_w, lever0_w, vm, vel, times, h)
            if not approaching:
                break
            if iteration >= hd.max_iterations:
                # fail-safe: rigid impact zones (Provot 1997, Bridson et al. 2002): everything
                # joined by a still-approaching contact moves as one rigid body (momentum kept;
                # at rest when the zone holds a static or pinned vertex) over the whole substep
                failsafe = True
                if zones is None:
                    zones = ImpactZones(P, B, hd.particle_inv_mass)
                idx = hd.detect.hits.host("vertices")[hd.detect.hits.host("approaching") != 0]
                if not zones.merge(hd.vertex_type[idx], hd.vertex_owner[idx]):
                    break  # only contacts inside rigidly moving zones remain (rounding)
                vel = vel if vel is not None else hd.velocities(state_pred)
                zone_flags = self.zone_motion(zones, state_in, vel)
                continue
            hd.ccd_events += approaching
            vel = vel if vel is not None else hd.velocities(state_pred)
            hd.detect.add_hits(False, approaching, read=False)  # the next round's read brings the count
            hd.gauss_seidel(vel, lever0_w, inv_inertia_w)
        if failsafe:
            hd.failsafe_count += 1
        if planned is None:  # nothing changed the prediction (no contact, no zone grew)
            return None
        if not cs.fresh:  # the last round found no candidate: its growth's count is still on the device
            hd.detect.read_counts()
        x1p_w, bq1_w, x1_w, _ = planned
        hd.note_contacts(ContactRecord(cs, x0_w, x1_w, h, hd.vertex_type))
        return State(
            particle_q=x1p_w if P else state_pred.particle_q,
            particle_qd=vel[0] if P else state_pred.particle_qd,
            body_q=bq1_w if B else state_pred.body_q,
            body_qd=vel[1] if B else state_pred.body_qd,
        )

    def device_rounds(self, iteration: int, x0_w, lever0_w, vm, vel, inv_inertia_w):
        """CCD rounds from round ``iteration`` on, recorded as one Warp graph and replayed
        (``wp.capture_while`` over the rounds, ``wp.capture_if`` over each round's growth and
        solve): each round is :meth:`plan`, the detection and decisions of
        :meth:`sim.contact.detect.ContactDetection.device_round`, then, while its continue test
        holds, the approaching hits added and Gauss-Seidel solved: the same kernels on the same
        data as the host's rounds, so the same bits (``tests/test_capture.py``). The host reads
        the counts once, after the graph. The narrow phase's statistics (``reuses``,
        ``reach_calls``, ``tested``) count the recorded round once, not each round the graph
        runs.

        Returns:
            (the round the graph stopped at, the last plan (as :meth:`plan`'s) when that round
            ended the rounds, else None: the caller runs that round again on the host, which
            tests the cover there or starts the fail-safe). Without a cover that serves rounds
            on the device: (``iteration``, None), nothing run.
        """
        hd, D, h = self.handler, self.handler.detect, self.h
        bound = D.device_round_bound()
        if bound is None:
            return iteration, None
        cs = hd.contact_set
        # room for every round's growth before the capture (each round adds at most its hits):
        # a capture must not reallocate (and copy) an array its recorded launches use
        cs.reserve(cs.rows_bound + (hd.max_iterations - iteration) * bound)
        hd.reserve_solve()
        D.start_rounds(iteration)
        last_plan = []

        def grow_and_solve():
            D.add_hits(False, 0, read=False)
            hd.gauss_seidel(vel, lever0_w, inv_inertia_w)

        def one_round():
            last_plan[:] = [self.plan(self.state_in, self.state_pred, vel, None, h)]
            x1_w, times = last_plan[0][2], last_plan[0][3]
            D.device_round(x0_w, x1_w, lever0_w, vm, vel, times, h, hd.max_iterations)
            wp.capture_if(D.go, on_true=grow_and_solve)

        with wp.ScopedCapture(device=hd.model.device) as capture:
            wp.capture_while(D.go, one_round)
        wp.capture_launch(capture.graph)
        hd.captured_round_graphs += 1
        counts, done = D.round_outcome()
        hd.ccd_events += int(counts[EVENTS])
        return int(counts[ROUND]), (last_plan[0] if done else None)

    def plan(self, state_in: State, state_pred: State, vel, zone_flags, h: float):
        """End positions of the substep ``h`` [s] for the contact set's earliest contact time per
        particle / body (:func:`kernels.active_set.owner_times_kernel`; 0 for the members of
        impact zones, ``zone_flags`` (P,), (B,) int32 device arrays or None) and the velocities
        after the impulses ``vel``: the replay's time-of-impact integration
        (:func:`kernels.integrate.time_of_impact_position`, ``time_of_impact_pose``), then the
        vertices' positions (:meth:`sim.contact.detect.ContactDetection.pose`).

        Returns:
            (particle positions (P,), body poses (B,), vertex positions (V + 1,), (particle
            times, body times) [s]: device arrays, the handler's buffers (the next plan
            overwrites them).
        """
        hd = self.handler
        empty, R, launch = hd.staging.empty, hd.replay, hd.launches.launch
        P, B, n = hd.n_particles, hd.n_bodies, hd.n_vertices + 1
        tp, tb = hd.particle_time_w, hd.body_time_w
        hd.owner_times(tp, tb, zone_flags if zone_flags is not None else (hd.no_zone_p, hd.no_zone_b))
        x1p, bq1 = hd.result.particle_q, hd.result.body_q
        x1 = empty("x_planned", n, wp.vec3d)
        particles = [state_in.particle_q, state_pred.particle_q, state_pred.particle_qd, vel[0], tp] if P else \
            [R.empty_vec] * 4 + [hd.no_time]
        bodies = [state_in.body_q, state_pred.body_q, state_pred.body_qd, vel[1], tb] if B else \
            [R.empty_pose, R.empty_pose, R.empty_twist, R.empty_twist, hd.no_time]
        # with bodies the vertices are posed by a second launch from the planned poses: in the
        # fused one every rigid vertex would integrate its body's pose again (a body of a few
        # hundred vertices made the plan 4x dearer); the same functions, so the same values
        launch("plan", planned_substep_kernel, P + B + (0 if B else n), [
            *particles, *bodies, float(h), R.vertex_type, R.vertex_owner, R.local, P, B, x1p, bq1, x1])
        if B:
            x1 = hd.detect.pose("planned", x1p if P else None, bq1)
        return x1p, bq1, x1, (tp, tb)

    def zone_motion(self, zones: "ImpactZones", state_in: State, vel):
        """Sets the velocities ``vel`` of the impact zones' members to their zone's
        momentum-conserving rigid motion (the replay's kernels,
        :meth:`sim.contact.replay.ContactReplay.zone_velocities`, off the tape) and returns the
        zones' member flags per particle / body (device int32 arrays)."""
        hd = self.handler
        P, B, R, m = hd.n_particles, hd.n_bodies, hd.replay, hd.model
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
        return hd.zone_flags(zones)
