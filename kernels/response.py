"""The exact impulse solve's rows (Warp, float64, taped): the Delassus matrix of the active normal
contacts, right-hand sides for the velocity and push targets, the velocities after the
impulses.
"""

import warp as wp

from kernels.pose import VERTEX_PARTICLE, vertex_velocity


@wp.func
def contact_responses(
    c: int,
    d: int,
    g0: wp.vec3d,
    g1: wp.vec3d,
    g2: wp.vec3d,
    count: int,
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
) -> wp.mat33d:
    """Changes of the relative velocity of contact ``c`` caused by impulses ``g0``, ``g1``,
    ``g2`` at contact ``d`` (the Delassus operator's 3x3 block times each), as the rows of the
    result, for the first ``count`` (1, 2 or 3) of them (the other rows stay zero): the pairs'
    shared particles and bodies are looked up once for all."""
    zero = wp.float64(0.0)
    out0 = wp.vec3d(zero, zero, zero)
    out1 = wp.vec3d(zero, zero, zero)
    out2 = wp.vec3d(zero, zero, zero)
    qc = pairs[c]
    qd = pairs[d]
    wc = weights[c]
    wd = weights[d]
    for k in range(4):
        if vertex_type[qc[k]] == VERTEX_PARTICLE:
            for l in range(4):
                if vertex_type[qd[l]] == VERTEX_PARTICLE and vertex_owner[qc[k]] == vertex_owner[qd[l]]:
                    shared = wc[k] * wd[l] * particle_inv_mass[vertex_owner[qc[k]]]
                    out0 = out0 + shared * g0
                    if count > 1:
                        out1 = out1 + shared * g1
                    if count > 2:
                        out2 = out2 + shared * g2
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
                    linear = wsc[s] * wsd[t] * body_inv_mass[body]
                    inertia = body_inv_inertia[body]
                    out0 = out0 + linear * g0
                    out0 = out0 - wp.cross(rc, inertia * wp.cross(rd, g0))
                    if count > 1:
                        out1 = out1 + linear * g1
                        out1 = out1 - wp.cross(rc, inertia * wp.cross(rd, g1))
                    if count > 2:
                        out2 = out2 + linear * g2
                        out2 = out2 - wp.cross(rc, inertia * wp.cross(rd, g2))
    return wp.matrix_from_rows(out0, out1, out2)


@wp.kernel
def delassus_kernel(
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
    """Entry (r, u) of the normal system of the active contacts: the normal relative velocity of
    active contact ``r`` per unit normal impulse at active contact ``u``. With ``friction`` mu
    and slip ``directions`` s, each normal impulse carries its contact's sliding friction along
    (the impulse ``n - mu s``: the sliding system), else (``friction`` 0) it is the plain normal
    system ``n_r . K_ru n_u``. The diagonal is scaled by ``1 + regularization`` so that redundant
    contacts (a singular matrix) still give a unique, bounded solution."""
    r, u = wp.tid()
    c = unknown_contact[r]
    d = unknown_contact[u]
    g = normals[d] - friction * directions[d]
    resp = contact_responses(
        c, d, g, g, g, 1, pairs, weights, vertex_type, vertex_owner, side_body, side_weight, rho_a, rho_b,
        particle_inv_mass, body_inv_mass, body_inv_inertia,
    )[0]
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


@wp.kernel
def normal_part_kernel(impulses: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
                       out: wp.array(dtype=wp.vec3d)):
    """The normal part ``(j . n) n`` of each contact's impulse."""
    c = wp.tid()
    n = normals[c]
    out[c] = wp.dot(impulses[c], n) * n


@wp.kernel
def add_vectors_kernel(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """``out = a + b`` (the normal impulses of a solve and of its refinement)."""
    i = wp.tid()
    out[i] = a[i] + b[i]


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
