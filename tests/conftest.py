"""Test-session set-up: a Warp kernel cache per pytest-xdist worker.

Two workers compiling the same module into one cache folder can race; each worker (and every
scene subprocess it starts, which inherits the environment) gets its own folder under
``.warp_cache/`` in the repository. Set before any test module imports warp.
"""

import os
from pathlib import Path

_worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
os.environ["WARP_CACHE_PATH"] = str(Path(__file__).resolve().parent.parent / ".warp_cache" / _worker)
