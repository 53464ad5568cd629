"""A user's mesh file as the static obstacle of a simulation scene (``--mesh``).

The mesh is read with :func:`sim.mesh_io.load_mesh` (OBJ, STL, PLY or any format meshio reads),
multiplied by ``--mesh-scale``, and placed resting on the ground (its lowest point at z = 0) with
its bounding box centred at the scene's landing point, moved by ``--mesh-offset X Y``. It
replaces the scene's own obstacles; the ground plane stays. A mesh that would reach into the
falling cloth or body at the start is refused before anything runs.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from scenes.registry import positive_float


def add_mesh_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """``--mesh``, ``--mesh-scale`` and ``--mesh-offset``; ``what`` says what falls onto it."""
    parser.add_argument("--mesh", type=Path, default=None,
                        help=f"an OBJ, STL or PLY file [m]: a static obstacle that {what}, resting on the "
                             "ground, in place of the scene's own obstacles (default: the scene's)")
    parser.add_argument("--mesh-scale", type=positive_float, default=None,
                        help="with --mesh: multiply the file's coordinates by this (default 1)")
    parser.add_argument("--mesh-offset", type=float, nargs=2, metavar=("X", "Y"), default=None,
                        help="with --mesh: move it by this in x and y [m] from the landing point (default 0 0)")


def placed_mesh(args: argparse.Namespace, centre_xy) -> tuple[np.ndarray, np.ndarray]:
    """The ``--mesh`` file's (vertices (N, 3) [m], triangles (T, 3)), scaled and placed (see the
    module docstring) around ``centre_xy`` (2,) [m]."""
    from sim.mesh_io import load_mesh

    vertices, triangles = load_mesh(args.mesh)
    vertices = vertices * (args.mesh_scale or 1.0)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    offset = np.asarray(args.mesh_offset or (0.0, 0.0), dtype=np.float64)
    shift = np.array([*(np.asarray(centre_xy, dtype=np.float64) + offset - 0.5 * (low[:2] + high[:2])), -low[2]])
    return vertices + shift, triangles


def check_mesh_arguments(args: argparse.Namespace, centre_xy, keep_out: tuple[np.ndarray, np.ndarray]) -> str | None:
    """A usage error for the mesh options (None when they are fine): options without
    ``--mesh``, a file that cannot be read, non-finite offsets, or a placed mesh whose bounding
    box meets ``keep_out`` (the box (low (3,), high (3,)) [m] of what falls at the start)."""
    if args.mesh is None:
        given = [flag for flag, value in (("--mesh-scale", args.mesh_scale), ("--mesh-offset", args.mesh_offset))
                 if value is not None]
        return f"{given[0]} applies with --mesh only" if given else None
    if args.mesh_offset is not None and not all(math.isfinite(c) for c in args.mesh_offset):
        return f"--mesh-offset must be finite, got {args.mesh_offset}"
    try:
        vertices, _ = placed_mesh(args, centre_xy)
    except Exception as exc:  # the reader's own message says what is wrong with the file
        return f"--mesh: {exc}"
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    if np.all(low < keep_out[1]) and np.all(high > keep_out[0]):
        return (f"--mesh: placed, it spans {np.round(low, 3).tolist()} to {np.round(high, 3).tolist()} m and reaches "
                f"into what falls onto it at the start ({np.round(keep_out[0], 3).tolist()} to "
                f"{np.round(keep_out[1], 3).tolist()} m): lower --mesh-scale or move it with --mesh-offset")
    return None
