"""Contact geometry at the time of impact (Warp, float64, taped): each contact's time, normal and
barycentric or segment weights, its side's velocity-change rows, and the merge of duplicate
rows.
"""

import warp as wp

from kernels.ccd_common import CCD_T_MAX, coplanarity_cubic, unit_scaled_cubic
from kernels.edge_edge import segment_segment_closest
from kernels.integrate import rebound_normal_velocity
from kernels.point_triangle import point_triangle_closest
from kernels.pose import (
    PAIR_EDGE_EDGE,
    PAIR_VERTEX_FACE,
    PAIR_VERTEX_PLANE,
    TIME_PLANE,
    TIME_START,
    VERTEX_BODY,
    VERTEX_PARTICLE,
    vertex_time,
    vertex_velocity,
)
from kernels.roots import cubic_roots


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


@wp.func
def vertex_gravity(v: int, vertex_type: wp.array(dtype=wp.int32), vertex_owner: wp.array(dtype=wp.int32),
                   particle_inv_mass: wp.array(dtype=wp.float64), body_inv_mass: wp.array(dtype=wp.float64),
                   gravity: wp.vec3d) -> wp.vec3d:
    """``gravity`` for a vertex that falls (an unpinned particle's, a body's with mass), else 0
    (static vertices, pinned particles)."""
    kind = vertex_type[v]
    falls = bool(False)
    if kind == VERTEX_PARTICLE:
        falls = particle_inv_mass[vertex_owner[v]] > wp.float64(0.0)
    elif kind == VERTEX_BODY:
        falls = body_inv_mass[vertex_owner[v]] > wp.float64(0.0)
    if falls:
        return gravity
    return wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.kernel
def contact_geometry_kernel(
    count: wp.array(dtype=wp.int32),
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
    particle_inv_mass: wp.array(dtype=wp.float64),
    body_inv_mass: wp.array(dtype=wp.float64),
    gravity: wp.vec3d,
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
      by the start offset, a rigid body's face always outwards (a hit from behind leaves the
      body and separates), or, for proximity pairs, the offset direction, the face's normal for
      a vertex over the face or its coplanar neighbours (``flat_keys``, ``flat_opposites``); touching pairs: the face's
      outward normal, crossing edges' cross product oriented by their lever arms, else a zero
      normal, which keeps the pair out of the contact set).
    * target: proximity ``max(-e v_n, rate (delta - d) / h)`` when it approaches faster than
      the separation speed ``rate delta / h`` (else ``rate (delta - d) / h``: resting contact;
      a pair beyond ``delta``, within the proximity pass's hysteresis, may approach at
      ``(delta - d) / h``, which brings it to ``delta`` at the end, and is not pulled); CCD
      the particle-plane law (:func:`kernels.integrate.plane_rebound`) along the normal,
      ``max(-e min(v_n + g_n / 2, 0) + c (1 - t*/h) - g_n / 2, rate delta / h)`` (``e = 0``:
      ``max(c (1 - t*/h), rate delta / h)``), ``v_n`` the normal velocity at ``t*``: each
      vertex's start velocity plus the forces' change up to ``t*`` (``v_start + (t*/h)(v- -
      v_start)``; the start velocity for proximity pairs) before its owner's earlier contact
      time, the current velocity after it; ``c = min(n.(v- - v_start), 0)`` the forces' inward
      change over the substep and ``g_n = min(n.g h, 0)`` gravity's (``gravity`` on the
      vertices that fall: unpinned particles, bodies with mass; zero under the exact ballistic
      update, whose stored velocity is the substep's end one). ``v_n`` is the pair's own
      velocity at ``t*`` (the plane law's takes only the forces' inward change into it). With ``split_push`` the target is the
      restitution's part alone (at least 0; a pair beyond ``delta``: ``(delta - d) / h``), and
      the separation's part, the push ``rate (delta - d) / h`` (proximity; beyond ``delta``:
      ``(delta - d) / h``) or ``rate delta / h`` (CCD), goes to ``pushes`` for a solve of its
      own that moves positions only (:func:`push_rhs_kernel`).

    Threads from ``count[0]`` on do nothing (a launch over a bound on the rows, their count on
    the device).
    """
    c = wp.tid()
    if c >= count[0]:
        return
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
    vforce = wp.vec3d(zero, zero, zero)  # the forces' change of the relative velocity over the substep
    grel = wp.vec3d(zero, zero, zero)  # gravity's part of it per unit time
    for k in range(4):
        vk = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd_minus, body_qd_minus)
        v0k = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd_start, body_qd_start)
        vforce = vforce + w[k] * (vk - v0k)
        grel = grel + w[k] * vertex_gravity(q[k], vertex_type, vertex_owner, particle_inv_mass, body_inv_mass, gravity)
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
            # oriented towards the vertex's side at the start, except a rigid body's face: its
            # faces are wound outwards over a closed surface (the builder checks it), and just
            # behind a face lies the body's inside, so a vertex that crosses one from behind is
            # leaving the body (the path of a vertex through a body, before its earlier hit on
            # the way in has turned it, crosses the far side too). The outward normal makes such
            # a hit separate, so it does not join the contact set; oriented by the start it
            # pushed the vertex back in
            rigid_face = kind == PAIR_VERTEX_FACE and geo_ok and vertex_type[q[1]] == VERTEX_BODY
            if not rigid_face and wp.dot(n, start_offset) < zero:
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
        # the particle-plane law (kernels.integrate.plane_rebound) along the pair's normal: the
        # rebound at t* of the velocity there (gravity's inward part entering over half a
        # substep more: the stored velocity is the middle of the substep before), then the
        # forces' inward change over the rest of the substep, the end velocity being what the
        # solve sets. So a ball leaves a mesh floor as it leaves a ground plane, and the end
        # state moves continuously with t* (with the rebound alone each substep boundary that
        # t* crossed was a jump, and the slope between them missed g (h - t*) dt*/dv)
        change_n = wp.min(wp.dot(vforce, n), zero)
        half_gravity = wp.float64(0.5) * wp.min(wp.dot(grel, n) * h, zero)
        target = rebound_normal_velocity(vn + half_gravity, change_n * (one - frac), half_gravity, restitution)
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
