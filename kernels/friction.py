"""Coulomb friction (Warp, float64): the one friction law of the replayed response. The
sticking system (three unknowns per contact), sliding contacts at ``mu j_n`` along their slip
direction, the cone test, when a sliding contact stops, and the shared per-contact friction
pass.
"""

import warp as wp

from kernels.pose import VERTEX_PARTICLE
from kernels.response import contact_responses, relative_velocity, unit_perpendicular


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
    ``t_a . K_cc t_a`` so that the rows are commensurate with the velocity rows.

    Launched over (n, n) for n unknown contacts: thread (i, j) writes the 3x3 block of rows
    ``3 i ..`` and columns ``3 j ..``."""
    i, j = wp.tid()
    c = unknown_contact[i]
    d = unknown_contact[j]
    s = slip[c]
    zero = wp.float64(0.0)
    sliding = wp.length_sq(s) > zero
    # row b of the block: the response at c to a unit impulse along axis b of contact d
    block = contact_responses(
        c, d, contact_axis(normals[d], 0), contact_axis(normals[d], 1), contact_axis(normals[d], 2), 3, pairs, weights,
        vertex_type, vertex_owner, side_body, side_weight, rho_a, rho_b, particle_inv_mass, body_inv_mass,
        body_inv_inertia,
    )
    for axis in range(3):
        t = contact_axis(normals[c], axis)
        for column in range(3):
            value = zero
            if axis != 0 and sliding:
                if i == j:
                    # the diagonal block: d is c, so row ``axis`` is the response to t itself
                    scale = wp.dot(t, block[axis])
                    if column == axis:
                        value = scale
                    elif column == 0:
                        value = scale * friction * wp.dot(s, t)
            else:
                value = wp.dot(t, block[column])
                if i == j and column == axis:
                    scale = regularization
                    if axis != 0:
                        scale = regularization * tangent_weight[c]
                    value = value * (wp.float64(1.0) + scale)
            matrix[3 * i + axis, 3 * j + column] = value


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
        change = contact_responses(c, c, friction, friction, friction, 1, pairs, weights, vertex_type, vertex_owner,
                                   side_body, side_weight, rho_a, rho_b, particle_inv_mass, body_inv_mass,
                                   body_inv_inertia)[0]
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


@wp.func
def coulomb_friction(stop: wp.vec3d, slip: wp.vec3d, limit: wp.float64) -> wp.vec3d:
    """Coulomb's law, the one definition every response uses: the friction impulse (or velocity
    change) of a contact whose sticking impulse would be ``stop``. Inside the cone
    ``|stop| <= limit`` (``limit = mu j_n``) the contact sticks and gets ``stop``; outside it
    slides and gets ``limit`` against its ``slip`` direction (zero for a zero ``slip``). Without
    a limit (no friction, or no normal impulse) there is no friction impulse, and no derivative
    with respect to ``stop``."""
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if limit <= wp.float64(0.0):
        return zero
    if not (wp.length(stop) > limit):  # a NaN stays a NaN (the divergence guard sees it)
        return stop
    length = wp.length(slip)
    if length > wp.float64(0.0):
        return (-limit / length) * slip
    return zero


SLIP_STICK = wp.constant(0)


SLIP_KEEP = wp.constant(1)


SLIP_START = wp.constant(2)


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
        tangential = contact_responses(c, c, t1, t2, n, 2, pairs, weights, vertex_type, vertex_owner, side_body,
                                       side_weight, rho_a, rho_b, particle_inv_mass, body_inv_mass, body_inv_inertia)
        k1 = tangential[0]
        k2 = tangential[1]
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
            # sliding friction opposes the sliding velocity (for an anisotropic K the stopping
            # impulse does not, and its projection on the cone would brake a sliding body by
            # less than mu j_n)
            impulses[c] = coulomb_friction(stop, b1 * t1 + b2 * t2, friction * jn)
