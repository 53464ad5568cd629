"""Mesh I/O through meshio (OBJ with quads and polygons, ASCII/binary PLY, ASCII/binary STL) and the
closed mesh generators. Files are written by meshio itself (or by hand for what meshio cannot
write) into pytest's tmp_path and read back with :func:`sim.mesh_io.load_mesh`."""

from __future__ import annotations

import warnings

import meshio
import numpy as np
import pytest

from sim.builder import ModelBuilder
from sim.mass_properties import mesh_mass_properties
from sim.mesh_io import (
    MeshReadError,
    box_mesh,
    icosphere,
    load_mesh,
    merge_vertices,
    save_mesh,
    triangulate_polygons,
)


def _closed_and_outward(v, t):
    """Every directed edge exactly once with its reverse present, and positive volume."""
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    directed = {tuple(x) for x in e.tolist()}
    assert len(directed) == len(e)
    assert all((b, a) in directed for a, b in directed)
    return mesh_mass_properties(v, t).volume > 0


def _same_triangles(v1, t1, v2, t2, atol=0.0):
    """(v1, t1) is (v2, t2) up to vertex order and rounding: same triangles, same winding."""
    d = np.linalg.norm(v1[:, None, :] - v2[None, :, :], axis=-1)
    match = d.argmin(axis=1)
    assert np.all(d[np.arange(len(v1)), match] <= atol)
    assert len(np.unique(match)) == len(v1)  # one-to-one

    def cyc(t):  # rotate each triangle so its smallest index comes first (keeps winding)
        k = np.argmin(t, axis=1)
        return {tuple(np.roll(row, -i)) for row, i in zip(t.tolist(), k)}

    assert cyc(match[t1]) == cyc(np.asarray(t2))


QUAD_BOX_V, _ = box_mesh([0.5, 1.0, 1.5])
QUAD_BOX_Q = np.array(  # the box's six faces as outward quads (same as box_mesh's)
    [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
)


@pytest.fixture(autouse=True)
def _no_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


def test_obj_quads_and_triangles_round_trip(tmp_path):
    path = tmp_path / "box.obj"
    # four faces as quads, the other two split into triangles: two cell blocks in the file
    tris = triangulate_polygons(QUAD_BOX_Q[4:])
    meshio.Mesh(QUAD_BOX_V, [("quad", QUAD_BOX_Q[:4]), ("triangle", tris)]).write(path)
    v, t = load_mesh(path)
    assert v.dtype == np.float64 and v.shape == (8, 3)
    assert t.dtype == np.int32 and t.shape == (12, 3)
    np.testing.assert_array_equal(v, QUAD_BOX_V)
    np.testing.assert_array_equal(t[:2], [[0, 2, 3], [0, 3, 1]])  # fan of the first quad
    assert _closed_and_outward(v, t)
    b = ModelBuilder()
    b.add_rigid_body(v, t, density=10.0)
    assert b.finalize().body_mass.numpy()[0] == pytest.approx(10.0 * 1.0 * 2.0 * 3.0, rel=1e-14)


def test_obj_polygons_texture_indices_colors_and_format_override(tmp_path):
    text = (
        "# pentagon (fan), a triangle written with v/vt/vn indices, vertex colours\n"
        "v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 1.5 1 0 1 0 0\nv 0.5 2 0 1 0 0\nv -0.5 1 0 1 0 0\n"
        "v 0 0 1 1 0 0\nvt 0 0\nvn 0 0 1\n"
        "f 1 2 3 4 5\n"
        "f 1/1/1 6/1/1 2/1/1\n"
    )
    path = tmp_path / "poly.obj"
    path.write_text(text)
    v, t = load_mesh(path)
    assert v.shape == (6, 3)
    np.testing.assert_array_equal(v[3], [0.5, 2, 0])
    np.testing.assert_array_equal(t, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 5, 1]])
    relative = tmp_path / "relative.obj"  # relative (negative) indices count back from the last v
    relative.write_text("v 9 9 9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 0 0 1\nf -4 -1 -3\n")
    np.testing.assert_array_equal(load_mesh(relative)[1], [[1, 2, 3], [1, 4, 2]])
    other = tmp_path / "poly.txt"
    other.write_text(text)
    v2, t2 = load_mesh(other, file_format="obj")
    np.testing.assert_array_equal(t2, t)


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    v0, t0 = icosphere(0.7, 2)
    path = tmp_path / "sphere.ply"
    save_mesh(path, v0, t0, binary=binary)
    v, t = load_mesh(path)
    np.testing.assert_array_equal(v, v0)  # PLY stores float64 exactly
    np.testing.assert_array_equal(t, t0)


def test_ply_mixed_faces(tmp_path):
    path = tmp_path / "mixed.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 6\nproperty double x\nproperty double y\n"
        "property double z\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 0\n2 1 0\n"
        "3 0 1 2\n4 1 4 5 2\n5 0 1 2 3 0\n"  # triangle, quad, pentagon closing on its first corner
    )
    v, t = load_mesh(path)
    np.testing.assert_array_equal(t, [[0, 1, 2], [1, 4, 5], [1, 5, 2], [0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("binary", [False, True])
def test_stl_round_trip_merges_vertices_closed(tmp_path, binary):
    v0, t0 = icosphere(0.5, 2)
    path = tmp_path / "sphere.stl"
    save_mesh(path, v0, t0, binary=binary)
    if not binary:  # really ASCII, so the numpy-2 overflow warning path is exercised
        assert path.read_text().startswith("solid")
    v, t = load_mesh(path)  # the autouse fixture turns any warning into an error
    assert v.shape == v0.shape and t.shape == t0.shape  # duplicates merged: 162 vertices again
    atol = 1e-7 if binary else 0.0  # binary STL is float32
    _same_triangles(v, t, v0, t0, atol=atol)
    assert _closed_and_outward(v, t)
    b = ModelBuilder()
    b.add_rigid_body(v, t, density=3.0)
    m0 = mesh_mass_properties(v0, t0, 3.0).mass
    assert b.finalize().body_mass.numpy()[0] == pytest.approx(m0, rel=1e-6 if binary else 1e-14)


def test_stl_written_per_facet_by_hand(tmp_path):
    """An ASCII STL with every facet's corners repeated (and a -0.0) becomes one closed box."""
    v0, t0 = box_mesh(0.25)
    lines = ["solid box"]
    for tri in t0:
        lines += ["facet normal 0 0 0", " outer loop"]
        for i in tri:
            x, y, z = (float(c) for c in v0[i])
            lines.append(f"  vertex {x!r} {y!r} {'-0.0' if z == 0 else repr(z)}")
        lines += [" endloop", "endfacet"]
    lines.append("endsolid box")
    path = tmp_path / "box.stl"
    path.write_text("\n".join(lines) + "\n")
    v, t = load_mesh(path)
    assert v.shape == (8, 3) and t.shape == (12, 3)
    _same_triangles(v, t, v0, t0)
    assert _closed_and_outward(v, t)
    v_raw, t_raw = load_mesh(path, merge=False)  # meshio merges exact duplicates itself
    assert len(v_raw) == 8


def test_merge_vertices():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-0.0, 0, 0], [1, 1e-9, 0], [0, 1, 0]], float)
    t = np.array([[0, 1, 2], [3, 4, 5], [0, 3, 1]])
    mv, mt = merge_vertices(v, t)
    assert mv.shape == (4, 3)  # -0.0 merged with 0.0, and the repeated (0, 1, 0)
    np.testing.assert_array_equal(mt, [[0, 1, 2], [0, 3, 2]])  # the collapsed triangle dropped
    mv, mt = merge_vertices(v, t, tolerance=1e-6)
    assert mv.shape == (3, 3)
    np.testing.assert_array_equal(mt, [[0, 1, 2], [0, 1, 2]])
    with pytest.raises(ValueError, match="tolerance"):
        merge_vertices(v, t, tolerance=-1.0)
    with pytest.raises(ValueError, match="out of range"):
        merge_vertices(v, [[0, 1, 6]])


def test_triangulate_polygons():
    np.testing.assert_array_equal(triangulate_polygons([[0, 1, 2, 3]]), [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(
        triangulate_polygons([[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]]),
        [[0, 1, 2], [0, 2, 3], [0, 3, 4], [5, 6, 7], [5, 7, 8], [5, 8, 9]],
    )
    with pytest.raises(ValueError, match="faces"):
        triangulate_polygons([[0, 1]])
    with pytest.raises(ValueError, match="integer"):
        triangulate_polygons([[0.0, 1.0, 2.0]])


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(FileNotFoundError, match="not a file"):
        load_mesh(tmp_path)
    bad_ext = tmp_path / "mesh.xyz"
    bad_ext.write_text("1 2 3\n")
    with pytest.raises(MeshReadError, match="unsupported mesh format"):
        load_mesh(bad_ext)
    with pytest.raises(ValueError, match="unsupported mesh format 'nope'"):
        load_mesh(bad_ext, file_format="nope")
    points_only = tmp_path / "points.obj"
    points_only.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshReadError, match="no triangle, quad or polygon faces"):
        load_mesh(points_only)
    lines_only = tmp_path / "lines.vtk"
    meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]).write(lines_only)
    with pytest.raises(MeshReadError, match="cell types found: line"):
        load_mesh(lines_only)
    bad_corner = tmp_path / "corner.obj"
    bad_corner.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 3\n")
    with pytest.raises(MeshReadError, match="bad face corner 'x'"):
        load_mesh(bad_corner)
    out_of_range = tmp_path / "range.obj"
    out_of_range.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(MeshReadError, match="out of range"):
        load_mesh(out_of_range)
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("v 0 0 zero\n")
    with pytest.raises(MeshReadError, match="could not read"):
        load_mesh(garbage)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshReadError, match="NaN"):
        load_mesh(nan)
    empty_stl = tmp_path / "empty.stl"
    empty_stl.write_text("solid empty\nendsolid empty\n")
    with pytest.raises(MeshReadError):
        load_mesh(empty_stl)


@pytest.mark.parametrize("subdivisions", [0, 1, 2, 3])
def test_icosphere(subdivisions):
    v, t = icosphere(2.0, subdivisions)
    assert v.shape == (10 * 4**subdivisions + 2, 3) and t.shape == (20 * 4**subdivisions, 3)
    assert v.dtype == np.float64 and t.dtype == np.int32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 2.0, rtol=1e-15)
    assert _closed_and_outward(v, t)
    assert len(np.unique(np.round(v, 12), axis=0)) == len(v)


def test_box_mesh():
    v, t = box_mesh([1.0, 2.0, 3.0])
    assert v.shape == (8, 3) and t.shape == (12, 3) and t.dtype == np.int32
    np.testing.assert_array_equal(np.abs(v), np.tile([1.0, 2.0, 3.0], (8, 1)))
    assert _closed_and_outward(v, t)
    assert mesh_mass_properties(v, t).volume == 48.0
    np.testing.assert_array_equal(box_mesh(0.5)[0], box_mesh([0.5, 0.5, 0.5])[0])
    for bad in (0.0, -1.0, np.nan, [1.0, 2.0], [1.0, 0.0, 1.0]):
        with pytest.raises(ValueError, match="half_extents"):
            box_mesh(bad)
    bad_spheres = (dict(radius=0.0), dict(radius=np.inf), dict(subdivisions=-1), dict(subdivisions=1.5), dict(subdivisions=8))
    for bad in bad_spheres:
        with pytest.raises(ValueError):
            icosphere(**bad)
