"""Compiles the project's Warp kernel modules into a kernel cache, for a test run's workers to copy.

``python tests/warm_kernels.py CACHE verify|plain``: ``verify`` compiles them as the test
processes do (``wp.config.verify_autograd_array_access`` on, set by ``tests/conftest.py``),
``plain`` as the scene subprocesses that tests start do (Warp's defaults). The option is part of
a module's hash, so each worker of ``pytest -n 2`` would otherwise compile every module twice
(about a minute of CPU each time); ``tests/conftest.py`` runs both configurations at once, in
two processes, before the workers start, and each worker starts from a copy of the cache.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import sys
from pathlib import Path

CONFIGURATIONS = ("verify", "plain")


def main(argv: list[str]) -> None:
    if len(argv) != 2 or argv[1] not in CONFIGURATIONS:
        raise SystemExit(f"usage: python tests/warm_kernels.py CACHE {{{'|'.join(CONFIGURATIONS)}}}")
    os.environ["WARP_CACHE_PATH"] = argv[0]
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import warp as wp

    wp.config.quiet = True
    wp.config.verify_autograd_array_access = argv[1] == "verify"
    wp.init()
    import kernels

    for info in pkgutil.iter_modules(kernels.__path__, "kernels."):
        importlib.import_module(info.name)
    # one module at a time: the other configuration compiles in a second process
    wp.force_load(device="cpu", max_workers=0)


if __name__ == "__main__":
    main(sys.argv[1:])
