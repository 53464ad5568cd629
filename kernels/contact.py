"""Closest-point offsets of contact primitive pairs (Warp, float64) for the collision response.

A contact pair is four vertex indices in the CCD order: vertex-face ``(p, a, b, c)`` or
edge-edge ``(a0, a1, b0, b1)``. The offset is the first primitive's closest point minus the
second's (exact closest points of the closed primitives, degenerate ones included), so its
direction is the contact normal pointing from the second primitive to the first and its length
the distance.
"""

import warp as wp

from kernels.ccd import box_farther_than, farther_than, filter_rounding, pair_vertex_indices
from kernels.ccd_common import CCD_T_MAX, coplanarity_cubic, max_abs_vec3, unit_scaled_cubic
from kernels.edge_edge import segment_segment_closest, segment_segment_offset
from kernels.integrate import time_of_impact_position
from kernels.point_triangle import point_triangle_closest, point_triangle_offset
from kernels.roots import cubic_roots


@wp.kernel
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


@wp.kernel
def solve_contacts_kernel(
    count: int,
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

    Contacts ``0 .. count - 1`` are used (the arrays may be longer: reused buffers). Contact ``c`` joins vertices ``pairs[c]`` with signed weights ``weights[c]`` (side A: slot 0
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
            jt_new = jt_old - (vrel - vn * n) / k_eff
            limit = friction * jn_new
            norm = wp.length(jt_new)
            if norm > limit:
                if norm > zero:
                    jt_new = jt_new * (limit / norm)
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


# ----------------------------------------------------------------------------------------------
# Replay of the collision response (taped): the smooth map from the start state and the predicted
# velocities to the velocities and positions after the impulses, given the discrete decisions of
# the detection stage (contact set, root slot, active set, friction regime, earliest contact per
# owner). See design.md "Differentiating collision response: decide, then replay".

VERTEX_PARTICLE = wp.constant(0)
VERTEX_BODY = wp.constant(1)
VERTEX_STATIC = wp.constant(2)

PAIR_VERTEX_FACE = wp.constant(0)
PAIR_EDGE_EDGE = wp.constant(1)
PAIR_VERTEX_PLANE = wp.constant(2)

TIME_START = wp.constant(0)  # proximity contact: t* = 0
TIME_DETECTED = wp.constant(4)  # a time the narrow phase found off the cubic (no derivative)
TIME_PLANE = wp.constant(6)  # vertex-plane crossing of the linear path


@wp.func
def vertex_pose(
    v: int,
    particle_q: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
):
    """(world position, lever arm from its body's centre of mass: zero for particles and static
    vertices) of collidable vertex ``v``; ``local`` holds body-frame positions of rigid vertices
    and world positions of static ones."""
    kind = vertex_type[v]
    o = vertex_owner[v]
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if kind == VERTEX_PARTICLE:
        return particle_q[o], zero
    if kind == VERTEX_BODY:
        r = body_lever(body_q[o], local[v])
        return wp.transform_get_translation(body_q[o]) + r, r
    return local[v], zero


@wp.func
def vertex_position(
    v: int,
    particle_q: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
) -> wp.vec3d:
    """World position of collidable vertex ``v`` (:func:`vertex_pose`'s without the lever arm)."""
    kind = vertex_type[v]
    o = vertex_owner[v]
    if kind == VERTEX_PARTICLE:
        return particle_q[o]
    if kind == VERTEX_BODY:
        return body_point(body_q[o], local[v])
    return local[v]


@wp.kernel
def pose_vertices_kernel(
    particle_q: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    lever: wp.array(dtype=wp.vec3d),
):
    """World position ``x`` of collidable vertex ``tid`` and its lever arm from its body's centre
    of mass (zero for particles and static vertices). ``local`` holds body-frame positions of
    rigid vertices and world positions of static ones."""
    v = wp.tid()
    p, r = vertex_pose(v, particle_q, body_q, vertex_type, vertex_owner, local)
    x[v] = p
    lever[v] = r


@wp.kernel
def pose_start_kernel(
    particle_q: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    vertex_count: int,
    body_count: int,
    x: wp.array(dtype=wp.vec3d),
    lever: wp.array(dtype=wp.vec3d),
    inv_inertia_w: wp.array(dtype=wp.mat33d),
):
    """:func:`pose_vertices_kernel` and, in the first ``body_count`` threads, the bodies' world
    inverse inertia tensors (:func:`world_inverse_inertia`) in one launch over
    ``max(vertex_count, body_count)`` threads: what the replayed response needs at the start of
    a substep."""
    v = wp.tid()
    if v < body_count:
        inv_inertia_w[v] = world_inverse_inertia(body_q[v], body_inv_inertia[v])
    if v >= vertex_count:
        return
    p, r = vertex_pose(v, particle_q, body_q, vertex_type, vertex_owner, local)
    x[v] = p
    lever[v] = r


@wp.kernel
def pose_positions_kernel(
    particle_q: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
):
    """:func:`pose_vertices_kernel`'s positions alone."""
    v = wp.tid()
    x[v] = vertex_position(v, particle_q, body_q, vertex_type, vertex_owner, local)


@wp.func
def body_lever(X: wp.transformd, local: wp.vec3d) -> wp.vec3d:
    """The lever arm (world offset from the centre of mass) of a body-frame point ``local`` of a
    body at pose ``X``."""
    return wp.quat_rotate(wp.transform_get_rotation(X), local)


@wp.func
def body_point(X: wp.transformd, local: wp.vec3d) -> wp.vec3d:
    """World position of a body-frame point ``local`` of a body at pose ``X``: its centre of
    mass plus :func:`body_lever`."""
    return wp.transform_get_translation(X) + body_lever(X, local)


@wp.kernel
def pose_substep_kernel(
    particle_q0: wp.array(dtype=wp.vec3d),
    body_q0: wp.array(dtype=wp.transformd),
    particle_q1: wp.array(dtype=wp.vec3d),
    body_q1: wp.array(dtype=wp.transformd),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    vertex_count: int,
    body_count: int,
    x0: wp.array(dtype=wp.vec3d),
    lever0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    inv_inertia_w: wp.array(dtype=wp.mat33d),
):
    """One launch for what a substep's collision handling needs first: the vertices at the start
    (``x0``, ``lever0``, as :func:`pose_vertices_kernel` poses ``particle_q0``, ``body_q0``), at
    the predicted end (``x1``, of ``particle_q1``, ``body_q1``) and, in the first threads, the
    bodies' world inverse inertia at the start (:func:`world_inverse_inertia`).
    Launched over ``max(vertex_count, body_count)`` threads."""
    v = wp.tid()
    if v < body_count:
        inv_inertia_w[v] = world_inverse_inertia(body_q0[v], body_inv_inertia[v])
    if v >= vertex_count:
        return
    p, r = vertex_pose(v, particle_q0, body_q0, vertex_type, vertex_owner, local)
    x0[v] = p
    lever0[v] = r
    x1[v] = vertex_position(v, particle_q1, body_q1, vertex_type, vertex_owner, local)


@wp.func
def vertex_velocity(
    v: int,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
) -> wp.vec3d:
    """Velocity of collidable vertex ``v`` (rigid: ``v + w x r`` with the start lever arm)."""
    kind = vertex_type[v]
    o = vertex_owner[v]
    if kind == VERTEX_PARTICLE:
        return particle_qd[o]
    if kind == VERTEX_BODY:
        t = body_qd[o]
        return wp.spatial_bottom(t) + wp.cross(wp.spatial_top(t), lever[v])
    return wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.func
def vertex_time(
    v: int,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
) -> wp.float64:
    """Time of impact [s] already assigned to the owner of vertex ``v`` (inf for none/static)."""
    kind = vertex_type[v]
    o = vertex_owner[v]
    if kind == VERTEX_PARTICLE:
        return particle_time[o]
    if kind == VERTEX_BODY:
        return body_time[o]
    return wp.float64(1.0e308) * wp.float64(10.0)


@wp.func
def pair_weights(kind: int, y0: wp.vec3d, y1: wp.vec3d, y2: wp.vec3d, y3: wp.vec3d) -> wp.vec4d:
    """Signed weights of the closest points: side A positive (sum 1), side B negative (sum -1)."""
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    if kind == PAIR_VERTEX_FACE:
        vw = point_triangle_closest(y0, y1, y2, y3)
        return wp.vec4d(one, -(one - vw[0] - vw[1]), -vw[0], -vw[1])
    if kind == PAIR_EDGE_EDGE:
        st = segment_segment_closest(y0, y1, y2, y3)
        return wp.vec4d(one - st[0], st[0], -(one - st[1]), -st[1])
    return wp.vec4d(one, zero, zero, zero)


@wp.func
def pair_geometric_normal(kind: int, y0: wp.vec3d, y1: wp.vec3d, y2: wp.vec3d, y3: wp.vec3d) -> wp.vec3d:
    """Face normal (vertex-face) or the edges' cross product (edge-edge), not normalised."""
    if kind == PAIR_VERTEX_FACE:
        return wp.cross(y2 - y1, y3 - y1)
    return wp.cross(y1 - y0, y3 - y2)


@wp.func
def pair_scale(y0: wp.vec3d, y1: wp.vec3d, y2: wp.vec3d, y3: wp.vec3d) -> wp.float64:
    """Largest coordinate deviation of the four points from their mean (size of the pair)."""
    m = (y0 + y1 + y2 + y3) * wp.float64(0.25)
    s = wp.float64(0.0)
    for k in range(3):
        s = wp.max(s, wp.max(wp.max(wp.abs(y0[k] - m[k]), wp.abs(y1[k] - m[k])), wp.max(wp.abs(y2[k] - m[k]), wp.abs(y3[k] - m[k]))))
    return s


@wp.func
def flat_edge_index(a: int, b: int, flat_keys: wp.array(dtype=wp.int64), base: wp.int64) -> int:
    """The row of the edge ``(a, b)`` in the sorted ``flat_keys`` (``lo * base + hi``), or -1
    when it is not an edge between two coplanar faces of a rigid or static surface
    (:func:`sim.collision_mesh.flat_edges`)."""
    key = wp.int64(wp.min(a, b)) * base + wp.int64(wp.max(a, b))
    lo = int(0)
    hi = flat_keys.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if flat_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < flat_keys.shape[0] and flat_keys[lo] == key:
        return lo
    return -1


@wp.func
def crossed(side: wp.float64, on_edge: bool) -> bool:
    """Whether a barycentric sign ``side`` puts a point beyond its edge (``on_edge``: also on it)."""
    return side < wp.float64(0.0) or (on_edge and side == wp.float64(0.0))


@wp.func
def beyond_flat_edge(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: int, ia: int, ib: int, n: wp.vec3d,
                     flat_keys: wp.array(dtype=wp.int64), flat_opposites: wp.array(dtype=wp.vec2i),
                     base: wp.int64, x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d),
                     frac: wp.float64, on_edge: bool) -> bool:
    """Whether ``p``, beyond the edge ``ab`` (vertices ``ia``, ``ib``) of a face whose third
    vertex is ``c`` and whose normal is ``n``, lies over the neighbouring face across it: the
    edge is flat and ``p`` crosses neither of the neighbour's other two edges, unless that edge is
    flat too (a point below a box face's corner is beyond the face's diagonal, but beside the
    face, not over its other half)."""
    row = flat_edge_index(ia, ib, flat_keys, base)
    if row < 0:
        return False
    o = flat_opposites[row]
    d = o[0]
    if d == c:
        d = o[1]
    if d < 0:
        return True
    y = x0[d] + frac * (x1[d] - x0[d])
    # the neighbour (b, a, d) has the face's orientation; its edges a-d and d-b
    if crossed(wp.dot(wp.cross(y - p, b - p), n), on_edge) and flat_edge_index(ib, d, flat_keys, base) < 0:
        return False
    if crossed(wp.dot(wp.cross(a - p, y - p), n), on_edge) and flat_edge_index(d, ia, flat_keys, base) < 0:
        return False
    return True


@wp.func
def beside_flat_region(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, q: wp.vec4i,
                       flat_keys: wp.array(dtype=wp.int64), flat_opposites: wp.array(dtype=wp.vec2i),
                       base: wp.int64, x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d),
                       frac: wp.float64, on_edge: bool) -> bool:
    """Whether the projection of ``p`` on the plane of the triangle ``abc`` (vertices
    ``q[1], q[2], q[3]``, positions at ``frac`` of the paths ``x0 -> x1``) lies inside it or over
    a coplanar neighbour across a flat edge (the signs of its unnormalised barycentric
    coordinates; an edge is crossed when the opposite vertex's is negative, or with ``on_edge``
    zero too; :func:`beyond_flat_edge`)."""
    n = wp.cross(b - a, c - a)
    inside = True
    if crossed(wp.dot(wp.cross(b - p, c - p), n), on_edge):
        inside = inside and beyond_flat_edge(p, b, c, q[1], q[2], q[3], n, flat_keys, flat_opposites, base, x0, x1,
                                             frac, on_edge)
    if crossed(wp.dot(wp.cross(c - p, a - p), n), on_edge):
        inside = inside and beyond_flat_edge(p, c, a, q[2], q[3], q[1], n, flat_keys, flat_opposites, base, x0, x1,
                                             frac, on_edge)
    if crossed(wp.dot(wp.cross(a - p, b - p), n), on_edge):
        inside = inside and beyond_flat_edge(p, a, b, q[3], q[1], q[2], n, flat_keys, flat_opposites, base, x0, x1,
                                             frac, on_edge)
    return inside


@wp.kernel
def contact_geometry_kernel(
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    lever: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    kinds: wp.array(dtype=wp.int32),
    sources: wp.array(dtype=wp.int32),
    detected: wp.array(dtype=wp.float64),
    plane_ids: wp.array(dtype=wp.int32),
    planes: wp.array(dtype=wp.vec4d),
    particle_qd_start: wp.array(dtype=wp.vec3d),
    body_qd_start: wp.array(dtype=wp.spatial_vectord),
    particle_qd_minus: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd_minus: wp.array(dtype=wp.spatial_vectord),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
    h: wp.float64,
    separation: wp.float64,
    restitution: wp.float64,
    separation_rate: wp.float64,
    touching_relative: wp.float64,
    max_derivative: wp.float64,
    nearest_slot: wp.int32,
    flat_keys: wp.array(dtype=wp.int64),
    flat_opposites: wp.array(dtype=wp.vec2i),
    flat_key_base: wp.int64,
    split_push: wp.int32,
    toi: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    pushes: wp.array(dtype=wp.float64),
):
    """Time of impact, weights, normal and target normal velocity of contact ``tid`` on the
    linear paths ``x0 -> x1`` of the substep ``h`` (differentiable; the branches are the
    decisions of the detection stage, repeated here).

    * ``t*``: 0 for proximity contacts (source 0); the real part of the cubic's root in slot
      ``source - 1`` for CCD hits at a root (through :func:`kernels.roots.cubic_roots`, whose
      adjoint is the mollified implicit derivative bounded by ``max_derivative``; with
      ``nearest_slot`` the slot whose real part is nearest the detected fraction instead: a
      narrow phase of another precision numbers its roots its own way); the linear
      crossing time for vertex-plane hits (source 6); otherwise the detected fraction.
    * weights and normal at ``t*`` (:func:`pair_weights`; the face / edge-edge normal oriented
      by the start offset, or, for proximity pairs, the offset direction, the face's normal for
      a vertex over the face or its coplanar neighbours (``flat_keys``, ``flat_opposites``); touching pairs: the face's
      outward normal, crossing edges' cross product oriented by their lever arms, else a zero
      normal, which keeps the pair out of the contact set).
    * target: proximity ``max(-e v_n, rate (delta - d) / h)`` when it approaches faster than
      the separation speed ``rate delta / h`` (else ``rate (delta - d) / h``: resting contact;
      a pair beyond ``delta``, within the proximity pass's hysteresis, may approach at
      ``(delta - d) / h``, which brings it to ``delta`` at the end, and is not pulled); CCD
      ``max(-e v_n, rate delta / h)``, ``v_n`` the normal velocity at ``t*``: each vertex's
      start velocity plus the forces' change up to ``t*`` (``v_start + (t*/h)(v- - v_start)``;
      the start velocity for proximity pairs) before its owner's earlier contact time, the
      current velocity after it. With ``split_push`` the target is the
      restitution's part alone (at least 0; a pair beyond ``delta``: ``(delta - d) / h``), and
      the separation's part, the push ``rate (delta - d) / h`` (proximity; beyond ``delta``:
      ``(delta - d) / h``) or ``rate delta / h`` (CCD), goes to ``pushes`` for a solve of its
      own that moves positions only (:func:`push_rhs_kernel`).
    """
    c = wp.tid()
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    q = pairs[c]
    kind = kinds[c]
    src = sources[c]
    a0 = x0[q[0]]
    a1 = x0[q[1]]
    a2 = x0[q[2]]
    a3 = x0[q[3]]
    b0 = x1[q[0]]
    b1 = x1[q[1]]
    b2 = x1[q[2]]
    b3 = x1[q[3]]
    frac = zero
    if src >= 1 and src <= 3:
        r = cubic_roots(unit_scaled_cubic(coplanarity_cubic(a0, a1, a2, a3, b0, b1, b2, b3)), CCD_T_MAX, max_derivative)
        slot = src - 1
        if nearest_slot != 0:
            for k in range(3):
                if wp.abs(wp.clamp(r[2 * k], zero, one) - detected[c]) < wp.abs(wp.clamp(r[2 * slot], zero, one) - detected[c]):
                    slot = k
        frac = wp.clamp(r[2 * slot], zero, one)
    elif src == TIME_PLANE:
        p = planes[plane_ids[c]]
        pn = wp.vec3d(p[0], p[1], p[2])
        frac = wp.clamp((p[3] - wp.dot(pn, a0)) / wp.dot(pn, b0 - a0), zero, one)
    elif src != TIME_START:
        frac = detected[c]
    y0 = a0 + frac * (b0 - a0)
    y1 = a1 + frac * (b1 - a1)
    y2 = a2 + frac * (b2 - a2)
    y3 = a3 + frac * (b3 - a3)
    w = pair_weights(kind, y0, y1, y2, y3)
    offset = w[0] * y0 + w[1] * y1 + w[2] * y2 + w[3] * y3
    start_offset = w[0] * a0 + w[1] * a1 + w[2] * a2 + w[3] * a3
    distance = wp.length(offset)
    n = wp.vec3d(zero, zero, one)
    if kind == PAIR_VERTEX_PLANE:
        p = planes[plane_ids[c]]
        n = wp.vec3d(p[0], p[1], p[2])
        distance = wp.dot(n, a0) - p[3]

    # velocities (the normal's orientation): v- for the proximity pass; at t* for CCD hits (v-
    # before the owner's t*).
    # The velocity the impact reflects is the one at t*: the start velocity plus the forces'
    # change up to t* (v_start + (t*/h)(v- - v_start)); the change after t* is not reflected,
    # so a resting contact does not bounce on the gravity of each substep
    vrel = wp.vec3d(zero, zero, zero)
    vrel_at = wp.vec3d(zero, zero, zero)
    for k in range(4):
        vk = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd_minus, body_qd_minus)
        v0k = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd_start, body_qd_start)
        at_k = v0k + frac * (vk - v0k)
        if src != TIME_START:
            if frac * h >= vertex_time(q[k], vertex_type, vertex_owner, particle_time, body_time):
                vk = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd, body_qd)
                at_k = vk
        vrel = vrel + w[k] * vk
        vrel_at = vrel_at + w[k] * at_k

    if kind != PAIR_VERTEX_PLANE:
        scale = pair_scale(y0, y1, y2, y3)
        geo = pair_geometric_normal(kind, y0, y1, y2, y3)
        geo_ok = wp.length(geo) > wp.float64(1.0e-12) * scale * scale
        if src == TIME_START:
            touching = distance <= touching_relative * separation
            over_face = False
            if kind == PAIR_VERTEX_FACE and geo_ok:
                # a vertex touching a face's border edge may lie in the face's plane (two
                # boxes flush side by side): only its inside gives the face's normal then
                over_face = beside_flat_region(y0, y1, y2, y3, q, flat_keys, flat_opposites, flat_key_base, x0, x1, frac,
                                               touching)
            if over_face:
                # the vertex lies over the face or over flat neighbours of it: the face's normal
                # (the offset to a flat edge's closest point tilts with the vertex's sideways
                # position, a torque out of nothing)
                n = wp.normalize(geo)
                if touching:
                    # a rigid or static face is wound outwards, and the vertex lies outside
                    # whichever way it moves; a cloth face has no outside: against the motion
                    if vertex_type[q[1]] == VERTEX_PARTICLE and wp.dot(n, vrel) > zero:
                        n = -n
                elif wp.dot(n, offset) < zero:
                    n = -n
            elif not touching:
                n = offset / distance
            else:
                # touching beside the face, or edges touching: the offset has no direction.
                # Crossing edges touching inside both take their cross product; a vertex
                # beside the face, or edges touching at an end, touch a feature that another
                # pair holds with a defined normal (the face the vertex lies on, the end
                # vertex's faces): a zero normal keeps the pair out of the contact set
                n = wp.vec3d(zero, zero, zero)
                if kind == PAIR_EDGE_EDGE and geo_ok and w[1] > zero and w[1] < one and w[3] < zero and w[3] > -one:
                    n = wp.normalize(geo)
                    # from B to A: a rigid edge's lever arm points out of its body (convex
                    # surroundings), towards the other side; else against the motion
                    outward = (w[0] * lever[q[0]] + w[1] * lever[q[1]]) + (w[2] * lever[q[2]] + w[3] * lever[q[3]])
                    side = -wp.dot(n, outward)
                    if side < zero or (side == zero and wp.dot(n, vrel) > zero):
                        n = -n
        else:
            if geo_ok:
                n = wp.normalize(geo)
            elif wp.length(start_offset) > touching_relative * separation:
                n = wp.normalize(start_offset)
            else:
                # parallel edges touching at the start (two faces flush against each other):
                # no direction is defined, and the faces' vertex-face pairs hold the contact;
                # a zero normal never approaches, so the hit joins no contact set
                n = wp.vec3d(zero, zero, zero)
            if wp.dot(n, start_offset) < zero:
                n = -n
    vn = wp.dot(vrel_at, n)
    target = zero
    push = separation_rate * separation / h
    beyond = False
    if src == TIME_START:
        # a pair already in contact bounces only when it approaches faster than the
        # separation speed: slower approach is resting contact (a body settling, or kicked by
        # rounding), whose bounce would be a jitter and a kink of the motion at rest
        bounce = -vn > separation_rate * separation / h
        if bounce:
            target = -restitution * vn
        push = separation_rate * (separation - distance) / h
        beyond = distance > separation
        if beyond:
            # a pair a hair beyond the separation (kept so that resting contact does not drop
            # out on rounding): it may approach until it reaches the separation at the end
            push = (separation - distance) / h
            if not bounce:
                target = push
    else:
        target = -restitution * vn
    if split_push == 0:
        target = wp.max(target, push)
    elif not beyond:
        target = wp.max(target, zero)
    toi[c] = frac * h
    weights[c] = w
    normals[c] = n
    targets[c] = target
    pushes[c] = push


@wp.kernel
def merge_contacts_kernel(
    old_toi: wp.array(dtype=wp.float64),
    old_targets: wp.array(dtype=wp.float64),
    old_weights: wp.array(dtype=wp.vec4d),
    old_normals: wp.array(dtype=wp.vec3d),
    new_toi: wp.array(dtype=wp.float64),
    new_targets: wp.array(dtype=wp.float64),
    new_weights: wp.array(dtype=wp.vec4d),
    new_normals: wp.array(dtype=wp.vec3d),
    old_pushes: wp.array(dtype=wp.float64),
    new_pushes: wp.array(dtype=wp.float64),
    new_index: wp.array(dtype=wp.int32),
    keep_old_toi: wp.array(dtype=wp.int32),
    keep_old_target: wp.array(dtype=wp.int32),
    old_count: int,
    toi: wp.array(dtype=wp.float64),
    targets: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    pushes: wp.array(dtype=wp.float64),
):
    """Contact ``tid`` of the grown set: the old row (``new_index < 0``) or this round's
    detection (its weights and normal; the earlier time and the larger target, as decided; the
    larger push: a CCD hit on a proximity row restores the whole separation). ``old_count``: the
    rows the set had before."""
    c = wp.tid()
    k = new_index[c]
    if k < 0:
        toi[c] = old_toi[c]
        targets[c] = old_targets[c]
        weights[c] = old_weights[c]
        normals[c] = old_normals[c]
        pushes[c] = old_pushes[c]
        return
    if c < old_count:
        pushes[c] = wp.max(old_pushes[c], new_pushes[k])
    else:
        pushes[c] = new_pushes[k]
    weights[c] = new_weights[k]
    normals[c] = new_normals[k]
    if keep_old_toi[c] != 0:
        toi[c] = old_toi[c]
    else:
        toi[c] = new_toi[k]
    if keep_old_target[c] != 0:
        targets[c] = old_targets[c]
    else:
        targets[c] = new_targets[k]


@wp.func
def world_inverse_inertia(X: wp.transformd, inv_inertia: wp.mat33d) -> wp.mat33d:
    """``R I^-1 R^T`` of a body at pose ``X`` (rotation R) with body-frame inverse inertia
    ``inv_inertia``."""
    R = wp.quat_to_matrix(wp.transform_get_rotation(X))
    return R * inv_inertia * wp.transpose(R)


@wp.kernel
def contact_sides_kernel(
    pairs: wp.array(dtype=wp.vec4i),
    kinds: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
):
    """Per contact and side: the rigid body (or -1), its weight sum ``W`` and weighted lever arm
    ``rho = sum w_k r_k``: a unit impulse ``j`` at the contact moves the body by ``W j / m`` and
    ``I^-1 (rho x j)``. (Scalar accumulators: Warp's adjoint of in-place vector-component
    updates is not reliable.)"""
    c = wp.tid()
    q = pairs[c]
    w = weights[c]
    zero = wp.float64(0.0)
    split = 1
    if kinds[c] == PAIR_EDGE_EDGE:
        split = 2
    body_a = int(-1)
    body_b = int(-1)
    wa = zero
    wb = zero
    ra = wp.vec3d(zero, zero, zero)
    rb = wp.vec3d(zero, zero, zero)
    for k in range(4):
        v = q[k]
        if vertex_type[v] == VERTEX_BODY:
            if k < split:
                body_a = vertex_owner[v]
                wa = wa + w[k]
                ra = ra + w[k] * lever[v]
            else:
                body_b = vertex_owner[v]
                wb = wb + w[k]
                rb = rb + w[k] * lever[v]
    side_body[c] = wp.vec2i(body_a, body_b)
    side_weight[c] = wp.vec2d(wa, wb)
    rho_a[c] = ra
    rho_b[c] = rb


@wp.func
def contact_response(
    c: int,
    d: int,
    g: wp.vec3d,
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
) -> wp.vec3d:
    """Change of the relative velocity of contact ``c`` caused by an impulse ``g`` at contact
    ``d`` (the Delassus operator's 3x3 block times ``g``)."""
    zero = wp.float64(0.0)
    out = wp.vec3d(zero, zero, zero)
    qc = pairs[c]
    qd = pairs[d]
    wc = weights[c]
    wd = weights[d]
    for k in range(4):
        if vertex_type[qc[k]] == VERTEX_PARTICLE:
            for l in range(4):
                if vertex_type[qd[l]] == VERTEX_PARTICLE and vertex_owner[qc[k]] == vertex_owner[qd[l]]:
                    out = out + (wc[k] * wd[l] * particle_inv_mass[vertex_owner[qc[k]]]) * g
    bc = side_body[c]
    bd = side_body[d]
    wsc = side_weight[c]
    wsd = side_weight[d]
    for s in range(2):
        body = bc[s]
        if body >= 0:
            rc = rho_a[c]
            if s == 1:
                rc = rho_b[c]
            for t in range(2):
                if bd[t] == body:
                    rd = rho_a[d]
                    if t == 1:
                        rd = rho_b[d]
                    out = out + (wsc[s] * wsd[t] * body_inv_mass[body]) * g
                    out = out - wp.cross(rc, body_inv_inertia[body] * wp.cross(rd, g))
    return out


@wp.kernel
def delassus_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    regularization: wp.float64,
    matrix: wp.array2d(dtype=wp.float64),
):
    """Entry (r, u) of the active set's normal system: the normal relative velocity of active
    contact ``r`` per unit normal impulse at active contact ``u`` (``n_r . K_ru n_u``); the
    diagonal is scaled by ``1 + regularization`` so that redundant contacts (a singular matrix)
    still give a unique, bounded solution."""
    r, u = wp.tid()
    c = unknown_contact[r]
    d = unknown_contact[u]
    resp = contact_response(
        c, d, normals[d], pairs, weights, vertex_type, vertex_owner, side_body, side_weight, rho_a, rho_b,
        particle_inv_mass, body_inv_mass, body_inv_inertia,
    )
    value = wp.dot(normals[c], resp)
    if r == u:
        value = value * (wp.float64(1.0) + regularization)
    matrix[r, u] = value


@wp.func
def unit_perpendicular(n: wp.vec3d) -> wp.vec3d:
    """A unit vector perpendicular to the unit vector ``n`` (crossed with the axis least aligned
    with it; the choice changes no basis-independent result)."""
    ax = wp.abs(n[0])
    ay = wp.abs(n[1])
    az = wp.abs(n[2])
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    axis = wp.vec3d(one, zero, zero)
    if ay <= ax and ay <= az:
        axis = wp.vec3d(zero, one, zero)
    elif az <= ax and az <= ay:
        axis = wp.vec3d(zero, zero, one)
    return wp.normalize(wp.cross(n, axis))


@wp.func
def relative_velocity(
    c: int,
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
) -> wp.vec3d:
    q = pairs[c]
    w = weights[c]
    vrel = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for k in range(4):
        vrel = vrel + w[k] * vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd, body_qd)
    return vrel


@wp.kernel
def contact_rhs_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    rhs: wp.array(dtype=wp.float64),
):
    """Right-hand side of equation ``tid``: target minus current normal relative velocity."""
    r = wp.tid()
    c = unknown_contact[r]
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    rhs[r] = targets[c] - wp.dot(normals[c], vrel)


@wp.kernel
def push_rhs_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    pushes: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    rhs: wp.array(dtype=wp.float64),
):
    """Right-hand side of push equation ``tid``: the part of the contact's push (the separation
    speed, :func:`contact_geometry_kernel`) that its normal velocity after the impulses does not
    already give, ``max(push - v_n, 0)``. The push moves positions only: it restores the
    separation without a velocity that outlives the substep (an inelastic impact rebounds
    with none)."""
    r = wp.tid()
    c = unknown_contact[r]
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    rhs[r] = wp.max(pushes[c] - wp.dot(normals[c], vrel), wp.float64(0.0))


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


@wp.func
def lu_factor(work: wp.array2d(dtype=wp.float64), pivots: wp.array(dtype=wp.int32)):
    """In-place LU factorisation of the square ``work`` by Gaussian elimination with partial
    pivoting (whole rows swapped, as LAPACK's getrf): the unit lower factor's multipliers below
    the diagonal, the upper factor on and above it, the row swapped with row ``k`` at step ``k``
    in ``pivots[k]``. A zero column leaves a zero pivot (its unknown is set to 0 by
    :func:`lu_substitute`)."""
    n = work.shape[0]
    for k in range(n):
        p = k
        best = wp.abs(work[k, k])
        for i in range(k + 1, n):
            if wp.abs(work[i, k]) > best:
                best = wp.abs(work[i, k])
                p = i
        pivots[k] = p
        if p != k:
            for j in range(n):
                tmp = work[k, j]
                work[k, j] = work[p, j]
                work[p, j] = tmp
        pivot = work[k, k]
        if pivot != wp.float64(0.0):
            for i in range(k + 1, n):
                f = work[i, k] / pivot
                work[i, k] = f
                if f != wp.float64(0.0):
                    for j in range(k + 1, n):
                        work[i, j] = work[i, j] - f * work[k, j]


@wp.func
def lu_substitute(work: wp.array2d(dtype=wp.float64), pivots: wp.array(dtype=wp.int32),
                  solution: wp.array(dtype=wp.float64)):
    """``solution`` (holding the right-hand side) overwritten by the solution of the system
    factorised by :func:`lu_factor`: the row swaps, then forward and back substitution."""
    n = work.shape[0]
    for k in range(n):
        p = pivots[k]
        if p != k:
            tmp = solution[k]
            solution[k] = solution[p]
            solution[p] = tmp
    for i in range(n):
        s = solution[i]
        for j in range(i):
            s = s - work[i, j] * solution[j]
        solution[i] = s
    for kk in range(n):
        k = n - 1 - kk
        s = solution[k]
        for j in range(k + 1, n):
            s = s - work[k, j] * solution[j]
        if work[k, k] != wp.float64(0.0):
            solution[k] = s / work[k, k]
        else:
            solution[k] = wp.float64(0.0)


@wp.kernel(enable_backward=False)
def lu_factor_kernel(
    matrix: wp.array2d(dtype=wp.float64),
    transpose: int,
    work: wp.array2d(dtype=wp.float64),
    pivots: wp.array(dtype=wp.int32),
):
    """:func:`lu_factor` of ``matrix`` (of its transpose when ``transpose``) into ``work`` and
    ``pivots``, launched with ``dim=1``."""
    n = matrix.shape[0]
    for i in range(n):
        for j in range(n):
            if transpose != 0:
                work[i, j] = matrix[j, i]
            else:
                work[i, j] = matrix[i, j]
    lu_factor(work, pivots)


@wp.kernel(enable_backward=False)
def lu_solve_kernel(
    work: wp.array2d(dtype=wp.float64),
    pivots: wp.array(dtype=wp.int32),
    rhs: wp.array(dtype=wp.float64),
    solution: wp.array(dtype=wp.float64),
):
    """``solution = A^-1 rhs`` from the factors of :func:`lu_factor_kernel`, launched with
    ``dim=1``. Not differentiated by the tape: the caller records the implicit adjoint (a solve
    with the transposed matrix) instead."""
    for i in range(rhs.shape[0]):
        solution[i] = rhs[i]
    lu_substitute(work, pivots, solution)


@wp.kernel
def solve_adjoint_kernel(
    adjoint: wp.array(dtype=wp.float64),
    solution: wp.array(dtype=wp.float64),
    matrix_grad: wp.array2d(dtype=wp.float64),
    rhs_grad: wp.array(dtype=wp.float64),
):
    """Implicit adjoint of ``x = A^-1 b`` given ``mu = A^-T x_bar``: ``b_bar += mu``,
    ``A_bar -= mu x^T`` (launched over (n, n))."""
    r, u = wp.tid()
    matrix_grad[r, u] = matrix_grad[r, u] - adjoint[r] * solution[u]
    if u == 0:
        rhs_grad[r] = rhs_grad[r] + adjoint[r]


@wp.func
def contact_axis(n: wp.vec3d, axis: int) -> wp.vec3d:
    """Axis ``axis`` of a contact's frame: the normal ``n`` (0) and the tangents
    :func:`unit_perpendicular` (1) and ``n x t1`` (2)."""
    if axis == 0:
        return n
    t1 = unit_perpendicular(n)
    if axis == 1:
        return t1
    return wp.cross(n, t1)


@wp.kernel
def sticking_delassus_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    regularization: wp.float64,
    tangent_weight: wp.array(dtype=wp.float64),
    slip: wp.array(dtype=wp.vec3d),
    friction: wp.float64,
    matrix: wp.array2d(dtype=wp.float64),
):
    """Entry (r, u) of the frictional system: three unknowns per active contact (the impulse
    along its normal and its two tangents, :func:`contact_axis`).

    A sticking contact (``slip[c]`` zero) asks for its whole relative velocity: its rows are
    ``e_r . K_cd e_u``, the diagonal scaled by ``1 + regularization`` as in
    :func:`delassus_kernel`, the tangential ones by ``1 + regularization tangent_weight[c]``.
    Redundant contacts (a face on four corners) leave the split of the friction among them free;
    the regularisation picks the split of least weighted norm, and weights inverse to the normal
    loads (:func:`tangent_weights_kernel`) make it the split in proportion to them, which stays
    in every contact's cone when the total friction stays in the total cone.

    A sliding contact (``slip[c]`` the unit direction its friction opposes) keeps its normal
    row; its tangential rows say that its friction is Coulomb's, ``j_t = -mu j_n s``:
    ``j_a + mu (s . t_a) j_n = 0`` per tangent ``t_a``, scaled by its own tangential response
    ``t_a . K_cc t_a`` so that the rows are commensurate with the velocity rows."""
    r, u = wp.tid()
    c = unknown_contact[r // 3]
    d = unknown_contact[u // 3]
    axis = r % 3
    s = slip[c]
    zero = wp.float64(0.0)
    if axis != 0 and wp.length_sq(s) > zero:
        value = zero
        if r // 3 == u // 3:
            t = contact_axis(normals[c], axis)
            scale = wp.dot(t, contact_response(
                c, c, t, pairs, weights, vertex_type, vertex_owner, side_body, side_weight, rho_a, rho_b,
                particle_inv_mass, body_inv_mass, body_inv_inertia,
            ))
            if u % 3 == axis:
                value = scale
            elif u % 3 == 0:
                value = scale * friction * wp.dot(s, t)
        matrix[r, u] = value
        return
    resp = contact_response(
        c, d, contact_axis(normals[d], u % 3), pairs, weights, vertex_type, vertex_owner, side_body, side_weight,
        rho_a, rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia,
    )
    value = wp.dot(contact_axis(normals[c], axis), resp)
    if r == u:
        scale = regularization
        if axis != 0:
            scale = regularization * tangent_weight[c]
        value = value * (wp.float64(1.0) + scale)
    matrix[r, u] = value


@wp.kernel
def slip_directions_kernel(
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    directions: wp.array(dtype=wp.vec3d),
):
    """Unit slip direction ``v_t / |v_t|`` of contact ``tid`` (zero where it does not slip)."""
    c = wp.tid()
    n = normals[c]
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    vt = vrel - wp.dot(vrel, n) * n
    length = wp.length(vt)
    zero = wp.float64(0.0)
    if length > zero:
        directions[c] = vt / length
    else:
        directions[c] = wp.vec3d(zero, zero, zero)


@wp.kernel
def sliding_delassus_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    directions: wp.array(dtype=wp.vec3d),
    friction: wp.float64,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    regularization: wp.float64,
    matrix: wp.array2d(dtype=wp.float64),
):
    """Entry (r, u) of the sliding system: the normal relative velocity of active contact ``r``
    per unit normal impulse at active contact ``u`` that carries its Coulomb friction along,
    the impulse ``n - mu s`` (``s`` its slip direction): ``n_r . K_ru (n_u - mu s_u)``; the
    diagonal scaled as in :func:`delassus_kernel`."""
    r, u = wp.tid()
    c = unknown_contact[r]
    d = unknown_contact[u]
    resp = contact_response(
        c, d, normals[d] - friction * directions[d], pairs, weights, vertex_type, vertex_owner, side_body,
        side_weight, rho_a, rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia,
    )
    value = wp.dot(normals[c], resp)
    if r == u:
        value = value * (wp.float64(1.0) + regularization)
    matrix[r, u] = value


@wp.kernel
def sliding_impulses_kernel(
    contact_unknown: wp.array(dtype=wp.int32),
    solution: wp.array(dtype=wp.float64),
    normals: wp.array(dtype=wp.vec3d),
    directions: wp.array(dtype=wp.vec3d),
    friction: wp.float64,
    impulses: wp.array(dtype=wp.vec3d),
):
    """Impulse ``j_n (n - mu s)`` of contact ``tid`` from the sliding system's solution."""
    c = wp.tid()
    u = contact_unknown[c]
    zero = wp.float64(0.0)
    j = wp.vec3d(zero, zero, zero)
    if u >= 0:
        j = solution[u] * (normals[c] - friction * directions[c])
    impulses[c] = j


@wp.func
def stops_sliding(j: wp.vec3d, n: wp.vec3d, vrel: wp.vec3d, s: wp.vec3d, reversal: wp.float64) -> bool:
    """Whether a contact sliding along ``s`` with impulse ``j`` (normal ``n``) sticks instead:
    it pulls (``j . n < 0``: its friction ``-mu j_n s`` would push along the slip), or its slip
    after the solve (relative velocity ``vrel``) turns back against ``s`` (``v_t . s <
    -reversal``)."""
    vt = vrel - wp.dot(vrel, n) * n
    return wp.dot(j, n) < wp.float64(0.0) or wp.dot(vt, s) < -reversal


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


@wp.kernel
def sticking_rhs_kernel(
    unknown_contact: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    slip: wp.array(dtype=wp.vec3d),
    rhs: wp.array(dtype=wp.float64),
):
    """Right-hand side of frictional equation ``tid`` (:func:`sticking_delassus_kernel`): the
    target (the normal one, 0 along the tangents) minus the current relative velocity along the
    axis; 0 for a sliding contact's tangential rows (Coulomb's law holds for the impulses of
    every pass, so for their sum)."""
    r = wp.tid()
    c = unknown_contact[r // 3]
    axis = r % 3
    if axis != 0 and wp.length_sq(slip[c]) > wp.float64(0.0):
        rhs[r] = wp.float64(0.0)
        return
    vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
    target = wp.float64(0.0)
    if axis == 0:
        target = targets[c]
    rhs[r] = target - wp.dot(contact_axis(normals[c], axis), vrel)


@wp.kernel
def sticking_impulses_kernel(
    contact_unknown: wp.array(dtype=wp.int32),
    solution: wp.array(dtype=wp.float64),
    normals: wp.array(dtype=wp.vec3d),
    impulses: wp.array(dtype=wp.vec3d),
):
    """Impulse of contact ``tid`` from the sticking system's solution (zero when inactive)."""
    c = wp.tid()
    u = contact_unknown[c]
    zero = wp.float64(0.0)
    j = wp.vec3d(zero, zero, zero)
    if u >= 0:
        n = normals[c]
        j = solution[3 * u] * n + solution[3 * u + 1] * contact_axis(n, 1) + solution[3 * u + 2] * contact_axis(n, 2)
    impulses[c] = j


@wp.kernel
def normal_part_kernel(impulses: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
                       out: wp.array(dtype=wp.vec3d)):
    """The normal part ``(j . n) n`` of each contact's impulse."""
    c = wp.tid()
    n = normals[c]
    out[c] = wp.dot(impulses[c], n) * n


SLIDING_HALF_STEP_LIMIT = wp.constant(0.25)
"""Sliding friction counts as a force over the substep (:func:`sliding_friction_half_kernel`)
while its change of the contact's relative velocity is at most this times the separation speed
``rate delta / h`` (fully; tapered to nothing at twice it): its half step then moves the
contact by at most ``rate delta / 8``. A box sliding on the ground at 8 substeps changes it by
half of that bound; at 4 substeps by more, and the slide keeps its first-order error there."""


@wp.kernel
def sliding_friction_half_kernel(
    impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    slip: wp.array(dtype=wp.vec3d),
    toi: wp.array(dtype=wp.float64),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    particle_qd_start: wp.array(dtype=wp.vec3d),
    body_qd_start: wp.array(dtype=wp.spatial_vectord),
    resting_speed: wp.float64,
    out: wp.array(dtype=wp.vec3d),
):
    """Minus half the friction part ``-(j - (j . n) n) / 2`` of each sliding contact's impulse
    (``slip`` non-zero) on resting contact between rigid bodies and static geometry, into the
    zeroed ``out``; zero for the others.

    Sliding friction on resting contact is a constant force over the substep, so half of its
    velocity change belongs in the positions: moved by the velocities after it, they would lag
    the exact ``h v0 - h^2 mu g / 2`` by ``h^2 mu g / 2`` each substep (a first-order error of
    the stopping distance). Resting: held from the substep's start (``t* = 0``), approaching at
    the start no faster than ``resting_speed`` (the separation speed ``rate delta / h`` below
    which :func:`contact_geometry_kernel` does not bounce), and the friction's own change of
    the contact's relative velocity at most :data:`SLIDING_HALF_STEP_LIMIT` times that speed:
    an impact's friction, or a violent one's, is an impulse. The weight tapers to zero from
    half the approach bound to the bound, and from the change bound to twice it, so that no
    position jumps where a contact crosses one. Both bounds scale with ``delta / h``: with a
    thin separation or a long substep a slide is first order again (Gauss-Seidel's too).

    Contacts with a cloth particle keep the impulse form: their friction is light and jerky
    rather than a steady slide, and with the half step a ball thrown into the hanging cloth
    (``cloth_rigid``) moved 4e-4 m apart under a change of scale (1e-9 m without it), and at
    200 m/s it steered the cloth into a contact set of 1,100 unknowns."""
    c = wp.tid()
    s = slip[c]
    q = pairs[c]
    rigid = True
    for k in range(4):
        if vertex_type[q[k]] == VERTEX_PARTICLE:
            rigid = False
    if rigid and toi[c] == wp.float64(0.0) and wp.dot(s, s) > wp.float64(0.0):
        n = normals[c]
        v0 = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd_start, body_qd_start)
        j = impulses[c]
        friction = j - wp.dot(j, n) * n
        change = contact_response(c, c, friction, pairs, weights, vertex_type, vertex_owner, side_body, side_weight,
                                  rho_a, rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia)
        # full below the limits, tapered to zero at twice them (no jump of the positions where a
        # contact crosses one)
        limit = wp.float64(SLIDING_HALF_STEP_LIMIT) * resting_speed
        by_change = wp.clamp((wp.float64(2.0) * limit - wp.length(change)) / limit, wp.float64(0.0), wp.float64(1.0))
        by_approach = wp.clamp((resting_speed + wp.dot(n, v0)) / (wp.float64(0.5) * resting_speed), wp.float64(0.0),
                               wp.float64(1.0))
        out[c] = (wp.float64(-0.5) * by_change * by_approach) * friction


@wp.func
def beyond_cone(j: wp.vec3d, n: wp.vec3d, friction: wp.float64) -> bool:
    """Whether impulse ``j`` at a contact of normal ``n`` lies outside the friction cone
    ``|j_t| <= mu j . n`` (a pulling impulse, ``j . n < 0``, always does)."""
    jn = wp.dot(j, n)
    return wp.length(j - jn * n) > friction * jn


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


SLIP_STICK = wp.constant(0)
SLIP_KEEP = wp.constant(1)
SLIP_START = wp.constant(2)


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


@wp.kernel
def slip_directions_from_impulses_kernel(
    codes: wp.array(dtype=wp.int32),
    impulses: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    slip: wp.array(dtype=wp.vec3d),
    slip_out: wp.array(dtype=wp.vec3d),
):
    """The friction directions of the next frictional solve (taped: they depend smoothly on the
    state through the trial's impulses): zero for a sticking contact, the same ``s`` for one
    that keeps sliding, and ``-j_t / |j_t|`` for one that starts (its friction at the cone's
    limit, in the direction it asked for); ``codes`` from :func:`slip_update_kernel`."""
    c = wp.tid()
    zero = wp.float64(0.0)
    code = codes[c]
    if code == SLIP_KEEP:
        slip_out[c] = slip[c]
    elif code == SLIP_START:
        n = normals[c]
        j = impulses[c]
        jt = j - wp.dot(j, n) * n
        slip_out[c] = -jt / wp.length(jt)
    else:
        slip_out[c] = wp.vec3d(zero, zero, zero)


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


@wp.kernel
def add_vectors_kernel(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """``out = a + b`` (the normal impulses of a solve and of its refinement)."""
    i = wp.tid()
    out[i] = a[i] + b[i]


@wp.kernel
def friction_impulses_kernel(
    normal_impulses: wp.array(dtype=wp.vec3d),
    share: wp.array(dtype=wp.float64),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    friction: wp.float64,
    impulses: wp.array(dtype=wp.vec3d),
):
    """Coulomb friction impulse of contact ``tid`` after its normal impulse ``j_n`` (> 0).

    The stopping impulse ``j_s = -share T (T^T K T)^-1 T^T v_t`` cancels the whole tangential
    relative velocity ``v_t`` (``T`` an orthonormal tangent basis, ``K`` the contact's 3x3
    Delassus block; ``share`` is one over the most active contacts any of its particles or bodies
    takes part in, so that stopping impulses applied together do not over-correct a shared
    vertex). Within the cone ``|j_s| <= mu j_n`` the contact sticks and gets ``j_s``; outside it
    slides and gets ``-mu j_n v_t / |v_t|`` (there ``|v_t| > 0``: a vanishing ``v_t`` gives a
    vanishing ``j_s``). The branch is taken here, per evaluation. ``j_s`` is linear in ``v_t``
    (the same for any basis ``T``), so the sticking impulse is smooth at ``v_t = 0`` (a body at
    rest): an effective mass along ``v_t / |v_t|`` would depend on the direction of a vanishing
    vector, and its derivative there on rounding noise. Where ``K`` is anisotropic (a rigid
    body's lever arm) ``j_s`` is not parallel to ``-v_t``, so the impulse changes direction, a
    jump, where a contact switches from sticking to sliding (a decision, like any contact's)."""
    c = wp.tid()
    zero = wp.float64(0.0)
    n = normals[c]
    jn = wp.dot(normal_impulses[c], n)  # signed: a pulling contact gets no friction
    impulses[c] = wp.vec3d(zero, zero, zero)
    if jn > zero:
        vrel = relative_velocity(c, pairs, weights, vertex_type, vertex_owner, lever, particle_qd, body_qd)
        t1 = unit_perpendicular(n)
        t2 = wp.cross(n, t1)
        k1 = contact_response(c, c, t1, pairs, weights, vertex_type, vertex_owner, side_body, side_weight, rho_a,
                              rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia)
        k2 = contact_response(c, c, t2, pairs, weights, vertex_type, vertex_owner, side_body, side_weight, rho_a,
                              rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia)
        a11 = wp.dot(t1, k1)
        a22 = wp.dot(t2, k2)
        a12 = wp.float64(0.5) * (wp.dot(t1, k2) + wp.dot(t2, k1))
        trace = a11 + a22
        if trace > zero:
            b1 = wp.dot(t1, vrel)
            b2 = wp.dot(t2, vrel)
            det = a11 * a22 - a12 * a12
            if det <= wp.float64(1e-12) * trace * trace:
                # (nearly) rank-deficient block: regularised by 1e-6 of its trace, a bounded
                # impulse that never overshoots the stop along the stiff direction
                a11 = a11 + wp.float64(1e-6) * trace
                a22 = a22 + wp.float64(1e-6) * trace
                det = a11 * a22 - a12 * a12
            x1 = (a22 * b1 - a12 * b2) / det
            x2 = (a11 * b2 - a12 * b1) / det
            stop = -share[c] * (x1 * t1 + x2 * t2)
            limit = friction * jn
            if wp.length(stop) <= limit:
                impulses[c] = stop
            else:
                # Coulomb: sliding friction opposes the sliding velocity (for an anisotropic K
                # the stopping impulse does not, and its projection on the cone would brake a
                # sliding body by less than mu j_n)
                vt = b1 * t1 + b2 * t2  # the slip the stick test saw (non-zero: j_s is not)
                impulses[c] = (-limit / wp.length(vt)) * vt


@wp.kernel
def contact_velocities_kernel(
    contact_count: int,
    particle_count: int,
    from_solution: int,
    contact_unknown: wp.array(dtype=wp.int32),
    solution: wp.array(dtype=wp.float64),
    normals: wp.array(dtype=wp.vec3d),
    impulses: wp.array(dtype=wp.vec3d),
    pairs: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    side_body: wp.array(dtype=wp.vec2i),
    side_weight: wp.array(dtype=wp.vec2d),
    rho_a: wp.array(dtype=wp.vec3d),
    rho_b: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    normal_impulses: wp.array(dtype=wp.vec3d),
    particle_qd_out: wp.array(dtype=wp.vec3d),
    body_qd_out: wp.array(dtype=wp.spatial_vectord),
):
    """Velocities after contact impulses, in one launch over ``C + P + B`` threads into the
    zeroed ``particle_qd_out`` (P,) and ``body_qd_out`` (B,) (every term is an atomic add, so no
    thread waits for another): the first ``C`` (``contact_count``) threads add their contact's
    changes, ``w_k j / m`` to its particles and ``W j / m``, ``I^-1 (rho x j)`` to its sides'
    bodies, the next ``P`` / ``B`` the velocities before (on the CPU, where threads run in
    order, the changes are summed first and the result is ``v + sum dv``). The impulse is
    ``impulses[c]``, or with ``from_solution`` the solved normal impulse
    ``solution[contact_unknown[c]] normals[c]`` (zero for an inactive contact,
    ``contact_unknown < 0``), then also written to
    ``normal_impulses[c]``."""
    i = wp.tid()
    if i >= contact_count:
        if i < contact_count + particle_count:
            wp.atomic_add(particle_qd_out, i - contact_count, particle_qd[i - contact_count])
        else:
            wp.atomic_add(body_qd_out, i - contact_count - particle_count, body_qd[i - contact_count - particle_count])
        return
    c = i
    j = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if from_solution != 0:
        u = contact_unknown[c]
        if u >= 0:
            j = solution[u] * normals[c]
        normal_impulses[c] = j
    else:
        j = impulses[c]
    q = pairs[c]
    w = weights[c]
    for k in range(4):
        if vertex_type[q[k]] == VERTEX_PARTICLE:
            o = vertex_owner[q[k]]
            wp.atomic_add(particle_qd_out, o, (w[k] * particle_inv_mass[o]) * j)
    b = side_body[c]
    ws = side_weight[c]
    for side in range(2):
        if b[side] >= 0:
            rho = rho_a[c]
            if side == 1:
                rho = rho_b[c]
            dv = (ws[side] * body_inv_mass[b[side]]) * j
            dw = body_inv_inertia[b[side]] * wp.cross(rho, j)
            wp.atomic_add(body_qd_out, b[side], wp.spatial_vectord(dw[0], dw[1], dw[2], dv[0], dv[1], dv[2]))


@wp.func
def quat_turn(q: wp.quatd, omega: wp.vec3d, duration: wp.float64) -> wp.quatd:
    """``q`` turned by the world angular velocity ``omega`` [rad/s] for ``duration`` [s]: the
    exact rotation (axis-angle), renormalised; smooth at ``omega = 0`` (series of sin(x/2)/x)."""
    th2 = wp.dot(omega, omega) * duration * duration
    s = wp.float64(0.5) - th2 / wp.float64(48.0)
    c = wp.float64(1.0) - th2 / wp.float64(8.0) + th2 * th2 / wp.float64(384.0)
    if th2 > wp.float64(1.0e-8):
        th = wp.sqrt(th2)
        s = wp.sin(wp.float64(0.5) * th) / th
        c = wp.cos(wp.float64(0.5) * th)
    a = omega * (duration * s)
    return wp.normalize(wp.quatd(a[0], a[1], a[2], c) * q)


@wp.func
def time_of_impact_pose(X: wp.transformd, v_minus: wp.spatial_vectord, v_plus: wp.spatial_vectord, ts: wp.float64,
                        h: wp.float64):
    """The same for a body pose: the centre of mass as a particle, the orientation turned by
    ``w-`` for ``t*`` and by ``w+`` for ``h - t*`` (twists angular, linear)."""
    p = time_of_impact_position(wp.transform_get_translation(X), wp.spatial_bottom(v_minus), wp.spatial_bottom(v_plus),
                                ts, h)
    r = quat_turn(quat_turn(wp.transform_get_rotation(X), wp.spatial_top(v_minus), ts), wp.spatial_top(v_plus), h - ts)
    return wp.transformd(p, r)


@wp.kernel
def time_of_impact_kernel(
    particle_count: int,
    x0: wp.array(dtype=wp.vec3d),
    x_pred: wp.array(dtype=wp.vec3d),
    particle_v_minus: wp.array(dtype=wp.vec3d),
    particle_v_plus: wp.array(dtype=wp.vec3d),
    particle_v_moving: wp.array(dtype=wp.vec3d),
    particle_contact: wp.array(dtype=wp.int32),
    q0: wp.array(dtype=wp.transformd),
    q_pred: wp.array(dtype=wp.transformd),
    body_v_minus: wp.array(dtype=wp.spatial_vectord),
    body_v_plus: wp.array(dtype=wp.spatial_vectord),
    body_v_moving: wp.array(dtype=wp.spatial_vectord),
    body_contact: wp.array(dtype=wp.int32),
    toi: wp.array(dtype=wp.float64),
    h: wp.float64,
    x1: wp.array(dtype=wp.vec3d),
    q1: wp.array(dtype=wp.transformd),
):
    """Time-of-impact integration of particle ``tid`` (first ``particle_count`` threads;
    :func:`time_of_impact_position`) and of body ``tid - particle_count``
    (:func:`time_of_impact_pose`) with the ``t*`` of its earliest contact row (-1: no contact,
    the prediction stays; -2: impact zone, its rigid motion from ``t* = 0``), plus the push:
    the moving velocities' excess over ``v+`` (``v_moving - v+``, the separation restored at
    the position level) as a displacement over the whole substep ``h``, whatever ``t*`` is (a
    contact found at the end of the substep still ends separated: ending it touching would
    leave the next substep no side to push it to)."""
    i = wp.tid()
    if i < particle_count:
        k = particle_contact[i]
        if k == -1:
            x1[i] = x_pred[i]
        elif k == -2:
            x1[i] = x0[i] + h * particle_v_moving[i]
        else:
            x1[i] = time_of_impact_position(x0[i], particle_v_minus[i], particle_v_plus[i], toi[k], h) + h * (
                particle_v_moving[i] - particle_v_plus[i])
        return
    b = i - particle_count
    kb = body_contact[b]
    if kb == -1:
        q1[b] = q_pred[b]
        return
    ts = wp.float64(0.0)
    if kb >= 0:
        ts = toi[kb]
    pose = time_of_impact_pose(q0[b], body_v_minus[b], body_v_plus[b], ts, h)
    push = body_v_moving[b] - body_v_plus[b]
    q1[b] = wp.transformd(wp.transform_get_translation(pose) + h * wp.spatial_bottom(push),
                          quat_turn(wp.transform_get_rotation(pose), wp.spatial_top(push), h))


@wp.func
def planned_position(x0: wp.vec3d, x_pred: wp.vec3d, v_minus: wp.vec3d, v_plus: wp.vec3d, ts: wp.float64,
                     h: wp.float64) -> wp.vec3d:
    """The Gauss-Seidel response's plan (not taped) of one particle: :func:`time_of_impact_position`
    at its earliest contact time ``ts`` [s] (inf: none, the prediction ``x_pred`` stays; 0 for
    an impact zone's)."""
    if wp.isinf(ts):
        return x_pred
    return time_of_impact_position(x0, v_minus, v_plus, ts, h)


@wp.func
def planned_pose(q0: wp.transformd, q_pred: wp.transformd, v_minus: wp.spatial_vectord, v_plus: wp.spatial_vectord,
                 ts: wp.float64, h: wp.float64) -> wp.transformd:
    """The same for a body's pose (:func:`time_of_impact_pose`)."""
    if wp.isinf(ts):
        return q_pred
    return time_of_impact_pose(q0, v_minus, v_plus, ts, h)


@wp.kernel
def planned_substep_kernel(
    particle_q0: wp.array(dtype=wp.vec3d),
    particle_q_pred: wp.array(dtype=wp.vec3d),
    particle_v_minus: wp.array(dtype=wp.vec3d),
    particle_v_plus: wp.array(dtype=wp.vec3d),
    particle_time: wp.array(dtype=wp.float64),
    body_q0: wp.array(dtype=wp.transformd),
    body_q_pred: wp.array(dtype=wp.transformd),
    body_v_minus: wp.array(dtype=wp.spatial_vectord),
    body_v_plus: wp.array(dtype=wp.spatial_vectord),
    body_time: wp.array(dtype=wp.float64),
    h: wp.float64,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    particle_count: int,
    body_count: int,
    particle_q1: wp.array(dtype=wp.vec3d),
    body_q1: wp.array(dtype=wp.transformd),
    x1: wp.array(dtype=wp.vec3d),
):
    """The Gauss-Seidel response's plan in one launch: the particles' ends
    (:func:`planned_position`) in the first ``P`` threads, the bodies' (:func:`planned_pose`)
    in the next ``B``, then the vertices posed at those ends (:func:`pose_vertices_kernel`), each
    vertex thread working out its owner's end itself (no thread waits for another's).
    Launched over ``P + B + vertices`` threads (``P``, ``B``: ``particle_count``,
    ``body_count``), or over ``P + B`` for the ends alone (the caller then poses the vertices
    from them, :func:`pose_vertices_kernel`: bodies with many vertices would otherwise
    integrate their pose once per vertex)."""
    i = wp.tid()
    P = particle_count
    B = body_count
    if i < P:
        particle_q1[i] = planned_position(particle_q0[i], particle_q_pred[i], particle_v_minus[i], particle_v_plus[i],
                                          particle_time[i], h)
        return
    if i < P + B:
        b = i - P
        body_q1[b] = planned_pose(body_q0[b], body_q_pred[b], body_v_minus[b], body_v_plus[b], body_time[b], h)
        return
    v = i - P - B
    kind = vertex_type[v]
    o = vertex_owner[v]
    if kind == VERTEX_PARTICLE:
        x1[v] = planned_position(particle_q0[o], particle_q_pred[o], particle_v_minus[o], particle_v_plus[o],
                                 particle_time[o], h)
    elif kind == VERTEX_BODY:
        x1[v] = body_point(planned_pose(body_q0[o], body_q_pred[o], body_v_minus[o], body_v_plus[o], body_time[o], h),
                           local[v])
    else:
        x1[v] = local[v]


# ---------------------------------------------------------------------------- impact zones
# A particle's / body's zone: 0.. a free zone, ZONE_NONE not in a zone, ZONE_WORLD in a zone
# that touches a static vertex or a pinned particle (at rest).
@wp.kernel
def zone_select_kernel(
    particle_count: int,
    zone_p: wp.array(dtype=wp.int32),
    zone_b: wp.array(dtype=wp.int32),
    moving_p: wp.array(dtype=wp.vec3d),
    moving_b: wp.array(dtype=wp.spatial_vectord),
    zone_vp: wp.array(dtype=wp.vec3d),
    zone_vb: wp.array(dtype=wp.spatial_vectord),
    out_p: wp.array(dtype=wp.vec3d),
    out_b: wp.array(dtype=wp.spatial_vectord),
):
    """The velocities that move the positions after the fail-safe (the first ``particle_count``
    threads particles, then bodies): an impact zone's member moves with its zone's rigid motion
    ``zone_v*``, anything else with its own, push included (``moving_*``)."""
    i = wp.tid()
    if i < particle_count:
        if zone_p[i] != 0:
            out_p[i] = zone_vp[i]
        else:
            out_p[i] = moving_p[i]
    else:
        b = i - particle_count
        if zone_b[b] != 0:
            out_b[b] = zone_vb[b]
        else:
            out_b[b] = moving_b[b]


ZONE_NONE = wp.constant(-1)
ZONE_WORLD = wp.constant(-2)
# rank cut-off of a zone's inertia (relative to its trace): looser than numpy's pinv (1e-15),
# so that rounding in the determinant does not decide the rank of collinear zones
PINV_RCOND = wp.constant(wp.float64(1.0e-12))


@wp.func
def zone_member_mass(inv_mass: wp.float64) -> wp.float64:
    """A particle's mass from its inverse mass (0 for a pinned particle, never a zone member)."""
    if inv_mass > wp.float64(0.0):
        return wp.float64(1.0) / inv_mass
    return wp.float64(0.0)


@wp.func
def world_inertia(q: wp.transformd, inertia: wp.mat33d) -> wp.mat33d:
    """``R I R^T``: a body's inertia about its centre of mass in world axes at pose ``q``."""
    R = wp.quat_to_matrix(wp.transform_get_rotation(q))
    return R * inertia * wp.transpose(R)


@wp.func
def symmetric_pinv_apply(A: wp.mat33d, b: wp.vec3d) -> wp.vec3d:
    """``pinv(A) b`` for a symmetric positive semi-definite ``A`` (a zone's inertia tensor).

    Rank 3: ``A^-1 b``. Rank 2 (collinear particles; null vector ``n`` from the cross product
    of two rows): ``(A + s n n^T)^-1 b - n (n.b) / s`` with ``s = trace(A)`` (for the exact null
    vector ``(A + s n n^T)^-1 = pinv(A) + n n^T / s``). Rank 1 (``A = s u u^T``): ``u (u.b) / s``.
    Rank 0: zero. The rank is decided with :data:`PINV_RCOND` (eigenvalues ``det / e2``,
    ``e2 / trace``, ``e2`` the sum of the principal 2x2 minors); within a rank every branch is
    differentiable, ``n`` and ``u`` included, so the tape's derivative is the constant-rank one.
    """
    tr = A[0, 0] + A[1, 1] + A[2, 2]
    if tr <= wp.float64(0.0):
        return wp.vec3d()
    e2 = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) + (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) + (
        A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
    det = wp.determinant(A)
    if e2 > PINV_RCOND * tr * tr and det > PINV_RCOND * tr * e2:
        return wp.inverse(A) * b
    r0 = wp.vec3d(A[0, 0], A[0, 1], A[0, 2])
    r1 = wp.vec3d(A[1, 0], A[1, 1], A[1, 2])
    r2 = wp.vec3d(A[2, 0], A[2, 1], A[2, 2])
    if e2 > PINV_RCOND * tr * tr:
        c01 = wp.cross(r0, r1)
        c02 = wp.cross(r0, r2)
        c12 = wp.cross(r1, r2)
        n = c01
        if wp.length_sq(c02) > wp.length_sq(n):
            n = c02
        if wp.length_sq(c12) > wp.length_sq(n):
            n = c12
        n = wp.normalize(n)
        return wp.inverse(A + tr * wp.outer(n, n)) * b - n * (wp.dot(n, b) / tr)
    u = r0
    if wp.length_sq(r1) > wp.length_sq(u):
        u = r1
    if wp.length_sq(r2) > wp.length_sq(u):
        u = r2
    u = wp.normalize(u)
    return u * (wp.dot(u, b) / tr)


@wp.func
def zone_member(
    i: int,
    n_particles: int,
    particle_zone: wp.array(dtype=wp.int32),
    body_zone: wp.array(dtype=wp.int32),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_mass: wp.array(dtype=wp.float64),
):
    """Zone member ``i`` (particle ``i``, then body ``i - n_particles``): its zone (< 0: none),
    mass, position (a body's centre of mass) and velocity (its centre's)."""
    z = int(-1)
    m = wp.float64(0.0)
    x = wp.vec3d()
    v = wp.vec3d()
    if i < n_particles:
        z = particle_zone[i]
        if z >= 0:
            m = zone_member_mass(particle_inv_mass[i])
            x = particle_q[i]
            v = particle_qd[i]
    else:
        b = i - n_particles
        z = body_zone[b]
        if z >= 0:
            m = body_mass[b]
            x = wp.transform_get_translation(body_q[b])
            v = wp.spatial_bottom(body_qd[b])
    return z, m, x, v


@wp.kernel
def zone_sums_kernel(
    n_particles: int,
    particle_zone: wp.array(dtype=wp.int32),
    body_zone: wp.array(dtype=wp.int32),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_mass: wp.array(dtype=wp.float64),
    zone_mass: wp.array(dtype=wp.float64),
    zone_first_moment: wp.array(dtype=wp.vec3d),
    zone_momentum: wp.array(dtype=wp.vec3d),
):
    """Per impact zone (thread ``tid``: particle ``tid``, then body ``tid - n_particles``): the
    total mass, first moment ``sum m x`` and linear momentum ``sum m v`` of its members at the
    start of the substep (atomic sums)."""
    i = wp.tid()
    z, m, x, v = zone_member(i, n_particles, particle_zone, body_zone, particle_q, particle_qd, particle_inv_mass,
                             body_q, body_qd, body_mass)
    if z >= 0:
        wp.atomic_add(zone_mass, z, m)
        wp.atomic_add(zone_first_moment, z, m * x)
        wp.atomic_add(zone_momentum, z, m * v)


@wp.kernel
def zone_moments_kernel(
    n_particles: int,
    particle_zone: wp.array(dtype=wp.int32),
    body_zone: wp.array(dtype=wp.int32),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_mass: wp.array(dtype=wp.float64),
    body_inertia: wp.array(dtype=wp.mat33d),
    zone_mass: wp.array(dtype=wp.float64),
    zone_first_moment: wp.array(dtype=wp.vec3d),
    zone_angular: wp.array(dtype=wp.vec3d),
    zone_inertia: wp.array(dtype=wp.mat33d),
):
    """Per impact zone, about its centre of mass ``c``: the angular momentum
    ``sum m r x v (+ R I R^T w for bodies)`` and the inertia tensor
    ``sum m (|r|^2 E - r r^T) (+ R I R^T)``, ``r = x - c`` (atomic sums)."""
    i = wp.tid()
    z, m, x, v = zone_member(i, n_particles, particle_zone, body_zone, particle_q, particle_qd, particle_inv_mass,
                             body_q, body_qd, body_mass)
    own_l = wp.vec3d()
    own_i = wp.mat33d()
    if z >= 0 and i >= n_particles:  # a body also spins: its own angular momentum and inertia
        b = i - n_particles
        own_i = world_inertia(body_q[b], body_inertia[b])
        own_l = own_i * wp.spatial_top(body_qd[b])
    if z >= 0:
        c = zone_first_moment[z] / zone_mass[z]
        r = x - c
        eye = wp.identity(n=3, dtype=wp.float64)
        wp.atomic_add(zone_angular, z, m * wp.cross(r, v) + own_l)
        wp.atomic_add(zone_inertia, z, m * (wp.dot(r, r) * eye - wp.outer(r, r)) + own_i)


@wp.kernel
def zone_rigid_motion_kernel(
    zone_mass: wp.array(dtype=wp.float64),
    zone_first_moment: wp.array(dtype=wp.vec3d),
    zone_momentum: wp.array(dtype=wp.vec3d),
    zone_angular: wp.array(dtype=wp.vec3d),
    zone_inertia: wp.array(dtype=wp.mat33d),
    zone_centre: wp.array(dtype=wp.vec3d),
    zone_linear: wp.array(dtype=wp.vec3d),
    zone_omega: wp.array(dtype=wp.vec3d),
):
    """Zone ``tid``'s rigid motion: centre of mass, its velocity (momentum / mass) and the
    angular velocity ``pinv(inertia) angular momentum`` (:func:`symmetric_pinv_apply`)."""
    z = wp.tid()
    zone_centre[z] = zone_first_moment[z] / zone_mass[z]
    zone_linear[z] = zone_momentum[z] / zone_mass[z]
    zone_omega[z] = symmetric_pinv_apply(zone_inertia[z], zone_angular[z])


@wp.kernel
def zone_particle_velocity_kernel(
    particle_zone: wp.array(dtype=wp.int32),
    particle_q: wp.array(dtype=wp.vec3d),
    zone_centre: wp.array(dtype=wp.vec3d),
    zone_linear: wp.array(dtype=wp.vec3d),
    zone_omega: wp.array(dtype=wp.vec3d),
    velocity: wp.array(dtype=wp.vec3d),
    out: wp.array(dtype=wp.vec3d),
):
    """Particle ``tid``: its zone's rigid velocity ``linear + omega x (x - c)`` at its start
    position, zero in a zone at rest, its own velocity outside any zone."""
    i = wp.tid()
    z = particle_zone[i]
    if z >= 0:
        out[i] = zone_linear[z] + wp.cross(zone_omega[z], particle_q[i] - zone_centre[z])
    elif z == ZONE_WORLD:
        out[i] = wp.vec3d()
    else:
        out[i] = velocity[i]


@wp.kernel
def zone_body_velocity_kernel(
    body_zone: wp.array(dtype=wp.int32),
    body_q: wp.array(dtype=wp.transformd),
    zone_centre: wp.array(dtype=wp.vec3d),
    zone_linear: wp.array(dtype=wp.vec3d),
    zone_omega: wp.array(dtype=wp.vec3d),
    velocity: wp.array(dtype=wp.spatial_vectord),
    out: wp.array(dtype=wp.spatial_vectord),
):
    """Body ``tid``: angular velocity ``omega`` and centre-of-mass velocity
    ``linear + omega x (com - c)`` of its zone, zero in a zone at rest, its own twist outside."""
    b = wp.tid()
    z = body_zone[b]
    if z >= 0:
        w = zone_omega[z]
        com = wp.transform_get_translation(body_q[b])
        v = zone_linear[z] + wp.cross(w, com - zone_centre[z])
        out[b] = wp.spatial_vectord(w[0], w[1], w[2], v[0], v[1], v[2])
    elif z == ZONE_WORLD:
        out[b] = wp.spatial_vectord()
    else:
        out[b] = velocity[b]
