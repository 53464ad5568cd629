"""Decision kernels of the collision response (Warp, float64), off the tape
(``enable_backward=False``): proximity of candidate pairs, the Gauss-Seidel impulse solve of the
fast response, and the active-set, push and friction-split decisions of the replayed one.
"""

import warp as wp

from kernels.ccd import box_farther_than, farther_than, filter_rounding, pair_vertex_indices
from kernels.ccd_common import max_abs_vec3
from kernels.contact_geometry import pair_weights
from kernels.edge_edge import segment_segment_offset
from kernels.friction import SLIP_KEEP, SLIP_START, SLIP_STICK, beyond_cone, coulomb_friction, stops_sliding
from kernels.point_triangle import point_triangle_offset
from kernels.response import relative_velocity


@wp.kernel(enable_backward=False)
def pair_proximity_kernel(
    vf_count: int,
    vf_pairs: wp.array(dtype=wp.vec2i),
    ee_pairs: wp.array(dtype=wp.vec2i),
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    edges: wp.array(dtype=wp.vec2i),
    max_distance: wp.float64,
    counter: wp.array(dtype=wp.int32),
    near_pairs: wp.array(dtype=wp.vec2i),
    near_kind: wp.array(dtype=wp.int32),
    near_offset: wp.array(dtype=wp.vec3d),
    near_weights: wp.array(dtype=wp.vec4d),
    near_vertices: wp.array(dtype=wp.vec4i),
    motion_radius: wp.array(dtype=wp.float64),
    reach_counter: wp.array(dtype=wp.int32),
    reach_vf: wp.array(dtype=wp.vec2i),
    reach_ee: wp.array(dtype=wp.vec2i),
):
    """Candidate pairs of a broad phase (:func:`kernels.ccd.pair_vertex_indices`; the first
    ``vf_count`` threads take the vertex-face pairs, the rest the edge-edge ones) whose
    primitives at positions ``x`` are at most ``max_distance`` apart, appended through
    ``counter`` with their kind, their offsets (the first primitive's exact closest point minus
    the second's, see the module docstring), the closest points' signed weights
    (:func:`pair_weights`) and their vertex indices: the proximity test without a per-pair array
    leaving the device.

    With a non-empty ``motion_radius`` (per vertex [m]) it also appends, through
    ``reach_counter[kind]`` into ``reach_vf`` / ``reach_ee``, the pairs that a zero-thickness CCD of a motion
    from ``x`` can hit when every vertex moves at most its radius: a point of a primitive is a
    convex combination of its vertices, so it moves at most their largest radius, and the CCD
    reports no hit of a pair farther apart at the start than its points can move relative to
    each other (:func:`kernels.ccd.ccd_query`). The bound is widened by the rounding of both
    distances and of the CCD's tolerance (:func:`kernels.ccd.filter_rounding`)."""
    i = wp.tid()
    kind = int(0)
    pair = wp.vec2i()
    if i < vf_count:
        pair = vf_pairs[i]
    else:
        kind = int(1)
        pair = ee_pairs[i - vf_count]
    q = pair_vertex_indices(kind, pair, faces, edges)
    y0 = x[q[0]]
    # the cheap plane / line bound first (most candidates are farther apart); the threshold adds
    # the bound's rounding and the exact distance's (kernels.ccd.filter_rounding), so it rejects
    # only pairs that the exact test rejects too
    extent = wp.max(max_abs_vec3(x[q[1]] - y0), wp.max(max_abs_vec3(x[q[2]] - y0), max_abs_vec3(x[q[3]] - y0)))
    reach = wp.float64(-1.0)
    if motion_radius.shape[0] > 0:
        reach_a = motion_radius[q[0]]
        reach_b = wp.max(motion_radius[q[2]], motion_radius[q[3]])
        if kind == 0:
            reach_b = wp.max(reach_b, motion_radius[q[1]])
        else:
            reach_a = wp.max(reach_a, motion_radius[q[1]])
        reach = reach_a + reach_b
        reach = reach + filter_rounding(extent + wp.float64(4.0) * reach, y0)
    threshold = wp.max(max_distance, reach) + filter_rounding(extent, y0)
    if box_farther_than(kind, y0, x[q[1]], x[q[2]], x[q[3]], threshold):
        return
    if farther_than(kind, y0, x[q[1]], x[q[2]], x[q[3]], threshold):
        return
    off = wp.vec3d()
    if kind == 0:
        off = point_triangle_offset(x[q[0]], x[q[1]], x[q[2]], x[q[3]])
    else:
        off = segment_segment_offset(x[q[0]], x[q[1]], x[q[2]], x[q[3]])
    distance2 = wp.dot(off, off)
    if distance2 <= max_distance * max_distance:
        slot = wp.atomic_add(counter, 0, 1)
        near_pairs[slot] = pair
        near_kind[slot] = wp.int32(kind)
        near_offset[slot] = off
        near_weights[slot] = pair_weights(kind, x[q[0]], x[q[1]], x[q[2]], x[q[3]])
        near_vertices[slot] = q
    if reach >= wp.float64(0.0) and distance2 <= reach * reach:
        if kind == 0:
            reach_vf[wp.atomic_add(reach_counter, 0, 1)] = pair
        else:
            reach_ee[wp.atomic_add(reach_counter, 1, 1)] = pair


@wp.func
def _is_edge_edge(kind: wp.int32) -> int:
    """1 for an edge-edge pair kind (1), else 0 (vertex-face 0, vertex-plane 2)."""
    if kind == 1:
        return 1
    return 0


@wp.func
def _side_begin_end(edge_edge: int, side: int) -> wp.vec2i:
    """Vertex slots [begin, end) of side A (0) or B (1) of a contact."""
    split = 1
    if edge_edge != 0:
        split = 2
    if side == 0:
        return wp.vec2i(0, split)
    return wp.vec2i(split, 4)


@wp.func
def _with_slot(v: wp.vec4i, slot: int, value: int) -> wp.vec4i:
    """``v`` with component ``slot`` set to ``value`` (a new vector: no in-place write)."""
    out = v
    if slot == 0:
        out = wp.vec4i(value, v[1], v[2], v[3])
    elif slot == 1:
        out = wp.vec4i(v[0], value, v[2], v[3])
    elif slot == 2:
        out = wp.vec4i(v[0], v[1], value, v[3])
    else:
        out = wp.vec4i(v[0], v[1], v[2], value)
    return out


@wp.func
def _apply_body_impulse(
    body: int,
    weight_sum: wp.float64,
    rho: wp.vec3d,
    impulse: wp.vec3d,
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
):
    """The impulse of one side's rigid vertices (summed weight, weighted lever arm) on their body
    (twist: angular, linear)."""
    t = body_qd[body]
    w = wp.spatial_top(t) + body_inv_inertia[body] * wp.cross(rho, impulse)
    v = wp.spatial_bottom(t) + (weight_sum * body_inv_mass[body]) * impulse
    body_qd[body] = wp.spatial_vectord(w[0], w[1], w[2], v[0], v[1], v[2])


@wp.kernel(enable_backward=False)
def solve_contacts_kernel(
    contact_count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    kinds: wp.array(dtype=wp.int32),
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
    contact_mass: wp.array(dtype=wp.float64),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_bodies: wp.array(dtype=wp.vec2i),
    contact_body_weight: wp.array(dtype=wp.vec2d),
    contact_lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    normal_impulse: wp.array(dtype=wp.float64),
    friction_impulse: wp.array(dtype=wp.vec3d),
    sweeps_done: wp.array(dtype=wp.int32),
):
    """Projected Gauss-Seidel over a contact set, launched with ``dim=1`` (the sweeps are
    sequential, so the result is deterministic and every impulse sees the previous ones).

    Contacts ``0 .. count - 1`` are used, ``count = contact_count[0]`` (read on the device; the
    arrays may be longer: reused buffers). Contact ``c`` joins vertices ``pairs[c]`` with signed weights ``weights[c]`` (side A: slot 0
    for vertex-face, slots 0-1 for edge-edge, weights summing to 1; side B the rest, summing to
    -1; ``kinds[c]``: 0 vertex-face, 1 edge-edge, 2 vertex-plane); its normal relative velocity
    ``sum_k w_k v_k . n`` must end at least ``targets[c]``.
    Vertex types: 0 particle (owner = particle index), 1 rigid (owner = body, lever arm
    ``lever_arm[vertex - shape_offset]`` from the centre of mass, world frame), 2 static. The
    accumulated normal impulse stays >= 0 and the friction impulse within ``friction`` times it.
    Velocities and impulses are updated in place; the sweeps stop once no contact's normal
    velocity is below its target by more than ``tolerance``.

    ``contact_mass``, ``contact_particles``, ``contact_bodies``, ``contact_body_weight`` (at
    least ``count`` rows) and ``contact_lever`` (``2 count``) are scratch: each contact's
    constants over the sweeps (effective inverse mass along its normal, the particle of each
    slot or -1, each side's body or -1 with its summed weight and weighted lever arm), computed
    once before the sweeps, so that a sweep reads no vertex type, owner, mass or inertia.
    """
    zero = wp.float64(0.0)
    count = int(contact_count[0])
    for c in range(count):
        q = pairs[c]
        w = weights[c]
        n = normals[c]
        ee = _is_edge_edge(kinds[c])
        k_eff = zero
        slot_particle = wp.vec4i(-1, -1, -1, -1)
        side_body = wp.vec2i(-1, -1)
        side_weight = wp.vec2d(zero, zero)
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
                    k_eff = k_eff + w[s] * w[s] * particle_inv_mass[o]
                    slot_particle = _with_slot(slot_particle, s, o)
                elif kind == 1:
                    body = o
                    weight_sum = weight_sum + w[s]
                    rho = rho + w[s] * lever_arm[v - shape_offset]
            if body >= 0:
                rn = wp.cross(rho, n)
                k_eff = k_eff + weight_sum * weight_sum * body_inv_mass[body] + wp.dot(rn, body_inv_inertia[body] * rn)
            if side == 0:
                side_body = wp.vec2i(body, side_body[1])
                side_weight = wp.vec2d(weight_sum, side_weight[1])
            else:
                side_body = wp.vec2i(side_body[0], body)
                side_weight = wp.vec2d(side_weight[0], weight_sum)
            contact_lever[c + c + side] = rho
        contact_mass[c] = k_eff
        contact_particles[c] = slot_particle
        contact_bodies[c] = side_body
        contact_body_weight[c] = side_weight
    sweep = int(0)
    while sweep < max_sweeps:
        sweep = sweep + 1
        worst = zero
        for c in range(count):
            k_eff = contact_mass[c]
            if k_eff <= zero:
                continue
            w = weights[c]
            n = normals[c]
            p = contact_particles[c]
            bodies = contact_bodies[c]
            body_weight = contact_body_weight[c]
            split = _side_begin_end(_is_edge_edge(kinds[c]), 0)[1]  # side B's first slot
            # the relative velocity in the order side A's particles, side A's body, side B's
            # particles, side B's body (the slots, unrolled)
            vrel = wp.vec3d(zero, zero, zero)
            for s in range(4):
                if s == split and bodies[0] >= 0:
                    t0 = body_qd[bodies[0]]
                    vrel = vrel + body_weight[0] * wp.spatial_bottom(t0) + wp.cross(wp.spatial_top(t0), contact_lever[c + c])
                if p[s] >= 0:
                    vrel = vrel + w[s] * particle_qd[p[s]]
            if bodies[1] >= 0:
                t1 = body_qd[bodies[1]]
                vrel = vrel + body_weight[1] * wp.spatial_bottom(t1) + wp.cross(wp.spatial_top(t1), contact_lever[c + c + 1])
            vn = wp.dot(vrel, n)
            worst = wp.max(worst, targets[c] - vn)
            jn_old = normal_impulse[c]
            jn_new = wp.max(jn_old + (targets[c] - vn) / k_eff, zero)
            jt_old = friction_impulse[c]
            # the accumulated friction impulse, projected on the cone (Coulomb's law against
            # its own direction)
            jt_stop = jt_old - (vrel - vn * n) / k_eff
            jt_new = coulomb_friction(jt_stop, -jt_stop, friction * jn_new)
            impulse = (jn_new - jn_old) * n + (jt_new - jt_old)
            normal_impulse[c] = jn_new
            friction_impulse[c] = jt_new
            for s in range(4):
                if s == split and bodies[0] >= 0:
                    _apply_body_impulse(bodies[0], body_weight[0], contact_lever[c + c], impulse,
                                        body_inv_mass, body_inv_inertia, body_qd)
                if p[s] >= 0:
                    particle_qd[p[s]] = particle_qd[p[s]] + (w[s] * particle_inv_mass[p[s]]) * impulse
            if bodies[1] >= 0:
                _apply_body_impulse(bodies[1], body_weight[1], contact_lever[c + c + 1], impulse,
                                    body_inv_mass, body_inv_inertia, body_qd)
        if worst <= tolerance:
            break
    sweeps_done[0] = sweep


@wp.kernel(enable_backward=False)
def push_active_kernel(
    active: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    pushes: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    flags: wp.array(dtype=wp.int32),
):
    """The push's unknowns (a decision): the active contacts, and those whose normal velocity
    after the impulses is below their push (a primitive resting inside the separation, which
    needs no impulse to stop but must still be moved out)."""
    c = wp.tid()
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    short = pushes[c] > wp.dot(normals[c], vrel)
    if active[c] != 0 or short:
        flags[c] = 1
    else:
        flags[c] = 0


@wp.kernel(enable_backward=False)
def slip_reversed_kernel(
    impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    directions: wp.array(dtype=wp.vec3d),
    contact_unknown: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    reversal: wp.float64,
    count: wp.array(dtype=wp.int32),
):
    """Counts the active contacts of a sliding solve that did not slip (no direction: no
    friction in the solve) or that stop sliding (:func:`stops_sliding`); a decision."""
    c = wp.tid()
    if contact_unknown[c] < 0:
        return
    s = directions[c]
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    if wp.length_sq(s) == wp.float64(0.0) or stops_sliding(impulses[c], normals[c], vrel, s, reversal):
        wp.atomic_add(count, 0, 1)


TANGENT_WEIGHT_MAX = wp.constant(wp.float64(100.0))


@wp.kernel(enable_backward=False)
def tangent_weights_kernel(
    count: int,
    contact_unknown: wp.array(dtype=wp.int32),
    normal_impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    weights_out: wp.array(dtype=wp.float64),
):
    """The sticking system's tangential regularisation weights (launched with ``dim=1``): the
    largest active normal impulse over each contact's, at most ``TANGENT_WEIGHT_MAX`` (a
    decision: it picks the split of the friction among redundant contacts, not the motion)."""
    largest = wp.float64(0.0)
    for c in range(count):
        if contact_unknown[c] >= 0:
            largest = wp.max(largest, wp.dot(normal_impulses[c], normals[c]))
    for c in range(count):
        w = TANGENT_WEIGHT_MAX
        jn = wp.dot(normal_impulses[c], normals[c])
        if jn * TANGENT_WEIGHT_MAX > largest:
            w = largest / jn
        weights_out[c] = w


@wp.kernel(enable_backward=False)
def outside_cone_kernel(
    impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    contact_unknown: wp.array(dtype=wp.int32),
    friction: wp.float64,
    count: wp.array(dtype=wp.int32),
):
    """Counts the active contacts whose impulse pulls (``j . n < 0``) or leaves the friction
    cone (``|j_t| > mu j . n``): a decision (whether every contact can stick)."""
    c = wp.tid()
    if contact_unknown[c] < 0:
        return
    if beyond_cone(impulses[c], normals[c], friction):
        wp.atomic_add(count, 0, 1)


@wp.kernel(enable_backward=False)
def slip_update_kernel(
    impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    contact_unknown: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    friction: wp.float64,
    reversal: wp.float64,
    slip: wp.array(dtype=wp.vec3d),
    codes: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """Which active contacts of a frictional solve (:func:`sticking_delassus_kernel`) stick and
    which slide next, a decision (``codes``, for :func:`slip_directions_from_impulses_kernel`).
    A sticking contact (``slip[c]`` zero) that pushes (``j_n > 0``) and whose impulse leaves its
    cone (``|j_t| > mu j_n``) starts sliding (``SLIP_START``); a sliding one that stops sliding
    (:func:`stops_sliding`, with its slip after the solve from ``particle_qd``, ``body_qd``)
    sticks (``SLIP_STICK``); the others keep their state. ``counts[0]`` counts
    the changes. A sticking contact that pulls is the caller's active set's to drop."""
    c = wp.tid()
    zero = wp.float64(0.0)
    s = slip[c]
    sliding = wp.length_sq(s) > zero
    code = SLIP_STICK
    if sliding:
        code = SLIP_KEEP
    if contact_unknown[c] >= 0:
        n = normals[c]
        j = impulses[c]
        jn = wp.dot(j, n)
        if not sliding:
            if jn > zero and beyond_cone(j, n, friction):
                code = SLIP_START
                wp.atomic_add(counts, 0, 1)
        else:
            vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
            if stops_sliding(j, n, vrel, s, reversal):
                code = SLIP_STICK
                wp.atomic_add(counts, 0, 1)
    codes[c] = code


@wp.kernel(enable_backward=False)
def push_overshoot_kernel(
    matrix: wp.array2d(dtype=wp.float64),
    rhs: wp.array(dtype=wp.float64),
    solution: wp.array(dtype=wp.float64),
    limit: wp.float64,
    count: wp.array(dtype=wp.int32),
):
    """Counts the push's unknowns whose impulse alone changes its own row's velocity
    (``|lambda_i| A_ii``) by more than ``limit`` times the largest push asked for (``rhs``): a
    decision (the push system's rows are near-copies asking for different pushes, and its
    impulses cancel each other at a large scale). Launched with one thread per unknown."""
    i = wp.tid()
    largest = wp.float64(0.0)
    for k in range(rhs.shape[0]):
        largest = wp.max(largest, wp.abs(rhs[k]))
    if wp.abs(solution[i]) * matrix[i, i] > limit * largest:
        wp.atomic_add(count, 0, 1)
