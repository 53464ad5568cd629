"""Vertex posing (Warp, float64): where a collidable vertex is and how fast it moves. A vertex is a
particle, a rigid body's mesh vertex or a static vertex (``VERTEX_*``, with an owner index);
contact pairs are of the kinds ``PAIR_*`` and carry a time source ``TIME_*``.
"""

import warp as wp



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
def world_inverse_inertia(X: wp.transformd, inv_inertia: wp.mat33d) -> wp.mat33d:
    """``R I^-1 R^T`` of a body at pose ``X`` (rotation R) with body-frame inverse inertia
    ``inv_inertia``."""
    R = wp.quat_to_matrix(wp.transform_get_rotation(X))
    return R * inv_inertia * wp.transpose(R)
