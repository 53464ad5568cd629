"""Scene ``rigid_toss``: a spinning box tossed onto the ground knocks into a resting box.

Box A (0.1 m half extents, density 500 kg/m^3) starts at (-0.6, 0, 0.3) with velocity
(3, 0, 1) m/s and angular velocity (0, 3, 1) rad/s; box B (same size and density) rests on the
ground at (0.8, 0, 0.1). The ground is a large static box (half extents (3, 3, 0.1), top face at
z = 0) plus a ground plane z = 0 (planes act on particles only; the static box carries the rigid
contacts). Restitution 0.2, friction 0.4. Components: rigid, static.

Runner, options and summary: see :mod:`scenes.sim_common`.
"""

from __future__ import annotations

import argparse
from typing import Any

from scenes.sim_common import PRECISIONS as PRECISIONS, SUPPORTS_STEPS as SUPPORTS_STEPS
from scenes import sim_common
from scenes.obstacle import add_mesh_arguments, check_mesh_arguments, placed_mesh
from scenes.sim_common import run_scene

NAME = "rigid_toss"
DESCRIPTION = "Spinning box tossed onto the ground into a resting box (rigid + static)"

BOX_HALF = 0.1
DENSITY = 500.0
TOSS_POS = (-0.6, 0.0, 0.3)
TOSS_VELOCITY = (3.0, 0.0, 1.0)
TOSS_ANGULAR_VELOCITY = (0.0, 3.0, 1.0)
REST_POS = (0.8, 0.0, 0.1)
GROUND_HALF = (3.0, 3.0, 0.1)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulation options without the cloth integrator's (no cloth here)."""
    sim_common.add_arguments(parser, cloth=False)
    add_mesh_arguments(parser, "the tossed box lands on and runs into (in place of the resting box)")


LANDING_XY = (0.3, 0.0)
"""Where ``--mesh`` is centred [m]: the tossed box's first touchdown is near here."""


def check_arguments(args: argparse.Namespace) -> str | None:
    """A usage error for the ``--mesh`` options (None when they are fine)."""
    import numpy as np

    return check_mesh_arguments(args, LANDING_XY, (np.asarray(TOSS_POS) - 2 * BOX_HALF, np.asarray(TOSS_POS) + 2 * BOX_HALF))


def build(builder: Any, args: argparse.Namespace) -> None:
    """Adds the two boxes (the resting one replaced by the ``--mesh`` obstacle,
    :mod:`scenes.obstacle`), the ground box and the ground plane."""
    from sim.mesh_io import box_mesh

    v, t = box_mesh(BOX_HALF)
    builder.add_rigid_body(v, t, density=DENSITY, pos=TOSS_POS, velocity=TOSS_VELOCITY,
                           angular_velocity=TOSS_ANGULAR_VELOCITY)
    if getattr(args, "mesh", None) is not None:
        builder.add_static_mesh(*placed_mesh(args, LANDING_XY))
    else:
        builder.add_rigid_body(v, t, density=DENSITY, pos=REST_POS)
    builder.add_static_mesh(*box_mesh(GROUND_HALF), pos=(0.0, 0.0, -GROUND_HALF[2]))
    builder.add_ground_plane()
    builder.set_contact(restitution=0.2, friction=0.4)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene (see :func:`scenes.sim_common.simulate`)."""
    return run_scene(build, args, log, NAME)
