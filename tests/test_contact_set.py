"""The collision response's contact bookkeeping on the device (:mod:`kernels.contact_set`,
:class:`sim.contact.contacts.Contacts` / :class:`~sim.contact.contacts.Hits`): hits in canonical
pair order, matched to the contact set, and the set's growth rules (a pair again: the new
geometry, the earlier time, the larger target; new pairs appended in order), each checked
against numpy on hand-made or random rows."""

import numpy as np
import warp as wp

from sim.contact.contacts import Contacts, Hits
from kernels.contact_set import KEY_NONE, add_contacts_kernel, gather_hits_kernel, match_contacts_kernel, sort_keys_kernel
from kernels.active_set import owner_rows_finish_kernel, owner_rows_kernel, owner_rows_reset_kernel, owner_times_kernel, owner_times_reset_kernel

wp.init()
DEV = "cpu"
KEY_BASE = 1000


def _key(kind, a, b):
    return (kind * KEY_BASE + a) * KEY_BASE + b


def test_heap_sort_orders_keys_and_carries_their_values():
    """Ascending keys with the values moved along, the left-out key last (sizes 0 to 3000, keys
    up to 2^62): numpy's sort is the reference."""
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 17, 256, 3000):
        keys = rng.choice(2 ** 62, size=n, replace=False).astype(np.int64)
        if n > 4:
            keys[rng.choice(n, 3, replace=False)] = int(KEY_NONE)
        k = wp.array(np.concatenate([keys, keys]) if n else np.zeros(2, np.int64), dtype=wp.int64, device=DEV)
        v = wp.array(np.arange(max(2 * n, 2), dtype=np.int32), dtype=wp.int32, device=DEV)
        wp.launch(sort_keys_kernel, 1, [n, k, v], device=DEV)
        order = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(k.numpy()[:n], keys[order])
        np.testing.assert_array_equal(keys[v.numpy()[:n]], keys[order])  # each value went with its key


def _fill(rows, **columns):
    rows.reserve(len(next(iter(columns.values()))))
    for name, values in columns.items():
        arr = getattr(rows, name)
        arr.assign(np.concatenate([np.asarray(values, dtype=arr.numpy().dtype).reshape((-1,) + arr.numpy().shape[1:]),
                                   arr.numpy()[len(values):]]))
    rows.count = len(next(iter(columns.values())))


def test_a_pair_again_takes_the_new_geometry_the_earlier_time_and_the_larger_target():
    """Two rows in the set; the hits (sorted): the second row's pair again (earlier time, smaller
    target), a new pair, a new pair that does not approach. The set grows by one row; the repeated
    pair takes the new weights and normal, the earlier time (and whether it is differentiated)
    and keeps its larger target and its impulses; the merge decisions say so per row."""
    cs, H = Contacts(DEV), Hits(DEV)
    w_old = [[1.0, -0.5, -0.25, -0.25]] * 2
    _fill(cs, kind=[0, 0], pair=[[1, 2], [3, 4]], vertices=[[0, 1, 2, 3], [4, 5, 6, 7]], toi=[0.0, 0.5],
          weights=w_old, normals=[[0.0, 0.0, 1.0]] * 2, targets=[0.1, 0.9], timed=[0, 0],
          normal_impulse=[2.0, 3.0], friction_impulse=[[0.1, 0.0, 0.0]] * 2)
    cs.counter.assign(np.array([2], dtype=np.int32))
    w_new = [[1.0, -0.2, -0.3, -0.5], [1.0, -1.0, 0.0, 0.0], [0.5, 0.5, -0.5, -0.5]]
    _fill(H, kind=[0, 0, 1], pair=[[3, 4], [5, 6], [7, 8]], vertices=[[4, 5, 6, 7], [8, 9, 10, 11], [1, 2, 3, 4]],
          source=[1, 4, 2], toi=[0.25, 0.75, 0.1], weights=w_new, normals=[[1.0, 0.0, 0.0]] * 3,
          targets=[0.4, 0.2, 0.3], approaching=[1, 1, 0])
    H.keys.assign(np.concatenate([[_key(0, 3, 4), _key(0, 5, 6), _key(1, 7, 8)], np.zeros(H.keys.shape[0] - 3)]).astype(np.int64))
    H.row.fill_(-1)
    hit_count = wp.array([H.count], dtype=wp.int32, device=DEV)
    # over the set's capacity: the rows past its count (on the device) do nothing
    wp.launch(match_contacts_kernel, cs.capacity, [cs.counter, cs.kind, cs.pair, KEY_BASE, H.keys, hit_count, H.row],
              device=DEV)
    np.testing.assert_array_equal(H.host("row"), [1, -1, -1])
    merge = [wp.zeros(8, dtype=wp.int32, device=DEV) for _ in range(3)]
    wp.launch(add_contacts_kernel, 1, [
        hit_count, 0, H.approaching, H.row, H.kind, H.pair, H.vertices, H.source, H.toi, H.weights, H.normals,
        H.targets, wp.zeros(16, dtype=wp.int32, device=DEV), 1, cs.kind, cs.pair, cs.vertices, cs.toi,
        cs.weights, cs.normals, cs.targets, cs.timed, cs.collided, cs.normal_impulse, cs.friction_impulse,
        cs.counter, *merge],
        device=DEV)
    cs.count = int(cs.counter.numpy()[0])
    assert cs.count == 3
    np.testing.assert_array_equal(cs.host("pair"), [[1, 2], [3, 4], [5, 6]])
    np.testing.assert_array_equal(cs.host("toi"), [0.0, 0.25, 0.75])
    np.testing.assert_array_equal(cs.host("targets"), [0.1, 0.9, 0.2])
    np.testing.assert_array_equal(cs.host("weights"), [w_old[0], w_new[0], w_new[1]])
    np.testing.assert_array_equal(cs.host("timed"), [0, 1, 0])  # source 1 (a root) is differentiated, 4 not
    np.testing.assert_array_equal(cs.host("collided"), [0, 1, 1])  # the rows this CCD round's hits reached
    np.testing.assert_array_equal(cs.host("normal_impulse"), [2.0, 3.0, 0.0])
    np.testing.assert_array_equal(cs.host("friction_impulse")[:, 0], [0.1, 0.1, 0.0])
    np.testing.assert_array_equal(merge[0].numpy()[:3], [-1, 0, 1])  # the hit each row takes
    np.testing.assert_array_equal(merge[1].numpy()[:3], [0, 0, 0])  # row 1 took the earlier time
    np.testing.assert_array_equal(merge[2].numpy()[:3], [0, 1, 0])  # and kept its larger target


def test_owner_times_and_rows_prefer_differentiated_then_later_rows():
    """Earliest time per particle (a vertex with a nonzero weight) and per body (any vertex), and
    the row that sets it: among rows at the same time a differentiated one, then the last;
    impact-zone members get time 0 and row -2. Numpy over the same rows is the reference."""
    # vertices: 0-3 particles 0-3, 4-5 rigid (body 0), 6 static
    vertex_type = wp.array([0, 0, 0, 0, 1, 1, 2], dtype=wp.int32, device=DEV)
    vertex_owner = wp.array([0, 1, 2, 3, 0, 0, 0], dtype=wp.int32, device=DEV)
    vertices = [[0, 1, 2, 6], [0, 4, 5, 6], [1, 4, 6, 6], [0, 2, 3, 6], [3, 1, 2, 6]]
    weights = [[1.0, -0.5, -0.5, 0.0], [1.0, -1.0, 0.0, 0.0], [1.0, -1.0, 0.0, 0.0], [1.0, 0.0, -1.0, 0.0],
               [1.0, -1.0, 0.0, 0.0]]
    toi = [0.3, 0.3, 0.1, 0.3, 0.2]
    timed = [1, 0, 1, 0, 0]
    C, P, B = len(toi), 4, 1
    arr = lambda a, t: wp.array(np.array(a), dtype=t, device=DEV)
    v_w, w_w, t_w, td_w = arr(vertices, wp.vec4i), arr(weights, wp.vec4d), arr(toi, wp.float64), arr(timed, wp.int32)
    tp, tb = wp.zeros(P, dtype=wp.float64, device=DEV), wp.zeros(B, dtype=wp.float64, device=DEV)
    kp, kb = wp.zeros(P, dtype=wp.int32, device=DEV), wp.zeros(B, dtype=wp.int32, device=DEV)
    rp, rb = wp.zeros(P, dtype=wp.int32, device=DEV), wp.zeros(B, dtype=wp.int32, device=DEV)
    for zone_p in ([0, 0, 0, 0], [0, 0, 1, 0]):
        zp, zb = arr(zone_p, wp.int32), arr([0], wp.int32)
        wp.launch(owner_times_reset_kernel, P + B, [P, zp, zb, tp, tb], device=DEV)
        wp.launch(owner_rows_reset_kernel, P + B, [P, kp, kb], device=DEV)
        # over more rows than the set holds: the rows past its count (on the device) are skipped
        wp.launch(owner_times_kernel, C + 3, [arr([C], wp.int32), v_w, w_w, t_w, vertex_type, vertex_owner, tp, tb],
                  device=DEV)
        wp.launch(owner_rows_kernel, C, [v_w, w_w, t_w, td_w, vertex_type, vertex_owner, tp, tb, kp, kb], device=DEV)
        wp.launch(owner_rows_finish_kernel, P + B, [P, kp, kb, zp, zb, rp, rb], device=DEV)
        # reference
        ref_t = np.full(P, np.inf)
        ref_r = np.full(P, -1)
        for particle in range(P):
            rows = [(toi[c], timed[c], c) for c in range(C) for s in range(4)
                    if vertices[c][s] == particle and weights[c][s] != 0.0]
            if rows:
                t = min(r[0] for r in rows)
                ref_t[particle] = t
                ref_r[particle] = max((r[1], r[2]) for r in rows if r[0] == t)[1]
            if zone_p[particle]:
                ref_t[particle], ref_r[particle] = 0.0, -2
        np.testing.assert_array_equal(tp.numpy(), ref_t)
        np.testing.assert_array_equal(rp.numpy(), ref_r)
        # body 0: rows 1 (0.3, untimed) and 2 (0.1, timed) -> time 0.1, row 2
        np.testing.assert_array_equal(tb.numpy(), [0.1])
        np.testing.assert_array_equal(rb.numpy(), [2])


def test_radix_sort_gives_the_heap_sorts_order():
    """Off the CPU a large detection pass is ordered by Warp's radix sort
    (:data:`sim.contact.tuning.DEVICE_SORT_MIN`): for distinct keys it must give the order of
    the heap sort (checked here on the CPU, where both run), so the contacts are the same
    whichever sorted them."""
    rng = np.random.default_rng(1)
    for n in (5, 2049, 5000):
        keys = rng.choice(2 ** 62, size=n, replace=False).astype(np.int64)
        heap_k = wp.array(np.concatenate([keys, keys]), dtype=wp.int64, device=DEV)
        heap_v = wp.array(np.arange(2 * n, dtype=np.int32), dtype=wp.int32, device=DEV)
        radix_k = wp.array(np.concatenate([keys, keys]), dtype=wp.int64, device=DEV)
        radix_v = wp.array(np.arange(2 * n, dtype=np.int32), dtype=wp.int32, device=DEV)
        wp.launch(sort_keys_kernel, 1, [n, heap_k, heap_v], device=DEV)
        wp.utils.radix_sort_pairs(radix_k, radix_v, n)
        np.testing.assert_array_equal(radix_k.numpy()[:n], heap_k.numpy()[:n])
        np.testing.assert_array_equal(radix_v.numpy()[:n], heap_v.numpy()[:n])


def test_gather_counts_a_pair_twice_and_the_handler_refuses_it():
    """The contact set's growth and its matching assume each pair once per detection pass: the
    gather kernel counts repeated keys, and the collision handler raises instead of adding a
    pair twice (a broad phase that returned a candidate twice)."""
    n = 4
    keys = wp.array(np.array([_key(0, 1, 2), _key(0, 3, 4), _key(0, 3, 4), _key(1, 5, 6)] * 2, dtype=np.int64),
                    dtype=wp.int64, device=DEV)
    order = wp.array(np.arange(2 * n, dtype=np.int32), dtype=wp.int32, device=DEV)
    H = Hits(DEV)
    mesh = dict(kind=wp.array(np.array([0, 0, 0, 1], dtype=np.int32), dtype=wp.int32, device=DEV),
                pairs=wp.array(np.array([[1, 2], [3, 4], [3, 4], [5, 6]], dtype=np.int32), dtype=wp.vec2i, device=DEV),
                vertices=wp.zeros(n, dtype=wp.vec4i, device=DEV), time=wp.zeros(n, dtype=wp.float64, device=DEV),
                source=wp.zeros(n, dtype=wp.int32, device=DEV))
    repeated = wp.zeros(1, dtype=wp.int32, device=DEV)
    for k in (keys, wp.array(np.array([_key(0, 1, 2), _key(0, 3, 4), _key(0, 5, 4), _key(1, 5, 6)] * 2,
                                      dtype=np.int64), dtype=wp.int64, device=DEV)):
        repeated.zero_()
        counts = wp.array([n], dtype=wp.int32, device=DEV)  # kept hits and mesh hits
        wp.launch(gather_hits_kernel, n, [k, order, counts, counts, mesh["kind"], mesh["pairs"], mesh["vertices"], mesh["time"],
                                          mesh["source"], wp.zeros(1, dtype=wp.vec2i, device=DEV),
                                          wp.zeros(1, dtype=wp.float64, device=DEV), 2, 9, H.kind, H.pair, H.vertices,
                                          H.detected, H.source, H.plane, H.row, repeated], device=DEV)
        assert int(repeated.numpy()[0]) == (1 if k is keys else 0)

    import pytest

    from sim.contact.response import ImpulseCollisionHandler
    from sim.builder import ModelBuilder
    from sim.mesh_io import box_mesh

    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particle((0.0, 0.0, 0.1 + 5e-4), velocity=(0.0, 0.0, -1.0), mass=0.1)
    b.add_static_mesh(*box_mesh((0.2, 0.2, 0.1)))
    b.set_contact(restitution=0.0, friction=0.0, thickness=1e-3)
    model = b.finalize()
    handler = ImpulseCollisionHandler(model)
    s0, s1 = model.state(), model.state()
    s1.particle_q.assign(s0.particle_q.numpy() + [0.0, 0.0, -1.0 / 240])
    s1.particle_qd.assign(s0.particle_qd.numpy())
    assert handler(s0, s1, 1.0 / 240) is not None  # the particle rests on the box: a proximity contact
    near = handler.detect.narrow.near_count_covered

    def near_twice(*args, **kwargs):  # every pair the proximity test finds, reported twice
        bound = near(*args, **kwargs)
        counter = handler.detect.narrow._counter  # the hits' count, on the device
        count = int(counter.numpy()[0])
        hits = handler.detect.narrow.hits
        for name in ("kind", "pairs", "offset", "weights", "vertices"):
            a = np.concatenate([hits[name].numpy()[:count]] * 2)
            hits[name].assign(np.concatenate([a, hits[name].numpy()[2 * count:]])[:hits[name].shape[0]])
        counter.assign(np.array([2 * count], dtype=np.int32))
        return 2 * bound

    handler.detect.narrow.near_count_covered = near_twice
    with pytest.raises(RuntimeError, match="pair twice"):
        handler(s0, s1, 1.0 / 240)


def test_proximity_hits_repeating_a_rigid_constraint_join_once():
    """The proximity pass into the empty set (``all_new``): a corner resting on a corner is found
    by the vertex-face pairs of several faces, each the same row (vertex 0 against vertex 1, the
    normal +z; the second hit with the pair's other orientation: vertex 1 against vertex 0, normal
    -z). Between rigid vertices the copies join once; the same rows between particles all join
    (cloth's near-copies part continuously); a hit with another weight or normal is no copy."""
    for vertex_type, expected in ((1, 3), (0, 5)):
        cs, H = Contacts(DEV), Hits(DEV)
        up, down = [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]
        _fill(H, kind=[0] * 5, pair=[[0, 1], [0, 2], [1, 3], [0, 4], [0, 5]],
              vertices=[[0, 1, 2, 3], [0, 4, 1, 5], [1, 0, 6, 7], [0, 1, 2, 3], [0, 1, 2, 3]],
              source=[0] * 5, toi=[0.0] * 5,
              weights=[[1.0, -1.0, 0.0, 0.0], [1.0, 0.0, -1.0, 0.0], [1.0, -1.0, 0.0, 0.0], [1.0, -0.5, -0.5, 0.0],
                       [1.0, -1.0, 0.0, 0.0]],
              normals=[up, up, down, up, [0.0, 1.0, 0.0]], targets=[0.1] * 5, approaching=[0] * 5)
        cs.reserve(8)
        merge = [wp.zeros(8, dtype=wp.int32, device=DEV) for _ in range(3)]
        wp.launch(add_contacts_kernel, 1, [
            wp.array([H.count], dtype=wp.int32, device=DEV), 1, H.approaching, H.row, H.kind, H.pair, H.vertices,
            H.source, H.toi, H.weights, H.normals, H.targets,
            wp.array(np.full(16, vertex_type, np.int32), dtype=wp.int32, device=DEV), 1, cs.kind,
            cs.pair, cs.vertices, cs.toi, cs.weights, cs.normals, cs.targets, cs.timed, cs.collided,
            cs.normal_impulse, cs.friction_impulse, cs.counter, *merge], device=DEV)
        count = int(cs.counter.numpy()[0])
        assert count == expected, (vertex_type, count)
        if vertex_type == 1:
            np.testing.assert_array_equal(merge[0].numpy()[:3], [0, 3, 4])  # the hit each row takes
