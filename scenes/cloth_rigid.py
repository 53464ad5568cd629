"""Scene ``cloth_rigid``: a rigid ball thrown into a cloth hanging from two corners.

A 12 x 12-cell cloth (0.6 m square in the x-z plane, y = 0, top edge at z = 0.8 m; areal density
0.5 kg/m^2, springs: stretch 60, shear 20, bending 2 N/m, damping 0.01 N s/m) hangs from its two
pinned top corners. A rigid ball (icosphere radius 0.08 m, density 100 kg/m^3, 0.21 kg) starts at
(0, -0.4, 0.5) with velocity (0, 4, 0) m/s (``--ball-speed``), hits the cloth, and drops onto a static
floor box (120 m square, top face z = 0, below the cloth's lowest edge at z = 0.2) on which it rolls away. Restitution 0, friction 0.3.
Components: cloth, rigid, static.

Runner, options and summary: see :mod:`scenes.sim_common`.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

from scenes.sim_common import PRECISIONS as PRECISIONS, SUPPORTS_STEPS as SUPPORTS_STEPS
from scenes import sim_common
from scenes.registry import positive_float, positive_int
from scenes.sim_common import run_scene

NAME = "cloth_rigid"
DESCRIPTION = "Rigid ball thrown at 4 m/s into a cloth hanging from two corners (cloth + rigid + static floor)"

CLOTH_CELLS = 12
CLOTH_SIZE = 0.6
CLOTH_TOP = 0.8
BALL_RADIUS = 0.08
BALL_DENSITY = 100.0
BALL_POS = (0.0, -0.4, 0.5)
BALL_SPEED = 4.0
THICKNESS = 1e-3
FLOOR_HALF = (60.0, 60.0, 0.05)  # the ball rolls on for the whole run (no rolling resistance)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The common simulation options plus ``--ball-speed``."""
    sim_common.add_arguments(parser)
    parser.add_argument("--ball-speed", type=positive_float, default=BALL_SPEED,
                        help=f"speed of the ball towards the cloth [m/s] (default {BALL_SPEED})")
    parser.add_argument("--cloth-res", type=positive_int, default=CLOTH_CELLS,
                        help=f"cloth cells per side (size, density and spring constants kept; default {CLOTH_CELLS})")


def build(builder: Any, args: argparse.Namespace) -> None:
    """Adds the hanging cloth and the ball."""
    from sim.mesh_io import box_mesh, icosphere

    n = int(getattr(args, "cloth_res", CLOTH_CELLS))
    cell = CLOTH_SIZE / n
    s = math.sqrt(0.5)
    rot = (s, 0.0, 0.0, s)  # +90 deg about x: local y -> world z (cloth in the x-z plane)
    top_left, top_right = n * (n + 1), n * (n + 1) + n
    builder.add_cloth_grid(
        (-CLOTH_SIZE / 2, 0.0, CLOTH_TOP - CLOTH_SIZE), rot, n, n, cell, cell,
        density=0.5, stretch_stiffness=60.0, shear_stiffness=20.0, bend_stiffness=2.0, damping=0.01,
        pinned=[top_left, top_right],
    )
    builder.add_rigid_body(*icosphere(BALL_RADIUS, 2), density=BALL_DENSITY, pos=BALL_POS,
                           velocity=(0.0, float(getattr(args, "ball_speed", BALL_SPEED)), 0.0))
    builder.add_static_mesh(*box_mesh(FLOOR_HALF), pos=(0.0, 0.0, -FLOOR_HALF[2]))
    builder.set_contact(restitution=0.0, friction=0.3, thickness=THICKNESS)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene (see :func:`scenes.sim_common.simulate`)."""
    return run_scene(build, args, log, NAME)
