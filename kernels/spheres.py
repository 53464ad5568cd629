"""Contacts of sphere bodies (Warp, float64): sphere-sphere pairs, and spheres against ground
planes and static triangles (:mod:`kernels.sphere_mesh`).

A substep of length ``h`` moves every sphere centre on the straight path of its predicted
velocity, ``x(t) = x0 + t v`` (after the forces, as the particles' plane contacts do). Two
spheres ``i``, ``j`` of radii ``r_i``, ``r_j`` touch when ``|d0 + t dv| = R`` with
``d0 = x0_i - x0_j``, ``dv = v_i - v_j`` and ``R = r_i + r_j + separation`` (the model's
thickness): the paper's
quadratic case, ``|dv|^2 t^2 + 2 (d0 . dv) t + (|d0| - R)(|d0| + R) = 0`` (the constant term in
factored form, exact to rounding when the spheres nearly touch). Its smaller root ``t-`` is the
time of impact; a miss is a complex pair.

Decide, then replay (design.md): :func:`decide_sphere_pairs` and :func:`decide_sphere_obstacles`
choose which pairs and obstacles act in the substep (off the tape: the choice is piecewise
constant); :func:`respond_sphere_pairs` and :func:`respond_sphere_obstacles` replay the smooth map
given that choice, on the tape. ``t-`` comes from :func:`kernels.point_ball.impact_time`
(:func:`kernels.roots.quadratic_roots`, whose adjoint is the mollified implicit derivative
bounded by ``max_derivative``).

The pairs act at once (a Jacobi pass, as DiffTaichi's billiards does): each applies its
impulse, computed from the predicted velocities, at its own time of impact, and the position
follows ``x1 = x0 + h v + (h - t*) dv`` for every velocity change ``dv`` (the one time-of-impact
integration, :func:`kernels.integrate.time_of_impact_position`). A ball in several contacts at
once can leave a pair still approaching, or separating but overlapping (the contacts' position
changes add up); further passes test the straight paths that end at the new poses with the new
velocities (:func:`straight_path_start`), give an approaching pair its impulse (a pair that
already had one in the substep is judged by its end state) and push an overlapping, separating
one apart along the line of centres, until no pair acts or ``SphereContacts.max_passes`` passes
have run (the stage counts the substeps left unresolved). Impulses are equal and
opposite, so the total momentum is kept to rounding. The impulse is along the line of centres,
``j_n = -(1 + e) v_n / (w_i + w_j)``, with Coulomb friction at the contact point
(:func:`kernels.friction.coulomb_friction`, the one friction law) against the contact point's
relative sliding velocity, which includes the spins.

Sphere inertia is isotropic, so body and world inverse inertia are the same matrix.
"""

import warp as wp

from kernels.friction import coulomb_friction
from kernels.integrate import earliest_plane, exact_rotation, plane_rebound, time_of_impact_position
from kernels.point_ball import entry_time, impact_time
from kernels.sphere_mesh import feature_contact, feature_entry_time

f64 = wp.float64

vec12d = wp.types.vector(length=12, dtype=wp.float64)
"""A body's changes from its pair contacts: angular velocity [rad/s] (0:3), linear velocity
[m/s] (3:6), position ``(h - t*) dv`` [m] (6:9) and rotation vector ``(h - t*) dw`` [rad] (9:12)."""


@wp.func
def pair_changes(dw: wp.vec3d, dv: wp.vec3d, rest: wp.float64) -> vec12d:
    """The :data:`vec12d` of one contact's velocity changes ``dw``, ``dv`` applied from ``h - rest``."""
    return vec12d(dw[0], dw[1], dw[2], dv[0], dv[1], dv[2], rest * dv[0], rest * dv[1], rest * dv[2],
                  rest * dw[0], rest * dw[1], rest * dw[2])


OVERLAP_RTOL = wp.constant(wp.float64(1.0e-12))
"""A separating pair overlapping at the end of a pass by more than this fraction of the sum of
its radii is pushed apart (rounding leaves touching balls ~1e-16 relative inside); a pair
approaches when its normal relative speed exceeds this fraction of its balls' speeds."""


@wp.func
def position_shift(dx: wp.vec3d) -> vec12d:
    """The :data:`vec12d` of a position change ``dx`` [m] alone."""
    zero = f64(0.0)
    return vec12d(zero, zero, zero, zero, zero, zero, dx[0], dx[1], dx[2], zero, zero, zero)


@wp.kernel(enable_backward=False)
def decide_sphere_pairs(
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    sphere_body: wp.array(dtype=wp.int32),
    sphere_radius: wp.array(dtype=wp.float64),
    separation: wp.float64,
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    h: wp.float64,
    t_max: wp.float64,
    responded: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    active_count: wp.array(dtype=wp.int32),
):
    """What pair ``k`` (spheres ``pair_a[k]``, ``pair_b[k]``) does in this pass, in
    ``active[k]`` (``active_count[0]`` counts the pairs that act). ``body_q``: the poses at the
    start of the pass's straight path; ``body_qd``: the velocities on it.

    A pair that has not had its impulse in this substep (``responded[k] == 0``): 1 when it
    approaches and touches within ``h`` [s] (a real ``t- <= h``, :func:`kernels.point_ball.entry_time`), or approaches while already
    touching. A pair that has (``responded[k] == 1``) is judged by its end state only (the
    pass's straight path is made up: it would cross the contact the pair already had): 3 when
    it still touches and approaches at the end (an impulse there). Either: 2 when it separates
    but overlaps at the end by more than :data:`OVERLAP_RTOL` of the sum of the radii (the
    response pushes it apart); else 0. Sets ``responded[k]`` for 1."""
    k = wp.tid()
    i = pair_a[k]
    j = pair_b[k]
    bi = sphere_body[i]
    bj = sphere_body[j]
    d0 = wp.transform_get_translation(body_q[bi]) - wp.transform_get_translation(body_q[bj])
    dv = wp.spatial_bottom(body_qd[bi]) - wp.spatial_bottom(body_qd[bj])
    d1 = d0 + h * dv
    reach = sphere_radius[i] + sphere_radius[j] + separation
    # approaching: faster than rounding of the two velocities (balls that move on together
    # after an inelastic impact have a relative velocity of rounding size)
    slack = OVERLAP_RTOL * (wp.length(wp.spatial_bottom(body_qd[bi])) + wp.length(wp.spatial_bottom(body_qd[bj])))
    flag = int(0)
    if wp.length(d1) == f64(0.0) or wp.length(d0) == f64(0.0):
        flag = 0  # coincident centres: no normal (the builder and rollout refuse such starts)
    elif responded[k] != 0:
        if wp.length(d1) <= reach and wp.dot(d1, dv) < -slack * wp.length(d1):
            flag = 3
        elif wp.length(d1) < reach * (f64(1.0) - OVERLAP_RTOL):
            flag = 2
    elif entry_time(d0, dv, reach, h, t_max, slack) >= f64(0.0):
        flag = 1
    elif wp.length(d1) < reach * (f64(1.0) - OVERLAP_RTOL):
        flag = 2  # separating, but overlapping at the end (several contacts' shifts at once)
    active[k] = wp.int32(flag)
    if flag == 1:
        responded[k] = 1
    if flag != 0:
        wp.atomic_add(active_count, 0, wp.int32(1))


@wp.func
def sliding_impulse(u: wp.vec3d, n: wp.vec3d, tangential_inverse_mass: wp.float64, limit: wp.float64) -> wp.vec3d:
    """Coulomb's friction impulse [N s] against the contact point's relative velocity ``u``
    [m/s] (normal ``n``), for a tangential inverse effective mass [1/kg] and the limit
    ``mu j_n`` [N s]."""
    slip = u - wp.dot(u, n) * n
    return coulomb_friction(-slip / tangential_inverse_mass, slip, limit)


@wp.kernel
def respond_sphere_pairs(
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    sphere_body: wp.array(dtype=wp.int32),
    sphere_radius: wp.array(dtype=wp.float64),
    separation: wp.float64,
    active: wp.array(dtype=wp.int32),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    restitution: wp.float64,
    friction: wp.float64,
    h: wp.float64,
    t_max: wp.float64,
    max_derivative: wp.float64,
    changes: wp.array(dtype=vec12d),
):
    """The response of every active pair (:func:`decide_sphere_pairs`: 1 an impulse at its time
    of impact, 3 an impulse at the pass's end, 2 a push apart), added to its two bodies'
    ``changes`` (:data:`vec12d`; a fresh zeroed array, per body)."""
    k = wp.tid()
    flag = active[k]
    if flag == 0:
        return
    i = pair_a[k]
    j = pair_b[k]
    bi = sphere_body[i]
    bj = sphere_body[j]
    d0 = wp.transform_get_translation(body_q[bi]) - wp.transform_get_translation(body_q[bj])
    twist_i = body_qd[bi]
    twist_j = body_qd[bj]
    dv = wp.spatial_bottom(twist_i) - wp.spatial_bottom(twist_j)
    r_i = sphere_radius[i]
    r_j = sphere_radius[j]
    reach = r_i + r_j + separation
    w_i = body_inv_mass[bi]
    w_j = body_inv_mass[bj]
    if flag == 2:
        # push the overlap apart along the line of centres, in proportion to the inverse masses
        d_end = d0 + h * dv
        dist = wp.length(d_end)
        shift = (reach - dist) / (w_i + w_j) * (d_end / dist)
        wp.atomic_add(changes, bi, position_shift(w_i * shift))
        wp.atomic_add(changes, bj, position_shift(-w_j * shift))
        return
    toi = h  # flag 3: a pair that had its impulse and still approaches at the end: one more there
    if flag == 1:
        toi = impact_time(d0, dv, reach, h, t_max, max_derivative)
    n = wp.normalize(d0 + toi * dv)  # from j to i at the impact
    jn = -(f64(1.0) + restitution) * wp.dot(n, dv) / (w_i + w_j)
    arm_i = -r_i * n  # centre to contact point
    arm_j = r_j * n
    u = dv + wp.cross(wp.spatial_top(twist_i), arm_i) - wp.cross(wp.spatial_top(twist_j), arm_j)
    ii = body_inv_inertia[bi]
    ij = body_inv_inertia[bj]
    tangential = w_i + w_j + r_i * r_i * ii[0, 0] + r_j * r_j * ij[0, 0]
    impulse = jn * n + sliding_impulse(u, n, tangential, friction * jn)  # on i; -impulse on j
    dv_i = w_i * impulse
    dv_j = -w_j * impulse
    dw_i = ii * wp.cross(arm_i, impulse)
    dw_j = ij * wp.cross(arm_j, -impulse)
    wp.atomic_add(changes, bi, pair_changes(dw_i, dv_i, h - toi))
    wp.atomic_add(changes, bj, pair_changes(dw_j, dv_j, h - toi))


@wp.kernel
def apply_sphere_changes(
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    changes: wp.array(dtype=vec12d),
    body_q_out: wp.array(dtype=wp.transformd),
    body_qd_out: wp.array(dtype=wp.spatial_vectord),
):
    """Body ``tid``'s predicted pose and twist plus the pairs' ``changes`` (fresh outputs)."""
    b = wp.tid()
    X = body_q[b]
    c = changes[b]
    turn = wp.vec3d(c[9], c[10], c[11])
    q = wp.normalize(exact_rotation(turn, f64(1.0)) * wp.transform_get_rotation(X))
    body_q_out[b] = wp.transformd(wp.transform_get_translation(X) + wp.vec3d(c[6], c[7], c[8]), q)
    body_qd_out[b] = body_qd[b] + wp.spatial_vectord(c[0], c[1], c[2], c[3], c[4], c[5])


@wp.kernel
def straight_path_start(body_q: wp.array(dtype=wp.transformd), body_qd: wp.array(dtype=wp.spatial_vectord),
                        h: wp.float64, start_q: wp.array(dtype=wp.transformd)):
    """The start ``x1 - h v`` of the straight path of length ``h`` [s] that ends at body
    ``tid``'s pose with its velocity (the next pass of pair contacts tests that path)."""
    b = wp.tid()
    X = body_q[b]
    start_q[b] = wp.transformd(wp.transform_get_translation(X) - h * wp.spatial_bottom(body_qd[b]),
                               wp.transform_get_rotation(X))


@wp.kernel(enable_backward=False)
def decide_sphere_obstacles(
    sphere_body: wp.array(dtype=wp.int32),
    sphere_radius: wp.array(dtype=wp.float64),
    separation: wp.float64,
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    planes: wp.array(dtype=wp.vec4d),
    plane_count: int,
    static_vertices: wp.array(dtype=wp.vec3d),
    static_faces: wp.array(dtype=wp.int32),
    face_count: int,
    h: wp.float64,
    t_max: wp.float64,
    obstacle: wp.array(dtype=wp.int32),
):
    """The first obstacle sphere ``tid`` reaches in the substep, on the straight path that ends
    at ``body_q`` with velocity ``body_qd``: -1 (none), a plane ``k`` (``0 <= k < plane_count``;
    the centre as a point that keeps ``radius + separation`` from the planes,
    :func:`kernels.integrate.earliest_plane`) or a static triangle's feature,
    ``plane_count + 7 f + feature`` (:func:`kernels.sphere_mesh.feature_entry_time`)."""
    s = wp.tid()
    b = sphere_body[s]
    v = wp.spatial_bottom(body_qd[b])
    x0 = wp.transform_get_translation(body_q[b]) - h * v
    reach = sphere_radius[s] + separation
    best = earliest_plane(x0, v, planes, plane_count, reach, h)
    best_t = h
    if best >= 0:
        p = planes[best]
        n = wp.vec3d(p[0], p[1], p[2])
        best_t = wp.max(f64(0.0), (p[3] + reach - wp.dot(n, x0)) / wp.dot(n, v))
    for f in range(face_count):
        a = static_vertices[static_faces[3 * f]]
        bb = static_vertices[static_faces[3 * f + 1]]
        c = static_vertices[static_faces[3 * f + 2]]
        for feature in range(7):
            t = feature_entry_time(x0, v, reach, a, bb, c, feature, h, t_max)
            if t >= f64(0.0) and (best < 0 or t < best_t):
                best = plane_count + 7 * f + feature
                best_t = t
    obstacle[s] = wp.int32(best)


@wp.kernel
def respond_sphere_obstacles(
    sphere_body: wp.array(dtype=wp.int32),
    sphere_radius: wp.array(dtype=wp.float64),
    separation: wp.float64,
    obstacle: wp.array(dtype=wp.int32),
    start_qd: wp.array(dtype=wp.spatial_vectord),
    predicted_qd: wp.array(dtype=wp.spatial_vectord),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_inv_mass: wp.array(dtype=wp.float64),
    body_inv_inertia: wp.array(dtype=wp.mat33d),
    planes: wp.array(dtype=wp.vec4d),
    plane_count: int,
    static_vertices: wp.array(dtype=wp.vec3d),
    static_faces: wp.array(dtype=wp.int32),
    restitution: wp.float64,
    friction: wp.float64,
    gravity: wp.vec3d,
    h: wp.float64,
    t_max: wp.float64,
    max_derivative: wp.float64,
    body_q_out: wp.array(dtype=wp.transformd),
    body_qd_out: wp.array(dtype=wp.spatial_vectord),
):
    """Sphere ``tid`` against its obstacle (:func:`decide_sphere_obstacles`): the particles'
    plane law (:func:`kernels.integrate.plane_rebound`) along the contact normal (a plane's, or
    from the triangle's feature to the centre), on the straight path that ends at ``body_q``
    with velocity ``body_qd`` (after the pairs), whose velocity at the substep's start was
    ``start_qd`` plus the pairs' change (``body_qd - predicted_qd``); Coulomb friction at the
    contact point spins the sphere. Bodies without an obstacle are copied."""
    s = wp.tid()
    b = sphere_body[s]
    X = body_q[b]
    twist = body_qd[b]
    k = obstacle[s]
    if k < 0:
        body_q_out[b] = X
        body_qd_out[b] = twist
        return
    v = wp.spatial_bottom(twist)
    w = wp.spatial_top(twist)
    x0 = wp.transform_get_translation(X) - h * v
    v_start = wp.spatial_bottom(start_qd[b]) + v - wp.spatial_bottom(predicted_qd[b])
    r = sphere_radius[s]
    reach = r + separation
    n = wp.vec3d(f64(0.0), f64(0.0), f64(1.0))
    toi = f64(0.0)
    if k < plane_count:
        p = planes[k]
        n = wp.vec3d(p[0], p[1], p[2])
        toi = wp.clamp((p[3] + reach - wp.dot(n, x0)) / wp.dot(n, v), f64(0.0), h)
    else:
        f = (k - plane_count) // 7
        contact = feature_contact(x0, v, reach, static_vertices[static_faces[3 * f]],
                                  static_vertices[static_faces[3 * f + 1]], static_vertices[static_faces[3 * f + 2]],
                                  (k - plane_count) % 7, h, t_max, max_derivative)
        toi = contact[0]
        n = wp.vec3d(contact[1], contact[2], contact[3])
    vn = wp.dot(n, v)
    zero = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    jn_velocity = plane_rebound(n, v_start, v, toi, h, gravity, zero, restitution) - vn  # >= 0
    w_inv = body_inv_mass[b]
    inv_inertia = body_inv_inertia[b]
    arm = -r * n
    u = v + wp.cross(w, arm)
    friction_impulse = sliding_impulse(u, n, w_inv + r * r * inv_inertia[0, 0], friction * jn_velocity / w_inv)
    v_plus = v + jn_velocity * n + w_inv * friction_impulse
    dw = inv_inertia * wp.cross(arm, friction_impulse)
    w_plus = w + dw
    q = wp.normalize(exact_rotation(dw, h - toi) * wp.transform_get_rotation(X))
    body_q_out[b] = wp.transformd(time_of_impact_position(x0, v, v_plus, toi, h), q)
    body_qd_out[b] = wp.spatial_vectord(w_plus[0], w_plus[1], w_plus[2], v_plus[0], v_plus[1], v_plus[2])
