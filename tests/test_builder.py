"""ModelBuilder: mass properties against closed forms and exact rational sums, cloth topology and
masses, pinning, finalize() output, and every validation error (raised before anything is written).

Ground truth:
* box: closed-form solid box (m = 8 rho hx hy hz, I_xx = m (hy^2 + hz^2) / 3, ...);
* icosphere: the exact mass properties of the same float64 polyhedron, summed in rational
  arithmetic (fractions.Fraction) with Eberly's "Polyhedral Mass Properties (Revisited)" formulas
  (an algorithm independent of the builder's tetrahedron covariance), plus rigorous bounds from the
  inscribed and circumscribed balls of the polyhedron.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import warp as wp

from core.rotation import quat_to_matrix
from sim.builder import ModelBuilder
from sim.mass_properties import mesh_mass_properties
from core.rotation import quat_from_matrix
from sim.mesh_io import box_mesh, icosphere
from sim.model import Model

CLOTH = dict(density=0.3, stretch_stiffness=1000.0, shear_stiffness=100.0, bend_stiffness=10.0, damping=0.5)
MESH_CLOTH = dict(density=0.3, stretch_stiffness=1000.0, bend_stiffness=10.0, damping=0.5)


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2) * axis, [np.cos(angle / 2)]])


Q0 = _rot([1.0, 2.0, -0.5], 0.9)  # a generic rotation (x, y, z, w)
R0 = quat_to_matrix(Q0)


def box_closed_form(h, rho):
    hx, hy, hz = h
    m = 8.0 * rho * hx * hy * hz
    return m, np.diag([m * (hy**2 + hz**2) / 3, m * (hx**2 + hz**2) / 3, m * (hx**2 + hy**2) / 3])


def eberly_exact(v, t, density=1):
    """Exact (rational) mass, COM and inertia about the COM of the float64 polyhedron (v, t)."""
    vs = [[Fraction(float(c)) for c in row] for row in v]
    integ = [Fraction(0)] * 10

    def sub(w0, w1, w2):
        temp0 = w0 + w1
        f1 = temp0 + w2
        temp1 = w0 * w0
        temp2 = temp1 + w1 * temp0
        f2 = temp2 + w2 * f1
        f3 = w0 * temp1 + w1 * temp2 + w2 * f2
        return f1, f2, f3, f2 + w0 * (f1 + w0), f2 + w1 * (f1 + w1), f2 + w2 * (f1 + w2)

    for i0, i1, i2 in np.asarray(t).tolist():
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = vs[i0], vs[i1], vs[i2]
        a1, b1, c1 = x1 - x0, y1 - y0, z1 - z0
        a2, b2, c2 = x2 - x0, y2 - y0, z2 - z0
        d0, d1, d2 = b1 * c2 - b2 * c1, a2 * c1 - a1 * c2, a1 * b2 - a2 * b1
        f1x, f2x, f3x, g0x, g1x, g2x = sub(x0, x1, x2)
        _, f2y, f3y, g0y, g1y, g2y = sub(y0, y1, y2)
        _, f2z, f3z, g0z, g1z, g2z = sub(z0, z1, z2)
        integ[0] += d0 * f1x
        integ[1] += d0 * f2x
        integ[2] += d1 * f2y
        integ[3] += d2 * f2z
        integ[4] += d0 * f3x
        integ[5] += d1 * f3y
        integ[6] += d2 * f3z
        integ[7] += d0 * (y0 * g0x + y1 * g1x + y2 * g2x)
        integ[8] += d1 * (z0 * g0y + z1 * g1y + z2 * g2y)
        integ[9] += d2 * (x0 * g0z + x1 * g1z + x2 * g2z)
    rho = Fraction(density)
    mult = [Fraction(1, 6)] + [Fraction(1, 24)] * 3 + [Fraction(1, 60)] * 3 + [Fraction(1, 120)] * 3
    integ = [rho * i * m for i, m in zip(integ, mult)]
    mass = integ[0]
    cx, cy, cz = integ[1] / mass, integ[2] / mass, integ[3] / mass
    ixx = integ[5] + integ[6] - mass * (cy * cy + cz * cz)
    iyy = integ[4] + integ[6] - mass * (cz * cz + cx * cx)
    izz = integ[4] + integ[5] - mass * (cx * cx + cy * cy)
    ixy = -(integ[7] - mass * cx * cy)
    iyz = -(integ[8] - mass * cy * cz)
    ixz = -(integ[9] - mass * cz * cx)
    inertia = [[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]
    return mass, [cx, cy, cz], inertia


def grid_spring_counts(nx, ny):
    stretch = nx * (ny + 1) + ny * (nx + 1)
    shear = 2 * nx * ny
    bend = max(nx - 1, 0) * (ny + 1) + max(ny - 1, 0) * (nx + 1)
    return stretch, shear, bend


# ------------------------------------------------------------------ rigid mass properties


def test_box_mass_properties_closed_form():
    h, rho = np.array([0.3, 0.5, 0.7]), 2.5
    v, t = box_mesh(h)
    m, inertia = box_closed_form(h, rho)
    props = mesh_mass_properties(v, t, rho)
    assert props.volume == pytest.approx(8 * h.prod(), rel=1e-14)
    assert props.mass == pytest.approx(m, rel=1e-14)
    np.testing.assert_allclose(props.com, 0.0, atol=1e-15)
    np.testing.assert_allclose(props.inertia, inertia, rtol=1e-13, atol=1e-15 * m)

    b = ModelBuilder()
    assert b.add_rigid_body(v, t, density=rho) == 0
    model = b.finalize()
    assert model.body_count == 1
    assert model.body_mass.numpy()[0] == pytest.approx(m, rel=1e-14)
    assert model.body_inv_mass.numpy()[0] == pytest.approx(1 / m, rel=1e-14)
    np.testing.assert_allclose(model.body_inertia.numpy()[0], inertia, rtol=1e-13, atol=1e-15 * m)
    np.testing.assert_allclose(model.body_inv_inertia.numpy()[0], np.linalg.inv(inertia), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.shape_vertices.numpy(), v, atol=1e-15)


def test_translated_rotated_box_parallel_axis():
    h, rho = np.array([0.2, 0.4, 0.1]), 700.0
    shift = np.array([1.5, -2.0, 0.75])
    v0, t = box_mesh(h)
    v = v0 @ R0.T + shift  # box rotated by R0 then translated, in the mesh frame
    m, i_box = box_closed_form(h, rho)
    props = mesh_mass_properties(v, t, rho)
    i_com = R0 @ i_box @ R0.T
    i_origin = i_com + m * (shift @ shift * np.eye(3) - np.outer(shift, shift))  # parallel axis theorem
    assert props.mass == pytest.approx(m, rel=1e-13)
    np.testing.assert_allclose(props.com, shift, rtol=0, atol=1e-14)
    np.testing.assert_allclose(props.inertia, i_com, rtol=0, atol=1e-12 * np.abs(i_box).max())
    np.testing.assert_allclose(props.inertia_origin, i_origin, rtol=0, atol=1e-12 * np.abs(i_origin).max())

    # placed in the world with pos/rot: body_q = (pos + R com, rot); surface = body_q applied to shape
    pos, q1 = np.array([0.1, 0.2, 3.0]), _rot([0, 0, 1], 0.4)
    r1 = quat_to_matrix(q1)
    b = ModelBuilder()
    b.add_rigid_body(v, t, density=rho, pos=pos, rot=q1, velocity=(1, 2, 3), angular_velocity=(4, 5, 6))
    model = b.finalize()
    bq = model.body_q.numpy()[0]
    np.testing.assert_allclose(bq[:3], pos + r1 @ shift, atol=1e-14)
    np.testing.assert_allclose(bq[3:], q1, atol=1e-15)
    np.testing.assert_allclose(model.body_qd.numpy()[0], [4, 5, 6, 1, 2, 3])
    world = bq[:3] + model.shape_vertices.numpy() @ r1.T
    np.testing.assert_allclose(world, pos + v @ r1.T, atol=1e-13)
    np.testing.assert_allclose(model.body_inertia.numpy()[0], i_com, atol=1e-12 * np.abs(i_box).max())
    # the same rotation given as a matrix gives the same pose
    b2 = ModelBuilder()
    b2.add_rigid_body(v, t, density=rho, pos=pos, rot=r1)
    np.testing.assert_allclose(b2.finalize().body_q.numpy()[0], bq, atol=1e-15)


@pytest.mark.parametrize("subdivisions", [3, 4])
def test_icosphere_against_exact_polyhedron_and_ball(subdivisions):
    radius, rho = 0.35, 1200.0
    v, t = icosphere(radius, subdivisions)
    props = mesh_mass_properties(v, t, rho)

    mass, com, inertia = eberly_exact(v, t, Fraction(rho))
    assert props.mass == pytest.approx(float(mass), rel=1e-13)
    np.testing.assert_allclose(props.com, [float(c) for c in com], rtol=0, atol=1e-15 * radius)
    i_exact = np.array([[float(x) for x in row] for row in inertia])
    np.testing.assert_allclose(props.inertia, i_exact, rtol=0, atol=1e-13 * i_exact.max())

    # icosahedral symmetry: isotropic inertia, centred
    assert np.ptp(np.diag(props.inertia)) <= 1e-12 * props.inertia[0, 0]
    assert np.abs(props.inertia - np.diag(np.diag(props.inertia))).max() <= 1e-12 * props.inertia[0, 0]

    # the polyhedron lies between its inscribed ball (radius = nearest face plane) and the
    # circumscribed ball (all vertices on the sphere): volume and I = (2/3) int |x|^2 rho dV bounded.
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    n = np.cross(b - a, c - a)
    r_in = np.min(np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1, keepdims=True), a))
    r_out = np.linalg.norm(v, axis=1).max()
    assert r_out == pytest.approx(radius, rel=1e-15)
    vol = lambda r: 4.0 / 3.0 * np.pi * r**3  # noqa: E731
    inertia_ball = lambda r: rho * 8.0 * np.pi * r**5 / 15.0  # noqa: E731
    assert vol(r_in) < props.volume < vol(r_out)
    assert inertia_ball(r_in) < props.inertia[0, 0] < inertia_ball(r_out)
    # and the relative error to the smooth ball shrinks ~4x per subdivision (measured 0.86% / 0.22%)
    rel = 1.0 - props.volume / vol(radius)
    assert 0 < rel < {3: 0.01, 4: 0.0025}[subdivisions]


def test_quaternion_matrix_round_trip():
    for q in [Q0, _rot([0, 1, 0], np.pi), _rot([1, 0, 0], np.pi - 1e-9), np.array([0, 0, 0, 1.0])]:
        r = quat_to_matrix(q)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-15)
        q2 = quat_from_matrix(r)
        np.testing.assert_allclose(q2 * np.sign(q2 @ q), q, atol=1e-12)


def test_rigid_body_drops_unused_vertices_and_offsets_shapes():
    v, t = box_mesh(0.5)
    extra = np.vstack([v, [[9.0, 9.0, 9.0]]])  # an unreferenced vertex
    b = ModelBuilder()
    b.add_rigid_body(extra, t, density=1.0)
    b.add_rigid_body(*icosphere(0.25, 1), density=2.0, pos=(3, 0, 0))
    model = b.finalize()
    assert model.body_count == 2
    assert model.shape_vertices.shape == (8 + 42,)
    np.testing.assert_array_equal(model.shape_vertex_body.numpy(), [0] * 8 + [1] * 42)
    faces = model.shape_faces.numpy()
    assert faces.shape == (12 + 80, 3)
    assert faces[:12].max() == 7 and faces[12:].min() == 8 and faces[12:].max() == 49
    assert model.components == frozenset({"rigid"})


# ------------------------------------------------------------------ cloth grid


@pytest.mark.parametrize("nx,ny", [(1, 1), (1, 5), (4, 1), (3, 2), (7, 5)])
def test_cloth_grid_counts_masses_springs(nx, ny):
    cx, cy = 0.1, 0.25
    b = ModelBuilder()
    rng = b.add_cloth_grid((0.5, -1.0, 2.0), Q0, nx, ny, cx, cy, **CLOTH)
    p = (nx + 1) * (ny + 1)
    assert rng == range(0, p)
    ns, nh, nb = grid_spring_counts(nx, ny)
    assert b.spring_count == ns + nh + nb
    assert b.tri_count == 2 * nx * ny
    model = b.finalize()
    assert model.particle_count == p and model.spring_count == ns + nh + nb and model.tri_count == 2 * nx * ny

    mass = model.particle_mass.numpy()
    assert mass.sum() == pytest.approx(CLOTH["density"] * nx * cx * ny * cy, rel=1e-13)
    if nx > 1 and ny > 1:  # an interior particle carries one cell's mass
        assert mass[1 * (nx + 1) + 1] == pytest.approx(CLOTH["density"] * cx * cy, rel=1e-13)
    np.testing.assert_allclose(model.particle_inv_mass.numpy(), 1.0 / mass)

    q = model.particle_q.numpy()
    local = (q - [0.5, -1.0, 2.0]) @ R0  # back to the grid frame
    np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-14)
    np.testing.assert_allclose(local[nx + 1], [0.0, cy, 0.0], atol=1e-14)  # index j*(nx+1)+i

    tri = model.tri_indices.numpy()
    nrm = np.cross(q[tri[:, 1]] - q[tri[:, 0]], q[tri[:, 2]] - q[tri[:, 0]])
    unit = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    np.testing.assert_allclose(unit, np.tile(R0[:, 2], (len(tri), 1)), atol=1e-12)  # all along R @ +z
    np.testing.assert_allclose(0.5 * np.linalg.norm(nrm, axis=1), 0.5 * cx * cy, rtol=1e-12)

    idx = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy()
    k = model.spring_stiffness.numpy()
    np.testing.assert_allclose(rest, np.linalg.norm(q[idx[:, 0]] - q[idx[:, 1]], axis=1), rtol=1e-14)
    assert len({tuple(sorted(s)) for s in idx.tolist()}) == len(idx)  # no duplicates
    np.testing.assert_array_equal(k, np.repeat([1000.0, 100.0, 10.0], [ns, nh, nb]))
    np.testing.assert_allclose(model.spring_damping.numpy(), 0.5)
    st, sh, be = rest[:ns], rest[ns : ns + nh], rest[ns + nh :]
    assert np.all(np.isclose(st, cx) | np.isclose(st, cy))
    np.testing.assert_allclose(sh, np.hypot(cx, cy))
    assert np.all(np.isclose(be, 2 * cx) | np.isclose(be, 2 * cy))
    assert model.components == frozenset({"cloth"})


def test_cloth_grid_pinned_forms_and_velocity():
    nx, ny = 3, 2
    p = (nx + 1) * (ny + 1)
    corners = [0, nx]
    masks = []
    for pinned in (corners, np.array(corners), np.isin(np.arange(p), corners), lambda i, x: i in (0, nx)):
        b = ModelBuilder()
        b.add_cloth_grid((0, 0, 0), None, nx, ny, 0.5, 0.5, **CLOTH, pinned=pinned, velocity=(0, 0, -1.0))
        m = b.finalize()
        mass, inv = m.particle_mass.numpy(), m.particle_inv_mass.numpy()
        masks.append(mass == 0)
        assert np.all(inv[corners] == 0) and np.all(mass[corners] == 0)
        free = np.setdiff1d(np.arange(p), corners)
        assert np.all(mass[free] > 0)
        np.testing.assert_allclose(inv[free], 1 / mass[free])
        np.testing.assert_allclose(m.particle_qd.numpy(), np.tile([0, 0, -1.0], (p, 1)))
    for mk in masks:
        np.testing.assert_array_equal(mk, masks[0])

    # the predicate sees world positions: pin the row at y = 1 of a cloth raised to z = 2
    b = ModelBuilder()
    r = b.add_cloth_grid((0, 0, 2), None, nx, ny, 0.5, 0.5, **CLOTH, pinned=lambda i, x: x[1] > 0.99)
    mass = b.finalize().particle_mass.numpy()
    np.testing.assert_array_equal(np.flatnonzero(mass == 0), np.arange(ny * (nx + 1), p))
    # per-particle velocities
    vel = np.arange(3 * p, dtype=float).reshape(p, 3)
    b.add_cloth_grid((0, 0, 0), None, nx, ny, 0.5, 0.5, **CLOTH, velocity=vel)
    np.testing.assert_array_equal(b.finalize().particle_qd.numpy()[r.stop :], vel)


def test_two_grids_offset_indices_and_matrix_rotation():
    b = ModelBuilder()
    b.add_cloth_grid((0, 0, 0), None, 2, 2, 0.1, 0.1, **CLOTH)
    r2 = b.add_cloth_grid((0, 0, 1), R0, 2, 2, 0.1, 0.1, **CLOTH)
    assert r2 == range(9, 18)
    m = b.finalize()
    idx, tri = m.spring_indices.numpy(), m.tri_indices.numpy()
    half_s, half_t = len(idx) // 2, len(tri) // 2
    np.testing.assert_array_equal(idx[half_s:], idx[:half_s] + 9)
    np.testing.assert_array_equal(tri[half_t:], tri[:half_t] + 9)
    b2 = ModelBuilder()
    b2.add_cloth_grid((0, 0, 1), Q0, 2, 2, 0.1, 0.1, **CLOTH)
    np.testing.assert_allclose(m.particle_q.numpy()[9:], b2.finalize().particle_q.numpy(), atol=1e-15)


# ------------------------------------------------------------------ cloth mesh


def test_cloth_mesh_square_and_sphere():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    b = ModelBuilder()
    b.add_cloth_mesh(v, t, **MESH_CLOTH, pinned=[3])
    m = b.finalize()
    idx = m.spring_indices.numpy()
    assert idx[:5].tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]  # stretch: unique edges
    assert idx[5:].tolist() == [[1, 3]]  # bending across the interior edge (0, 2)
    np.testing.assert_array_equal(m.spring_stiffness.numpy(), [1000.0] * 5 + [10.0])
    assert m.spring_rest_length.numpy()[5] == pytest.approx(np.sqrt(2.0))
    mass = m.particle_mass.numpy()
    np.testing.assert_allclose(mass, 0.3 * np.array([1 / 3, 1 / 6, 1 / 3, 0.0]))
    assert m.particle_inv_mass.numpy()[3] == 0

    vs, ts = icosphere(1.0, 2)
    b = ModelBuilder()
    b.add_cloth_mesh(vs, ts, **MESH_CLOTH, pos=(0, 0, 5), rot=Q0, velocity=(1, 0, 0))
    m = b.finalize()
    n_edges = 3 * len(ts) // 2
    assert m.spring_count == 2 * n_edges  # closed: every edge interior, one bending spring each
    a, bb, c = vs[ts[:, 0]], vs[ts[:, 1]], vs[ts[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(bb - a, c - a), axis=1).sum()
    assert m.particle_mass.numpy().sum() == pytest.approx(0.3 * area, rel=1e-13)
    np.testing.assert_allclose(m.particle_q.numpy(), (0, 0, 5) + vs @ R0.T, atol=1e-14)


def test_cloth_mesh_of_grid_matches_grid_masses():
    b = ModelBuilder()
    b.add_cloth_grid((0, 0, 0), None, 4, 3, 0.2, 0.3, **CLOTH)
    g = b.finalize()
    b2 = ModelBuilder()
    b2.add_cloth_mesh(g.particle_q.numpy(), g.tri_indices.numpy(), **MESH_CLOTH)
    m = b2.finalize()
    np.testing.assert_allclose(m.particle_mass.numpy(), g.particle_mass.numpy(), rtol=1e-13)
    # stretch springs of the mesh = grid edges + one diagonal per cell
    assert m.spring_count == (4 * 4 + 3 * 5 + 12) + (4 * 4 + 3 * 5 + 12 - 2 * (4 + 3))


# ------------------------------------------------------------------ static colliders, finalize


def test_static_mesh_planes_settings_components():
    b = ModelBuilder(gravity=(0, -9.81, 0))
    assert b.add_static_mesh(*box_mesh(1.0)) == 0
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], float)  # last vertex unused
    assert b.add_static_mesh(v, [[0, 1, 2]], pos=(0, 0, -1)) == 1
    assert b.add_ground_plane((0, 0, 2.0), offset=-0.5) == 0
    b.restitution, b.friction, b.thickness = 0.3, 0.8, 1e-3
    b.set_contact(friction=0.2)
    b.enable_self_collision()
    m = b.finalize()
    assert isinstance(m, Model)
    assert m.components == frozenset({"static", "self_collision"})
    np.testing.assert_array_equal(m.gravity, [0, -9.81, 0])
    assert (m.restitution, m.friction, m.thickness) == (0.3, 0.2, 1e-3)
    assert m.static_vertices.shape == (11,) and m.static_faces.shape == (13, 3)
    np.testing.assert_array_equal(m.static_faces.numpy()[12], [8, 9, 10])
    np.testing.assert_allclose(m.static_vertices.numpy()[8:], [[0, 0, -1], [1, 0, -1], [0, 1, -1]])
    assert m.plane_count == 1
    np.testing.assert_allclose(m.planes.numpy(), [[0, 0, 1, -0.5]])
    b.set_gravity(-3.0)
    np.testing.assert_array_equal(b.gravity, [0, 0, -3.0])


def test_finalize_dtypes_empty_and_grad():
    m = ModelBuilder().finalize()
    assert m.components == frozenset()
    for name, dtype in [
        ("particle_q", wp.vec3d), ("particle_qd", wp.vec3d), ("particle_mass", wp.float64),
        ("particle_inv_mass", wp.float64), ("spring_indices", wp.int32), ("spring_rest_length", wp.float64),
        ("spring_stiffness", wp.float64), ("spring_damping", wp.float64), ("tri_indices", wp.int32),
        ("body_q", wp.transformd), ("body_qd", wp.spatial_vectord), ("body_mass", wp.float64),
        ("body_inv_mass", wp.float64), ("body_inertia", wp.mat33d), ("body_inv_inertia", wp.mat33d),
        ("shape_vertices", wp.vec3d), ("shape_vertex_body", wp.int32), ("shape_faces", wp.int32),
        ("static_vertices", wp.vec3d), ("static_faces", wp.int32), ("planes", wp.vec4d),
    ]:  # fmt: skip
        a = getattr(m, name)
        assert a is not None and a.dtype == dtype and a.shape[0] == 0, name
    s = m.state()
    assert s.particle_q.shape == (0,) and s.body_q.shape == (0,)

    b = ModelBuilder()
    b.add_cloth_grid((0, 0, 0), None, 2, 2, 0.1, 0.1, **CLOTH)
    b.add_rigid_body(*box_mesh(0.1), density=10.0, pos=(0.0, 0.0, 1.0))  # clear of the cloth
    b.add_particle((0, 0, 3), (0, 0, -1), 0.5)
    m = b.finalize(requires_grad=True)
    assert m.particle_q.requires_grad and m.body_qd.requires_grad and m.spring_stiffness.requires_grad
    assert not m.tri_indices.requires_grad
    assert m.spring_indices.shape == (m.spring_count, 2) and m.tri_indices.shape == (8, 3)
    assert m.particle_count == 10 and m.particle_mass.numpy()[9] == 0.5
    st = m.state(requires_grad=True)
    assert st.particle_q.requires_grad
    np.testing.assert_array_equal(st.particle_q.numpy(), m.particle_q.numpy())
    # finalize leaves the builder usable and unchanged
    m2 = b.finalize()
    np.testing.assert_array_equal(m2.particle_q.numpy(), m.particle_q.numpy())


# ------------------------------------------------------------------ validation


def _snapshot(b: ModelBuilder):
    return (
        b.particle_count, b.spring_count, b.tri_count, b.body_count, b.plane_count,
        b.static_vertex_count, b.static_face_count, b.components, tuple(b.gravity),
        b.restitution, b.friction, b.thickness,
    )  # fmt: skip


BOX_V, BOX_T = box_mesh(0.5)
SQ_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
SQ_T = np.array([[0, 1, 2], [0, 2, 3]])
NAN_V = SQ_V.copy()
NAN_V[2, 1] = np.nan
INF_V = SQ_V.copy()
INF_V[0, 0] = np.inf
COLLINEAR_V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], float)
FIN_V = np.vstack([SQ_V, [[0.5, 0.5, 1.0]]])  # a third triangle on the square's diagonal
TWO_BOX_V = np.vstack([BOX_V, BOX_V + [2.0, 0, 0]])


def grid(**kw):
    args = dict(pos=(0, 0, 0), rot=None, dim_x=3, dim_y=2, cell_x=0.1, cell_y=0.1, **CLOTH)
    args.update(kw)
    pos, rot, nx, ny, cx, cy = (args.pop(k) for k in ("pos", "rot", "dim_x", "dim_y", "cell_x", "cell_y"))
    return lambda b: b.add_cloth_grid(pos, rot, nx, ny, cx, cy, **args)


def cmesh(v=SQ_V, t=SQ_T, **kw):
    args = dict(MESH_CLOTH)
    args.update(kw)
    return lambda b: b.add_cloth_mesh(v, t, **args)


def rigid(v=BOX_V, t=BOX_T, **kw):
    args = dict(density=100.0)
    args.update(kw)
    return lambda b: b.add_rigid_body(v, t, **args)


def _set(attr, value):
    return lambda b: setattr(b, attr, value)


BAD = {
    # cloth grid
    "grid dim_x=0": (grid(dim_x=0), "dim_x"),
    "grid dim_y<0": (grid(dim_y=-2), "dim_y"),
    "grid dim_x float": (grid(dim_x=2.5), "dim_x"),
    "grid cell_x=0": (grid(cell_x=0.0), "cell_x"),
    "grid cell_y nan": (grid(cell_y=np.nan), "cell_y"),
    "grid density=0": (grid(density=0.0), "density"),
    "grid density<0": (grid(density=-1.0), "density"),
    "grid stretch<0": (grid(stretch_stiffness=-1.0), "stretch_stiffness"),
    "grid shear nan": (grid(shear_stiffness=np.nan), "shear_stiffness"),
    "grid bend inf": (grid(bend_stiffness=np.inf), "bend_stiffness"),
    "grid damping<0": (grid(damping=-0.1), "damping"),
    "grid pos nan": (grid(pos=(0, np.nan, 0)), "pos"),
    "grid pos shape": (grid(pos=(0, 0)), "pos"),
    "grid rot quat norm": (grid(rot=(0, 0, 1, 1)), "rot"),
    "grid rot quat shape": (grid(rot=(0, 0, 1)), "rot"),
    "grid rot matrix scaled": (grid(rot=2 * np.eye(3)), "rot"),
    "grid rot reflection": (grid(rot=np.diag([1.0, 1.0, -1.0])), "rot"),
    "grid rot nan": (grid(rot=(0, 0, np.nan, 1)), "rot"),
    "grid pinned range": (grid(pinned=[0, 12]), "pinned"),
    "grid pinned negative": (grid(pinned=[-1]), "pinned"),
    "grid pinned mask": (grid(pinned=np.ones(5, bool)), "pinned"),
    "grid pinned float": (grid(pinned=[0.5]), "pinned"),
    "grid velocity shape": (grid(velocity=np.zeros((5, 3))), "velocity"),
    "grid velocity nan": (grid(velocity=(np.nan, 0, 0)), "velocity"),
    # cloth mesh
    "mesh vertices nan": (cmesh(v=NAN_V), "vertices"),
    "mesh vertices inf": (cmesh(v=INF_V), "vertices"),
    "mesh vertices shape": (cmesh(v=SQ_V[:, :2]), "vertices"),
    "mesh triangles range": (cmesh(t=[[0, 1, 4]]), "triangles"),
    "mesh triangles negative": (cmesh(t=[[0, 1, -1], [0, 2, 3]]), "triangles"),
    "mesh triangles float": (cmesh(t=SQ_T.astype(float)), "triangles"),
    "mesh triangles shape": (cmesh(t=[[0, 1, 2, 3]]), "triangles"),
    "mesh triangles empty": (cmesh(t=np.zeros((0, 3), int)), "triangles"),
    "mesh degenerate collinear": (cmesh(v=COLLINEAR_V, t=[[0, 1, 2], [0, 2, 3]]), "degenerate"),
    "mesh degenerate repeated": (cmesh(t=[[0, 1, 1], [0, 2, 3]]), "degenerate"),
    "mesh unused vertex": (cmesh(t=[[0, 1, 2]]), "vertices"),
    "mesh duplicate triangle": (cmesh(t=[[0, 1, 2], [1, 2, 0], [0, 2, 3]]), "duplicate"),
    "mesh non-manifold": (cmesh(v=FIN_V, t=[[0, 1, 2], [0, 2, 3], [0, 2, 4]]), "non-manifold"),
    "mesh density": (cmesh(density=0.0), "density"),
    "mesh stretch": (cmesh(stretch_stiffness=-5.0), "stretch_stiffness"),
    "mesh pinned": (cmesh(pinned=[4]), "pinned"),
    # rigid
    "rigid density=0": (rigid(density=0.0), "density"),
    "rigid density<0": (rigid(density=-3.0), "density"),
    "rigid density nan": (rigid(density=np.nan), "density"),
    "rigid vertices nan": (rigid(v=np.where(np.arange(24).reshape(8, 3) == 5, np.nan, BOX_V)), "vertices"),
    "rigid vertices shape": (rigid(v=BOX_V.T), "vertices"),
    "rigid triangles range": (rigid(t=np.where(BOX_T == 7, 8, BOX_T)), "triangles"),
    "rigid open": (rigid(t=BOX_T[:-1]), "open"),
    "rigid inverted": (rigid(t=BOX_T[:, ::-1]), "inverted"),
    "rigid inconsistent": (rigid(t=np.vstack([BOX_T[:-1], BOX_T[-1:, ::-1]])), "inconsistently oriented"),
    "rigid non-manifold": (rigid(v=TWO_BOX_V, t=np.vstack([BOX_T, BOX_T, BOX_T + 8])), "non-manifold"),
    "rigid flat": (rigid(v=SQ_V, t=[[0, 1, 2], [0, 2, 1]]), "zero volume"),
    "rigid degenerate": (rigid(v=np.vstack([BOX_V, [[0.5, 0.5, 0.5]]]), t=np.vstack([BOX_T, [[7, 8, 7]]])),
                         "degenerate"),
    "rigid pos": (rigid(pos=(1, 2)), "pos"),
    "rigid rot": (rigid(rot=np.ones((3, 3))), "rot"),
    "rigid velocity": (rigid(velocity=(0, np.inf, 0)), "velocity"),
    "rigid angular_velocity": (rigid(angular_velocity=(0, 0)), "angular_velocity"),
    # static, planes, particles, settings
    "static vertices nan": (lambda b: b.add_static_mesh(NAN_V, SQ_T), "vertices"),
    "static triangles range": (lambda b: b.add_static_mesh(SQ_V, [[0, 1, 9]]), "triangles"),
    "static degenerate": (lambda b: b.add_static_mesh(SQ_V, [[0, 1, 1]]), "degenerate"),
    "plane zero normal": (lambda b: b.add_ground_plane((0, 0, 0)), "normal"),
    "plane offset nan": (lambda b: b.add_ground_plane(offset=np.nan), "offset"),
    "particle mass=0": (lambda b: b.add_particle((0, 0, 0), mass=0.0), "mass"),
    "particle mass<0": (lambda b: b.add_particle((0, 0, 0), mass=-1.0), "mass"),
    "particle pos": (lambda b: b.add_particle((0, np.nan, 0)), "pos"),
    "gravity nan": (lambda b: b.set_gravity((0, 0, np.nan)), "g"),
    "gravity shape": (lambda b: b.set_gravity((0, -9.81)), "g"),
    "restitution>1": (_set("restitution", 1.5), "restitution"),
    "friction<0": (_set("friction", -0.1), "friction"),
    "thickness nan": (_set("thickness", np.nan), "thickness"),
    "set_contact partial": (lambda b: b.set_contact(friction=0.1, thickness=-1.0), "thickness"),
    "component": (lambda b: b.add_component("fluid"), "name"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_validation_errors_leave_builder_unchanged(case):
    call, match = BAD[case]
    b = ModelBuilder()
    b.add_cloth_grid((0, 0, 0), None, 1, 1, 0.1, 0.1, **CLOTH)  # something already there
    before = _snapshot(b)
    with pytest.raises(ValueError, match=match):
        call(b)
    assert _snapshot(b) == before


def test_rigid_bodies_that_start_interpenetrating_are_warned_about():
    """A box placed partly inside another: InitialPenetrationWarning naming the count (the
    independent checker's); boxes touching face to face and resting on the ground: silence."""
    import warnings

    from sim.mesh_io import box_mesh
    from sim.penetration import InitialPenetrationWarning

    v, t = box_mesh(0.1)

    def build(second_pos):
        b = ModelBuilder()
        b.add_rigid_body(v, t, density=500.0, pos=(0.0, 0.0, 0.1))
        b.add_rigid_body(v, t, density=500.0, pos=second_pos)
        b.add_static_mesh(*box_mesh((3.0, 3.0, 0.1)), pos=(0.0, 0.0, -0.1))
        b.add_ground_plane()
        return b.finalize()

    with pytest.warns(InitialPenetrationWarning, match="2 interpenetrations of rigid bodies"):
        build((0.15, 0.05, 0.15))
    with warnings.catch_warnings():
        warnings.simplefilter("error", InitialPenetrationWarning)
        build((0.2, 0.0, 0.1))  # touching face to face
