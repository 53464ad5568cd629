"""The project's one Warp initialisation."""

from __future__ import annotations

import warp as wp

_initialised = False


def init_warp() -> None:
    """``wp.init()`` once, with Warp's start-up banner kept off stdout (scene CLIs print exactly
    one JSON line there). Safe to call repeatedly."""
    global _initialised
    if not _initialised:
        wp.config.log_level = wp.LOG_WARNING if hasattr(wp, "LOG_WARNING") else wp.config.log_level
        wp.init()
        _initialised = True
