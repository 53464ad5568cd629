"""The collision response's per-owner and active-set decisions on the device (Warp, off the tape):
each particle's and body's earliest contact time and row, the active set of the exact impulse
solve and its repairs, and the friction pass's per-contact shares."""

import warp as wp

from kernels.contact_set import infinity
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, vertex_velocity


@wp.kernel(enable_backward=False)
def owner_times_reset_kernel(
    particle_count: int,
    particle_zone: wp.array(dtype=wp.int32),
    body_zone: wp.array(dtype=wp.int32),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
):
    """Before :func:`owner_times_kernel`: each particle's (first ``particle_count`` threads) and
    body's earliest contact time is inf, or 0 for a member of an impact zone (nonzero zone
    flag: it moves rigidly over the whole substep)."""
    i = wp.tid()
    if i < particle_count:
        t = infinity()
        if particle_zone[i] != 0:
            t = wp.float64(0.0)
        particle_time[i] = t
        return
    b = i - particle_count
    t = infinity()
    if body_zone[b] != 0:
        t = wp.float64(0.0)
    body_time[b] = t


@wp.kernel(enable_backward=False)
def owner_times_kernel(
    count: wp.array(dtype=wp.int32),
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    toi: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
):
    """Earliest contact time [s] per particle (a vertex with a nonzero weight) and per body (any
    of its vertices) over the contact set's row ``tid``: the velocity switches from ``v-`` to
    ``v+`` then (a minimum: the same on every device whatever the order, for the finite times of
    a finite state). Rows from ``count[0]`` on (a launch over the set's capacity) are skipped."""
    c = wp.tid()
    if c >= count[0]:
        return
    q = vertices[c]
    w = weights[c]
    t = toi[c]
    for s in range(4):
        v = q[s]
        kind = vertex_type[v]
        if kind == VERTEX_PARTICLE:
            if w[s] != wp.float64(0.0):
                wp.atomic_min(particle_time, vertex_owner[v], t)
        elif kind == VERTEX_BODY:
            wp.atomic_min(body_time, vertex_owner[v], t)


OWNER_TIMED = wp.constant(1 << 30)
"""Added to a contact row in :func:`owner_rows_kernel`'s keys when its time is differentiated
(rows below 2^30)."""


@wp.kernel(enable_backward=False)
def owner_rows_reset_kernel(particle_count: int, particle_key: wp.array(dtype=wp.int32),
                            body_key: wp.array(dtype=wp.int32)):
    """-1 (no contact) for each particle's (first ``particle_count`` threads) and body's key."""
    i = wp.tid()
    if i < particle_count:
        particle_key[i] = -1
    else:
        body_key[i - particle_count] = -1


@wp.kernel(enable_backward=False)
def owner_rows_kernel(
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    toi: wp.array(dtype=wp.float64),
    timed: wp.array(dtype=wp.int32),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
    particle_key: wp.array(dtype=wp.int32),
    body_key: wp.array(dtype=wp.int32),
):
    """The contact row whose time is its owner's earliest (:func:`owner_times_kernel`), per
    particle / body, as the largest key ``row + OWNER_TIMED timed``: among ties (the same
    ``t*``: a corner on a face diagonal is several pairs) a row whose time the replay
    differentiates, then the last row (a maximum: the same on every device)."""
    c = wp.tid()
    q = vertices[c]
    w = weights[c]
    t = toi[c]
    key = wp.int32(c)
    if timed[c] != 0:
        key = key + OWNER_TIMED
    for s in range(4):
        v = q[s]
        kind = vertex_type[v]
        o = vertex_owner[v]
        if kind == VERTEX_PARTICLE:
            if w[s] != wp.float64(0.0) and t == particle_time[o]:
                wp.atomic_max(particle_key, o, key)
        elif kind == VERTEX_BODY:
            if t == body_time[o]:
                wp.atomic_max(body_key, o, key)


@wp.kernel(enable_backward=False)
def owner_rows_finish_kernel(
    particle_count: int,
    particle_key: wp.array(dtype=wp.int32),
    body_key: wp.array(dtype=wp.int32),
    particle_zone: wp.array(dtype=wp.int32),
    body_zone: wp.array(dtype=wp.int32),
    particle_row: wp.array(dtype=wp.int32),
    body_row: wp.array(dtype=wp.int32),
):
    """Each particle's / body's contact row for the time-of-impact integration
    (:func:`kernels.integrate.time_of_impact_kernel`): -1 none, -2 a member of an impact
    zone (nonzero zone flag), else the row of :func:`owner_rows_kernel`'s key."""
    i = wp.tid()
    if i < particle_count:
        k = particle_key[i]
        if k >= 0:
            k = k % OWNER_TIMED
        if particle_zone[i] != 0:
            k = -2
        particle_row[i] = k
        return
    b = i - particle_count
    k = body_key[b]
    if k >= 0:
        k = k % OWNER_TIMED
    if body_zone[b] != 0:
        k = -2
    body_row[b] = k


@wp.func
def _mobile_row(q: wp.vec4i, w: wp.vec4d, mobile_vertex: wp.array(dtype=wp.int32)) -> int:
    """Whether a contact moves something: a vertex with a nonzero weight that an impulse can
    move (a rigid vertex or an unpinned particle)."""
    for s in range(4):
        if w[s] != wp.float64(0.0) and mobile_vertex[q[s]] != 0:
            return 1
    return 0


@wp.kernel(enable_backward=False)
def initial_active_kernel(
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normal_impulse: wp.array(dtype=wp.float64),
    mobile_vertex: wp.array(dtype=wp.int32),
    mobile: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """The first active set of the exact solve: the contacts whose Gauss-Seidel normal impulse
    ended positive and that move something (``mobile``, kept for
    :func:`active_set_update_kernel`)."""
    c = wp.tid()
    m = _mobile_row(vertices[c], weights[c], mobile_vertex)
    mobile[c] = wp.int32(m)
    a = 0
    if m != 0 and normal_impulse[c] > wp.float64(0.0):
        a = 1
    active[c] = wp.int32(a)


@wp.kernel(enable_backward=False)
def active_set_update_kernel(
    count: int,
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    collided: wp.array(dtype=wp.int32),
    mobile: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    normal: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    tolerance: wp.float64,
    collided_tolerance: wp.float64,
    pulling: wp.float64,
    normal_scratch: wp.array(dtype=wp.float64),
    repaired: wp.array(dtype=wp.int32),
    changes: wp.array(dtype=wp.int32),
):
    """The active set's repair after an exact solve (launched with ``dim=1``: the rule needs the
    largest normal impulse first): an active contact whose normal impulse ``normal . n`` pulls
    (below ``-pulling`` times the largest magnitude) leaves the set; an inactive one that moves
    something and whose normal relative velocity after the solve (``particle_qd``, ``body_qd``)
    is below its target by more than ``tolerance`` (``collided_tolerance`` for the rows a CCD hit
    reached: their primitives meet within the substep, so the least approach left would be a
    hit of the next CCD round again) joins it. ``repaired``: the new set; ``changes[0]``: how
    many contacts changed."""
    zero = wp.float64(0.0)
    largest = zero
    for c in range(count):
        jn = wp.dot(normal[c], normals[c])
        normal_scratch[c] = jn
        largest = wp.max(largest, wp.abs(jn))
    largest = wp.max(largest, wp.float64(1.0e-300))
    n_changes = int(0)
    for c in range(count):
        a = active[c]
        new = a
        if a != 0:
            if normal_scratch[c] < -pulling * largest:
                new = 0
        elif mobile[c] != 0:
            q = vertices[c]
            w = weights[c]
            vrel = wp.vec3d(zero, zero, zero)
            for s in range(4):
                vrel = vrel + w[s] * vertex_velocity(q[s], vertex_type, vertex_owner, lever, particle_qd, body_qd)
            tol = tolerance
            if collided[c] != 0:
                tol = collided_tolerance
            if wp.dot(vrel, normals[c]) < targets[c] - tol:
                new = 1
        repaired[c] = new
        if new != a:
            n_changes = n_changes + 1
    changes[0] = wp.int32(n_changes)


@wp.kernel(enable_backward=False)
def flags_differ_kernel(a: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.int32), counter: wp.array(dtype=wp.int32)):
    """Counts in ``counter[0]`` the entries where the flags ``a`` and ``b`` differ."""
    i = wp.tid()
    if (a[i] != 0) != (b[i] != 0):
        wp.atomic_add(counter, 0, 1)


@wp.kernel(enable_backward=False)
def set_impulses_kernel(
    active: wp.array(dtype=wp.int32),
    normal: wp.array(dtype=wp.vec3d),
    normals: wp.array(dtype=wp.vec3d),
    normal_impulse: wp.array(dtype=wp.float64),
    friction_impulse: wp.array(dtype=wp.vec3d),
):
    """The contact set's accumulated impulses after an exact solve: the normal impulse of an
    active contact (``normal . n``), 0 for the others, no friction impulse (the next
    Gauss-Seidel pass starts from them)."""
    c = wp.tid()
    jn = wp.float64(0.0)
    if active[c] != 0:
        jn = wp.dot(normal[c], normals[c])
    normal_impulse[c] = jn
    friction_impulse[c] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.func
def _share_node(q: wp.vec4i, w: wp.vec4d, s: int, particle_count: int, vertex_type: wp.array(dtype=wp.int32),
                vertex_owner: wp.array(dtype=wp.int32)) -> int:
    """The particle (a vertex with a nonzero weight) or body (``particle_count`` + body) that
    slot ``s`` of a contact moves, or -1."""
    v = q[s]
    kind = vertex_type[v]
    if kind == VERTEX_PARTICLE and w[s] != wp.float64(0.0):
        return int(vertex_owner[v])
    if kind == VERTEX_BODY:
        return particle_count + int(vertex_owner[v])
    return -1


@wp.kernel(enable_backward=False)
def friction_share_count_kernel(
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    active: wp.array(dtype=wp.int32),
    particle_count: int,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
):
    """How many active contacts move each particle / body (each contact counted once per node)."""
    c = wp.tid()
    if active[c] == 0:
        return
    q = vertices[c]
    w = weights[c]
    for s in range(4):
        node = _share_node(q, w, s, particle_count, vertex_type, vertex_owner)
        if node >= 0:
            seen = int(0)
            for r in range(s):
                if _share_node(q, w, r, particle_count, vertex_type, vertex_owner) == node:
                    seen = 1
            if seen == 0:
                wp.atomic_add(node_count, node, 1)


@wp.kernel(enable_backward=False)
def friction_share_kernel(
    vertices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4d),
    particle_count: int,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    share: wp.array(dtype=wp.float64),
):
    """Per contact: one over the largest number of active contacts that any particle or body it
    moves takes part in (:func:`kernels.friction.friction_impulses_kernel` applies the friction
    impulses of one pass together)."""
    c = wp.tid()
    q = vertices[c]
    w = weights[c]
    most = int(1)
    for s in range(4):
        node = _share_node(q, w, s, particle_count, vertex_type, vertex_owner)
        if node >= 0:
            most = wp.max(most, int(node_count[node]))
    share[c] = wp.float64(1.0) / wp.float64(most)


@wp.kernel(enable_backward=False)
def active_unknowns_kernel(
    count: int,
    active: wp.array(dtype=wp.int32),
    unknowns: wp.array(dtype=wp.int32),
    contact_unknown: wp.array(dtype=wp.int32),
    unknown_count: wp.array(dtype=wp.int32),
):
    """The exact solve's unknowns (launched with ``dim=1``, in row order): ``unknowns`` the
    active contacts, ``contact_unknown[c]`` each contact's unknown (-1 inactive),
    ``unknown_count[0]`` their number."""
    n = int(0)
    for c in range(count):
        if active[c] != 0:
            unknowns[n] = wp.int32(c)
            contact_unknown[c] = wp.int32(n)
            n = n + 1
        else:
            contact_unknown[c] = -1
    unknown_count[0] = wp.int32(n)
