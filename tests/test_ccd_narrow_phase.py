"""Narrow-phase CCD: hand-made cases, malformed input, and the differentiable time of impact.

Ground truth here is closed-form geometry (dyadic coordinates, exact answers) and mpmath at 50
digits for the time of impact and its derivative; the sample-query benchmark and the generated
exact-touch set have their own test files.
"""

import mpmath as mp
import numpy as np
import pytest
import warp as wp

from collision.ccd import edge_edge_ccd, edge_edge_roots, point_triangle_ccd, point_triangle_roots
from kernels import ccd as kccd

wp.init()

TRI = (np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))


def vf(p0, p1, tri0=TRI, tri1=TRI, **kw):
    return point_triangle_ccd(np.atleast_2d(p0), *tri0, np.atleast_2d(p1), *tri1, **kw)


def test_vertex_through_triangle_interior_edge_corner_and_miss():
    cases = [
        ([0.25, 0.25, 1.0], [0.25, 0.25, -1.0], True, 0.5),  # interior
        ([0.5, 0.0, 1.0], [0.5, 0.0, -3.0], True, 0.25),  # on an edge
        ([0.0, 0.0, 0.5], [0.0, 0.0, -0.5], True, 0.5),  # through a corner
        ([1.0, 1.0, 1.0], [1.0, 1.0, -1.0], False, np.inf),  # misses beside the hypotenuse
        ([0.25, 0.25, 1.0], [0.25, 0.25, 0.5], False, np.inf),  # stops short
        ([0.25, 0.25, 1.0], [0.25, 0.25, 0.0], True, 1.0),  # touches exactly at t = 1
        ([0.25, 0.25, 0.0], [0.25, 0.25, 1.0], True, 0.0),  # touching at t = 0
    ]
    for p0, p1, want_hit, want_toi in cases:
        hit, toi = vf(p0, p1)
        assert hit[0] == want_hit, (p0, p1)
        assert toi[0] == want_toi, (p0, p1, toi)


def test_sliding_in_plane_vertex_enters_triangle():
    # coplanar for the whole step: the vertex slides in the triangle's plane across the edge x = 0
    hit, toi = vf([-1.0, 0.25, 0.0], [1.0, 0.25, 0.0])
    assert hit[0] and toi[0] == 0.5
    hit, toi = vf([-1.0, 2.0, 0.0], [1.0, 2.0, 0.0])  # slides past, outside
    assert not hit[0]


def test_degenerate_triangle_and_zero_length_edges():
    flat = (np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[2.0, 0, 0]]))  # zero area
    hit, toi = vf([0.5, 1.0, 0.0], [0.5, -1.0, 0.0], flat, flat)
    assert hit[0] and toi[0] == 0.5
    point = [np.array([[0.5, 0.0, 1.0]]), np.array([[0.5, 0.0, 1.0]])]  # zero-length edge a
    seg = [np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])]
    hit, toi = edge_edge_ccd(*point, *seg, np.array([[0.5, 0.0, -1.0]]), np.array([[0.5, 0.0, -1.0]]), *seg)
    assert hit[0] and toi[0] == 0.5


def test_edge_edge_crossing_parallel_and_collinear():
    a0, a1 = np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 1.0]])
    b0, b1 = np.array([[0.5, -1.0, 0.0]]), np.array([[0.5, 1.0, 0.0]])
    down = np.array([[0.0, 0.0, -2.0]])
    hit, toi = edge_edge_ccd(a0, a1, b0, b1, a0 + down, a1 + down, b0, b1)
    assert hit[0] and toi[0] == 0.5
    # parallel edges approaching each other
    c0, c1 = np.array([[0.0, 1.0, 1.0]]), np.array([[1.0, 1.0, 1.0]])
    hit, toi = edge_edge_ccd(a0, a1, c0, c1, a0, a1, c0 - [[0, 1, 0]], c1 - [[0, 1, 0]])
    assert hit[0] and toi[0] == 1.0
    # collinear, sliding into overlap: edge b on the same line approaches edge a
    d0, d1 = np.array([[2.0, 0.0, 1.0]]), np.array([[3.0, 0.0, 1.0]])
    hit, toi = edge_edge_ccd(a0, a1, d0, d1, a0, a1, d0 - [[2, 0, 0]], d1 - [[2, 0, 0]])
    assert hit[0] and toi[0] == 0.5
    # skew edges that pass each other at distance 1
    hit, _ = edge_edge_ccd(a0, a1, b0 + [[0, 0, 3]], b1 + [[0, 0, 3]], a0, a1, b0 + [[0, 0, 2]], b1 + [[0, 0, 2]])
    assert not hit[0]


def test_thickness_reports_the_first_time_within_reach():
    hit, toi = vf([0.25, 0.25, 1.0], [0.25, 0.25, 0.5], thickness=0.75)
    assert hit[0] and toi[0] == pytest.approx(0.5, abs=1e-9)
    assert toi[0] <= 0.5 + 1e-12  # conservative: never after the exact time
    hit, _ = vf([0.25, 0.25, 1.0], [0.25, 0.25, 0.5], thickness=0.25)
    assert not hit[0]


def test_scaled_and_translated_scenes_give_the_same_answer():
    rng = np.random.default_rng(0)
    p0 = rng.uniform(-1, 1, (200, 3))
    p1 = rng.uniform(-1, 1, (200, 3))
    t0 = [rng.uniform(-1, 1, (200, 3)) for _ in range(3)]
    t1 = [x + rng.uniform(-0.5, 0.5, (200, 3)) for x in t0]
    hit, toi = point_triangle_ccd(p0, *t0, p1, *t1)
    for scale in (2.0**-20, 2.0**20):
        h2, toi2 = point_triangle_ccd(p0 * scale, *[x * scale for x in t0], p1 * scale, *[x * scale for x in t1])
        np.testing.assert_array_equal(hit, h2)
        np.testing.assert_array_equal(toi, toi2)
    shift = 1024.0  # dyadic offset: positions stay exact, relative vectors are unchanged
    h3, toi3 = point_triangle_ccd(p0 + shift, *[x + shift for x in t0], p1 + shift, *[x + shift for x in t1])
    np.testing.assert_array_equal(hit, h3)
    np.testing.assert_allclose(toi[hit], toi3[hit], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "args, message",
    [
        ((np.zeros((2, 3)),) * 7 + (np.zeros((3, 3)),), "t2_t1: has 3 rows"),
        ((np.zeros((2, 2)),) + (np.zeros((2, 3)),) * 7, "p_t0: expected shape (N, 3)"),
        ((np.array([[np.nan, 0, 0]]),) + (np.zeros((1, 3)),) * 7, "p_t0: positions must be finite"),
        ((np.zeros((1, 3)),) * 4 + (np.array([[0, np.inf, 0]]),) + (np.zeros((1, 3)),) * 3, "p_t1[0, 1]=inf"),
    ],
)
def test_malformed_input_is_a_clear_error(args, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[").replace("]", r"\]")):
        point_triangle_ccd(*args)
    with pytest.raises(ValueError, match="thickness"):
        point_triangle_ccd(*(np.zeros((1, 3)),) * 8, thickness=-1.0)


# ------------------------------------------------------------------------------------------
# differentiable time of impact
# ------------------------------------------------------------------------------------------


def _mp_toi(x, near):
    """Root of the coplanarity cubic of the (8, 3) mp matrix ``x`` nearest ``near`` (50 digits)."""
    d = [[x[k][c] - x[0][c] for c in range(3)] for k in (1, 2, 3)]
    e = [[(x[k + 4][c] - x[4][c]) - d[k - 1][c] for c in range(3)] for k in (1, 2, 3)]

    def f(t):
        v = [[d[k][c] + t * e[k][c] for c in range(3)] for k in range(3)]
        cr = [v[0][1] * v[1][2] - v[0][2] * v[1][1], v[0][2] * v[1][0] - v[0][0] * v[1][2], v[0][0] * v[1][1] - v[0][1] * v[1][0]]
        return sum(cr[c] * v[2][c] for c in range(3))

    return mp.findroot(f, mp.mpf(near), tol=mp.mpf(10) ** -45)


def _tape_toi_gradient(queries, source, toi, max_derivative=1000.0):
    q = wp.array(queries, dtype=kccd.mat83d, requires_grad=True)
    s = wp.array(source, dtype=wp.int32)
    detected = wp.array(toi, dtype=wp.float64)
    out = wp.zeros(len(queries), dtype=wp.float64, requires_grad=True)
    roots = wp.zeros(len(queries), dtype=kccd.vec6d, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(kccd.ccd_time_of_impact_kernel, dim=len(queries), inputs=[q, s, detected, wp.float64(max_derivative)], outputs=[out, roots])
    tape.backward(grads={out: wp.ones(len(queries), dtype=wp.float64)})
    return out.numpy(), q.grad.numpy()


def _transversal_queries(n, seed):
    rng = np.random.default_rng(seed)
    qs = []
    while len(qs) < n:
        tri0 = rng.uniform(-1, 1, (3, 3))
        tri1 = tri0 + rng.uniform(-0.3, 0.3, (3, 3))
        w = rng.dirichlet([2, 2, 2])
        t_hit = rng.uniform(0.2, 0.8)
        hit_point = w @ (tri0 + t_hit * (tri1 - tri0))
        direction = rng.normal(size=3)
        p0 = hit_point - t_hit * direction
        p1 = p0 + direction
        qs.append(np.vstack([p0, tri0, p1, tri1]))
    return np.array(qs)


def test_time_of_impact_matches_exact_root_and_its_gradient_matches_finite_differences():
    from collision.ccd import narrow_phase

    queries = _transversal_queries(4, seed=1)
    hit, toi, source = narrow_phase(0, queries, 0.0)
    assert hit.all() and np.all((source >= 1) & (source <= 3))
    toi_tape, grad = _tape_toi_gradient(queries, source, toi)
    # the taped recomputation solves the unit-scaled cubic (same roots, other rounding, which
    # depends on the CPU the kernels are compiled for: up to 14 ulp apart measured); both are
    # checked against the exact root below
    np.testing.assert_allclose(toi_tape, toi, rtol=64 * np.finfo(float).eps, atol=0)
    mp.mp.dps = 50
    h = mp.mpf(10) ** -20
    for i, x in enumerate(queries):
        xm = [[mp.mpf(float(v)) for v in r] for r in x]
        exact = _mp_toi(xm, toi[i])
        assert abs(float(exact) - toi[i]) <= 1e-12 * max(1.0, abs(float(exact)))
        for r in range(8):
            for c in range(3):
                xp = [row[:] for row in xm]
                xn = [row[:] for row in xm]
                xp[r][c] += h
                xn[r][c] -= h
                fd = (_mp_toi(xp, exact) - _mp_toi(xn, exact)) / (2 * h)
                assert abs(grad[i, r, c] - float(fd)) <= 1e-7 * max(1.0, abs(float(fd))), (i, r, c, grad[i, r, c], float(fd))


def _grazing_query(gap):
    """Vertex p = (t, 1/4, 1/2 + gap - t) under a triangle whose corner B = (1, 0, 1 - 2t) tilts:
    the coplanarity cubic is proportional to 2 (t - 1/2)^2 + gap, a double root at t = 1/2 for
    gap = 0 (the vertex grazes the face at (1/2, 1/4, 0)), two real roots for gap < 0, none for
    gap > 0."""
    start = np.array([[0.0, 0.25, 0.5 + gap], [0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    end = np.array([[1.0, 0.25, -0.5 + gap], [0.0, 0.0, 0.0], [1.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return np.vstack([start, end])


def test_grazing_contact_is_detected_and_its_gradient_is_finite_and_bounded():
    from collision.ccd import narrow_phase

    gaps = [0.0, -1e-12, -1e-8, -1e-4, 1e-4, 1e-2]
    queries = np.array([_grazing_query(g) for g in gaps])
    hit, toi, source = narrow_phase(0, queries, 0.0)
    assert hit[:4].all(), "touching and crossing grazes are hits"
    assert not hit[4:].any(), "clear misses (gap >= 1e-4) are not"
    assert abs(toi[0] - 0.5) <= 1e-7  # double root: accuracy ~ sqrt(u)
    assert abs(toi[3] - (0.5 - np.sqrt(0.5e-4))) <= 1e-12
    toi_tape, grad = _tape_toi_gradient(queries, source, np.where(hit, toi, 1.0))
    assert np.all(np.isfinite(grad)) and np.all(np.isfinite(toi_tape))
    # dt/dx = (mollified dt/dcoef, |.| <= 5 M) x (dcoef/dx, O(1) here): bounded at the double root
    assert np.abs(grad).max() <= 5 * 1000.0 * 10.0
    # away from grazing the derivative is the exact one; at the double root it is the clamp
    assert np.abs(grad[0]).max() > np.abs(grad[3]).max()


def test_lifted_roots_of_a_miss_are_complex_and_differentiable():
    # vertex passes beside the triangle: no real root in [0, 1] with the point inside
    roots = point_triangle_roots(np.array([[2.0, 2.0, 1.0]]), *TRI, np.array([[2.0, 2.0, -1.0]]), *TRI)
    assert roots.shape == (1, 3)
    assert np.all(np.isfinite(roots.real)) and np.all(np.isfinite(roots.imag))
    r = edge_edge_roots(*([np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 1]]), np.array([[0.5, -1, 0]]), np.array([[0.5, 1, 0]])] * 2))
    assert r.shape == (1, 3)


def test_lifted_roots_gradient_matches_finite_differences_for_a_miss():
    """A vertex that misses: the coplanarity roots it would need are complex; under a tape their
    derivative w.r.t. the positions is the mollified implicit one, here (well-separated roots,
    clamp inactive) equal to 50-digit finite differences of the exact roots."""
    from collision.ccd import narrow_phase

    from collision.ccd import point_triangle_roots as roots_of

    rng = np.random.default_rng(7)
    while True:  # a query whose cubic has a complex pair and bounded roots
        x = rng.uniform(-1, 1, (8, 3))
        z = roots_of(*[x[k][None] for k in range(8)])[0]
        if np.all(np.abs(z) < 10) and np.abs(z.imag).max() > 0.1:
            break
    queries = x[None]
    hit, toi, source = narrow_phase(0, queries, 0.0)
    q = wp.array(queries, dtype=kccd.mat83d, requires_grad=True)
    out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    roots = wp.zeros(1, dtype=kccd.vec6d, requires_grad=True)
    weights = np.array([0.3, -0.7, 1.1, 0.4, -0.2, 0.9])
    tape = wp.Tape()
    with tape:
        wp.launch(kccd.ccd_time_of_impact_kernel, dim=1, inputs=[q, wp.array(source, dtype=wp.int32), wp.array(np.where(hit, toi, 1.0), dtype=wp.float64), wp.float64(1000.0)], outputs=[out, roots])
    tape.backward(grads={roots: wp.array(weights[None], dtype=kccd.vec6d)})
    grad = q.grad.numpy()[0]
    r = roots.numpy()[0]
    assert np.any(r[1::2] != 0), "expected a complex pair for this miss"

    mp.mp.dps = 50

    def mp_roots(xm):
        d = [[xm[k][c] - xm[0][c] for c in range(3)] for k in (1, 2, 3)]
        e = [[(xm[k + 4][c] - xm[4][c]) - d[k - 1][c] for c in range(3)] for k in (1, 2, 3)]

        def cross(u, v):
            return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

        def dot(u, v):
            return sum(a * b for a, b in zip(u, v))

        c0 = dot(cross(d[0], d[1]), d[2])
        c1 = dot(cross(e[0], d[1]), d[2]) + dot(cross(d[0], e[1]), d[2]) + dot(cross(d[0], d[1]), e[2])
        c2 = dot(cross(e[0], e[1]), d[2]) + dot(cross(e[0], d[1]), e[2]) + dot(cross(d[0], e[1]), e[2])
        c3 = dot(cross(e[0], e[1]), e[2])
        return mp.polyroots([c3, c2, c1, c0], maxsteps=200, extraprec=200)

    def weighted(xm):
        rts = mp_roots(xm)
        total = mp.mpf(0)
        for s in range(3):  # match each computed slot to the nearest exact root
            z = complex(r[2 * s], r[2 * s + 1])
            best = min(rts, key=lambda w: abs(complex(w) - z))
            total += weights[2 * s] * best.real + weights[2 * s + 1] * best.imag
        return total

    xm = [[mp.mpf(float(v)) for v in row_] for row_ in x]
    h = mp.mpf(10) ** -20
    for i in range(8):
        for c in range(3):
            xp = [row_[:] for row_ in xm]
            xn = [row_[:] for row_ in xm]
            xp[i][c] += h
            xn[i][c] -= h
            fd = float((weighted(xp) - weighted(xn)) / (2 * h))
            assert abs(grad[i, c] - fd) <= 1e-7 * max(1.0, abs(fd)), (i, c, grad[i, c], fd)


def _grid(n: int, lo: float, hi: float):
    """An n x n vertex grid over [lo, hi]^2 at z = 0 and its triangles (two per cell)."""
    xs, ys = np.meshgrid(np.linspace(lo, hi, n), np.linspace(lo, hi, n))
    vertices = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(n * n)])
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    return vertices, np.array(faces)


def test_mesh_ccd_cloth_drop_earliest_time_and_errors():
    from collision.ccd import mesh_ccd

    n = 12
    cloth, faces = _grid(n, -1.0, 1.0)
    cloth[:, 2] = 0.25
    ground = np.array([[-3.0, -3.0, 0.0], [3.0, -3.0, 0.0], [0.0, 3.0, 0.0]])
    x0 = np.vstack([cloth, ground])
    x1 = x0.copy()
    x1[: n * n, 2] -= 1.0  # falls 1 m in the step: touches the plane z = 0 at t = 1/4
    all_faces = np.vstack([faces, [[n * n, n * n + 1, n * n + 2]]])
    groups = np.r_[np.zeros(n * n, int), np.ones(3, int)]
    result = mesh_ccd(x0, x1, all_faces, groups=groups, self_collision=[True, False], static=[False, True])
    assert result.time_of_impact == 0.25
    assert result.vf_hit.sum() >= n * n  # every cloth vertex hits the ground triangle
    bad_faces = all_faces.copy()
    bad_faces[0, 0] = len(x0) + 5
    with pytest.raises(ValueError, match="faces"):
        mesh_ccd(x0, x1, bad_faces)
    x_nan = x1.copy()
    x_nan[3, 1] = np.nan
    with pytest.raises(ValueError, match="x1"):
        mesh_ccd(x0, x_nan, all_faces)


# ------------------------------------------------------------------ candidates on the device


def _crumpled_sheets(seed: int):
    """Two 7x7 sheets 1 cm apart, crumpled by noise, moving at random: self and mutual pairs."""
    rng = np.random.default_rng(seed)
    n = 7
    sheet, faces = _grid(n, 0.0, 0.3)
    x0 = np.vstack([sheet, sheet + [0.01, 0.02, 0.01]]) + rng.normal(scale=4e-3, size=(2 * n * n, 3))
    x1 = x0 + rng.normal(scale=1.5e-2, size=x0.shape)
    return x0, x1, np.vstack([faces, faces + n * n])


def _point_segment_distance(p, a, b):
    ab = b - a
    s = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + s * ab))


def _point_triangle_distance(p, a, b, c):
    """Exact distance (plane projection inside the triangle, else the nearest edge)."""
    n = np.cross(b - a, c - a)
    q = p - np.dot(p - a, n) / np.dot(n, n) * n
    inside = all(np.dot(np.cross(v1 - v0, q - v0), n) >= 0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return np.linalg.norm(p - q)
    return min(_point_segment_distance(p, a, b), _point_segment_distance(p, b, c), _point_segment_distance(p, c, a))


def _segment_segment_distance(a0, a1, b0, b1):
    """Exact distance: the unconstrained minimum when it lies in the unit square, else the
    smallest of the four edge minima (each a point-segment distance)."""
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    A, B, C, D, E = u @ u, u @ v, v @ v, u @ w, v @ w
    det = A * C - B * B
    best = min(_point_segment_distance(a0, b0, b1), _point_segment_distance(a1, b0, b1),
               _point_segment_distance(b0, a0, a1), _point_segment_distance(b1, a0, a1))
    if det > 1e-14 * A * C:
        s, t = (B * E - C * D) / det, (A * E - B * D) / det
        if 0 <= s <= 1 and 0 <= t <= 1:
            best = min(best, np.linalg.norm(w + s * u - t * v))
    return best


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_candidate_narrow_phase_equals_the_stacked_narrow_phase_and_brute_force_distances(seed):
    """CandidateNarrowPhase (pairs and positions read on the device, hits appended) gives the
    hits of mesh_ccd (stacked queries through narrow_phase) bit for bit and in its sorted order;
    its proximity pairs are exactly the non-adjacent pairs an independent numpy distance puts
    within the limit."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(seed)
    edges = mesh_edges(faces)
    bp = BroadPhase(faces, edges, num_vertices=len(x0))
    narrow = CandidateNarrowPhase(bp)
    kind, pair, toi, source, vertices = narrow.ccd(x0, x1)
    ref = mesh_ccd(x0, x1, faces, edges)
    want_pair = np.vstack([ref.vf[ref.vf_hit], ref.ee[ref.ee_hit]])
    want_kind = np.r_[np.zeros(ref.vf_hit.sum(), int), np.ones(ref.ee_hit.sum(), int)]
    want_toi = np.r_[ref.vf_toi[ref.vf_hit], ref.ee_toi[ref.ee_hit]]
    assert len(kind) > 20 and (kind == 0).any() and (kind == 1).any()
    np.testing.assert_array_equal(kind, want_kind)
    np.testing.assert_array_equal(pair, want_pair)
    np.testing.assert_array_equal(toi, want_toi)
    assert set(np.unique(source)) <= {0, 1, 2, 3, 4}
    want_vertices = np.where((kind == 0)[:, None],
                             np.column_stack([pair[:, 0], faces[np.where(kind == 0, pair[:, 1], 0)]]),
                             np.column_stack([edges[pair[:, 0]], edges[np.where(kind == 1, pair[:, 1], 0)]]))
    np.testing.assert_array_equal(vertices, want_vertices)

    limit = 0.012
    kind, pair, off, weights, vertices = narrow.near(x0, limit)
    got = {(int(k), int(a), int(b)) for k, (a, b) in zip(kind, pair)}
    dist = np.linalg.norm(off, axis=1)
    want, border = set(), set()
    for v in range(len(x0)):
        for f, tri in enumerate(faces):
            if v in tri:
                continue
            d = _point_triangle_distance(x0[v], *x0[tri])
            (border if abs(d - limit) < 1e-12 else want if d < limit else set()).add((0, v, f))
    for a in range(len(edges)):
        for b in range(a + 1, len(edges)):
            if set(edges[a]) & set(edges[b]):
                continue
            d = _segment_segment_distance(*x0[edges[a]], *x0[edges[b]])
            (border if abs(d - limit) < 1e-12 else want if d < limit else set()).add((1, a, b))
    assert len(want) > 50
    assert got - border == want - border
    ref_d = {(0, v, f): _point_triangle_distance(x0[v], *x0[faces[f]]) for (k, v, f) in got if k == 0}
    for (k, a, b), d in zip(((int(k), int(a), int(b)) for k, (a, b) in zip(kind, pair)), dist):
        if k == 0:
            assert abs(d - ref_d[(0, a, b)]) <= 1e-12
    order = np.lexsort((pair[:, 1], pair[:, 0], kind))
    np.testing.assert_array_equal(order, np.arange(len(kind)))
    # the weights are the closest points': side A sums to 1, side B to -1, and the weighted
    # positions give the offset
    idx = np.where((kind == 0)[:, None], np.column_stack([pair[:, 0], faces[np.where(kind == 0, pair[:, 1], 0)]]),
                   np.column_stack([edges[pair[:, 0]], edges[pair[:, 1]]]))
    np.testing.assert_array_equal(vertices, idx)  # the pairs' vertex indices, as the mesh numbers them
    split = np.where(kind == 0, 1, 2)[:, None] > np.arange(4)
    np.testing.assert_allclose(np.where(split, weights, 0).sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.where(split, 0, weights).sum(1), -1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ck,ckd->cd", weights, x0[idx]), off, atol=1e-12)


def test_candidate_cover_answers_covered_calls_and_requeries_the_rest():
    """One cover query serves the proximity test at the start positions and CCD of end positions
    within 0.45 margin of the covered ones, with the hits of fresh queries; an end moved further
    queries afresh (and still gives the same hits as mesh_ccd)."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(3)
    edges = mesh_edges(faces)
    narrow = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    fresh = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    margin = 0.004
    narrow.cover(x0, x1, margin)
    rng = np.random.default_rng(7)
    for k, move in enumerate((0.0, 0.2 * margin, 0.44 * margin, 3.0 * margin)):
        x1k = x1 + rng.uniform(-move, move, size=x1.shape)
        before = narrow.reuses
        got = narrow.ccd(x0, x1k)
        assert narrow.reuses == before + (1 if move < 0.45 * margin else 0)
        want = fresh.ccd(x0, x1k)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        ref = mesh_ccd(x0, x1k, faces, edges)
        assert len(got[0]) == int(ref.vf_hit.sum() + ref.ee_hit.sum())
        if k == 0:  # still covered: the proximity test too
            before = narrow.reuses
            near = narrow.near(x0, margin)
            assert narrow.reuses == before + 1
            for g, w in zip(near, fresh.near(x0, margin)):
                np.testing.assert_array_equal(g, w)
    # the last call re-queried: the cover is gone, a wider proximity test queries too
    before = narrow.queries
    narrow.near(x0, margin)
    assert narrow.queries == before + 1


def test_ccd_after_near_with_motion_radii_tests_only_reachable_pairs_with_the_same_hits():
    """near(x0, d, motion_radius) keeps the candidates that a CCD from x0 can hit while every
    vertex moves at most its radius; such a CCD tests only those (far fewer) and finds exactly
    the hits of a fresh narrow phase and of mesh_ccd. A vertex moving past its radius, another
    start or a thickness falls back to every candidate, with the same hits."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(6)
    x1 = x0 + 0.3 * (x1 - x0)
    edges = mesh_edges(faces)
    narrow = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    fresh = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    margin, slack = 0.004, 0.001
    narrow.cover(x0, x1, margin)
    radius = np.linalg.norm(x1 - x0, axis=1) + slack
    near = narrow.near(x0, 0.001, radius)
    for g, w in zip(near, fresh.near(x0, 0.001)):  # the proximity answer is unchanged
        np.testing.assert_array_equal(g, w)
    rng = np.random.default_rng(11)
    candidates = narrow.covered_candidates()

    def check(y1, start=x0, thickness=0.0):
        got = narrow.ccd(start, y1, thickness)
        for g, w in zip(got, fresh.ccd(start, y1, thickness)):
            np.testing.assert_array_equal(g, w)
        return got

    total = 0
    for k in range(4):  # ends anywhere within the radii (the predicted end moved by < slack)
        u = rng.normal(size=x0.shape)
        u *= (0.99 * slack * rng.uniform(size=(len(x0), 1))) / np.linalg.norm(u, axis=1, keepdims=True)
        y1 = x1 + u
        calls, tested = narrow.reach_calls, narrow.tested
        got = check(y1)
        assert narrow.reach_calls == calls + 1
        assert narrow.tested - tested < candidates / 2
        ref = mesh_ccd(x0, y1, faces, edges)
        assert len(got[0]) == int(ref.vf_hit.sum() + ref.ee_hit.sum())
        total += len(got[0])
    assert total > 0
    # one vertex past its radius, another start, a thickness: every candidate
    far = x1.copy()
    step = x1[3] - x0[3]  # continued just past the radius: still inside the cover
    far[3] = x0[3] + step * (1.001 * radius[3] / np.linalg.norm(step))
    moved = x0.copy()
    moved[5, 2] += 1e-9
    for y1, start, thickness in ((far, x0, 0.0), (x1, moved, 0.0), (x1, x0, 1e-4)):
        calls, tested = narrow.reach_calls, narrow.tested
        check(y1, start, thickness)
        assert narrow.reach_calls == calls
        assert narrow.tested - tested == candidates
    # a call from another start refills the start's device buffer: a later call from near()'s
    # start must not take that buffer for its positions (it still keeps to the kept pairs)
    check(x1, x0 + 0.5 * (x1 - x0))
    calls = narrow.reach_calls
    assert len(check(x1)[0]) > 0
    assert narrow.reach_calls == calls + 1
    with pytest.raises(ValueError, match="motion_radius"):
        narrow.near(x0, 0.001, radius[:-1])
    for bad_distance in (-1e-3, np.nan, np.inf):
        with pytest.raises(ValueError, match="max_distance"):
            narrow.near(x0, bad_distance, radius)
    bad = radius.copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match="motion_radius"):
        narrow.near(x0, 0.001, bad)


def test_reachable_pairs_keep_a_contact_at_the_end_of_both_radii():
    """The kept pairs' bound is tight: a vertex and a triangle 2 r (1 - 1e-9) apart, each moving
    straight at the other by its radius r, touch at the very end of the step, and the CCD that
    tests only the kept pairs reports that hit; 2 r (1 + 1e-6) apart they are not kept (and
    do not touch)."""
    from collision.broad_phase import BroadPhase
    from collision.narrow_phase import CandidateNarrowPhase

    faces = np.array([[1, 2, 3]])
    edges = np.array([[1, 2], [2, 3], [1, 3]])
    r = 0.002
    for gap, hit in ((2 * r * (1 - 1e-9), True), (2 * r * (1 + 1e-6), False)):
        tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) * 0.1
        x0 = np.vstack([[0.02, 0.02, gap], tri])
        x1 = x0 + np.array([[0.0, 0.0, -r]] + [[0.0, 0.0, r]] * 3)
        narrow = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=4))
        narrow.cover(x0, x1, 0.01)
        narrow.near(x0, 0.001, np.full(4, r))
        kind, pair, toi, _, _ = narrow.ccd(x0, x1)
        assert narrow.reach_calls == 1
        assert narrow.tested == (1 if hit else 0)
        assert len(kind) == (1 if hit else 0)
        if hit:
            assert abs(toi[0] - 1.0) < 1e-6


def test_kept_cover_serves_later_motions_inside_its_boxes_with_the_hits_of_fresh_queries():
    """cover(..., slack) keeps the current cover while both ends of every vertex's new motion lie
    within the slack of the box of its covered motion (the next substep of resting contact):
    no broad-phase query, and the proximity test and CCD of the new motion (moved start and
    end) give exactly the hits of a fresh query and of mesh_ccd; a motion beyond the slack
    queries afresh."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(5)
    edges = mesh_edges(faces)
    narrow = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    fresh = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    margin, slack = 0.02, 0.005
    narrow.cover(x0, x1, margin, slack)
    rng = np.random.default_rng(3)
    # the next motion starts somewhere on the covered one and ends near the covered end
    s = rng.uniform(0.0, 1.0, size=(len(x0), 1))
    y0 = x0 + s * (x1 - x0) + rng.uniform(-0.9 * slack, 0.9 * slack, size=x0.shape)
    y1 = x1 + rng.uniform(-0.9 * slack, 0.9 * slack, size=x0.shape)
    queries, kept = narrow.queries, narrow.kept_covers
    narrow.cover(y0, y1, margin, slack)
    assert (narrow.queries, narrow.kept_covers) == (queries, kept + 1)
    reuses = narrow.reuses
    got = narrow.ccd(y0, y1)
    near = narrow.near(y0, 0.01)
    assert narrow.reuses == reuses + 2 and narrow.queries == queries
    for g, w in zip(got, fresh.ccd(y0, y1)):
        np.testing.assert_array_equal(g, w)
    for g, w in zip(near, fresh.near(y0, 0.01)):
        np.testing.assert_array_equal(g, w)
    assert len(near[0]) > 0
    ref = mesh_ccd(y0, y1, faces, edges)
    assert len(got[0]) == int(ref.vf_hit.sum() + ref.ee_hit.sum()) > 0
    # a start moved beyond the slack (outside its covered box): a new query
    far = y0.copy()
    far[0] = np.maximum(x0[0], x1[0]) + 2.0 * slack
    narrow.cover(far, y1, margin, slack)
    assert narrow.queries == queries + 1
    # without slack every cover queries
    narrow.cover(far, y1, margin)
    assert narrow.queries == queries + 2
    # a NaN position is never covered: the fresh query refuses it, naming the argument
    bad = y1.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="x1"):
        narrow.cover(far, bad, margin, slack)
    narrow.cover(far, y1, margin)
    with pytest.raises(ValueError, match="x1"):
        narrow.ccd(far, bad)
    with pytest.raises(ValueError, match="x0"):
        narrow.near(np.where(np.arange(len(far))[:, None] == 2, np.nan, far), 0.01)


def test_cover_outside_distance_is_exact_per_end_and_never_covers_nan():
    """The cover test's distance of a motion's ends outside the covered boxes is the largest of
    ``lo - x`` and ``x - hi`` over both ends and all coordinates, bit for bit (it is computed
    from ``min(x0, x1)`` and ``max(x0, x1)``, which must not round differently), 0 for ends
    inside or on the boxes, and inf for a NaN end."""
    from collision.narrow_phase import CandidateNarrowPhase

    rng = np.random.default_rng(11)
    n = 200
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    cover = (None, lo, hi, 0.1, 0, np.empty((3, n, 3)))
    outside = CandidateNarrowPhase._outside

    def reference(*ends):
        return max(0.0, *(float(np.max(lo - x)) for x in ends), *(float(np.max(x - hi)) for x in ends))

    inside = lo + rng.uniform(0.0, 1.0, size=(n, 3)) * (hi - lo)
    assert outside(inside, inside, cover) == 0.0
    assert outside(lo.copy(), hi.copy(), cover) == 0.0  # ends on the boxes' faces
    on_faces = np.where(rng.uniform(size=(n, 3)) < 0.5, lo, hi)
    for scale in (1e-12, 1e-3, 1.0, 1e6):
        # ends around the boxes' faces: about half the coordinates just outside
        x0 = on_faces + scale * rng.normal(size=(n, 3))
        x1 = on_faces + scale * rng.normal(size=(n, 3))
        assert outside(x0, x1, cover) == reference(x0, x1) > 0.0
        assert outside(x0, x0, cover) == reference(x0)
        assert outside(x1, x0, cover) == reference(x0, x1)
    bad = inside.copy()
    bad[7, 2] = np.nan
    assert outside(inside, bad, cover) == np.inf
    assert outside(bad, bad, cover) == np.inf
    empty = (None, lo[:0], hi[:0], 0.1, 0, np.empty((3, 0, 3)))
    assert outside(lo[:0], hi[:0], empty) == 0.0


def test_cover_continued_ahead_serves_the_next_substeps_of_steady_motion_with_fresh_hits():
    """cover(..., ahead, ahead_limit) queries each vertex's motion continued ``ahead`` more
    substeps (clipped to ``ahead_limit`` per coordinate): the following substeps of the same
    motion keep it (no query) and give exactly the hits of fresh queries and of mesh_ccd, where a
    cover of the one substep alone queries again once the motion leaves its slack; a limit below
    the motion leaves the fast vertices uncovered (a new query)."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(5)
    edges = mesh_edges(faces)
    margin, slack = 0.02, 0.005
    step = (x1 - x0) * (2.0 * slack / np.abs(x1 - x0).max())  # the largest moves 2 slack per substep
    fresh = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    ahead = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    plain = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    hits = 0
    for k in range(4):
        y0, y1 = x0 + k * step, x0 + (k + 1) * step
        ahead.cover(y0, y1, margin, slack, 3.0, 1.0)
        plain.cover(y0, y1, margin, slack)
        got, near = ahead.ccd(y0, y1), ahead.near(y0, 0.01)
        for g, w in zip(got, fresh.ccd(y0, y1)):
            np.testing.assert_array_equal(g, w)
        for g, w in zip(near, fresh.near(y0, 0.01)):
            np.testing.assert_array_equal(g, w)
        ref = mesh_ccd(y0, y1, faces, edges)
        assert len(got[0]) == int(ref.vf_hit.sum() + ref.ee_hit.sum())
        hits += len(got[0]) + len(near[0])
    assert hits > 0
    assert (ahead.queries, ahead.kept_covers) == (1, 3)  # the first cover served all four substeps
    assert plain.queries >= 3  # each cover spans one substep: the motion leaves it
    for sign in (1.0, -1.0):  # the continuation follows the motion's sign, per coordinate
        # a limit above the motion: the continued boxes cover the next substeps
        long = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
        for k in range(3):
            long.cover(x0 + sign * k * step, x0 + sign * (k + 1) * step, margin, slack, 3.0, 1.0)
        assert (long.queries, long.kept_covers) == (1, 2)
        # a limit below it: the continued boxes stop short, the second substep queries
        short = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
        for k in range(2):
            short.cover(x0 + sign * k * step, x0 + sign * (k + 1) * step, margin, slack, 3.0, 0.1 * slack)
        assert short.queries == 2


def test_candidate_ccd_with_thickness_and_a_cover_refilled_by_another_query():
    """With a thickness, pairs closer than it are candidates (the broad phase is inflated by
    it): two still sheets 5 cm apart and a 6 cm thickness hit as in mesh_ccd, with and without
    a cover; a cover whose broad-phase buffers another query refilled is not reused."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import mesh_ccd
    from collision.narrow_phase import CandidateNarrowPhase

    n = 6
    sheet, faces = _grid(n, 0.0, 0.5)
    faces = np.vstack([faces, faces + n * n])
    x0 = np.vstack([sheet, sheet + [0.0, 0.0, 0.05]])
    edges = mesh_edges(faces)
    bp = BroadPhase(faces, edges, num_vertices=len(x0))
    narrow = CandidateNarrowPhase(bp)
    want = mesh_ccd(x0, x0, faces, edges, thickness=0.06).num_contacts
    assert want > 0
    assert len(narrow.ccd(x0, x0, 0.06)[0]) == want
    narrow.cover(x0, x0, 1.0)
    assert len(narrow.ccd(x0, x0, 0.06)[0]) == want
    narrow.cover(x0, x0, 1.0)
    bp.query(x0, x0 + 5.0)  # someone else's query refills the buffers
    before = narrow.queries
    assert len(narrow.ccd(x0, x0, 0.06)[0]) == want
    assert narrow.queries == before + 1


@pytest.mark.parametrize("options", [{"precision": "float32"}, {"tolerance_scale": 0.01},
                                     {"max_iterations": 3, "tolerance": 1e-6},
                                     {"precision": "float32", "tolerance_scale": 10.0}])
def test_candidate_narrow_phase_knobs_give_the_stacked_narrow_phase_of_the_same_knobs(options):
    """The simulator's narrow phase with a generated variant (float32, tolerance scale, root
    iteration cap) hits exactly the pairs, at the times, of :func:`narrow_phase` with the same
    knobs on the broad phase's candidates (both in float32 from float64 positions)."""
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import narrow_phase
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(1)
    edges = mesh_edges(faces)
    bp = BroadPhase(faces, edges, num_vertices=len(x0))
    vf, ee = bp.query(x0, x1, 0.0)
    kind, pair, toi, source, _ = CandidateNarrowPhase(bp, **options).ccd(x0, x1)
    want_kind, want_pair, want_toi = [], [], []
    for k, pairs in ((0, vf), (1, ee)):
        idx = (np.column_stack([pairs[:, 0], faces[pairs[:, 1]]]) if k == 0
               else np.column_stack([edges[pairs[:, 0]], edges[pairs[:, 1]]]))
        hit, t, _ = narrow_phase(k, np.concatenate([x0[idx], x1[idx]], axis=1), **options)
        want_kind.append(np.full(hit.sum(), k))
        want_pair.append(pairs[hit])
        want_toi.append(t[hit])
    assert len(kind) > 10  # (3 root iterations miss some of the ~25 float64 hits)
    np.testing.assert_array_equal(kind, np.concatenate(want_kind))
    np.testing.assert_array_equal(pair, np.vstack(want_pair))
    np.testing.assert_array_equal(toi, np.concatenate(want_toi))
    assert toi.dtype == np.float64 and set(np.unique(source)) <= {0, 1, 2, 3, 4}


def test_candidate_narrow_phase_bad_knob_is_a_value_error_naming_it():
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.narrow_phase import CandidateNarrowPhase

    _, _, faces = _crumpled_sheets(0)
    bp = BroadPhase(faces, mesh_edges(faces), num_vertices=int(faces.max()) + 1)
    for options, name in (({"precision": "float16"}, "precision"), ({"tolerance_scale": 0.0}, "tolerance_scale"),
                          ({"max_iterations": 0}, "max_iterations"), ({"tolerance": float("nan")}, "tolerance")):
        with pytest.raises(ValueError, match=name):
            CandidateNarrowPhase(bp, **options)


def test_float32_narrow_phase_rejects_positions_that_overflow_float32():
    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.ccd import narrow_phase
    from collision.narrow_phase import CandidateNarrowPhase

    queries = np.zeros((1, 8, 3))
    queries[0, 5, 0] = 1e300
    with pytest.raises(ValueError, match="queries overflows float32"):
        narrow_phase(0, queries, precision="float32")
    x0, x1, faces = _crumpled_sheets(0)
    narrow = CandidateNarrowPhase(BroadPhase(faces, mesh_edges(faces), num_vertices=len(x0)), precision="float32")
    far = x1.copy()
    far[0] = 1e39  # finite in float64, not in float32
    with pytest.raises(ValueError, match="x1 overflows float32"):
        narrow.ccd(x0, far)


@wp.kernel
def _filter_soundness_kernel(
    kinds: wp.array(dtype=wp.int32),
    queries: wp.array(dtype=kccd.mat83d),
    distance_factor: wp.float64,
    rejected: wp.array(dtype=wp.int32),
    exact_rejects: wp.array(dtype=wp.int32),
    box_rejected: wp.array(dtype=wp.int32),
    threshold: wp.array(dtype=wp.float64),
    rounding: wp.array(dtype=wp.float64),
):
    """Per query: does the plane / line prefilter reject it (at the narrow phase's threshold,
    with the distance error factor given: 256 x tolerance_scale), does the bounding-box one
    (kernels.ccd.box_farther_than, the proximity kernel's, same threshold), and does the exact
    start distance test they stand in for reject it too."""
    i = wp.tid()
    kind = int(kinds[i])
    m = queries[i]
    speed = kccd.relative_motion_bound(kind, m)
    extent = kccd.relative_extent(m) + speed
    tol = distance_factor * kccd.UNIT_ROUNDOFF * extent
    y0 = kccd.row(m, 0)
    rounding[i] = kccd.filter_rounding(extent, y0)
    threshold[i] = tol + speed + rounding[i]
    rejected[i] = 0
    if kccd.farther_than(kind, y0, kccd.row(m, 1), kccd.row(m, 2), kccd.row(m, 3),
                         tol + speed + kccd.filter_rounding(extent, y0)):
        rejected[i] = 1
    box_rejected[i] = 0
    if kccd.box_farther_than(kind, y0, kccd.row(m, 1), kccd.row(m, 2), kccd.row(m, 3),
                             tol + speed + kccd.filter_rounding(extent, y0)):
        box_rejected[i] = 1
    exact_rejects[i] = 0
    if kccd.distance_at(kind, m, wp.float64(0.0)) > tol + speed:
        exact_rejects[i] = 1


def _start_gap_queries(rng, n_per_cell, far=False):
    """Vertex-face and edge-edge queries whose primitives start within 1 to 1e4 roundings of
    their coordinates' size of each other (near the distance tests' thresholds; ``far``: 1e-6 to
    1 of the primitives' size instead), at centres from 0 to 1e5 (where the vertex-face
    distance's rounding is set by the coordinates, not the primitives' size), moving by about the
    gap or not at all."""
    u = 2.0**-53
    kinds, queries = [], []
    for centre in (0.0, 1.0, 10.0, 1e3, 1e5):
        for size in (1e-2, 1.0):
            for _ in range(n_per_cell):
                if far:
                    scale = size * 10.0 ** rng.uniform(-6, 0)
                else:
                    scale = u * (centre + size) * 10.0 ** rng.uniform(0, 4)
                gap = rng.uniform(0, 1) * scale
                motion = rng.normal(size=(4, 3)) * scale * rng.choice([0.0, 0.1, 1.0])
                a = centre + rng.uniform(-size, size, 3)
                b, c = a + rng.uniform(-size, size, 3), a + rng.uniform(-size, size, 3)
                normal = np.cross(b - a, c - a)
                p = rng.dirichlet([1, 1, 1]) @ np.array([a, b, c]) + gap * normal / np.linalg.norm(normal)
                start = np.array([p, a, b, c])
                kinds.append(0)
                queries.append(np.vstack([start, start + motion]))
                e, f = rng.normal(size=3), rng.normal(size=3)
                normal = np.cross(e, f)
                s, t = rng.uniform(0.05, 0.95, 2)
                a0 = a - s * size * e
                b0 = a + gap * normal / np.linalg.norm(normal) - t * size * f
                start = np.array([a0, a0 + size * e, b0, b0 + size * f])
                kinds.append(1)
                queries.append(np.vstack([start, start + motion]))
    return np.array(kinds, dtype=np.int32), np.array(queries)


def _box_border_queries(rng, n):
    """Still vertex-face and edge-edge queries whose primitives touch at one point, one side's
    box lying on the other's along an axis (a triangle's top vertex and the vertex above it;
    an edge's top end and the other edge's bottom end), at centres from 0 to 1e5; and per query
    the unit step along that axis which moves the upper primitive away: shifted by a gap ``g``
    the boxes lie ``g`` apart and so do the primitives (the box test's border)."""
    kinds, queries, shifts = [], [], []
    for centre in (0.0, 1.0, 10.0, 1e3, 1e5):
        for size in (1e-2, 1.0):
            for _ in range(n):
                axis = rng.integers(3)
                up = np.eye(4 * 3)[axis].reshape(4, 3)  # row 0 moves
                tri = centre + rng.uniform(-size, size, (3, 3))
                start = np.array([tri[np.argmax(tri[:, axis])], *tri])
                kinds.append(0)
                queries.append(start)
                shifts.append(up)
                a = centre + rng.uniform(-size, size, (2, 3))
                b0 = a[np.argmax(a[:, axis])]
                d = rng.normal(size=3)
                d[axis] = abs(d[axis]) + 0.1
                start = np.array([*a, b0, b0 + size * d])
                kinds.append(1)
                queries.append(start)
                shifts.append(np.vstack([np.zeros((2, 3)), np.eye(3)[[axis, axis]]]))  # rows 2, 3 move
    return np.array(kinds, dtype=np.int32), np.array(queries), np.array(shifts)


def _still(queries):
    return np.concatenate([queries, queries], axis=1)


def _prefilter_and_exact(kinds, queries, tolerance_scale, box=False):
    n = len(kinds)
    rejected = wp.zeros(n, dtype=wp.int32)
    exact = wp.zeros(n, dtype=wp.int32)
    box_rejected = wp.zeros(n, dtype=wp.int32)
    threshold = wp.zeros(n, dtype=wp.float64)
    filter_rounding = wp.zeros(n, dtype=wp.float64)
    wp.launch(_filter_soundness_kernel, dim=n,
              inputs=[wp.array(kinds, dtype=wp.int32), wp.array(queries, dtype=kccd.mat83d),
                      wp.float64(256.0 * tolerance_scale), rejected, exact, box_rejected, threshold,
                      filter_rounding])
    if box == "threshold":  # the exact test's (tol + speed) and the prefilters' (plus rounding)
        return threshold.numpy(), threshold.numpy() - filter_rounding.numpy()
    return (box_rejected if box else rejected).numpy().astype(bool), exact.numpy().astype(bool)


@pytest.mark.parametrize("tolerance_scale", [1.0, 0.01])
def test_distance_prefilter_rejects_only_what_the_exact_start_distance_rejects(tolerance_scale):
    """The narrow phase rejects a far candidate by a plane / line distance bound before the exact
    distance (kernels.ccd.farther_than, threshold kernels.ccd.filter_rounding): it must never
    reject a pair the exact start distance test keeps, far from the origin and at a small
    tolerance_scale too (a threshold in units of the distance tolerance failed both). Ground
    truth: the exact test's own decision on the same query. On pairs far apart for their motion
    the bound must answer for most (else it filters nothing)."""
    rng = np.random.default_rng(3)
    rejected, exact = _prefilter_and_exact(*_start_gap_queries(rng, 200), tolerance_scale)
    assert not (rejected & ~exact).any(), np.flatnonzero(rejected & ~exact)[:10]
    rejected, exact = _prefilter_and_exact(*_start_gap_queries(rng, 50, far=True), tolerance_scale)
    assert not (rejected & ~exact).any(), np.flatnonzero(rejected & ~exact)[:10]
    assert rejected.sum() >= 0.8 * exact.sum() > 0, (rejected.sum(), exact.sum())


@pytest.mark.parametrize("tolerance_scale", [1.0, 0.01])
def test_box_prefilter_rejects_only_what_the_exact_start_distance_rejects(tolerance_scale):
    """The proximity kernel's bounding-box test (kernels.ccd.box_farther_than, at the plane
    test's threshold) never rejects a pair the exact start distance keeps: on queries at the
    plane test's border, on far ones, and at its own border (primitives touching at one point
    along an axis, then moved apart along it by 0.9 to 1.1 times the threshold: the exact
    distance is the gap), by 0.9 to 1.1 times the exact test's threshold, or 1 to 1.5 times
    its own (the exact one plus rounding). Ground truth: the exact test's own decision. Past
    its own threshold it must reject the pairs (else it filters nothing)."""
    rng = np.random.default_rng(4)
    for queries in (_start_gap_queries(rng, 100), _start_gap_queries(rng, 50, far=True)):
        rejected, exact = _prefilter_and_exact(*queries, tolerance_scale, box=True)
        assert not (rejected & ~exact).any(), np.flatnonzero(rejected & ~exact)[:10]
    kinds, touching, shift = _box_border_queries(rng, 100)
    own, exact_threshold = _prefilter_and_exact(kinds, _still(touching), tolerance_scale, box="threshold")
    at_exact = rng.uniform(size=len(kinds)) < 0.5
    gap = np.where(at_exact, exact_threshold * rng.uniform(0.9, 1.1, len(kinds)), own * rng.uniform(1.0, 1.5, len(kinds)))
    rejected, exact = _prefilter_and_exact(kinds, _still(touching + gap[:, None, None] * shift), tolerance_scale, box=True)
    assert not (rejected & ~exact).any(), np.flatnonzero(rejected & ~exact)[:10]
    assert 0.1 * at_exact.sum() < (~exact & at_exact).sum() < 0.9 * at_exact.sum()  # the exact border is crossed
    assert rejected[~at_exact].mean() > 0.95, rejected[~at_exact].mean()


def test_narrow_phase_hits_at_the_start_every_pair_within_the_distance_tolerance():
    """Every query whose exact start distance is within the distance tolerance is a hit at t = 0
    (the narrow phase's first test), whatever the prefilter before it: vertex-face queries near
    centres up to 1e5 broke this (143 of 15000 turned into misses) with a prefilter threshold in
    units of the tolerance."""
    from collision.ccd import narrow_phase

    kinds, queries = _start_gap_queries(np.random.default_rng(4), 200)
    n = len(kinds)
    within = wp.zeros(n, dtype=wp.int32)
    # the exact start test at tolerance 0 of the speed: distance <= tol_distance
    wp.launch(_start_within_kernel, dim=n, inputs=[wp.array(kinds, dtype=wp.int32),
                                                   wp.array(queries, dtype=kccd.mat83d), within])
    within = within.numpy().astype(bool)
    assert within.sum() > 100
    for kind in (0, 1):
        sel = within & (kinds == kind)
        hit, toi, source = narrow_phase(kind, queries[sel], 0.0)
        assert hit.all() and (toi == 0.0).all() and (source == 0).all(), np.flatnonzero(~hit)[:10]


@wp.kernel
def _start_within_kernel(kinds: wp.array(dtype=wp.int32), queries: wp.array(dtype=kccd.mat83d),
                         within: wp.array(dtype=wp.int32)):
    i = wp.tid()
    kind = int(kinds[i])
    m = queries[i]
    extent = kccd.relative_extent(m) + kccd.relative_motion_bound(kind, m)
    within[i] = 0
    if kccd.distance_at(kind, m, wp.float64(0.0)) <= kccd.DISTANCE_ERROR_FACTOR * kccd.UNIT_ROUNDOFF * extent:
        within[i] = 1


def test_the_cover_test_and_the_proximity_pass_on_device_positions_decide_as_the_host_does():
    """cover_test_device keeps a cover exactly where cover()'s host test does (a motion within
    the slack, a start just beyond it, one on it to rounding, a NaN end), and near_count_covered from the covered start
    gives near()'s pairs and, with the end positions, the same motion radii bit for bit (the
    host's (x^2 + y^2) + z^2), the same kept pairs, so the CCD from them tests the same pairs;
    a radius that is not finite is counted, and its kept pairs are dropped."""
    import warp as wp

    from collision.broad_phase import BroadPhase, mesh_edges
    from collision.narrow_phase import CandidateNarrowPhase

    x0, x1, faces = _crumpled_sheets(5)
    edges = mesh_edges(faces)
    on_host = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    on_device = CandidateNarrowPhase(BroadPhase(faces, edges, num_vertices=len(x0)))
    margin, slack = 0.02, 0.005
    flag = wp.zeros(1, dtype=wp.int32)
    dev = lambda a: wp.array(a, dtype=wp.vec3d)  # noqa: E731
    flag.fill_(7)
    assert not on_device.cover_test_device(dev(x0), dev(x1), margin, slack, flag)
    assert flag.numpy()[0] == 7  # no cover yet: nothing launched
    on_host.cover(x0, x1, margin, slack)
    on_device.query_cover(x0, x1, margin)
    rng = np.random.default_rng(5)
    s = rng.uniform(0.0, 1.0, size=(len(x0), 1))
    y0 = x0 + s * (x1 - x0) + rng.uniform(-0.9 * slack, 0.9 * slack, size=x0.shape)
    y1 = x1 + rng.uniform(-0.9 * slack, 0.9 * slack, size=x0.shape)
    beyond = y0.copy()
    beyond[7, 2] = max(x0[7, 2], x1[7, 2]) + slack * (1.0 + 1e-12)  # a hair past the slack
    at_edge = y0.copy()
    at_edge[7, 2] = max(x0[7, 2], x1[7, 2]) + slack  # on the slack to rounding: either, as the host decides
    nan_end = y1.copy()
    nan_end[2, 0] = np.nan
    for start, end, kept in ((y0, y1, True), (beyond, y1, False), (at_edge, y1, None), (y0, nan_end, False)):
        assert on_device.cover_test_device(dev(start), dev(end), margin, slack, flag)
        on_host.query_cover(x0, x1, margin)  # the same cover (a failed test below queries afresh)
        queries = on_host.queries
        if np.isnan(end).any():
            with pytest.raises(ValueError):  # not kept: the fresh query refuses the NaN
                on_host.cover(start, end, margin, slack)
            host_kept = False
        else:
            on_host.cover(start, end, margin, slack)
            host_kept = on_host.queries == queries
        assert (flag.numpy()[0] == 0) == host_kept
        assert kept is None or host_kept == kept
    # the proximity pass from a kept cover's start, with motion radii
    assert on_device.cover_test_device(dev(y0), dev(y1), margin, slack, flag) and flag.numpy()[0] == 0
    on_device.keep_cover(slack)
    on_host.query_cover(x0, x1, margin)
    on_host.cover(y0, y1, margin, slack)
    reach_slack = 0.001
    radius = np.sqrt(np.square(y1 - y0) @ np.ones(3)) + reach_slack
    unbounded = wp.zeros(1, dtype=wp.int32)
    # a distance whose room in the cover (COVER_SAFETY (m - d)) is narrower than the slack the
    # start may lie out: refused (near() would test the positions on the host)
    with pytest.raises(RuntimeError, match="outside the cover"):
        on_device.near_count_covered(dev(y0), 0.01, dev(y1), reach_slack, unbounded)
    host_count = on_host.near_count(y0, 0.005, radius)
    device_count = on_device.near_count_covered(dev(y0), 0.005, dev(y1), reach_slack, unbounded)
    assert device_count == host_count > 0 and unbounded.numpy()[0] == 0
    assert on_device._radius.numpy().tobytes() == radius.tobytes()
    got, want = on_device._reach.buffers(), on_host._reach.buffers()
    assert got[1] == want[1] and got[3] == want[3] and got[1] + got[3] > 0
    for kind in (0, 2):
        np.testing.assert_array_equal(got[kind].numpy()[:got[kind + 1]], want[kind].numpy()[:want[kind + 1]])
    np.testing.assert_array_equal(on_device._reach.positions(), y0)
    for g, w in zip(on_device.ccd(y0, y1), on_host.ccd(y0, y1)):
        np.testing.assert_array_equal(g, w)
    assert on_device.reach_calls == on_host.reach_calls == 1
    # a step that overflows: counted, and the caller drops the kept pairs
    huge = y1.copy()
    huge[1] = 1e200
    on_device.near_count_covered(dev(y0), 0.005, dev(huge), reach_slack, unbounded)
    assert unbounded.numpy()[0] == 1
    with pytest.raises(ValueError, match="unbounded"):
        on_device.near_count_covered(dev(y0), 0.005, dev(y1))
