"""Impact zones (Warp, float64): the momentum-conserving rigid motion of a zone of vertices that
kept colliding, with the pseudo-inverse of its inertia for degenerate zones.
"""

import warp as wp



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
