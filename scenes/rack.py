"""The rack of DiffTaichi's billiards: where its balls sit, where a shot may start, and which ball a
shot must strike first to send a given ball towards a goal (plain geometry, no simulation)."""

from __future__ import annotations

import numpy as np

RADIUS = 0.03  # [m]
ROWS = 4


def rack_positions(rows: int = ROWS) -> np.ndarray:
    """Ball centres of a rack of ``rows`` rows (DiffTaichi's layout), (rows (rows + 1) / 2, 2) [m]:
    row ``i`` holds ``i + 1`` balls at ``x = 0.5 + 2 r i``, ``y = 0.5 + 2 r j - 0.7 r i``."""
    return np.array([(0.5 + 2 * RADIUS * i, 0.5 + 2 * RADIUS * j - 0.7 * RADIUS * i)
                     for i in range(rows) for j in range(i + 1)], dtype=np.float64)


def outside_the_rack(shot, rows: int = ROWS) -> tuple[float, float, float, float]:
    """``shot`` with the cue's position moved out of any rack ball it overlaps, radially to
    touching (the projection of an optimiser's iterate onto the shots that can be played)."""
    x = np.asarray(shot, dtype=np.float64).copy()
    rack = rack_positions(rows)
    for _ in range(len(rack)):
        offsets = x[None, :2] - rack
        gaps = np.linalg.norm(offsets, axis=1) - 2 * RADIUS
        k = int(np.argmin(gaps))
        if gaps[k] >= 0.0:
            break
        norm = float(np.linalg.norm(offsets[k]))
        direction = offsets[k] / norm if norm > 0.0 else np.array([-1.0, 0.0])
        x[:2] = rack[k] + direction * 2 * RADIUS * (1.0 + 1e-9)
    gaps = np.linalg.norm(x[None, :2] - rack, axis=1) - 2 * RADIUS
    if gaps.min() < 0.0:
        # wedged between touching balls: onto the circle around the whole rack instead
        centre = rack.mean(axis=0)
        offset = x[:2] - centre
        norm = float(np.linalg.norm(offset))
        direction = offset / norm if norm > 0.0 else np.array([-1.0, 0.0])
        x[:2] = centre + direction * (np.linalg.norm(rack - centre, axis=1).max() + 2 * RADIUS) * (1.0 + 1e-9)
    return tuple(float(c) for c in x)


def push_chain(centres, target: int, goal, radius: float = RADIUS) -> tuple[int, np.ndarray]:
    """The ball a shot must strike first to send ``target`` towards ``goal``, and the direction
    to strike it in: ``(head, direction)`` (a body index and a unit vector (2,)).

    The rule, on the balls at rest (``centres`` (B, 2) [m]): the target must be pushed straight
    at the goal, by a ball touching it from the opposite side. If another ball overlaps that
    striking position, it is in the way and becomes the one to push, along the line of centres
    (a ball struck along the line of centres leaves along it); and so on until the striking
    position is free. On DiffTaichi's rack the chain runs down the diagonal from the target to
    the apex: the apex, struck about 33 degrees above the table's x axis."""
    centres = np.asarray(centres, dtype=np.float64)
    ball = int(target)
    direction = np.asarray(goal, dtype=np.float64) - centres[ball]
    direction = direction / np.linalg.norm(direction)
    chain = {ball}
    while True:
        striker = centres[ball] - 2 * radius * direction
        gaps = np.linalg.norm(centres - striker[None], axis=1) - 2 * radius
        gaps[sorted(chain)] = np.inf
        blocker = int(np.argmin(gaps))
        if gaps[blocker] >= 0.0:
            return ball, direction
        direction = centres[ball] - centres[blocker]
        direction = direction / np.linalg.norm(direction)
        ball = blocker
        chain.add(ball)
