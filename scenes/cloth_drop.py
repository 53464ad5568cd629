"""Scene ``cloth_drop``: a square cloth falls onto a static sphere and a static box on the ground.

A 16 x 16-cell cloth (0.8 m square, areal density 0.2 kg/m^2, springs: stretch 20, shear 10,
bending 1 N/m, spring damping 0.01 N s/m) starts flat and at rest 0.7 m above the ground and falls onto a static
icosphere (radius 0.2 m, centre (0, 0, 0.2), resting on the ground) and a static box (0.1 m half
extents, centre (0.35, 0, 0.1)) beside it; a ground plane z = 0 catches the rest. Restitution 0,
friction 0.3. Components: cloth, static.

Runner, options (``--steps``, ``--dt``, ``--substeps``, ``--device``), entities and summary: see
:mod:`scenes.sim_common`.
"""

from __future__ import annotations

import argparse
from typing import Any

from scenes import sim_common
from scenes.obstacle import add_mesh_arguments, check_mesh_arguments, placed_mesh
from scenes.registry import positive_int
from scenes.sim_common import PRECISIONS as PRECISIONS, SUPPORTS_STEPS as SUPPORTS_STEPS
from scenes.sim_common import run_scene

NAME = "cloth_drop"
DESCRIPTION = "16x16 cloth dropped from 0.7 m onto a static sphere and box on the ground (cloth + static)"

CLOTH_CELLS = 16
CLOTH_SIZE = 0.8
CLOTH_HEIGHT = 0.7
CLOTH_CENTRE_XY = (0.1, 0.0)
SPHERE_RADIUS = 0.2
SPHERE_CENTRE = (0.0, 0.0, 0.2)
BOX_HALF = 0.1
BOX_CENTRE = (0.35, 0.0, 0.1)
THICKNESS = 1e-3
DENSITY = 0.2
FRICTION = 0.3
RESTITUTION = 0.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sim_common.add_arguments(parser)
    parser.add_argument("--cloth-res", type=positive_int, default=CLOTH_CELLS,
                        help=f"cloth cells per side (the cloth's size, density and spring constants kept; "
                             f"default {CLOTH_CELLS})")
    add_mesh_arguments(parser, "the cloth falls onto")


def _cloth_box(args: argparse.Namespace):
    """The cloth's box at the start (low (3,), high (3,)) [m], its thickness included."""
    import numpy as np

    centre = np.array([*CLOTH_CENTRE_XY, CLOTH_HEIGHT])
    half = np.array([CLOTH_SIZE / 2, CLOTH_SIZE / 2, 0.0]) + THICKNESS
    return centre - half, centre + half


def check_arguments(args: argparse.Namespace) -> str | None:
    """A usage error for the ``--mesh`` options (None when they are fine)."""
    return check_mesh_arguments(args, CLOTH_CENTRE_XY, _cloth_box(args))


def build(builder: Any, args: argparse.Namespace) -> None:
    """Adds the cloth (``--cloth-res`` cells per side), the sphere and the box (or the ``--mesh``
    obstacle, :mod:`scenes.obstacle`) and the ground plane."""
    from sim.mesh_io import box_mesh, icosphere

    cells = int(getattr(args, "cloth_res", CLOTH_CELLS))
    cell = CLOTH_SIZE / cells
    corner = (CLOTH_CENTRE_XY[0] - CLOTH_SIZE / 2, CLOTH_CENTRE_XY[1] - CLOTH_SIZE / 2, CLOTH_HEIGHT)
    builder.add_cloth_grid(
        corner, None, cells, cells, cell, cell,
        density=DENSITY, stretch_stiffness=20.0, shear_stiffness=10.0, bend_stiffness=1.0, damping=0.01,
    )
    if getattr(args, "mesh", None) is not None:
        builder.add_static_mesh(*placed_mesh(args, CLOTH_CENTRE_XY))
    else:
        builder.add_static_mesh(*icosphere(SPHERE_RADIUS, 2), pos=SPHERE_CENTRE)
        builder.add_static_mesh(*box_mesh(BOX_HALF), pos=BOX_CENTRE)
    builder.add_ground_plane()
    builder.set_contact(restitution=RESTITUTION, friction=FRICTION, thickness=THICKNESS)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene (see :func:`scenes.sim_common.simulate`)."""
    return run_scene(build, args, log, NAME)
