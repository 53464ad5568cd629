"""Closest-point offsets of contact primitive pairs (Warp, float64) for the collision response.

A contact pair is four vertex indices in the CCD order: vertex-face ``(p, a, b, c)`` or
edge-edge ``(a0, a1, b0, b1)``. The offset is the first primitive's closest point minus the
second's (exact closest points of the closed primitives, degenerate ones included), so its
direction is the contact normal pointing from the second primitive to the first and its length
the distance.
"""

import warp as wp

from kernels.edge_edge import segment_segment_offset
from kernels.point_triangle import point_triangle_offset


@wp.kernel
def contact_offsets_kernel(
    x: wp.array(dtype=wp.vec3d),
    pairs: wp.array(dtype=wp.vec4i),
    edge_edge: wp.array(dtype=wp.int32),
    offset: wp.array(dtype=wp.vec3d),
):
    """``offset[i]`` of pair ``pairs[i]`` (vertex-face when ``edge_edge[i] == 0``) at positions ``x``."""
    i = wp.tid()
    q = pairs[i]
    if edge_edge[i] == 0:
        offset[i] = point_triangle_offset(x[q[0]], x[q[1]], x[q[2]], x[q[3]])
    else:
        offset[i] = segment_segment_offset(x[q[0]], x[q[1]], x[q[2]], x[q[3]])


@wp.func
def _side_begin_end(edge_edge: int, side: int) -> wp.vec2i:
    """Vertex slots [begin, end) of side A (0) or B (1) of a contact."""
    split = 1
    if edge_edge != 0:
        split = 2
    if side == 0:
        return wp.vec2i(0, split)
    return wp.vec2i(split, 4)


@wp.kernel
def solve_contacts_kernel(
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    edge_edge: wp.array(dtype=wp.int32),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever_arm: wp.array(dtype=wp.vec3d),
    shape_offset: int,
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    friction: wp.float64,
    max_sweeps: int,
    tolerance: wp.float64,
    particle_qd: wp.array(dtype=wp.vec3d),
    body_linear: wp.array(dtype=wp.vec3d),
    body_angular: wp.array(dtype=wp.vec3d),
    normal_impulse: wp.array(dtype=wp.float64),
    friction_impulse: wp.array(dtype=wp.vec3d),
    sweeps_done: wp.array(dtype=wp.int32),
):
    """Projected Gauss-Seidel over a contact set, launched with ``dim=1`` (the sweeps are
    sequential, so the result is deterministic and every impulse sees the previous ones).

    Contact ``c`` joins vertices ``pairs[c]`` with signed weights ``weights[c]`` (side A: slot 0
    for vertex-face, slots 0-1 for edge-edge, weights summing to 1; side B the rest, summing to
    -1); its normal relative velocity ``sum_k w_k v_k . n`` must end at least ``targets[c]``.
    Vertex types: 0 particle (owner = particle index), 1 rigid (owner = body, lever arm
    ``lever_arm[vertex - shape_offset]`` from the centre of mass, world frame), 2 static. The
    accumulated normal impulse stays >= 0 and the friction impulse within ``friction`` times it.
    Velocities and impulses are updated in place; the sweeps stop once no contact's normal
    velocity is below its target by more than ``tolerance``.
    """
    zero = wp.float64(0.0)
    count = pairs.shape[0]
    sweep = int(0)
    while sweep < max_sweeps:
        sweep = sweep + 1
        worst = zero
        for c in range(count):
            q = pairs[c]
            w = weights[c]
            n = normals[c]
            ee = edge_edge[c]
            vrel = wp.vec3d(zero, zero, zero)
            k_eff = zero
            # particles: one by one; rigid vertices: per side (one body per side)
            for side in range(2):
                span = _side_begin_end(ee, side)
                body = int(-1)
                weight_sum = zero
                rho = wp.vec3d(zero, zero, zero)
                for s in range(span[0], span[1]):
                    v = q[s]
                    kind = vertex_type[v]
                    o = vertex_owner[v]
                    if kind == 0:
                        vrel = vrel + w[s] * particle_qd[o]
                        k_eff = k_eff + w[s] * w[s] * particle_inv_mass[o]
                    elif kind == 1:
                        body = o
                        weight_sum = weight_sum + w[s]
                        rho = rho + w[s] * lever_arm[v - shape_offset]
                if body >= 0:
                    vrel = vrel + weight_sum * body_linear[body] + wp.cross(body_angular[body], rho)
                    rn = wp.cross(rho, n)
                    k_eff = k_eff + weight_sum * weight_sum * body_inv_mass[body] + wp.dot(rn, body_inv_inertia[body] * rn)
            if k_eff <= zero:
                continue
            vn = wp.dot(vrel, n)
            worst = wp.max(worst, targets[c] - vn)
            jn_old = normal_impulse[c]
            jn_new = wp.max(jn_old + (targets[c] - vn) / k_eff, zero)
            jt_old = friction_impulse[c]
            jt_new = jt_old - (vrel - vn * n) / k_eff
            limit = friction * jn_new
            norm = wp.length(jt_new)
            if norm > limit:
                if norm > zero:
                    jt_new = jt_new * (limit / norm)
            impulse = (jn_new - jn_old) * n + (jt_new - jt_old)
            normal_impulse[c] = jn_new
            friction_impulse[c] = jt_new
            for side in range(2):
                span = _side_begin_end(ee, side)
                body = int(-1)
                weight_sum = zero
                rho = wp.vec3d(zero, zero, zero)
                for s in range(span[0], span[1]):
                    v = q[s]
                    kind = vertex_type[v]
                    o = vertex_owner[v]
                    if kind == 0:
                        particle_qd[o] = particle_qd[o] + (w[s] * particle_inv_mass[o]) * impulse
                    elif kind == 1:
                        body = o
                        weight_sum = weight_sum + w[s]
                        rho = rho + w[s] * lever_arm[v - shape_offset]
                if body >= 0:
                    body_linear[body] = body_linear[body] + (weight_sum * body_inv_mass[body]) * impulse
                    body_angular[body] = body_angular[body] + body_inv_inertia[body] * wp.cross(rho, impulse)
        if worst <= tolerance:
            break
    sweeps_done[0] = sweep
