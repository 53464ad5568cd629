"""The collision response's contact bookkeeping on the device (Warp, float64): the decisions of
"decide, then replay" (design.md) between the narrow phase and the impulse solve, so that no
per-contact array crosses to the host within a substep.

A substep's *hits* (one detection pass: the proximity pairs at the start, or one CCD round's
crossings) are appended by the detection kernels through counters, then put into one canonical
order (:func:`hit_keys_kernel`, :func:`sort_keys_kernel` and :func:`gather_hits_kernel`:
ascending pair keys, the same order whatever the thread schedule or the broad phase's candidate
order). The *contact set* (:class:`sim.contact.contacts.Contacts`) grows by those hits
(:func:`add_contacts_kernel`, sequential: new pairs are appended in the hits' order, a pair
already in the set takes the new geometry and the earlier time). A pair is ``(kind, a, b)``:
kind 0 vertex-face ``(vertex, face)``, 1 edge-edge ``(edge, edge)``, 2 vertex-plane
``(vertex, plane)``; its key is ``(kind K + a) K + b`` for a base ``K`` above every index.
"""

from typing import Any

import warp as wp

from kernels.pose import (PAIR_VERTEX_PLANE, TIME_DETECTED, TIME_PLANE, TIME_START, VERTEX_PARTICLE, vertex_time,
                          vertex_velocity)

KEY_NONE = wp.constant(wp.int64(9223372036854775807))
"""The key of a hit left out (sorts after every pair's key)."""


@wp.func
def pair_key(kind: wp.int32, pair: wp.vec2i, key_base: wp.int64) -> wp.int64:
    """The one integer ``(kind K + a) K + b`` of the pair ``(kind, a, b)`` (``K = key_base``)."""
    return (wp.int64(kind) * key_base + wp.int64(pair[0])) * key_base + wp.int64(pair[1])


@wp.func
def infinity() -> wp.float64:
    return wp.float64(1.0e308) * wp.float64(10.0)


@wp.kernel(enable_backward=False)
def hit_keys_kernel(
    mesh_count: wp.array(dtype=wp.int32),
    plane_count: wp.array(dtype=wp.int32),
    mesh_kind: wp.array(dtype=wp.int32),
    mesh_pairs: wp.array(dtype=wp.vec2i),
    mesh_offset: wp.array(dtype=wp.vec3d),
    max_distance: wp.float64,
    plane_pairs: wp.array(dtype=wp.vec2i),
    key_base: wp.int64,
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    kept: wp.array(dtype=wp.int32),
):
    """Sort keys of one detection pass's hits, launched over a bound on their number (the
    counts stay on the device): the first ``mesh_count[0]`` threads take the narrow phase's
    (vertex-face / edge-edge) hits, the next ``plane_count[0]`` the vertex-plane ones, and the
    rest write :data:`KEY_NONE` (so a sort of the whole launch leaves them last). With
    ``max_distance >= 0`` (the proximity pass) a mesh hit whose closest points are not nearer
    than it (``|mesh_offset| < max_distance`` fails: the narrow phase's test had a hair of
    slack) gets :data:`KEY_NONE`; ``kept[0]`` counts the others. ``order[i] = i``."""
    i = wp.tid()
    meshes = mesh_count[0]
    key = KEY_NONE
    if i < meshes:
        key = pair_key(mesh_kind[i], mesh_pairs[i], key_base)
        if max_distance >= wp.float64(0.0):
            if not (wp.length(mesh_offset[i]) < max_distance):
                key = KEY_NONE
    elif i < meshes + plane_count[0]:
        key = pair_key(wp.int32(PAIR_VERTEX_PLANE), plane_pairs[i - meshes], key_base)
    keys[i] = key
    order[i] = wp.int32(i)
    if key != KEY_NONE:
        wp.atomic_add(kept, 0, 1)


@wp.func
def _sift_down(keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32), start: int, end: int):
    """Moves ``keys[start]`` (and its value) down the max-heap ``keys[0:end]``."""
    root = start
    while 2 * root + 1 < end:
        child = 2 * root + 1
        if child + 1 < end and keys[child] < keys[child + 1]:
            child = child + 1
        if keys[root] < keys[child]:
            k = keys[root]
            keys[root] = keys[child]
            keys[child] = k
            v = values[root]
            values[root] = values[child]
            values[child] = v
            root = child
        else:
            root = end  # done


@wp.func
def heap_sort(keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32), n: int):
    """Heap sort of ``keys[0:n]`` (ascending) with their ``values``, in one thread."""
    start = n / 2 - 1
    while start >= 0:
        _sift_down(keys, values, start, n)
        start = start - 1
    end = n - 1
    while end > 0:
        k = keys[0]
        keys[0] = keys[end]
        keys[end] = k
        v = values[0]
        values[0] = values[end]
        values[end] = v
        _sift_down(keys, values, 0, end)
        end = end - 1


@wp.kernel(enable_backward=False)
def sort_keys_kernel(count: int, keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32)):
    """Heap sort of ``keys[0:count]`` (ascending) with their ``values``, launched with ``dim=1``:
    on the CPU, where every launch runs its threads one after another, it costs a few
    microseconds for the tens to hundreds of hits of a substep (Warp's radix sort has a fixed
    cost of ~75 us there). The keys are distinct except :data:`KEY_NONE`, so the order is unique
    up to the left-out hits."""
    heap_sort(keys, values, count)


@wp.kernel(enable_backward=False)
def sort_hit_keys_kernel(mesh_count: wp.array(dtype=wp.int32), plane_count: wp.array(dtype=wp.int32),
                         keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32)):
    """:func:`sort_keys_kernel` of a detection pass's ``mesh_count[0] + plane_count[0]`` keys
    (:func:`hit_keys_kernel`'s), with the count read on the device; ``dim=1``."""
    heap_sort(keys, values, mesh_count[0] + plane_count[0])


@wp.kernel(enable_backward=False)
def gather_hits_kernel(
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    kept: wp.array(dtype=wp.int32),
    mesh_count: wp.array(dtype=wp.int32),
    mesh_kind: wp.array(dtype=wp.int32),
    mesh_pairs: wp.array(dtype=wp.vec2i),
    mesh_vertices: wp.array(dtype=wp.vec4i),
    mesh_time: wp.array(dtype=Any),
    mesh_source: wp.array(dtype=wp.int32),
    plane_pairs: wp.array(dtype=wp.vec2i),
    plane_time: wp.array(dtype=wp.float64),
    time_mode: int,
    dummy_vertex: int,
    kind: wp.array(dtype=wp.int32),
    pair: wp.array(dtype=wp.vec2i),
    vertices: wp.array(dtype=wp.vec4i),
    detected: wp.array(dtype=wp.float64),
    source: wp.array(dtype=wp.int32),
    plane: wp.array(dtype=wp.int32),
    row: wp.array(dtype=wp.int32),
    repeated: wp.array(dtype=wp.int32),
):
    """Hit ``tid`` (below ``kept[0]``: the kept hits, read on the device) in sorted order
    (``order``: :func:`sort_keys_kernel`'s values) from the narrow
    phase's buffers or the vertex-plane ones: its kind, pair, vertex indices (vertex-plane: the
    vertex and three times the dummy static vertex), detected time (fraction of the substep),
    source (:func:`kernels.contact_geometry.contact_geometry_kernel`'s) and plane index (0 for mesh
    pairs); ``row`` (the hit's row in the contact set, :func:`match_contacts_kernel`) is reset
    to -1. ``time_mode``: 0 every hit is a proximity contact at ``t* = 0`` (source
    ``TIME_START``); 1 a root's slot (1-3) for the narrow phase's hits at a root of the cubic,
    ``TIME_PLANE`` for plane crossings (the replay recomputes and differentiates ``t*`` for
    those) and ``TIME_DETECTED`` for the other hits; 2 every hit at its detected time
    (``TIME_DETECTED``: the Gauss-Seidel response). ``repeated[0]`` counts the hits whose key
    equals the previous one's (a pair twice in one pass: the contact set's growth and matching
    assume distinct pairs, so the caller refuses it)."""
    i = wp.tid()
    if i >= kept[0]:
        return
    j = int(order[i])
    row[i] = -1
    if i > 0:
        if keys[i] == keys[i - 1]:
            wp.atomic_add(repeated, 0, 1)
    meshes = mesh_count[0]
    if j < meshes:
        kind[i] = mesh_kind[j]
        pair[i] = mesh_pairs[j]
        vertices[i] = mesh_vertices[j]
        plane[i] = 0
        if time_mode == 0:
            detected[i] = wp.float64(0.0)
            source[i] = TIME_START
        else:
            detected[i] = wp.float64(mesh_time[j])
            src = mesh_source[j]
            # only a root's time is recomputed (and differentiated) by the replay: a hit at the
            # start, a collinear or an advancement time enters as the detected constant
            if time_mode == 2 or src < 1 or src > 3:
                src = TIME_DETECTED
            source[i] = src
        return
    p = plane_pairs[j - meshes]
    kind[i] = PAIR_VERTEX_PLANE
    pair[i] = p
    vertices[i] = wp.vec4i(p[0], dummy_vertex, dummy_vertex, dummy_vertex)
    plane[i] = p[1]
    if time_mode == 0:
        detected[i] = wp.float64(0.0)
        source[i] = TIME_START
    else:
        detected[i] = plane_time[j - meshes]
        source[i] = TIME_PLANE
        if time_mode == 2:
            source[i] = TIME_DETECTED


@wp.kernel(enable_backward=False)
def plane_proximity_kernel(
    x: wp.array(dtype=wp.vec3d),
    vertex_ids: wp.array(dtype=wp.int32),
    threshold: wp.array(dtype=wp.float64),
    planes: wp.array(dtype=wp.vec4d),
    plane_count: int,
    separation: wp.float64,
    distance: wp.array(dtype=wp.float64),
    counter: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
):
    """Signed distances of plane-tested vertex ``vertex_ids[tid]`` at positions ``x`` from every
    plane (``distance[tid planes + k]``, kept for the CCD rounds' crossing test) and the
    vertex-plane proximity pairs ``(vertex, plane)``, appended through ``counter[0]``: distance
    below ``threshold[tid] separation`` (a particle resting at the separation is no contact:
    its threshold is a hair below 1)."""
    i = wp.tid()
    v = vertex_ids[i]
    xv = x[v]
    for k in range(plane_count):
        p = planes[k]
        d = wp.dot(xv, wp.vec3d(p[0], p[1], p[2])) - p[3]
        distance[i * plane_count + k] = d
        if d < threshold[i] * separation:
            pairs[wp.atomic_add(counter, 0, 1)] = wp.vec2i(v, k)


@wp.kernel(enable_backward=False)
def plane_crossing_kernel(
    x1: wp.array(dtype=wp.vec3d),
    vertex_ids: wp.array(dtype=wp.int32),
    planes: wp.array(dtype=wp.vec4d),
    plane_count: int,
    start_distance: wp.array(dtype=wp.float64),
    counter: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    time: wp.array(dtype=wp.float64),
):
    """Vertex-plane hits of the straight path from the start (signed distances
    ``start_distance``, :func:`plane_proximity_kernel`) to ``x1``: the vertex ends behind the
    plane, moving inwards; appended through ``counter[0]`` with the crossing time as a fraction
    of the path, ``clamp(d0 / (d0 - d1), 0, 1)``."""
    i = wp.tid()
    v = vertex_ids[i]
    xv = x1[v]
    for k in range(plane_count):
        p = planes[k]
        d1 = wp.dot(xv, wp.vec3d(p[0], p[1], p[2])) - p[3]
        d0 = start_distance[i * plane_count + k]
        if d1 < wp.float64(0.0) and d1 < d0:
            slot = wp.atomic_add(counter, 0, 1)
            pairs[slot] = wp.vec2i(v, k)
            time[slot] = wp.clamp(d0 / (d0 - d1), wp.float64(0.0), wp.float64(1.0))


@wp.kernel(enable_backward=False)
def match_contacts_kernel(
    contact_count: wp.array(dtype=wp.int32),
    contact_kind: wp.array(dtype=wp.int32),
    contact_pair: wp.array(dtype=wp.vec2i),
    key_base: wp.int64,
    hit_keys: wp.array(dtype=wp.int64),
    hit_count: wp.array(dtype=wp.int32),
    row: wp.array(dtype=wp.int32),
):
    """``row[h] = tid`` for the hit ``h`` whose pair is the pair of contact ``tid`` (below
    ``contact_count[0]``; binary search in the ``hit_count[0]`` hits' ascending ``hit_keys``;
    each pair is at most once in the set and once among the hits, so no two threads write one
    entry). Launched over the set's capacity: both counts are read on the device."""
    c = wp.tid()
    if c >= contact_count[0]:
        return
    key = pair_key(contact_kind[c], contact_pair[c], key_base)
    hits = int(hit_count[0])
    lo = int(0)
    hi = hits
    while lo < hi:
        mid = (lo + hi) / 2
        if hit_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < hits:
        if hit_keys[lo] == key:
            row[lo] = wp.int32(c)


@wp.kernel(enable_backward=False)
def approach_kernel(
    hit_count: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3d),
    x1: wp.array(dtype=wp.vec3d),
    lever: wp.array(dtype=wp.vec3d),
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    vertices: wp.array(dtype=wp.vec4i),
    toi: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    row: wp.array(dtype=wp.int32),
    contact_toi: wp.array(dtype=wp.float64),
    particle_qd_minus: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_qd_minus: wp.array(dtype=wp.spatial_vectord),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    particle_time: wp.array(dtype=wp.float64),
    body_time: wp.array(dtype=wp.float64),
    h: wp.float64,
    separation_speed: wp.float64,
    leaving_speed: wp.float64,
    approach_eps: wp.float64,
    end_of_substep: wp.float64,
    counter: wp.array(dtype=wp.int32),
    approaching: wp.array(dtype=wp.int32),
):
    """Whether CCD hit ``tid`` (time ``toi`` [s], weights and normal at it:
    :func:`kernels.contact_geometry.contact_geometry_kernel`) approaches, counted in ``counter[0]``: its
    normal relative velocity at ``t*`` (each vertex's ``v-`` before its owner's earliest
    contact time, the current velocity from then on), or its mean over the straight paths
    ``x0 -> x1`` that the CCD checked, is below ``-approach_eps`` times the largest vertex
    velocity component plus the separation speed (rounding of an exactly separating or
    tangential pair stays inside). A hit whose pair is in the contact set (``row``) at the very
    end of the substep, detected there again, and leaving there at ``leaving_speed`` at least
    (the replayed response's 0: an inelastic impact's normal velocity is 0, and its push has no
    time left) is judged by its velocities alone: its path ends on the contact instead of
    passing through. Threads from ``hit_count[0]`` on (a launch over a bound) do nothing."""
    i = wp.tid()
    if i >= hit_count[0]:
        return
    zero = wp.float64(0.0)
    q = vertices[i]
    w = weights[i]
    n = normals[i]
    ts = toi[i]
    vrel = wp.vec3d(zero, zero, zero)
    vpath = wp.vec3d(zero, zero, zero)
    largest = zero
    for k in range(4):
        vk = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd_minus, body_qd_minus)
        if not (ts < vertex_time(q[k], vertex_type, vertex_owner, particle_time, body_time)):
            vk = vertex_velocity(q[k], vertex_type, vertex_owner, lever, particle_qd, body_qd)
        vrel = vrel + w[k] * vk
        vpath = vpath + w[k] * ((x1[q[k]] - x0[q[k]]) / h)
        largest = wp.max(largest, wp.max(wp.abs(vk[0]), wp.max(wp.abs(vk[1]), wp.abs(vk[2]))))
    vn = wp.dot(vrel, n)
    vn_path = wp.dot(vpath, n)
    eps = approach_eps * (largest + separation_speed)
    leaving = 0
    r = row[i]
    if r >= 0:
        end = h * (wp.float64(1.0) - end_of_substep)
        if contact_toi[r] >= end and ts >= end:
            if (leaving_speed > zero and vn > leaving_speed) or (leaving_speed <= zero and vn >= -eps):
                leaving = 1
    result = 0
    if vn < -eps:
        result = 1
    elif vn_path < -eps and leaving == 0:
        result = 1
    approaching[i] = wp.int32(result)
    if result != 0:
        wp.atomic_add(counter, 0, 1)


DUPLICATE_ROW_TOLERANCE = 1.0e-9
"""Two contacts are one constraint when they move the same vertices with weighted normals
``w_k n`` that agree to this (weights are barycentric, O(1))."""


@wp.func
def row_entry_matches(v: int, wn: wp.vec3d, vertices: wp.vec4i, weights: wp.vec4d, normal: wp.vec3d) -> bool:
    """Whether the contact ``(vertices, weights, normal)`` moves vertex ``v`` with the weighted
    normal ``wn``."""
    found = bool(False)
    for j in range(4):
        if weights[j] != wp.float64(0.0) and vertices[j] == v:
            if wp.length(weights[j] * normal - wn) <= wp.float64(DUPLICATE_ROW_TOLERANCE):
                found = True
    return found


@wp.func
def same_constraint(va: wp.vec4i, wa: wp.vec4d, na: wp.vec3d, vb: wp.vec4i, wb: wp.vec4d, nb: wp.vec3d) -> bool:
    """Whether two contacts are the same constraint on the velocities: the same vertices with
    the same weighted normals (a corner resting on a corner is found by the vertex-face pairs
    of every face at either corner, each with the vertical normal; either orientation of the
    pair gives the same row)."""
    count_a = int(0)
    count_b = int(0)
    same = bool(True)
    for k in range(4):
        if wa[k] != wp.float64(0.0):
            count_a += 1
            if not row_entry_matches(va[k], wa[k] * na, vb, wb, nb):
                same = False
        if wb[k] != wp.float64(0.0):
            count_b += 1
    return same and count_a == count_b


@wp.func
def rigid_only(vertices: wp.vec4i, weights: wp.vec4d, vertex_type: wp.array(dtype=wp.int32)) -> bool:
    """Whether no vertex a contact moves (nonzero weight) is a particle."""
    rigid = bool(True)
    for k in range(4):
        if weights[k] != wp.float64(0.0) and vertex_type[vertices[k]] == VERTEX_PARTICLE:
            rigid = False
    return rigid


@wp.kernel(enable_backward=False)
def add_contacts_kernel(
    hit_count: wp.array(dtype=wp.int32),
    all_new: int,
    approaching: wp.array(dtype=wp.int32),
    row: wp.array(dtype=wp.int32),
    kind: wp.array(dtype=wp.int32),
    pair: wp.array(dtype=wp.vec2i),
    vertices: wp.array(dtype=wp.vec4i),
    source: wp.array(dtype=wp.int32),
    toi: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.vec4d),
    normals: wp.array(dtype=wp.vec3d),
    targets: wp.array(dtype=wp.float64),
    vertex_type: wp.array(dtype=wp.int32),
    record_merge: int,
    contact_kind: wp.array(dtype=wp.int32),
    contact_pair: wp.array(dtype=wp.vec2i),
    contact_vertices: wp.array(dtype=wp.vec4i),
    contact_toi: wp.array(dtype=wp.float64),
    contact_weights: wp.array(dtype=wp.vec4d),
    contact_normals: wp.array(dtype=wp.vec3d),
    contact_targets: wp.array(dtype=wp.float64),
    contact_timed: wp.array(dtype=wp.int32),
    contact_collided: wp.array(dtype=wp.int32),
    normal_impulse: wp.array(dtype=wp.float64),
    friction_impulse: wp.array(dtype=wp.vec3d),
    count: wp.array(dtype=wp.int32),
    merge_hit: wp.array(dtype=wp.int32),
    keep_toi: wp.array(dtype=wp.int32),
    keep_target: wp.array(dtype=wp.int32),
):
    """Grows the contact set (``count[0]`` rows) by the approaching ones of the ``hit_count[0]``
    hits (every hit with a normal with ``all_new``: the proximity pass into the empty set, less
    the hits between rigid or static surfaces that repeat an accepted hit's constraint,
    :func:`same_constraint`: their targets agree to rounding, being computed from the same
    points), launched with ``dim=1`` so that new pairs are appended in the hits' order on every
    device. A hit whose pair is in the set (``row``) gives it its weights and normal, the
    earlier of the two times (ties and NaN keep the old one; ``timed``, whether the replay
    differentiates the time, goes with it) and the larger target; a new pair is appended with
    zero accumulated impulses. ``collided``: 1 for the rows a CCD round's hit reached (``all_new
    == 0``), 0 for the proximity pass's. ``count[0]``: the rows after the call.

    With ``record_merge`` the decisions the taped replay repeats
    (:func:`kernels.contact_geometry.merge_contacts_kernel`) are written per row of the grown set:
    ``merge_hit`` the hit a row takes its geometry from (-1: unchanged), ``keep_toi`` /
    ``keep_target`` whether it kept its own time / target."""
    zero = wp.float64(0.0)
    base = int(count[0])
    n = base
    if record_merge != 0:
        for r in range(base):
            merge_hit[r] = -1
            keep_toi[r] = 0
            keep_target[r] = 0
    for h in range(int(hit_count[0])):
        if all_new == 0 and approaching[h] == 0:
            continue
        if all_new != 0 and wp.length_sq(normals[h]) == zero:
            continue  # a touching pair with no defined normal (contact_geometry_kernel)
        if all_new != 0 and rigid_only(vertices[h], weights[h], vertex_type):
            # a proximity hit between rigid or static surfaces that repeats an accepted one's
            # constraint (same_constraint) adds a redundant row: the solves would split one
            # load among copies of itself (cloth is left alone: its near-copies part
            # continuously as it bends, and dropping one below a threshold would be a jump)
            duplicate = bool(False)
            for r2 in range(base, n):
                if not duplicate and same_constraint(vertices[h], weights[h], normals[h], contact_vertices[r2],
                                                     contact_weights[r2], contact_normals[r2]):
                    duplicate = True
            if duplicate:
                continue
        r = int(-1)
        if all_new == 0:
            r = int(row[h])
        src = source[h]
        timed = int(0)
        if (src >= 1 and src <= 3) or src == TIME_PLANE:
            timed = 1
        if r >= 0:
            if record_merge != 0:
                merge_hit[r] = wp.int32(h)
                if contact_toi[r] <= toi[h]:
                    keep_toi[r] = 1
                if contact_targets[r] >= targets[h]:
                    keep_target[r] = 1
            contact_weights[r] = weights[h]
            contact_normals[r] = normals[h]
            if toi[h] < contact_toi[r]:
                contact_toi[r] = toi[h]
                contact_timed[r] = wp.int32(timed)
            if targets[h] > contact_targets[r]:
                contact_targets[r] = targets[h]
            contact_collided[r] = wp.int32(1)
        else:
            r = n
            n = n + 1
            contact_kind[r] = kind[h]
            contact_pair[r] = pair[h]
            contact_vertices[r] = vertices[h]
            contact_toi[r] = toi[h]
            contact_weights[r] = weights[h]
            contact_normals[r] = normals[h]
            contact_targets[r] = targets[h]
            contact_timed[r] = wp.int32(timed)
            contact_collided[r] = wp.int32(1 - all_new)
            normal_impulse[r] = zero
            friction_impulse[r] = wp.vec3d(zero, zero, zero)
            if record_merge != 0:
                merge_hit[r] = wp.int32(h)
                keep_toi[r] = 0
                keep_target[r] = 0
    count[0] = wp.int32(n)


@wp.kernel(enable_backward=False)
def round_control_kernel(counts: wp.array(dtype=wp.int32), kept: int, repeated: int, approaching: int,
                         uncovered: int, beyond_reach: int, round_index: int, events: int, go: int,
                         max_hits: int, max_iterations: int):
    """The continue test of a Gauss-Seidel CCD round run on the device (launched with ``dim=1``
    after the round's detection and decisions): ``counts[go]`` becomes 1, ``counts[round_index]``
    moves to the next round and ``counts[events]`` adds the approaching hits when the round's hits
    approach, its motion stayed in the broad-phase cover and within the reach radii, no pair came
    twice, the hits are within ``max_hits`` and the round is below ``max_iterations`` (the round's
    contacts are then added and solved); otherwise ``counts[go]`` becomes 0 and the round is left
    for the host (done when nothing approaches; else tested again there, or the fail-safe's). The
    other arguments are slots of ``counts`` (:data:`sim.contact.detect.COUNT_SLOTS`)."""
    n = counts[approaching]
    held = counts[uncovered] == 0 and counts[beyond_reach] == 0 and counts[repeated] == 0
    if n > 0 and held and counts[kept] <= max_hits and counts[round_index] < max_iterations:
        counts[go] = 1
        counts[round_index] = counts[round_index] + 1
        counts[events] = counts[events] + n
    else:
        counts[go] = 0
