"""Triangle meshes in and out of files (through meshio), and small closed meshes for tests/scenes.

:func:`load_mesh` reads any surface format meshio knows (OBJ, PLY, STL, OFF, VTK, ... ) into a
``(vertices float64 (N, 3), triangles int32 (T, 3))`` pair:

* quads and larger polygons (meshio hands OBJ/PLY quads over as a separate ``quad`` cell block,
  larger faces as ``polygon`` blocks) are fan-triangulated from their first corner, which keeps
  the face's winding (exact for convex planar faces);
* STL stores every triangle with its own three corners; coincident corners are merged
  (:func:`merge_vertices`) so a closed solid comes back as a closed, indexed mesh that
  :meth:`sim.builder.ModelBuilder.add_rigid_body` accepts;
* meshio's ASCII-STL sniffing overflows a ``uint32`` under numpy 2 (``RuntimeWarning: overflow
  encountered in scalar multiply``); that warning is silenced, nothing else is;
* missing files raise :class:`FileNotFoundError`; unknown formats, unreadable files and meshes
  without any surface face raise :class:`MeshReadError` (a :class:`ValueError`).

Generators: :func:`box_mesh` and :func:`icosphere` build closed meshes with outward (counter-
clockwise seen from outside) triangles.
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import numpy as np

__all__ = [
    "MeshReadError",
    "box_mesh",
    "icosphere",
    "load_mesh",
    "merge_vertices",
    "save_mesh",
    "triangulate_polygons",
]

_SURFACE_CELL_TYPES = ("triangle", "quad", "polygon")
"""meshio cell block types that describe surface faces (other blocks, e.g. lines, are ignored)."""


class MeshReadError(ValueError):
    """A mesh file could not be turned into a triangle mesh (format, content or parse error)."""


def triangulate_polygons(faces: np.ndarray) -> np.ndarray:
    """Fan-triangulates faces that all have the same corner count.

    Face ``(v0, v1, ..., v{k-1})`` becomes ``(v0, v_i, v_{i+1})`` for ``i = 1 .. k-2``: the winding
    (and so the outward normal) of every face is kept. Exact for convex planar polygons.

    Args:
        faces: Vertex indices, integer array (F, k) with k >= 3.

    Returns:
        Triangles, int64 array (F * (k - 2), 3); the triangles of face ``f`` are consecutive.

    Raises:
        ValueError: If ``faces`` is not a 2-D integer array with at least 3 columns.
    """
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] < 3:
        raise ValueError(f"faces must have shape (F, k) with k >= 3, got {faces.shape}")
    if faces.size and not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an integer array, got dtype {faces.dtype}")
    k = faces.shape[1]
    if k == 3:
        return faces.astype(np.int64, copy=True)
    i = np.arange(1, k - 1)
    tris = np.stack(
        [np.broadcast_to(faces[:, :1], (faces.shape[0], k - 2)), faces[:, i], faces[:, i + 1]], axis=-1
    )
    return tris.reshape(-1, 3).astype(np.int64)


def merge_vertices(
    vertices: np.ndarray, triangles: np.ndarray, tolerance: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Merges coincident vertices and drops the triangles that collapse.

    With ``tolerance == 0`` vertices merge when their coordinates are exactly equal (``-0.0`` and
    ``0.0`` count as equal). With ``tolerance > 0`` coordinates are first snapped to a grid of that
    spacing [m], so points closer than ``tolerance`` usually (not always: two points straddling a
    grid line stay apart) merge. The first occurrence of every merged vertex is kept, in order.
    Triangles that end up with a repeated index are removed; unreferenced vertices stay.

    Args:
        vertices: Positions [m], float array (N, 3).
        triangles: Indices, integer array (T, 3), each in [0, N).
        tolerance: Snapping grid spacing [m], >= 0.

    Returns:
        ``(vertices float64 (M, 3), triangles int32 (T', 3))`` with ``M <= N``, ``T' <= T``.

    Raises:
        ValueError: On wrong shapes, out-of-range indices or a negative/non-finite tolerance.
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"triangles must have shape (T, 3), got {t.shape}")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(f"triangles index out of range [0, {len(v)})")
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance must be finite and >= 0, got {tolerance}")
    if len(v) == 0:
        return v.reshape(0, 3).copy(), t.astype(np.int32).reshape(-1, 3)
    key = v + 0.0  # -0.0 -> 0.0 so the byte-wise unique below treats them as equal
    if tolerance > 0.0:
        key = np.round(v / tolerance)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # unique groups in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    new_index = rank[inverse]
    merged = v[first[order]].copy()
    tri = new_index[t.astype(np.int64)]
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    return merged, tri[keep].astype(np.int32)


def _format_of(path: Path, file_format: str | None) -> str:
    import meshio

    if file_format is not None:
        if file_format not in meshio._helpers.reader_map:
            raise MeshReadError(
                f"unsupported mesh format {file_format!r}; meshio reads "
                f"{sorted(meshio._helpers.reader_map)}"
            )
        return file_format
    suffixes = [s.lower() for s in path.suffixes]
    # longest matching suffix chain first (".vtu", ".msh", ".ply", but also e.g. ".vtk.gz" style)
    for k in range(len(suffixes), 0, -1):
        ext = "".join(suffixes[-k:])
        if ext in meshio.extension_to_filetypes:
            return meshio.extension_to_filetypes[ext][0]
    raise MeshReadError(
        f"unsupported mesh format for {str(path)!r} (extension {path.suffix!r}); supported "
        f"extensions include .obj, .ply, .stl, .off, .vtk, .vtu (pass file_format= to override)"
    )


def _obj_buffer(path: Path) -> io.StringIO:
    """The OBJ file reduced to what meshio's OBJ reader handles robustly.

    meshio stores ``vt``/``vn`` as point data and fails when their count differs from the vertex
    count (common in real files), does not resolve relative (negative) face indices, and cannot
    stack ``v`` lines of different lengths (``v x y z`` next to ``v x y z r g b``). So: texture
    coordinates and normals are dropped, ``v`` lines keep x y z, and face corners become absolute
    1-based vertex indices (``f 1/2/3 -1`` -> ``f 1 <n>``).
    """
    out = []
    n_vertices = 0
    for line in path.read_text(errors="replace").splitlines():
        split = line.split()
        if not split:
            continue
        if split[0] == "v":
            out.append("v " + " ".join(split[1:4]))
            n_vertices += 1
        elif split[0] == "f":
            corners = []
            for item in split[1:]:
                token = item.split("/")[0]
                try:
                    k = int(token)
                except ValueError:
                    raise MeshReadError(f"{str(path)!r}: bad face corner {item!r} in line {line!r}") from None
                corners.append(str(n_vertices + 1 + k if k < 0 else k))
            out.append("f " + " ".join(corners))
        elif split[0] in ("vt", "vn", "vp"):
            continue
        else:
            out.append(line)
    return io.StringIO("\n".join(out) + "\n")


def load_mesh(
    path: str | os.PathLike[str],
    *,
    file_format: str | None = None,
    merge: bool | None = None,
    merge_tolerance: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Reads a surface mesh file as float64 vertices and int32 triangles.

    All ``triangle``, ``quad`` and ``polygon`` cell blocks are collected in meshio's block order;
    quads and polygons are fan-triangulated (:func:`triangulate_polygons`), dropping fan triangles
    with a repeated corner (polygons that list a vertex twice). Other cells (lines, points,
    volume cells) are ignored. Extra vertex columns (OBJ ``v x y z r g b`` / ``v x y z w``) are
    dropped; 2-D points get ``z = 0``. OBJ relative (negative) face indices are resolved and
    texture/normal indices (``f v/vt/vn``) ignored.

    Args:
        path: Mesh file (``.obj``, ``.ply``, ``.stl``, or any other format meshio reads).
        file_format: meshio format name (``"obj"``, ``"ply"``, ``"stl"``, ...) when the extension
            does not tell it.
        merge: Merge coincident vertices (:func:`merge_vertices`). ``None`` (default) merges for
            STL only, which stores every triangle's corners separately.
        merge_tolerance: Snapping distance [m] used when merging; 0 merges exact duplicates.

    Returns:
        ``(vertices, triangles)``: positions [m] as float64 (N, 3) and vertex indices as int32
        (T, 3). Vertices not referenced by any face are kept.

    Raises:
        FileNotFoundError: If ``path`` does not exist (or is not a file).
        MeshReadError: Unsupported format, a file meshio cannot parse, non-finite coordinates,
            out-of-range face indices, or no surface faces at all.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {str(path)!r}")
    if not path.is_file():
        raise FileNotFoundError(f"mesh path is not a file: {str(path)!r}")
    fmt = _format_of(path, file_format)
    try:
        with warnings.catch_warnings(), np.errstate(over="ignore"):
            # meshio's STL reader multiplies the uint32 it reads from an ASCII header ("soli")
            # by 50 to test for a binary file: harmless overflow that numpy 2 reports.
            warnings.filterwarnings("ignore", message="overflow encountered", category=RuntimeWarning)
            source = _obj_buffer(path) if fmt == "obj" else path
            mesh = meshio.read(source, file_format=fmt)
    except MeshReadError:
        raise
    except (meshio.ReadError, ValueError, IndexError, KeyError, UnicodeDecodeError, EOFError) as e:
        raise MeshReadError(f"could not read {str(path)!r} as {fmt}: {type(e).__name__}: {e}") from e

    points = np.asarray(mesh.points)
    if points.size == 0:
        points = np.zeros((0, 3))
    if points.ndim != 2 or points.shape[1] < 2:
        raise MeshReadError(f"{str(path)!r}: points have shape {points.shape}, expected (N, 3)")
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    vertices = np.ascontiguousarray(points[:, :3], dtype=np.float64)
    if not np.all(np.isfinite(vertices)):
        raise MeshReadError(f"{str(path)!r}: vertices contain NaN or inf")

    blocks = []
    for block in mesh.cells:
        if block.type not in _SURFACE_CELL_TYPES:
            continue
        data = np.asarray(block.data)
        if data.size == 0:
            continue
        try:
            if data.dtype == object or data.ndim != 2:  # ragged polygon block: one face at a time
                tri = np.concatenate([triangulate_polygons(np.asarray(f, dtype=np.int64)[None]) for f in data])
            else:
                tri = triangulate_polygons(data.astype(np.int64))
        except ValueError as e:
            raise MeshReadError(f"{str(path)!r}: bad {block.type} cells: {e}") from e
        if block.type != "triangle":
            # polygons that repeat a corner (e.g. the first one closing the loop) fan out into
            # triangles with a repeated index: drop those; genuine triangles are kept as they are
            tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
        blocks.append(tri)
    if not blocks or sum(len(b) for b in blocks) == 0:
        found = sorted({b.type for b in mesh.cells}) or ["none"]
        raise MeshReadError(
            f"{str(path)!r} has no triangle, quad or polygon faces (cell types found: {', '.join(found)})"
        )
    tris = np.concatenate(blocks, axis=0)
    if tris.min() < 0 or tris.max() >= len(vertices):
        raise MeshReadError(
            f"{str(path)!r}: face indices out of range [0, {len(vertices)}) (min {tris.min()}, "
            f"max {tris.max()})"
        )
    if merge is None:
        merge = fmt.startswith("stl")
    if merge:
        return merge_vertices(vertices, tris, merge_tolerance)
    return vertices, tris.astype(np.int32)


def save_mesh(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    file_format: str | None = None,
    binary: bool | None = None,
) -> None:
    """Writes a triangle mesh with meshio (format from the extension unless ``file_format``).

    Args:
        path: Output file.
        vertices: Positions [m], float (N, 3).
        triangles: Indices, integer (T, 3).
        file_format: meshio format name, e.g. ``"obj"``, ``"ply"``, ``"stl"``.
        binary: For PLY/STL: binary (True) or ASCII (False); ``None`` keeps meshio's default.
    """
    import meshio

    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"triangles must have shape (T, 3), got {t.shape}")
    kwargs = {} if binary is None else {"binary": bool(binary)}
    # PLY has no 64-bit integers; int32 avoids meshio's "casting down" notice
    meshio.Mesh(v, [("triangle", t.astype(np.int32))]).write(path, file_format=file_format, **kwargs)


def box_mesh(half_extents: float | np.ndarray = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Closed box centred at the origin, axis-aligned, 8 vertices and 12 outward triangles.

    Args:
        half_extents: Half side lengths [m], scalar or (3,), all > 0.

    Returns:
        ``(vertices float64 (8, 3), triangles int32 (12, 3))``. Vertex ``i`` has coordinate
        signs ``(-1)^(1 - bit_k(i))`` on axis ``k`` (bit 0: x, bit 1: y, bit 2: z).

    Raises:
        ValueError: If a half extent is not finite and positive, or the shape is wrong.
    """
    h = np.asarray(half_extents, dtype=np.float64)
    if h.ndim == 0:
        h = np.full(3, float(h))
    if h.shape != (3,):
        raise ValueError(f"half_extents must be a scalar or have shape (3,), got {h.shape}")
    if not np.all(np.isfinite(h)) or np.any(h <= 0.0):
        raise ValueError(f"half_extents must be finite and > 0, got {h}")
    bits = np.arange(8)
    signs = np.stack([(bits >> k) & 1 for k in range(3)], axis=1) * 2.0 - 1.0
    vertices = signs * h
    # each face as a quad listed counter-clockwise seen from outside, then split
    quads = np.array(
        [
            [0, 2, 3, 1],  # z = -h
            [4, 5, 7, 6],  # z = +h
            [0, 1, 5, 4],  # y = -h
            [2, 6, 7, 3],  # y = +h
            [0, 4, 6, 2],  # x = -h
            [1, 3, 7, 5],  # x = +h
        ]
    )
    return vertices, triangulate_polygons(quads).astype(np.int32)


def icosphere(radius: float = 1.0, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Closed sphere mesh from a recursively subdivided icosahedron, outward triangles.

    Every subdivision splits each triangle into four through its edge midpoints, which are pushed
    onto the sphere. All vertices lie on the sphere of ``radius`` (to rounding): the solid is an
    inscribed polyhedron, slightly smaller than the ball.

    Args:
        radius: Sphere radius [m], > 0.
        subdivisions: Number of 1-to-4 splits, 0 <= subdivisions <= 7.

    Returns:
        ``(vertices float64 (10 * 4^s + 2, 3), triangles int32 (20 * 4^s, 3))``.

    Raises:
        ValueError: Non-positive/non-finite radius, or subdivisions outside [0, 7].
    """
    if not (np.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius must be finite and > 0, got {radius}")
    if int(subdivisions) != subdivisions or not 0 <= subdivisions <= 7:
        raise ValueError(f"subdivisions must be an integer in [0, 7], got {subdivisions}")
    p = (1.0 + np.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0],
            [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
            [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1],
        ],
        dtype=np.float64,
    )  # fmt: skip
    f = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )  # fmt: skip
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(int(subdivisions)):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(v) + inv.reshape(3, -1).T  # midpoints of edges (01, 12, 20) per triangle
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate(
            [
                np.stack([a, m01, m20], 1),
                np.stack([b, m12, m01], 1),
                np.stack([c, m20, m12], 1),
                np.stack([m01, m12, m20], 1),
            ]
        )
        v = np.concatenate([v, mid])
    return v * float(radius), f.astype(np.int32)
