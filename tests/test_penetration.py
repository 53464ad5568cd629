"""sim.penetration: hand-made scenes with known answers, touching vs penetrating, and speed.

Ground truth: closed forms (distances to axis-aligned box faces and planes) and, for the sphere
scenes, the convex polyhedron itself: a point is inside a convex polyhedron iff it is on the inner
side of every face plane, and its distance to the surface is then the smallest of those plane
distances (an algorithm independent of the checker's winding numbers).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import warp as wp

from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh, icosphere
from sim.penetration import DEFAULT_TOL, PenetrationChecker, penetrations, vertex_components

# the checker's tests build interpenetrating models on purpose: finalize's warning about them is
# the point of other tests (tests/test_builder.py), not of these
pytestmark = pytest.mark.filterwarnings("ignore::sim.penetration.InitialPenetrationWarning")

CLOTH = dict(density=0.2, stretch_stiffness=1e3, shear_stiffness=1e2, bend_stiffness=10.0, damping=0.1)
MESH_CLOTH = dict(density=0.2, stretch_stiffness=1e3, bend_stiffness=10.0, damping=0.1)
ONE_TRI = np.array([[0, 1, 2]])


def _quat_z(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def _state(model, particle_q=None, body_q=None) -> dict:
    s = model.state()
    return {
        "particle_q": s.particle_q.numpy() if particle_q is None else np.asarray(particle_q, float),
        "body_q": s.body_q.numpy() if body_q is None else np.asarray(body_q, float),
    }


# ------------------------------------------------------------------------------------- planes


def test_vertex_below_plane_has_its_depth():
    b = ModelBuilder()
    b.add_particle((0.3, 0.2, 1.0))
    b.add_particle((0.0, 0.0, -0.1))
    b.add_ground_plane()
    m = b.finalize()
    count, depth = penetrations(m, m.state())
    assert count == 1 and depth == pytest.approx(0.1, abs=1e-15)
    rep = PenetrationChecker(m).check(m.state())
    assert rep.plane_vertices.tolist() == [1] and rep.plane_ids.tolist() == [0]


def test_tilted_plane_with_offset():
    b = ModelBuilder()
    n = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    b.add_ground_plane((1.0, 0.0, 1.0), offset=0.5)
    b.add_particle(0.5 * n - 0.25 * n)  # 0.25 below
    b.add_particle(0.5 * n + 0.25 * n)  # above
    m = b.finalize()
    assert penetrations(m, m.state()) == (1, pytest.approx(0.25, abs=1e-15))


def test_resting_exactly_on_plane_is_not_a_penetration():
    b = ModelBuilder()
    b.add_cloth_grid((-0.5, -0.5, 0.0), None, 4, 4, 0.25, 0.25, **CLOTH)  # lies on z = 0
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(2.0, 0.0, 0.1))  # bottom face at z = 0
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(3.0, 0.0, 0.1), rot=_quat_z(0.7))
    b.add_ground_plane()
    m = b.finalize()
    assert penetrations(m, m.state()) == (0, 0.0)


def test_rigid_vertex_below_plane():
    b = ModelBuilder()
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(0.0, 0.0, 0.1))
    b.add_ground_plane()
    m = b.finalize()
    bq = m.state().body_q.numpy()
    bq[0, 2] = 0.1 - 0.03  # sunk by 0.03: the four bottom vertices
    count, depth = penetrations(m, _state(m, body_q=bq))
    assert count == 4 and depth == pytest.approx(0.03, abs=1e-15)


# ------------------------------------------------------------------------------------- solids


def _two_boxes(rigid_pos, rot=None, half=0.25):
    b = ModelBuilder()
    b.add_static_mesh(*box_mesh(0.5))  # [-0.5, 0.5]^3
    b.add_rigid_body(*box_mesh(half), density=500.0, pos=rigid_pos, rot=rot)
    return b.finalize()


def test_box_interpenetrating_box_by_005():
    m = _two_boxes((0.5 + 0.25 - 0.05, 0.0, 0.0))  # rigid [0.45, 0.95] x [-.25, .25]^2
    rep = PenetrationChecker(m).check(m.state())
    assert rep.count == 4 and rep.inside_count == 4 and rep.crossing_count == 0
    assert rep.max_depth == pytest.approx(0.05, abs=1e-14)
    assert np.allclose(rep.inside_depths, 0.05, atol=1e-14)
    solids = PenetrationChecker(m).solids
    assert {solids[i].kind for i in rep.inside_solids} == {"static"}


def test_rotated_box_corner_into_box_and_pose_from_state():
    half = 0.2
    m = _two_boxes((3.0, 0.0, 0.0), half=half)
    assert penetrations(m, m.state()) == (0, 0.0)
    bq = m.state().body_q.numpy()
    bq[0, :3] = (0.5 + half * np.sqrt(2.0) - 0.05, 0.0, 0.0)  # corner edge 0.05 deep
    bq[0, 3:] = _quat_z(np.pi / 4)
    rep = PenetrationChecker(m).check(_state(m, body_q=bq))
    assert rep.inside_count == 2 and rep.max_depth == pytest.approx(0.05, abs=1e-14)
    # the same through a Warp State
    s = m.state()
    s.body_q = wp.array(bq, dtype=wp.transformd)
    assert penetrations(m, s) == (rep.count, pytest.approx(rep.max_depth, abs=1e-15))


def test_static_vertices_inside_a_rigid_body_count():
    b = ModelBuilder()
    b.add_static_mesh(*box_mesh(0.1), pos=(0.0, 0.0, 0.0))  # small static box
    b.add_rigid_body(*box_mesh(0.5), density=500.0, pos=(0.0, 0.0, 0.0))  # engulfs it
    m = b.finalize()
    rep = PenetrationChecker(m).check(m.state())
    assert rep.inside_count == 8 and rep.max_depth == pytest.approx(0.4, abs=1e-14)


@pytest.mark.parametrize("gap", [1e-9, 0.0])
def test_separated_or_touching_boxes_do_not_penetrate(gap):
    m = _two_boxes((0.5 + 0.25 + gap, 0.0, 0.0))
    assert penetrations(m, m.state()) == (0, 0.0)
    m = _two_boxes((0.5 + 0.25 + gap, 0.25, 0.25))  # touching faces, shared edges and corners
    assert penetrations(m, m.state()) == (0, 0.0)


def test_shallow_penetration_below_tol_is_contact():
    m = _two_boxes((0.5 + 0.25 - 1e-11, 0.0, 0.0))
    assert penetrations(m, m.state()) == (0, 0.0)
    count, depth = penetrations(m, m.state(), tol=0.0)
    assert count == 4 and depth == pytest.approx(1e-11, rel=1e-4)


# ------------------------------------------------------------------------------------- cloth


def _cloth_tri_and_box(tri, static=False):
    b = ModelBuilder()
    b.add_cloth_mesh(np.asarray(tri, float), ONE_TRI, **MESH_CLOTH)
    if static:
        b.add_static_mesh(*box_mesh(0.25))
    else:
        b.add_rigid_body(*box_mesh(0.25), density=500.0)
    return b.finalize()


@pytest.mark.parametrize("static", [False, True])
def test_cloth_triangle_piercing_box_face_with_vertex_inside(static):
    m = _cloth_tri_and_box([(-0.5, 0.0, 0.6), (0.5, 0.0, 0.6), (0.0, 0.0, 0.15)], static)
    rep = PenetrationChecker(m).check(m.state())
    assert rep.inside_vertices.tolist() == [2] and rep.crossing_count == 0 and rep.count == 1
    assert rep.max_depth == pytest.approx(0.1, abs=1e-14)


@pytest.mark.parametrize("static", [False, True])
def test_cloth_triangle_slicing_box_edge_without_vertex_inside(static):
    tri = np.array([(0.0, 0.0, 0.45), (0.45, 0.0, 0.0), (0.6, 0.0, 0.6)])
    m = _cloth_tri_and_box(tri, static)
    rep = PenetrationChecker(m).check(m.state())
    assert rep.inside_count == 0 and rep.crossing_count >= 2 and rep.count == rep.crossing_count
    assert rep.max_depth == 0.0
    assert np.all(rep.crossing_faces[:, 0] == 0)  # the cloth triangle (global face 0) in every pair
    # moved 0.06 along +x and +z, the triangle clears the box (its hypotenuse x + z = 0.57 > 0.5)
    assert penetrations(m, _state(m, particle_q=tri + [0.06, 0.0, 0.06])) == (0, 0.0)


def test_cloth_crossing_an_open_static_mesh():
    b = ModelBuilder()
    b.add_cloth_mesh(np.array([(-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (0.0, 1.0, 0.0)]), ONE_TRI, **MESH_CLOTH)
    b.add_static_mesh(np.array([(0.0, -0.2, -0.5), (0.0, 0.2, -0.5), (0.0, 0.0, 0.5)]), ONE_TRI)  # a wall
    m = b.finalize()
    rep = PenetrationChecker(m).check(m.state())
    assert rep.count == 1 and rep.crossing_faces.tolist() == [[0, 1]] and rep.max_depth == 0.0
    q = m.state().particle_q.numpy()
    assert penetrations(m, _state(m, particle_q=q + [0, 0, 0.5 + 1e-9])) == (0, 0.0)


def test_cloth_resting_on_box_top_and_over_its_edges_is_contact():
    b = ModelBuilder()
    b.add_cloth_grid((-0.6, -0.6, 0.25), None, 6, 6, 0.2, 0.2, **CLOTH)  # flat on the top face
    b.add_rigid_body(*box_mesh(0.25), density=500.0)
    b.add_static_mesh(*box_mesh(0.25), pos=(3.0, 0.0, 0.0))
    m = b.finalize()
    assert penetrations(m, m.state()) == (0, 0.0)
    q = m.state().particle_q.numpy()
    assert penetrations(m, _state(m, particle_q=q + [0, 0, 1e-9])) == (0, 0.0)
    over = q.copy()
    out = np.max(np.abs(q[:, :2]), axis=1) > 0.25  # hang the outer ring down: drape over edges
    over[out, 2] = 0.0
    count, depth = penetrations(m, _state(m, particle_q=over))
    # hanging vertices outside the box; triangles from the top face to them cut the box's edges
    assert count > 0 and depth == 0.0
    under = q - [0, 0, 0.02]
    count, depth = penetrations(m, _state(m, particle_q=under))
    inside = np.sum(np.all(np.abs(under[:, :2]) < 0.25, axis=1))
    assert count >= inside and depth == pytest.approx(0.02, abs=1e-14)


def test_vertex_components_and_bad_inputs():
    v, f = box_mesh(0.5)
    lab = vertex_components(np.concatenate([f, f + 8]), 17)
    assert lab.tolist() == [0] * 8 + [1] * 8 + [2]
    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 1.0))
    m = b.finalize()
    with pytest.raises(ValueError, match="tol"):
        PenetrationChecker(m, tol=-1.0)
    with pytest.raises(ValueError, match="particles"):
        penetrations(m, {"particle_q": np.zeros((2, 3))})
    with pytest.raises(ValueError, match="NaN"):
        penetrations(m, {"particle_q": np.full((1, 3), np.nan)})
    assert DEFAULT_TOL < 1e-9


# ------------------------------------------------------------------------------------- sphere / speed


@pytest.fixture(scope="module")
def drape():
    """64 x 64 cloth (4225 particles) over a 642-vertex icosphere of radius 1 at the origin."""
    b = ModelBuilder()
    b.add_cloth_grid((-1.5, -1.5, 2.0), None, 64, 64, 3 / 64, 3 / 64, **CLOTH)
    sv, sf = icosphere(1.0, 3)
    assert len(sv) == 642
    b.add_rigid_body(sv, sf, density=100.0)
    m = b.finalize()
    poly = sv  # placed at pos = 0, rot = identity: world vertices are the mesh's
    n = np.cross(poly[sf[:, 1]] - poly[sf[:, 0]], poly[sf[:, 2]] - poly[sf[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    off = np.einsum("ij,ij->i", n, poly[sf[:, 0]])
    checker = PenetrationChecker(m)
    checker.check(m.state())  # compile / warm up
    q0 = m.state().particle_q.numpy()
    return m, checker, q0, n, off


def _heightfield(q0, radius, drop=0.0):
    q = q0.copy()
    r = np.linalg.norm(q[:, :2], axis=1)
    q[:, 2] = np.sqrt(np.clip(radius**2 - r**2, 0.0, None)) - drop
    return q


def test_draped_cloth_clear_of_the_sphere_is_fast_and_clean(drape):
    m, checker, q0, _, _ = drape
    q = _heightfield(q0, 1.02)  # 2 cm above the ball; chords sag < 1e-3
    t = time.perf_counter()
    rep = checker.check({"particle_q": q, "body_q": m.state().body_q.numpy()})
    elapsed = time.perf_counter() - t
    assert rep.count == 0
    assert elapsed < 2.0, elapsed  # ~0.1 s on one core; generous for loaded CI machines


def test_sunk_cloth_matches_the_convex_polyhedron(drape):
    m, checker, q0, n, off = drape
    q = _heightfield(q0, 1.02, drop=0.08)
    t = time.perf_counter()
    rep = checker.check({"particle_q": q, "body_q": m.state().body_q.numpy()})
    elapsed = time.perf_counter() - t
    signed = q @ n.T - off  # (P, F): < 0 on the inner side of a face
    depth = -signed.max(axis=1)  # distance to the surface for interior points
    truth = np.flatnonzero(depth > DEFAULT_TOL)
    assert len(truth) > 100
    assert sorted(rep.inside_vertices.tolist()) == truth.tolist()
    assert rep.max_depth == pytest.approx(depth.max(), abs=1e-12)
    assert np.allclose(rep.inside_depths, depth[rep.inside_vertices], atol=1e-12)
    assert elapsed < 2.0, elapsed


def test_cloth_touching_the_polyhedron_crossings_are_real(drape):
    """Vertices 1e-6 outside the ball's polyhedron but chords dip inside: every reported crossing
    triangle really enters the polyhedron (checked by sampling it densely)."""
    m, checker, q0, n, off = drape
    q = _heightfield(q0, 1.0 + 1e-6)
    rep = checker.check({"particle_q": q, "body_q": m.state().body_q.numpy()})
    assert rep.inside_count == 0 and rep.crossing_count > 0
    tris = m.tri_indices.numpy()
    rng = np.random.default_rng(0)
    w = rng.dirichlet([0.3, 0.3, 0.3], 200)
    cloth_faces = np.unique(rep.crossing_faces[:, 0])
    sample = rng.choice(cloth_faces, size=min(80, len(cloth_faces)), replace=False)
    pts = np.einsum("sk,fkd->fsd", w, q[tris[sample]])  # (80, 200, 3)
    inside = (pts @ n.T - off).max(axis=2) < 0.0  # (80, 200)
    assert inside.any(axis=1).mean() >= 0.95
