"""The sticking/sliding split of the frictional contact solve (:class:`FrictionSplit`)."""

from __future__ import annotations

import numpy as np
import warp as wp

from core.tape import paused_tape
from kernels.decide import outside_cone_kernel, slip_update_kernel, tangent_weights_kernel
from kernels.friction import (slip_directions_from_impulses_kernel, sticking_delassus_kernel, sticking_impulses_kernel,
                              sticking_rhs_kernel)
from kernels.response import normal_part_kernel
from sim.contact.tuning import FRICTION_SPLIT_ITERATIONS, REGULARIZATION, SLIP_REVERSAL


class FrictionSplit:
    """The frictional solves of one active set with Coulomb's limit (:meth:`sim.contact.replay.ContactReplay.solve`):
    three unknowns per active contact (:func:`kernels.friction.contact_axis`) in one system
    (:func:`kernels.friction.sticking_delassus_kernel`), where a sticking contact's relative
    velocity is brought to its normal target and zero slip, and a sliding one keeps its normal
    target with the friction ``j_t = -mu j_n s`` against its slip direction ``s``.

    :meth:`sticking` tries every contact sticking; :meth:`mixed` continues from its last trial:
    contacts whose impulse leaves the friction cone slide, their friction ``mu j_n`` along the
    friction they asked for, and sliding contacts whose slip turns back stick again
    (:func:`kernels.decide.slip_update_kernel`), until the split holds, returns to one it
    tried, or :data:`FRICTION_SPLIT_ITERATIONS` solves are done.

    Redundant contacts leave the split of the friction among them free: it is chosen in
    proportion to normal loads (:func:`kernels.decide.tangent_weights_kernel`): the normal
    pass's impulses, and after a trial that leaves a contact outside its cone, the last trial's
    own (a decision, which changes the split, not the motion; under a tape the rejected trials'
    launches stay recorded). Which contacts slide is a decision too; their directions come from
    the impulses of the trial where they started sliding, on the tape, so the split's friction
    directions carry their derivative. A sliding contact keeps that direction while its slip
    does not turn back against it: its friction opposes the friction it asked for, which is
    the slip's direction only approximately.

    Args:
        replay: the :class:`sim.contact.replay.ContactReplay` whose arrays and launches it uses.
        The others: as in :meth:`sim.contact.replay.ContactReplay.solve`.
    """

    def __init__(self, replay, uc, cu, c: int, n_u: int, contacts, pairs_w, weights, sides, masses,
                 lever, vm_p, vm_b):
        self.r = replay
        self.uc, self.cu, self.c, self.n_u = uc, cu, c, n_u
        self.contacts, self.pairs_w, self.weights, self.sides, self.masses, self.lever = (
            contacts, pairs_w, weights, sides, masses, lever)
        self.vm = (vm_p, vm_b)
        self.mu = wp.float64(replay.friction)
        self.last = None  # (particle_qd, body_qd, impulses, slip) of the last trial
        self.outside = 0  # active contacts whose impulse pulled or left the cone in the last sticking trial

    def _trial(self, loads, slip):
        r, c, (_, targets, _, normals, _) = self.r, self.c, self.contacts
        m = 3 * self.n_u
        tangent_weight = r.take(c, wp.float64, zero=False, grad=False)
        with paused_tape():
            r.launch(tangent_weights_kernel, dim=1, inputs=[c, self.cu, loads, normals], outputs=[tangent_weight],
                      device=r.device)
        matrix = r.take((m, m), wp.float64, zero=False)  # every entry written
        r.launch(sticking_delassus_kernel, dim=(self.n_u, self.n_u),
                  inputs=[self.uc, self.pairs_w, self.weights, normals, r.vertex_type, r.vertex_owner, *self.sides,
                          *self.masses, wp.float64(REGULARIZATION), tangent_weight, slip, self.mu],
                  outputs=[matrix], device=r.device)
        vp, vb, total = r.refined_impulses(matrix, m, sticking_rhs_kernel, sticking_impulses_kernel, (), self.uc,
                                            self.cu, c, self.pairs_w, self.weights, normals, targets, self.sides,
                                            self.masses, self.lever, *self.vm, rhs_args=(slip,))
        self.last = (vp, vb, total, slip)
        return self.last

    def _changes(self):
        """The next split after the last trial and how many contacts it changes: the directions
        (fresh, taped from the trial's impulses) after the decision which contacts slide."""
        r, (vp, vb, total, slip) = self.r, self.last
        normals = self.contacts[3]
        counts = r.take(1, wp.int32, grad=False)
        codes = r.take(self.c, wp.int32, zero=False, grad=False)
        with paused_tape():
            r.launch(slip_update_kernel, dim=self.c,
                      inputs=[total, normals, self.cu, self.pairs_w, self.weights, r.vertex_type, r.vertex_owner,
                              self.lever, r.or_empty(vp, r.empty_vec), r.or_empty(vb, r.empty_twist), self.mu,
                              wp.float64(SLIP_REVERSAL), slip],
                      outputs=[codes, counts], device=r.device)
        changes = int(counts.numpy()[0])
        if not changes:
            return slip, 0
        slip_next = r.take(self.c, wp.vec3d, zero=False)
        r.launch(slip_directions_from_impulses_kernel, dim=self.c, inputs=[codes, total, normals, slip],
                  outputs=[slip_next], device=r.device)
        return slip_next, changes

    def _result(self):
        r, (vp, vb, total, _) = self.r, self.last
        normal_part = r.zeros(self.c, wp.vec3d)
        r.launch(normal_part_kernel, dim=self.c, inputs=[total, self.contacts[3]], outputs=[normal_part],
                  device=r.device)
        return vp, vb, normal_part

    def sticking(self, normal):
        """Every active contact sticking (split by the loads ``normal``, then by the trial's
        own): ``(particle_qd, body_qd, normal impulses)`` as :meth:`sim.contact.replay.ContactReplay.solve`, or None
        when some impulse pulls or leaves its cone (how many: :attr:`outside`)."""
        r = self.r
        slip = r.take(self.c, wp.vec3d, grad=False)  # zero: every contact sticking
        for loads in (normal, None):
            _, _, total, _ = self._trial(normal if loads is not None else self.last[2], slip)
            count = r.take(1, wp.int32, grad=False)
            with paused_tape():
                r.launch(outside_cone_kernel, dim=self.c, inputs=[total, self.contacts[3], self.cu, self.mu],
                          outputs=[count], device=r.device)
            self.outside = int(count.numpy()[0])
            if not self.outside:
                return self._result()
        return None

    def mixed(self):
        """Some contacts sticking, the others sliding, from the last sticking trial: as
        :meth:`sticking`, or None when the split returns to one it tried or still changes after
        :data:`FRICTION_SPLIT_ITERATIONS` solves. A sticking contact that pulls is left to the
        caller's active set, which drops it."""
        seen = {np.zeros(self.c, dtype=bool).tobytes()}  # every contact sticking: tried
        for _ in range(FRICTION_SPLIT_ITERATIONS):
            slip, changes = self._changes()
            if not changes:
                return self._result()
            sliding = (np.abs(slip.numpy()[: self.c]).sum(axis=1) > 0.0).tobytes()
            if sliding in seen:
                return None  # the split cycles
            seen.add(sliding)
            self._trial(self.last[2], slip)
        return None
