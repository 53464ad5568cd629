"""Scene ``cloth_rigid``: a rigid ball thrown into a cloth hanging from two corners.

A 12 x 12-cell cloth (0.6 m square in the x-z plane, y = 0, top edge at z = 0.8 m; areal density
0.5 kg/m^2, springs: stretch 60, shear 20, bending 2 N/m, damping 0.01 N s/m) hangs from its two
pinned top corners. A rigid ball (icosphere radius 0.08 m, density 800 kg/m^3) starts at
(0, -0.4, 0.5) with velocity (0, 6, 0) m/s and hits the cloth. No ground. Restitution 0,
friction 0.3. Components: cloth, rigid.

Runner, options and summary: see :mod:`scenes.sim_common`.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

from scenes.sim_common import PRECISIONS as PRECISIONS, SUPPORTS_STEPS as SUPPORTS_STEPS
from scenes.sim_common import add_arguments as add_arguments
from scenes.sim_common import run_scene

NAME = "cloth_rigid"
DESCRIPTION = "Rigid ball thrown at 6 m/s into a cloth hanging from two corners (cloth + rigid)"

CLOTH_CELLS = 12
CLOTH_SIZE = 0.6
CLOTH_TOP = 0.8
BALL_RADIUS = 0.08
BALL_DENSITY = 800.0
BALL_POS = (0.0, -0.4, 0.5)
BALL_SPEED = 6.0
THICKNESS = 1e-3


def build(builder: Any, args: argparse.Namespace) -> None:
    """Adds the hanging cloth and the ball."""
    from sim.mesh_io import icosphere

    n = CLOTH_CELLS
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
                           velocity=(0.0, BALL_SPEED, 0.0))
    builder.set_contact(restitution=0.0, friction=0.3, thickness=THICKNESS)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene (see :func:`scenes.sim_common.simulate`)."""
    return run_scene(build, args, log, NAME)
