"""The project's one Warp initialisation."""

from __future__ import annotations

import sys
from pathlib import Path

import warp as wp

_initialised = False

FIRST_COMPILE_NOTICE = ("tunnelsim: first run with this kernel cache ({cache}): Warp compiles each kernel module "
                        "on first use (about a minute in all on a CPU, cached for later runs); one line per module "
                        "follows")


def cold_kernel_cache(cache: str | None) -> bool:
    """Whether the Warp kernel cache ``cache`` holds none of the project's compiled kernels."""
    return cache is not None and not any(Path(cache).glob("wp_kernels.*"))


def init_warp() -> None:
    """``wp.init()`` once, with Warp's start-up banner kept off stdout (scene CLIs print exactly
    one JSON line there). Safe to call repeatedly. With a cold kernel cache it says on stderr
    that kernels compile now, and lets Warp print a line per module it loads, so the first run's
    minute of compiling is not silent."""
    global _initialised
    if not _initialised:
        wp.config.log_level = wp.LOG_WARNING if hasattr(wp, "LOG_WARNING") else wp.config.log_level
        wp.init()
        _initialised = True
        cache = getattr(wp.config, "kernel_cache_dir", None)
        if cold_kernel_cache(cache) and not getattr(wp.config, "quiet", False) and hasattr(wp, "LOG_INFO"):
            print(FIRST_COMPILE_NOTICE.format(cache=cache), file=sys.stderr, flush=True)
            wp.config.log_level = wp.LOG_INFO
