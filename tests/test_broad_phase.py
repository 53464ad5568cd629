"""Broad phase (collision.broad_phase) against a brute-force O(n^2) numpy reference.

The reference computes every swept box in float64 and tests every vertex-face and edge-edge pair:
a pair is a candidate when the boxes are within ``inflation`` on every axis, it is not adjacent,
and the body rules allow it. The Warp BVH must return every reference pair (zero misses); the only
extra pairs it may return are within the documented float32 pad of touching.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from collision.broad_phase import PAD_ABS, PAD_REL, BroadPhase, candidate_pairs, mesh_edges

# ------------------------------------------------------------------------------------------------
# reference


def _boxes(x0, x1, idx):
    pts = np.concatenate([x0[idx], x1[idx]], axis=1)  # (N, 2k, 3)
    return pts.min(axis=1), pts.max(axis=1)


def _overlap(lo_a, hi_a, lo_b, hi_b, tol):
    """(Na, Nb) bool: boxes within ``tol`` of each other on every axis (closed)."""
    return np.all(
        (lo_a[:, None, :] - tol <= hi_b[None, :, :]) & (lo_b[None, :, :] <= hi_a[:, None, :] + tol), axis=-1
    )


def reference_pairs(x0, x1, faces, edges, *, groups=None, inflation=0.0, self_ok=None, static=None, slack=0.0):
    """Brute force. ``self_ok`` / ``static``: per-body bool arrays (default: all self, none static).
    ``slack`` widens the tolerance (to bound the pad's extra pairs from above)."""
    nv = len(x0)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    groups = np.zeros(nv, dtype=np.int64) if groups is None else np.asarray(groups)
    nb = int(groups.max()) + 1 if nv else 1
    self_ok = np.ones(nb, bool) if self_ok is None else np.asarray(self_ok, bool)
    static = np.zeros(nb, bool) if static is None else np.asarray(static, bool)
    self_ok = self_ok & ~static

    def allowed(ba, bb):
        same = ba[:, None] == bb[None, :]
        return np.where(same, self_ok[ba][:, None], ~(static[ba][:, None] & static[bb][None, :]))

    tol = inflation + slack
    vlo, vhi = _boxes(x0, x1, np.arange(nv)[:, None])
    vf = np.zeros((0, 2), np.int64)
    if len(faces):
        flo, fhi = _boxes(x0, x1, faces)
        m = _overlap(vlo, vhi, flo, fhi, tol)
        m &= ~np.any(faces[None, :, :] == np.arange(nv)[:, None, None], axis=-1)
        m &= allowed(groups, groups[faces[:, 0]])
        vf = np.argwhere(m)
    ee = np.zeros((0, 2), np.int64)
    if len(edges):
        elo, ehi = _boxes(x0, x1, edges)
        m = _overlap(elo, ehi, elo, ehi, tol)
        m &= np.triu(np.ones_like(m), 1)
        share = (edges[:, None, 0:1] == edges[None, :, :]).any(-1) | (edges[:, None, 1:2] == edges[None, :, :]).any(-1)
        m &= ~share
        eg = groups[edges[:, 0]]
        m &= allowed(eg, eg)
        ee = np.argwhere(m)
    return vf, ee  # argwhere is row-major: already lexicographically sorted


def _as_set(pairs):
    return set(map(tuple, np.asarray(pairs).tolist()))


def check_against_reference(x0, x1, faces, edges=None, *, groups=None, inflation=0.0, self_collision=True, static=None):
    """Run the broad phase and compare with the reference; returns (vf, ee, ref_vf, ref_ee)."""
    vf, ee = candidate_pairs(
        x0, x1, faces, edges, groups=groups, inflation=inflation, self_collision=self_collision, static=static
    )
    e = mesh_edges(faces) if edges is None else np.asarray(edges)
    nb = int(np.max(groups)) + 1 if groups is not None else 1
    self_ok = np.full(nb, self_collision) if isinstance(self_collision, bool) else np.asarray(self_collision)
    ref_kw = dict(groups=groups, inflation=inflation, self_ok=self_ok, static=static)
    rvf, ree = reference_pairs(x0, x1, faces, e, **ref_kw)
    # the float32 pad may add pairs within ~PAD_REL * |coordinate| of touching, never more
    scale = max(np.abs(x0).max(initial=0.0), np.abs(x1).max(initial=0.0)) + inflation
    slack = 4 * PAD_REL * scale + 4 * PAD_ABS
    svf, see = reference_pairs(x0, x1, faces, e, slack=slack, **ref_kw)

    for name, got, ref, loose in (("vf", vf, rvf, svf), ("ee", ee, ree, see)):
        assert got.dtype == np.int64 and got.ndim == 2 and got.shape[1] == 2, name
        g, r = _as_set(got), _as_set(ref)
        missed = r - g
        assert not missed, f"{name}: {len(missed)} missed pairs, e.g. {sorted(missed)[:5]}"
        extra = g - _as_set(loose)
        assert not extra, f"{name}: pairs beyond the pad tolerance, e.g. {sorted(extra)[:5]}"
        assert len(g) == len(got), f"{name}: duplicate rows"
        assert np.array_equal(got, np.array(sorted(g), dtype=np.int64).reshape(-1, 2)), f"{name}: not sorted"
    return vf, ee, rvf, ree


# ------------------------------------------------------------------------------------------------
# meshes


def grid(n, size=1.0, z=0.0):
    """n x n vertex grid in the plane z, two triangles per cell."""
    u = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    x = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return x, faces


def icosphere(level, radius=1.0):
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    v = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(level):
        cache, nf = {}, []

        def mid(i, j):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = v[i] + v[j]
                v.append(m / np.linalg.norm(m))
                cache[key] = len(v) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = nf
    return np.array(v) * radius, np.array(f)


def triangle_soup(rng, n_tri, box=1.0, size=0.15, motion=0.1):
    """n_tri independent triangles (no shared vertices) with random linear motion."""
    centres = rng.uniform(-box, box, (n_tri, 1, 3))
    x0 = (centres + rng.normal(0, size, (n_tri, 3, 3))).reshape(-1, 3)
    x1 = x0 + rng.normal(0, motion, x0.shape)
    faces = np.arange(3 * n_tri).reshape(n_tri, 3)
    return x0, x1, faces


# ------------------------------------------------------------------------------------------------
# correctness against the reference


@pytest.mark.parametrize("seed", range(4))
def test_triangle_soup_matches_reference(seed):
    rng = np.random.default_rng(seed)
    x0, x1, faces = triangle_soup(rng, 300)
    vf, ee, rvf, ree = check_against_reference(x0, x1, faces, inflation=[0.0, 1e-3, 0.02, 0.1][seed])
    assert len(rvf) > 50 and len(ree) > 50  # the scenes are not trivially empty


@pytest.mark.parametrize("seed", range(3))
def test_random_connected_mesh_matches_reference(seed):
    """A noisy sphere mesh (shared vertices and edges) crumpling randomly: self-collision."""
    rng = np.random.default_rng(100 + seed)
    x0, faces = icosphere(2)  # 162 vertices, 320 faces
    x0 = x0 + rng.normal(0, 0.05, x0.shape)
    x1 = x0 * rng.uniform(0.3, 1.2, (len(x0), 1)) + rng.normal(0, 0.1, x0.shape)
    check_against_reference(x0, x1, faces, inflation=0.01 * seed)


@pytest.mark.parametrize("fold", [0.0, 0.5, 1.0])
def test_folding_cloth_matches_reference(fold):
    """A 16x16 cloth folding over itself: near-contact everywhere."""
    x0, faces = grid(16, 1.0)
    x1 = x0.copy()
    right = x0[:, 0] > 0
    x1[right, 0] = -x0[right, 0] * fold + x0[right, 0] * (1 - fold)
    x1[right, 2] = 0.02 + 0.1 * (1 - fold) * x0[right, 0]
    x1[:, 2] += 1e-3 * np.sin(7 * x0[:, 1])
    vf, ee, rvf, ree = check_against_reference(x0, x1, faces, inflation=5e-3)
    assert len(rvf) > 100 and len(ree) > 100


def test_explicit_edges_and_free_vertices():
    """Explicit edge list (a subset, in any order, flipped) and vertices that belong to no face."""
    rng = np.random.default_rng(7)
    x0, x1, faces = triangle_soup(rng, 120)
    extra = rng.uniform(-1, 1, (40, 3))
    x0 = np.concatenate([x0, extra])
    x1 = np.concatenate([x1, extra + rng.normal(0, 0.2, extra.shape)])
    edges = mesh_edges(faces)[rng.permutation(len(faces) * 3)[:200]][:, ::-1].copy()
    edges = np.concatenate([edges, [[len(x0) - 1, len(x0) - 2], [len(x0) - 3, len(x0) - 4]]])
    check_against_reference(x0, x1, faces, edges, inflation=0.01)


def test_two_bodies_and_self_collision_flags():
    """Cloth (body 0) over a sphere (body 1): self-collision on/off, per body, static sphere."""
    xc, fc = grid(12, 1.4, 0.55)
    xs, fs = icosphere(2, 0.5)
    x0 = np.concatenate([xc, xs])
    faces = np.concatenate([fc, fs + len(xc)])
    groups = np.r_[np.zeros(len(xc), int), np.ones(len(xs), int)]
    x1 = x0.copy()
    x1[: len(xc), 2] -= 0.3 * np.cos(2 * xc[:, 0]) * np.cos(2 * xc[:, 1])
    x1[len(xc):] += [0.0, 0.0, 0.05]  # the sphere moves too (not static in most cases)

    results = {}
    for name, kw in {
        "all": dict(self_collision=True),
        "none": dict(self_collision=False),
        "cloth_only": dict(self_collision=[True, False]),
        "sphere_only": dict(self_collision=np.array([False, True])),
        "static_sphere": dict(self_collision=True, static=[False, True]),
        "both_static": dict(self_collision=True, static=[True, True]),
    }.items():
        results[name] = check_against_reference(x0, x1, faces, groups=groups, inflation=1e-2, **kw)

    vbody = groups
    fbody = groups[faces[:, 0]]
    ebody = groups[mesh_edges(faces)[:, 0]]
    vf, ee = results["none"][:2]
    assert len(vf) and np.all(vbody[vf[:, 0]] != fbody[vf[:, 1]])
    assert len(ee) and np.all(ebody[ee[:, 0]] != ebody[ee[:, 1]])
    vf, ee = results["cloth_only"][:2]
    same = vbody[vf[:, 0]] == fbody[vf[:, 1]]
    assert same.any() and np.all(vbody[vf[same, 0]] == 0)
    vf, ee = results["static_sphere"][:2]
    assert not np.any((vbody[vf[:, 0]] == 1) & (fbody[vf[:, 1]] == 1))
    assert not np.any((ebody[ee[:, 0]] == 1) & (ebody[ee[:, 1]] == 1))
    assert np.any((vbody[vf[:, 0]] == 0) & (fbody[vf[:, 1]] == 0))
    vf, ee = results["both_static"][:2]
    assert len(vf) == 0 and len(ee) == 0
    assert len(results["all"][0]) > len(results["cloth_only"][0]) > len(results["none"][0])


def test_static_bodies_never_collide_with_each_other():
    """Bodies 1 and 2 are static and overlap each other; body 0 (cloth) falls through both."""
    xc, fc = grid(10, 1.4, 0.3)
    xa, fa = icosphere(1, 0.4)
    xb, fb = xa + [0.3, 0.0, 0.0], fa
    x0 = np.concatenate([xc, xa, xb])
    faces = np.concatenate([fc, fa + len(xc), fb + len(xc) + len(xa)])
    groups = np.r_[np.zeros(len(xc), int), np.ones(len(xa), int), np.full(len(xb), 2)]
    x1 = x0.copy()
    x1[: len(xc), 2] -= 0.6
    vbody, fbody = groups, groups[faces[:, 0]]
    ebody = groups[mesh_edges(faces)[:, 0]]
    for static in ([False, True, True], [False, False, False]):
        vf, ee, _, _ = check_against_reference(x0, x1, faces, groups=groups, inflation=1e-2, static=static)
        cross = {(1, 2), (2, 1)}
        n_vf = sum((int(p), int(q)) in cross for p, q in zip(vbody[vf[:, 0]], fbody[vf[:, 1]]))
        n_ee = sum((int(p), int(q)) in cross for p, q in zip(ebody[ee[:, 0]], ebody[ee[:, 1]]))
        if static[1]:
            assert n_vf == 0 and n_ee == 0
            assert np.any(vbody[vf[:, 0]] == 0) and np.any(fbody[vf[:, 1]] != 0)  # cloth still hits them
        else:
            assert n_vf > 0 and n_ee > 0  # the overlap is real: only the static rule removes it


@pytest.mark.parametrize("seed", range(3))
def test_many_bodies_mixed_flags_match_reference(seed):
    """Several bodies (per-body BVHs) with interleaved numbering against the brute-force reference.

    Bodies: 0 a cloth with self-collision, 1 a deforming sphere, 2 and 3 static (overlapping each
    other), 4 loose vertices with no face, 5 unused (no vertex), 6 a single free triangle with a
    lone extra edge. Vertex ids, faces and edges are shuffled so no body is contiguous in the
    caller's numbering (the body sort and the index maps back must be exact); a reused BroadPhase
    refits and rebuilds the per-body trees over moving steps, with changing inflation and a pair
    buffer that grows mid-run, and matches a fresh query each time.
    """
    rng = np.random.default_rng(300 + seed)
    xc, fc = grid(9, 1.2, 0.2)
    xs, fs = icosphere(1, 0.35)
    xa, fa = icosphere(1, 0.3)
    xb, fb = grid(6, 1.0, -0.05)
    xl = rng.uniform(-0.6, 0.6, (25, 3))
    xt = np.array([[0.0, 0.0, 0.1], [0.3, 0.0, 0.1], [0.0, 0.3, 0.1], [0.2, 0.2, 0.05]])
    parts = [(xc, fc, 0), (xs + [0.1, 0.0, 0.3], fs, 1), (xa, fa, 2), (xb, fb, 3), (xl, None, 4), (xt, [[0, 1, 2]], 6)]
    x0, faces, edges, groups = [], [], [], []
    n = 0
    for x, f, body in parts:
        x0.append(x)
        groups.append(np.full(len(x), body))
        if f is not None:
            f = np.asarray(f) + n
            faces.append(f)
            edges.append(mesh_edges(f))
        n += len(x)
    edges.append([[n - 2, n - 1]])  # body 6: an edge that belongs to no face
    x0, groups = np.concatenate(x0), np.concatenate(groups)
    faces, edges = np.concatenate(faces), np.concatenate(edges)
    # shuffle vertex ids, face order, edge order and edge direction
    perm = rng.permutation(len(x0))  # new id of old vertex i is inv[i]
    inv = np.argsort(perm)
    x0, groups = x0[perm], groups[perm]
    faces = inv[faces][rng.permutation(len(faces))]
    edges = inv[edges][rng.permutation(len(edges))]
    flip = rng.random(len(edges)) < 0.5
    edges[flip] = edges[flip, ::-1]

    self_collision = [True, False, True, False, False, True, False]  # 2 static: its flag is ignored
    static = [False, False, True, True, False, False, False]
    moving = ~np.isin(groups, [2, 3])

    def motion(step):
        a = x0 + 0.02 * step * moving[:, None] * [0.0, 0.0, -1.0]
        b = a + moving[:, None] * rng.normal(0, 0.08, a.shape)
        b[groups == 0, 2] -= 0.25
        return a, b

    kw = dict(groups=groups, self_collision=self_collision, static=static)
    a, b = motion(0)
    vf, ee, _, _ = check_against_reference(a, b, faces, edges, inflation=0.02, **kw)
    vbody, fbody, ebody = groups[vf[:, 0]], groups[faces[vf[:, 1], 0]], groups[edges[ee, 0]]
    pairs_vf = set(zip(vbody.tolist(), fbody.tolist()))
    pairs_ee = {tuple(sorted(p)) for p in ebody.tolist()}
    assert {(0, 0), (0, 2), (0, 3), (1, 0), (2, 0), (4, 0)} <= pairs_vf  # the scene exercises many groups
    assert {(0, 0), (0, 2), (0, 3)} <= pairs_ee
    assert not pairs_vf & {(1, 1), (2, 2), (2, 3), (3, 2), (3, 3), (6, 6)}
    assert not pairs_ee & {(1, 1), (2, 2), (2, 3), (3, 3), (6, 6)}

    bp = BroadPhase(faces, edges, num_vertices=len(x0), rebuild_every=3, **kw)
    assert np.array_equal(bp.faces, faces) and np.array_equal(bp.edges, edges)  # caller's numbering
    inflations = [0.02, 0.0, 0.05, 0.02, 0.6, 0.01, 0.0]  # 0.6: the pair buffers grow mid-run
    for step, inflation in enumerate(inflations):  # build, refits, rebuilds; a refit after the last
        a, b = motion(step)
        got = bp.query(a, b, inflation, rebuild=None if step < len(inflations) - 1 else False)
        want = candidate_pairs(a, b, faces, edges, inflation=inflation, **kw)
        for g, w in zip(got, want):
            assert np.array_equal(g, w)
        if inflation == 0.6:
            assert len(got[0]) > 8 * len(x0) and len(got[1]) > 8 * len(edges)
    check_against_reference(a, b, faces, edges, inflation=inflations[-1], **kw)


def test_adjacency_excluded_even_with_huge_inflation():
    """With every box overlapping every other, exactly the non-adjacent pairs remain."""
    x0, faces = grid(6, 1.0)
    x1 = x0 + 0.1
    edges = mesh_edges(faces)
    vf, ee = candidate_pairs(x0, x1, faces, inflation=10.0)
    assert not np.any(np.any(faces[vf[:, 1]] == vf[:, [0]], axis=1))
    ea, eb = edges[ee[:, 0]], edges[ee[:, 1]]
    assert np.all(ee[:, 0] < ee[:, 1])
    assert not np.any((ea[:, :, None] == eb[:, None, :]).any(axis=(1, 2)))
    nv, nf, ne = len(x0), len(faces), len(edges)
    assert len(vf) == nv * nf - 3 * nf  # every face minus its own three vertices
    n_share = sum(
        1
        for i in range(ne)
        for j in range(i + 1, ne)
        if set(edges[i].tolist()) & set(edges[j].tolist())
    )
    assert len(ee) == ne * (ne - 1) // 2 - n_share


def test_touching_boxes_and_inflation_boundary():
    """Closed intervals: boxes that touch are candidates; a gap of exactly `inflation` too."""
    faces = np.array([[0, 1, 2]])
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for z, inflation, expect in [(0.0, 0.0, True), (0.25, 0.25, True), (0.25, 0.0, False), (0.3, 0.25, False)]:
        x0 = np.concatenate([tri, [[0.2, 0.2, z]]])
        vf, _ = candidate_pairs(x0, x0, faces, inflation=inflation)
        assert (len(vf) == 1) == expect, (z, inflation)
    # a gap of one float64 ulp is within the pad: conservative, so still a candidate
    x0 = np.concatenate([tri, [[0.2, 0.2, np.nextafter(0.0, 1.0)]]])
    assert len(candidate_pairs(x0, x0, faces)[0]) == 1


@pytest.mark.parametrize("scale", [1e-30, 1e-8, 1.0, 1e6, 1e12, 1e30])
def test_scales_and_offsets_never_miss(scale):
    """Near-touching pairs far from the origin and at extreme scales: float32 boxes stay conservative."""
    rng = np.random.default_rng(int(np.log10(scale)) + 50)
    x0, x1, faces = triangle_soup(rng, 150, box=1.0, size=0.1, motion=0.05)
    offset = rng.uniform(-1, 1, 3) * 1e3
    check_against_reference((x0 + offset) * scale, (x1 + offset) * scale, faces, inflation=1e-3 * scale)


def test_beyond_float32_range_and_subnormal():
    """Coordinates past FLT_MAX are clamped (still conservative); float32-subnormal gaps are padded."""
    faces = np.array([[0, 1, 2]])
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    huge = np.concatenate([tri * 1e39, [[2e38, 2e38, 0.0]]])
    assert len(candidate_pairs(huge, huge, faces)[0]) == 1
    tiny = np.concatenate([tri * 1e-40, [[2e-41, 2e-41, 1e-45]]])
    assert len(candidate_pairs(tiny, tiny, faces)[0]) == 1
    check_against_reference(huge, huge * 1.5, faces)


def test_deterministic_and_reusable():
    rng = np.random.default_rng(3)
    x0, x1, faces = triangle_soup(rng, 200)
    first = candidate_pairs(x0, x1, faces, inflation=0.01)
    again = candidate_pairs(x0, x1, faces, inflation=0.01)
    bp = BroadPhase(faces, num_vertices=len(x0), rebuild_every=3)
    for step in range(7):  # builds, refits and rebuilds: identical pairs every time
        y0, y1 = x0 + 0.01 * step, x1 + 0.01 * step
        got = bp.query(y0, y1, 0.01)
        want = candidate_pairs(y0, y1, faces, inflation=0.01)
        for g, w in zip(got, want):
            assert np.array_equal(g, w)
    for a, b in zip(first, again):
        assert np.array_equal(a, b)
    # refit after a large deformation is still exact
    y1 = x1[::-1].copy()
    for g, w in zip(bp.query(x0, y1, 0.01, rebuild=False), candidate_pairs(x0, y1, faces, inflation=0.01)):
        assert np.array_equal(g, w)


def test_buffer_overflow_grows_and_retries():
    """More pairs than the initial capacity (8 per primitive): the retry returns all of them."""
    x0, faces = grid(10, 1.0)
    bp = BroadPhase(faces, num_vertices=len(x0))
    vf, ee = bp.query(x0, x0, inflation=5.0)  # everything overlaps: ~V*F and ~E^2/2 pairs
    assert len(vf) > 8 * len(x0) and len(ee) > 8 * len(bp.edges)
    rvf, ree = reference_pairs(x0, x0, faces, bp.edges, inflation=5.0)
    assert np.array_equal(vf, rvf) and np.array_equal(ee, ree)


def test_empty_inputs():
    x = np.zeros((0, 3))
    vf, ee = candidate_pairs(x, x, np.zeros((0, 3), int))
    assert vf.shape == (0, 2) and ee.shape == (0, 2)
    x = np.random.default_rng(0).normal(size=(5, 3))
    vf, ee = candidate_pairs(x, x, np.zeros((0, 3), int))
    assert vf.shape == (0, 2) and ee.shape == (0, 2)
    vf, ee = candidate_pairs(x, x, [[0, 1, 2]])
    assert vf.shape == (0, 2) and ee.shape == (0, 2)


def test_mesh_edges():
    faces = np.array([[0, 1, 2], [2, 1, 3], [3, 4, 2]])
    e = mesh_edges(faces)
    assert e.dtype == np.int64
    assert e.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3], [2, 4], [3, 4]]
    x, f = grid(5)
    assert len(mesh_edges(f)) == 3 * 4 * 4 + 2 * 4
    assert mesh_edges(np.zeros((0, 3), int)).shape == (0, 2)


# ------------------------------------------------------------------------------------------------
# validation


_X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
_F = np.array([[0, 1, 2], [0, 1, 3]])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(x0=_X[:, :2]), r"x0: expected shape \(V, 3\)"),
        (dict(x1=_X[:3]), r"x1: shape \(3, 3\) does not match x0 shape \(4, 3\)"),
        (dict(x0=np.where(np.eye(4, 3) == 1, np.nan, _X)), r"x0: positions must be finite.*x0\[0\]"),
        (dict(x1=np.where(np.eye(4, 3) == 1, np.inf, _X)), r"x1: positions must be finite"),
        (dict(x0=_X.astype(complex)), r"x0: positions must be real"),
        (dict(x0=np.array([["a", "b", "c"]] * 4)), r"x0: expected a numeric"),
        (dict(faces=_F[:, :2]), r"faces: expected shape \(N, 3\)"),
        (dict(faces=_F.astype(float)), r"faces: expected integer vertex indices"),
        (dict(faces=np.array([[0, 1, -1]])), r"faces: negative vertex index -1 at faces\[0, 2\]"),
        (dict(faces=np.array([[0, 1, 2], [0, 1, 4]])), r"faces: vertex index 4 at faces\[1, 2\] is out of range for 4"),
        (dict(faces=np.array([[0, 1, 1]])), r"faces: face 0 repeats a vertex index"),
        (dict(edges=np.array([[0, 1, 2]])), r"edges: expected shape \(N, 2\)"),
        (dict(edges=np.array([[0, 5]])), r"edges: vertex index 5 at edges\[0, 1\] is out of range"),
        (dict(edges=np.array([[-2, 1]])), r"edges: negative vertex index -2"),
        (dict(edges=np.array([[3, 3]])), r"edges: edge 0 repeats a vertex index"),
        (dict(groups=[0, 0, 0]), r"groups: expected shape \(4,\)"),
        (dict(groups=[0, 0, -1, 0]), r"groups: body ids must be non-negative, got groups\[2\]=-1"),
        (dict(groups=[0.0, 0, 0, 0]), r"groups: expected integer body ids"),
        (dict(groups=[0, 0, 1, 1]), r"groups: face 0 \[0, 1, 2\] spans bodies \[0, 1\]"),
        (dict(faces=np.array([[0, 1, 2]]), edges=[[2, 3]], groups=[0, 0, 0, 1]), r"groups: edge 0 \[2, 3\] spans"),
        (dict(groups=[0, 0, 0, 0], self_collision=[]), r"self_collision: expected one flag per body id"),
        (dict(groups=[1, 1, 1, 1], static=[True]), r"static: expected one flag per body id \(groups has 2"),
        (dict(self_collision="yes"), r"self_collision: expected a bool"),
        (dict(static=[[True]]), r"static: expected a bool or a 1-D sequence"),
        (dict(inflation=-1.0), r"inflation: expected a non-negative finite number, got -1.0"),
        (dict(inflation=float("nan")), r"inflation: expected a non-negative finite number"),
        (dict(inflation="big"), r"inflation: expected a non-negative finite number"),
    ],
)
def test_validation_errors(kwargs, match):
    args = dict(x0=_X, x1=_X, faces=_F, edges=None)
    args.update(kwargs)
    x0, x1, faces, edges = args.pop("x0"), args.pop("x1"), args.pop("faces"), args.pop("edges")
    with pytest.raises(ValueError, match=match):
        candidate_pairs(x0, x1, faces, edges, **args)


def test_broad_phase_object_validation():
    bp = BroadPhase(_F, num_vertices=4)
    with pytest.raises(ValueError, match=r"x0: expected 4 vertices"):
        bp.query(_X[:3], _X[:3])
    with pytest.raises(ValueError, match=r"rebuild_every"):
        BroadPhase(_F, num_vertices=4, rebuild_every=0)
    with pytest.raises(ValueError, match=r"faces: vertex index 3 .* out of range for 3 vertices"):
        BroadPhase(_F, num_vertices=3)


# ------------------------------------------------------------------------------------------------
# timing (printed, not asserted)


def test_timing_cloth_falling_on_sphere(capsys):
    """64x64 cloth (body 0, self-collision on) falling onto a static icosphere (body 1)."""
    xc, fc = grid(64, 1.2, 0.53)
    xs, fs = icosphere(3, 0.5)  # 642 vertices, 1280 faces
    x0 = np.concatenate([xc, xs])
    faces = np.concatenate([fc, fs + len(xc)])
    groups = np.r_[np.zeros(len(xc), int), np.ones(len(xs), int)]
    rng = np.random.default_rng(0)
    dt, v = 1.0 / 60.0, np.array([0.0, 0.0, -2.0])
    kw = dict(groups=groups, self_collision=True, static=[False, True])
    inflation = 1e-3

    def step_positions(k):
        a = x0.copy()
        a[: len(xc)] += v * dt * k + rng.normal(0, 1e-3, (len(xc), 3))
        b = a.copy()
        b[: len(xc)] += v * dt
        return a, b

    a, b = step_positions(0)
    vf, ee = candidate_pairs(a, b, faces, inflation=inflation, **kw)  # compile / warm up
    t_cp = []
    for _ in range(5):
        t = time.perf_counter()
        vf, ee = candidate_pairs(a, b, faces, inflation=inflation, **kw)
        t_cp.append(time.perf_counter() - t)

    bp = BroadPhase(faces, num_vertices=len(x0), **kw)
    t_q, counts = [], []
    for k in range(12):
        a, b = step_positions(k)
        t = time.perf_counter()
        qvf, qee = bp.query(a, b, inflation)
        t_q.append(time.perf_counter() - t)
        counts.append((len(qvf), len(qee)))
    with capsys.disabled():
        print(
            f"\n[broad phase timing] cloth 64x64 + icosphere(3): V={len(x0)} F={len(faces)} "
            f"E={len(bp.edges)}; candidates at contact: vf={len(vf)} ee={len(ee)}\n"
            f"  candidate_pairs (validate + edges + build BVHs + query): median {1e3 * np.median(t_cp):.1f} ms\n"
            f"  BroadPhase.query over 12 falling steps (refit, rebuild every 16): "
            f"median {1e3 * np.median(t_q):.1f} ms, first (build) {1e3 * t_q[0]:.1f} ms; "
            f"vf/ee per step {counts[0]} .. {counts[-1]}"
        )
    assert len(vf) > 0 and len(ee) > 0
