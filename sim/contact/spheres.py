"""The collision stage of sphere bodies: pairs, then obstacles (ground planes and static
triangles), per substep (:mod:`kernels.spheres`, :mod:`kernels.sphere_mesh`).

Every pair of spheres is tested every substep (an all-pairs broad phase: one thread per pair,
no host read). ``benchmarks/billiards.py`` measures its cost against the ball count.
Every sphere tests every static triangle (a model with spheres has small static meshes: walls,
ramps). Decisions (which pairs touch, which obstacle each sphere reaches) are off the tape; the responses
are taped launches, so gradients flow through the time of impact (the quadratic's mollified
derivative), the impulse and the time-of-impact positions.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from kernels.roots import DEFAULT_MAX_DERIVATIVE, DEFAULT_T_MAX
from core.buffers import host
from kernels.spheres import (apply_sphere_changes, decide_sphere_obstacles, decide_sphere_pairs, respond_sphere_obstacles,
                             respond_sphere_pairs, straight_path_start, vec12d)
from sim.model import Model, State


MAX_PASSES = 64
"""Passes of pair contacts per substep at most (:mod:`kernels.spheres`): a row of n touching
balls struck at one end takes about n passes."""


class SphereContacts:
    """Sphere-sphere, sphere-plane and sphere-static-triangle contacts of a model's spheres.

    Args:
        model: a model with ``sphere_count > 0``.
        max_derivative: the bound ``M`` of the time of impact's mollified derivative.

    Attributes:
        pair_count: number of sphere pairs, ``Ns (Ns - 1) / 2``.
        pair_a, pair_b: the spheres of each pair (``a < b``), wp.array(int32) (pair_count,).
        separation: distance [m] the spheres keep from each other and from the planes (the
            model's thickness).
        active_pairs: pairs acting in the last pass of the last substep (0 once resolved).
        passes: passes of pair contacts in the last substep.
        unresolved_substeps: substeps whose pairs still acted after ``max_passes`` passes.
    """

    def __init__(self, model: Model, max_derivative: float = DEFAULT_MAX_DERIVATIVE, max_passes: int = MAX_PASSES):
        if model.sphere_count < 1:
            raise ValueError("SphereContacts needs a model with spheres")
        self.model = model
        self.max_derivative = float(max_derivative)
        self.max_passes = int(max_passes)
        self.device = model.device
        a, b = np.triu_indices(model.sphere_count, k=1)
        self.pair_count = len(a)
        self.pair_a = wp.array(a.astype(np.int32), dtype=wp.int32, device=self.device)
        self.pair_b = wp.array(b.astype(np.int32), dtype=wp.int32, device=self.device)
        self.separation = float(model.thickness)
        self.gravity = wp.vec3d(*(float(g) for g in np.asarray(model.gravity, dtype=np.float64)))
        self._active = wp.zeros(max(self.pair_count, 1), dtype=wp.int32, device=self.device)
        self._obstacle = wp.zeros(model.sphere_count, dtype=wp.int32, device=self.device)
        self._obstacle_out = (wp.zeros(model.body_count, dtype=wp.transformd, device=self.device),
                              wp.zeros(model.body_count, dtype=wp.spatial_vectord, device=self.device))
        self.face_count = 0 if model.static_faces is None else int(model.static_faces.shape[0])
        self.static_vertices = model.static_vertices if self.face_count else wp.zeros(0, dtype=wp.vec3d,
                                                                                      device=self.device)
        # the kernels read a flat (3 F,) view of the (F, 3) triangles
        self.static_faces = (model.static_faces.flatten() if self.face_count
                             else wp.zeros(0, dtype=wp.int32, device=self.device))
        self._count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._responded = wp.zeros(max(self.pair_count, 1), dtype=wp.int32, device=self.device)
        self.active_pairs = 0
        self.passes = 0
        self.unresolved_substeps = 0

    def __call__(self, s_in: State, pred: State, h: float, requires_grad: bool):
        """The predicted bodies of ``pred`` after the substep's sphere contacts, as
        ``(body_q, body_qd)``: new arrays when a contact changed them (fresh ones per pass under a
        tape; the pair passes allocate without a tape too, the obstacles reuse the stage's own),
        else ``pred``'s own (nothing is copied). ``s_in``: the substep's start; ``h``: its
        length [s].

        One host read per pass: the number of acting pairs (none: the pass ends the loop)."""
        m, d = self.model, self.device
        hd = wp.float64(h)
        sep = wp.float64(self.separation)
        bodies_q, bodies_qd = pred.body_q, pred.body_qd
        obstacles = m.plane_count > 0 or self.face_count > 0
        start_q = s_in.body_q
        self.passes = 0
        if self.pair_count:
            self._responded.zero_()  # read by the decisions only (off the tape)
        for npass in range(self.pair_count and self.max_passes):
            if npass:
                start_q = wp.empty_like(bodies_q, requires_grad=requires_grad)
                wp.launch(straight_path_start, dim=m.body_count, inputs=[bodies_q, bodies_qd, hd], outputs=[start_q],
                          device=d)
            # the tape's backward reads the decisions as they were: fresh arrays under a tape
            active = wp.empty(self.pair_count, dtype=wp.int32, device=d) if requires_grad else self._active
            self._count.zero_()
            wp.launch(decide_sphere_pairs, dim=self.pair_count,
                      inputs=[self.pair_a, self.pair_b, m.sphere_body, m.sphere_radius, sep, start_q, bodies_qd,
                              hd, wp.float64(DEFAULT_T_MAX), self._responded],
                      outputs=[active, self._count], device=d, record_tape=False)
            self.active_pairs = int(host(self._count)[0])
            if not self.active_pairs:
                break
            self.passes += 1
            changes = wp.zeros(m.body_count, dtype=vec12d, device=d, requires_grad=requires_grad)
            wp.launch(respond_sphere_pairs, dim=self.pair_count,
                      inputs=[self.pair_a, self.pair_b, m.sphere_body, m.sphere_radius, sep, active, start_q,
                              bodies_qd, m.body_inv_mass, m.body_inv_inertia, wp.float64(m.restitution),
                              wp.float64(m.friction), hd, wp.float64(DEFAULT_T_MAX), wp.float64(self.max_derivative)],
                      outputs=[changes], device=d)
            next_q = wp.empty_like(bodies_q, requires_grad=requires_grad)
            next_qd = wp.empty_like(bodies_qd, requires_grad=requires_grad)
            wp.launch(apply_sphere_changes, dim=m.body_count, inputs=[bodies_q, bodies_qd, changes],
                      outputs=[next_q, next_qd], device=d)
            bodies_q, bodies_qd = next_q, next_qd
        else:
            if self.pair_count:
                self.unresolved_substeps += 1
        if obstacles:
            if requires_grad:
                out_q = wp.empty_like(bodies_q, requires_grad=True)
                out_qd = wp.empty_like(bodies_qd, requires_grad=True)
            else:
                out_q, out_qd = self._obstacle_out
            obstacle = wp.empty(m.sphere_count, dtype=wp.int32, device=d) if requires_grad else self._obstacle
            wp.launch(decide_sphere_obstacles, dim=m.sphere_count,
                      inputs=[m.sphere_body, m.sphere_radius, sep, bodies_q, bodies_qd, m.planes, int(m.plane_count),
                              self.static_vertices, self.static_faces, self.face_count, hd, wp.float64(DEFAULT_T_MAX)],
                      outputs=[obstacle], device=d, record_tape=False)
            wp.launch(respond_sphere_obstacles, dim=m.sphere_count,
                      inputs=[m.sphere_body, m.sphere_radius, sep, obstacle, s_in.body_qd, pred.body_qd,
                              bodies_q, bodies_qd, m.body_inv_mass, m.body_inv_inertia, m.planes, int(m.plane_count),
                              self.static_vertices, self.static_faces, wp.float64(m.restitution),
                              wp.float64(m.friction), self.gravity, hd, wp.float64(DEFAULT_T_MAX),
                              wp.float64(self.max_derivative)],
                      outputs=[out_q, out_qd], device=d)
            return out_q, out_qd
        return bodies_q, bodies_qd
