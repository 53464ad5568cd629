"""Collision handling for the stepper: CCD on every surface, impulses applied at the time of impact.

:class:`ImpulseCollisionHandler` is plugged into :class:`sim.integrator.SemiImplicitIntegrator`
as its ``collision_handler``. Per substep of length ``h`` it receives the start State and the
predicted end State (velocities ``v-`` after forces) and:

1. gathers every collidable surface into one vertex set with linear motion over the substep:
   cloth particles, rigid-body surface vertices (body frame -> world at the start and predicted
   poses), static mesh vertices (not moving); the model's components decide which groups exist
   and which collide with themselves (cloth only with "self_collision"; a rigid body never with
   itself; static meshes never with each other);
2. runs :func:`collision.ccd.mesh_ccd` (broad phase + vertex-face / edge-edge narrow phase on the
   coplanarity cubic) and, for each primitive with a hit, takes its earliest time of impact t*;
3. applies a normal impulse with restitution and a Coulomb friction impulse at t*, split by
   barycentric weights and inverse masses (cloth) or through the body's inverse mass and world
   inverse inertia (rigid), and moves each primitive with its old velocity until t* and the new
   one after: ``x(h) = x0 + t* v- + (h - t*) v+`` (rigid bodies: the same for the centre of
   mass, the orientation turned by w- for t* then w+ for h - t*);
4. repeats 2-3 until the substep is collision free or ``max_iterations`` is reached; then the
   fail-safe freezes every primitive still involved in a collision at its start position (zero
   displacement and zero velocity this substep) and re-checks, growing the frozen
   set until no collision remains. The start of a substep is collision free, so this always
   terminates with no interpenetration.

This first version evaluates the response in numpy on the host (the detection runs in Warp
kernels); the derivative of the trajectory through t* is available for particle-plane contacts
(:mod:`kernels.integrate`), not yet for this general mesh response.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from collision.ccd import mesh_ccd
from sim.model import Model, State
from sim.rotation import quat_to_matrix, quat_turn


class ImpulseCollisionHandler:
    """CCD + impulse response at the time of impact (see the module docstring).

    Args:
        model: the finalised model (its surfaces, masses, restitution, friction, thickness).
        max_iterations: detection/response rounds before the fail-safe.
    """

    def __init__(self, model: Model, max_iterations: int = 8):
        self.model = model
        self.max_iterations = int(max_iterations)
        comps = model.components
        self._np = {}
        m = model
        faces, groups, self_collision, static = [], [], [], []
        self.n_particles = m.particle_count if "cloth" in comps else 0
        offset = 0
        if self.n_particles:
            faces.append(m.tri_indices.numpy().reshape(-1, 3))
            groups.append(np.zeros(self.n_particles, dtype=np.int64))
            self_collision.append("self_collision" in comps)
            static.append(False)
            offset = self.n_particles
        self.shape_offset = offset
        self.n_shape = 0
        if m.body_count and m.shape_vertices is not None and m.shape_vertices.shape[0]:
            self.shape_vertices = m.shape_vertices.numpy()
            self.shape_body = m.shape_vertex_body.numpy().astype(np.int64)
            self.n_shape = len(self.shape_vertices)
            faces.append(m.shape_faces.numpy().reshape(-1, 3) + offset)
            base = len(self_collision)
            groups.append(base + self.shape_body)
            self_collision.extend([False] * m.body_count)
            static.extend([False] * m.body_count)
            offset += self.n_shape
        self.static_offset = offset
        self.static_vertices = np.zeros((0, 3))
        if m.static_vertices is not None and m.static_vertices.shape[0]:
            self.static_vertices = m.static_vertices.numpy()
            faces.append(m.static_faces.numpy().reshape(-1, 3) + offset)
            groups.append(np.full(len(self.static_vertices), len(self_collision), dtype=np.int64))
            self_collision.append(False)
            static.append(True)
            offset += len(self.static_vertices)
        self.n_vertices = offset
        self.faces = np.concatenate(faces).astype(np.int64) if faces else np.zeros((0, 3), dtype=np.int64)
        self.groups = np.concatenate(groups) if groups else np.zeros(0, dtype=np.int64)
        self.self_collision = np.array(self_collision, dtype=bool)
        self.static = np.array(static, dtype=bool)
        self.particle_inv_mass = m.particle_inv_mass.numpy() if self.n_particles else np.zeros(0)
        if m.body_count:
            self.body_inv_mass = m.body_inv_mass.numpy()
            self.body_inv_inertia = m.body_inv_inertia.numpy().reshape(-1, 3, 3)
        self.last_contacts = np.zeros((0, 3))
        self.last_normals = np.zeros((0, 3))
        self.last_times = np.zeros(0)
        self.failsafe_count = 0

    # ------------------------------------------------------------------------------------------

    def _vertices(self, particle_q, body_q):
        """World positions of all collidable vertices for particle and body arrays (numpy)."""
        parts = []
        if self.n_particles:
            parts.append(particle_q[: self.n_particles])
        if self.n_shape:
            pos, quat = body_q[:, :3], body_q[:, 3:7]
            rot = quat_to_matrix(quat)[self.shape_body]
            parts.append(pos[self.shape_body] + np.einsum("nij,nj->ni", rot, self.shape_vertices))
        if len(self.static_vertices):
            parts.append(self.static_vertices)
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def _vertex_velocity(self, idx, pv, bq, bv):
        """Velocity of collidable vertex ``idx`` (numpy int array) given particle velocities and body
        poses / twists (angular, linear)."""
        vel = np.zeros((len(idx), 3))
        is_p = idx < self.static_offset
        is_p &= idx < self.shape_offset
        vel[is_p] = pv[idx[is_p]]
        is_s = (idx >= self.shape_offset) & (idx < self.static_offset)
        if is_s.any():
            sv = idx[is_s] - self.shape_offset
            b = self.shape_body[sv]
            r = quat_to_matrix(bq[b, 3:7]) @ self.shape_vertices[sv][..., None]
            vel[is_s] = bv[b, 3:6] + np.cross(bv[b, :3], r[..., 0])
        return vel

    def __call__(self, state_in: State, state_pred: State, h: float) -> State:
        x0p = state_in.particle_q.numpy() if self.n_particles else np.zeros((0, 3))
        bq0 = state_in.body_q.numpy() if self.n_shape else np.zeros((0, 7))
        vp = state_pred.particle_qd.numpy().copy() if self.n_particles else np.zeros((0, 3))
        bq1 = state_pred.body_q.numpy().copy() if self.n_shape else np.zeros((0, 7))
        bv = state_pred.body_qd.numpy().copy() if self.n_shape else np.zeros((0, 6))
        x1p = state_pred.particle_q.numpy().copy() if self.n_particles else np.zeros((0, 3))
        if self.n_vertices == 0 or len(self.faces) == 0:
            return None
        x0 = self._vertices(x0p, bq0)
        frozen_p = np.zeros(len(x0p), dtype=bool)
        frozen_b = np.zeros(len(bq0), dtype=bool)
        changed = False
        contacts, normals, times = [], [], []
        for iteration in range(self.max_iterations + 64):
            x1 = self._vertices(x1p, bq1)
            res = mesh_ccd(
                x0, x1, self.faces, groups=self.groups, self_collision=self.self_collision,
                static=self.static, thickness=self.model.thickness,
            )
            if res.num_contacts == 0:
                break
            hit_vf = res.vf[res.vf_hit]
            toi_vf = res.vf_toi[res.vf_hit]
            hit_ee = res.ee[res.ee_hit]
            toi_ee = res.ee_toi[res.ee_hit]
            # a contact only needs resolving while the primitives approach each other: touching
            # primitives that slide or separate (a resting contact after its impulse) are fine
            approaching = self._approaching(hit_vf, toi_vf, hit_ee, toi_ee, res.edges, x0, x1, vp, bq0, bv)
            n_vf = len(hit_vf)
            hit_vf, toi_vf = hit_vf[approaching[:n_vf]], toi_vf[approaching[:n_vf]]
            hit_ee, toi_ee = hit_ee[approaching[n_vf:]], toi_ee[approaching[n_vf:]]
            if len(hit_vf) + len(hit_ee) == 0:
                break
            changed = True
            if iteration >= self.max_iterations:
                # fail-safe: freeze everything involved at its start position
                involved = np.unique(np.concatenate([hit_vf[:, 0], self.faces[hit_vf[:, 1]].ravel(), res.edges[hit_ee].ravel()]))
                self._freeze(involved, x0p, bq0, x1p, bq1, frozen_p, frozen_b)
                vp[frozen_p] = 0.0  # a frozen primitive must not keep gathering velocity
                bv[frozen_b] = 0.0
                self.failsafe_count += 1
                continue
            idx, tois = self._primitives(hit_vf, toi_vf, hit_ee, toi_ee, res.edges)
            n, w = self._normals_and_weights(idx, x0, x1, tois, len(hit_vf))
            contacts.append(np.einsum("ck,ckd->cd", np.abs(w[:, :2]) / np.abs(w[:, :2]).sum(1, keepdims=True), (x0[idx[:, :2]] + tois[:, None, None] * (x1[idx[:, :2]] - x0[idx[:, :2]]))))
            normals.append(n)
            times.append(tois * h)
            self._respond(idx, w, n, tois, x0p, vp, bq0, bq1, bv, x1p, h)
            x1p[frozen_p] = x0p[frozen_p]
            bq1[frozen_b] = bq0[frozen_b]
        self.last_contacts = np.concatenate(contacts) if contacts else np.zeros((0, 3))
        self.last_normals = np.concatenate(normals) if normals else np.zeros((0, 3))
        self.last_times = np.concatenate(times) if times else np.zeros(0)
        if not changed:
            return None
        d = self.model.device
        out = State(
            particle_q=wp.array(np.concatenate([x1p, state_pred.particle_q.numpy()[len(x1p):]]) if self.n_particles else state_pred.particle_q.numpy(), dtype=wp.vec3d, device=d),
            particle_qd=wp.array(np.concatenate([vp, state_pred.particle_qd.numpy()[len(vp):]]) if self.n_particles else state_pred.particle_qd.numpy(), dtype=wp.vec3d, device=d),
            body_q=wp.array(bq1, dtype=wp.transformd, device=d) if self.n_shape else state_pred.body_q,
            body_qd=wp.array(bv, dtype=wp.spatial_vectord, device=d) if self.n_shape else state_pred.body_qd,
        )
        return out

    # ------------------------------------------------------------------------------------------

    def _primitives(self, hit_vf, toi_vf, hit_ee, toi_ee, edges):
        idx = np.concatenate(
            [np.column_stack([hit_vf[:, 0], self.faces[hit_vf[:, 1]]]).reshape(-1, 4),
             np.column_stack([edges[hit_ee[:, 0]], edges[hit_ee[:, 1]]]).reshape(-1, 4)]
        ).astype(np.int64)
        return idx, np.concatenate([toi_vf, toi_ee])

    def _approaching(self, hit_vf, toi_vf, hit_ee, toi_ee, edges, x0, x1, vp, bq, bv):
        idx, tois = self._primitives(hit_vf, toi_vf, hit_ee, toi_ee, edges)
        if len(idx) == 0:
            return np.zeros(0, dtype=bool)
        n, w = self._normals_and_weights(idx, x0, x1, tois, len(hit_vf))
        vel = np.stack([self._vertex_velocity(idx[:, k], vp, bq, bv) for k in range(4)], 1)
        vn = np.einsum("cd,cd->c", np.einsum("ck,ckd->cd", w, vel), n)
        return vn < 0.0

    def _normals_and_weights(self, idx, x0, x1, tois, n_vf):
        """Contact normals (pointing from the second primitive to the first) and signed weights
        w such that sum_k w_k x_k is the relative position of the closest points."""
        t = tois[:, None, None]
        y = x0[idx] + t * (x1[idx] - x0[idx])
        c = len(idx)
        n = np.zeros((c, 3))
        w = np.zeros((c, 4))
        if n_vf:
            p, a, b, cc = y[:n_vf, 0], y[:n_vf, 1], y[:n_vf, 2], y[:n_vf, 3]
            nv = np.cross(b - a, cc - a)
            bary = _barycentric(p, a, b, cc)
            w[:n_vf] = np.column_stack([np.ones(n_vf), -bary])
            n[:n_vf] = nv
            # orient by the side the vertex came from (relative position at the start)
            rel0 = x0[idx[:n_vf, 0]] - np.einsum("ck,ckd->cd", bary, x0[idx[:n_vf, 1:]])
        if c > n_vf:
            e = slice(n_vf, c)
            a0, a1, b0, b1 = y[e, 0], y[e, 1], y[e, 2], y[e, 3]
            s, u = _segment_params(a0, a1, b0, b1)
            w[e] = np.column_stack([1 - s, s, -(1 - u), -u])
            n[e] = np.cross(a1 - a0, b1 - b0)
            rel0_e = np.einsum("ck,ckd->cd", w[e], x0[idx[e]])
        rel = np.zeros((c, 3))
        if n_vf:
            rel[:n_vf] = rel0
        if c > n_vf:
            rel[n_vf:] = rel0_e
        # degenerate normals (parallel edges, zero-area faces): use the start offset direction
        norm = np.linalg.norm(n, axis=1)
        bad = norm <= 1e-12 * np.maximum(1e-300, np.linalg.norm(rel, axis=1) ** 2 + 1e-300)
        n[bad] = rel[bad]
        norm = np.linalg.norm(n, axis=1)
        n = np.divide(n, norm[:, None], out=np.tile([0.0, 0.0, 1.0], (c, 1)), where=norm[:, None] > 0)
        flip = np.einsum("cd,cd->c", n, rel) < 0
        n[flip] *= -1
        return n, w

    def _lever_arms(self, vtx, body_q):
        """For rigid-surface vertices ``vtx``: their bodies, world lever arms from the centre of
        mass, and the bodies' world inverse inertia tensors R I^-1 R^T."""
        sv = vtx - self.shape_offset
        b = self.shape_body[sv]
        rmat = quat_to_matrix(body_q[b, 3:7])
        r = np.einsum("nij,nj->ni", rmat, self.shape_vertices[sv])
        return b, r, rmat @ self.body_inv_inertia[b] @ np.swapaxes(rmat, 1, 2)

    def _respond(self, idx, w, n, tois, x0p, vp, bq0, bq1, bv, x1p, h):
        m = self.model
        e = m.restitution
        mu = m.friction
        bq_now = bq0
        vel = np.stack([self._vertex_velocity(idx[:, k], vp, bq_now, bv) for k in range(4)], 1)
        vrel = np.einsum("ck,ckd->cd", w, vel)
        vn = np.einsum("cd,cd->c", vrel, n)
        approaching = vn < 0
        # per-contact effective inverse mass: particles by w^2 / m, rigid vertices through the body
        k_eff = np.zeros(len(idx))
        for k in range(4):
            vtx = idx[:, k]
            is_p = vtx < self.shape_offset
            k_eff[is_p] += w[is_p, k] ** 2 * self.particle_inv_mass[vtx[is_p]]
            is_s = (vtx >= self.shape_offset) & (vtx < self.static_offset)
            if is_s.any():
                b, r, inv_i = self._lever_arms(vtx[is_s], bq_now)
                rn = np.cross(r, n[is_s])
                k_eff[is_s] += w[is_s, k] ** 2 * (self.body_inv_mass[b] + np.einsum("ni,nij,nj->n", rn, inv_i, rn))
        ok = approaching & (k_eff > 0)
        jn = np.zeros(len(idx))
        jn[ok] = -(1.0 + e) * vn[ok] / k_eff[ok]
        vt = vrel - vn[:, None] * n
        vt_norm = np.linalg.norm(vt, axis=1)
        tdir = np.divide(vt, vt_norm[:, None], out=np.zeros_like(vt), where=vt_norm[:, None] > 0)
        jt = np.zeros(len(idx))
        jt[ok] = np.minimum(mu * jn[ok], vt_norm[ok] / k_eff[ok])
        impulse = jn[:, None] * n - jt[:, None] * tdir
        # accumulate the earliest time of impact and the velocity change per particle / body
        t_p = np.full(len(vp), np.inf)
        t_b = np.full(len(bv), np.inf)
        dvp = np.zeros_like(vp)
        dbv = np.zeros_like(bv)
        # simultaneous contacts are resolved Jacobi-style with averaging: each particle / body
        # takes the mean of the velocity changes its contacts ask for (the sum would overshoot
        # when one body touches many primitives at once); the outer iterations converge it
        n_p = np.zeros(len(vp))
        n_b = np.zeros(len(bv))
        for k in range(4):
            vtx = idx[:, k]
            is_p = (vtx < self.shape_offset) & ok & (w[:, k] != 0)
            np.add.at(n_p, vtx[is_p], 1.0)
            is_s = (vtx >= self.shape_offset) & (vtx < self.static_offset) & ok & (w[:, k] != 0)
            if is_s.any():
                np.add.at(n_b, self.shape_body[vtx[is_s] - self.shape_offset], 1.0)
        for k in range(4):
            vtx = idx[:, k]
            is_p = vtx < self.shape_offset
            np.add.at(dvp, vtx[is_p], (w[is_p, k] * self.particle_inv_mass[vtx[is_p]])[:, None] * impulse[is_p])
            np.minimum.at(t_p, vtx[is_p], tois[is_p])
            is_s = (vtx >= self.shape_offset) & (vtx < self.static_offset)
            if is_s.any():
                b, r, inv_i = self._lever_arms(vtx[is_s], bq_now)
                jb = w[is_s, k][:, None] * impulse[is_s]
                np.add.at(dbv[:, 3:6], b, self.body_inv_mass[b][:, None] * jb)
                np.add.at(dbv[:, 0:3], b, np.einsum("nij,nj->ni", inv_i, np.cross(r, jb)))
                np.minimum.at(t_b, b, tois[is_s])
        dvp /= np.maximum(n_p, 1.0)[:, None]
        dbv /= np.maximum(n_b, 1.0)[:, None]
        # time-of-impact integration: old velocity until t*, new one after
        hit_p = np.isfinite(t_p)
        if hit_p.any():
            ts = t_p[hit_p] * h
            v_minus = vp[hit_p].copy()
            v_plus = v_minus + dvp[hit_p]
            x1p[hit_p] = x0p[hit_p] + ts[:, None] * v_minus + (h - ts)[:, None] * v_plus
            vp[hit_p] = v_plus
        hit_b = np.isfinite(t_b)
        if hit_b.any():
            ts = t_b[hit_b] * h
            v_minus = bv[hit_b].copy()
            v_plus = v_minus + dbv[hit_b]
            bq1[hit_b, :3] = bq0[hit_b, :3] + ts[:, None] * v_minus[:, 3:6] + (h - ts)[:, None] * v_plus[:, 3:6]
            q_mid = quat_turn(bq0[hit_b, 3:7], v_minus[:, :3], ts)
            bq1[hit_b, 3:7] = quat_turn(q_mid, v_plus[:, :3], h - ts)
            bv[hit_b] = v_plus

    def _freeze(self, involved, x0p, bq0, x1p, bq1, frozen_p, frozen_b):
        is_p = involved < self.shape_offset
        frozen_p[involved[is_p]] = True
        is_s = (involved >= self.shape_offset) & (involved < self.static_offset)
        if is_s.any():
            frozen_b[np.unique(self.shape_body[involved[is_s] - self.shape_offset])] = True
        x1p[frozen_p] = x0p[frozen_p]
        bq1[frozen_b] = bq0[frozen_b]


def _barycentric(p, a, b, c):
    """Barycentric weights of the closest point of triangle abc to p, (n, 3), clamped to the
    triangle (weights of the projection, clipped and renormalised)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("nd,nd->n", v0, v0)
    d01 = np.einsum("nd,nd->n", v0, v1)
    d11 = np.einsum("nd,nd->n", v1, v1)
    d20 = np.einsum("nd,nd->n", v2, v0)
    d21 = np.einsum("nd,nd->n", v2, v1)
    den = d00 * d11 - d01 * d01
    safe = np.where(np.abs(den) > 0, den, 1.0)
    v = (d11 * d20 - d01 * d21) / safe
    w = (d00 * d21 - d01 * d20) / safe
    u = 1.0 - v - w
    bary = np.clip(np.column_stack([u, v, w]), 0.0, 1.0)
    s = bary.sum(1, keepdims=True)
    bary = np.divide(bary, s, out=np.full_like(bary, 1.0 / 3.0), where=s > 0)
    bary[np.abs(den) == 0] = 1.0 / 3.0
    return bary


def _segment_params(a0, a1, b0, b1):
    """Parameters (s on a, u on b) of the closest points of two segments (clamped)."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a = np.einsum("nd,nd->n", d1, d1)
    e = np.einsum("nd,nd->n", d2, d2)
    f = np.einsum("nd,nd->n", d2, r)
    c = np.einsum("nd,nd->n", d1, r)
    b = np.einsum("nd,nd->n", d1, d2)
    den = a * e - b * b
    s = np.where(den > 1e-30 * np.maximum(a * e, 1e-300), np.clip((b * f - c * e) / np.where(den > 0, den, 1.0), 0, 1), 0.0)
    u = np.where(e > 0, (b * s + f) / np.where(e > 0, e, 1.0), 0.0)
    s = np.where(u < 0, np.where(a > 0, np.clip(-c / np.where(a > 0, a, 1.0), 0, 1), 0.0), s)
    s = np.where(u > 1, np.where(a > 0, np.clip((b - c) / np.where(a > 0, a, 1.0), 0, 1), 0.0), s)
    u = np.clip(u, 0, 1)
    return s, u
