"""Test-session set-up: a Warp kernel cache per pytest-xdist worker, and Warp's check that no
array a tape read is written before its backward pass.

Two workers compiling the same module into one cache folder can race; each worker (and every
scene subprocess it starts, which inherits the environment) gets its own folder under
``.warp_cache/`` in the repository. Set before any test module imports warp. In a run with
workers (``-n``), the controller first compiles the kernel modules into ``.warp_cache/seed`` (both
configurations of ``tests/warm_kernels.py`` at once), and each worker starts from a copy of it.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

_worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
_CACHES = Path(__file__).resolve().parent.parent / ".warp_cache"
_SEED = _CACHES / "seed"
os.environ["WARP_CACHE_PATH"] = str(_CACHES / _worker)
if _worker != "main" and _SEED.is_dir():
    shutil.copytree(_SEED, _CACHES / _worker, dirs_exist_ok=True)

import warp as wp  # noqa: E402  (after the cache path)

# every taped launch marks the arrays it reads; a later write to one of them by a launch or a
# copy (which would corrupt the backward pass silently) is an error (pyproject's filterwarnings)
wp.config.verify_autograd_array_access = True


def pytest_configure(config):
    """In the controller of a run with workers: the kernel modules compiled into the seed cache
    (:mod:`tests.warm_kernels`, its two configurations in parallel) before the workers start."""
    if _worker != "main" or not getattr(config.option, "numprocesses", None):
        return
    script = Path(__file__).resolve().parent / "warm_kernels.py"
    warmers = [subprocess.Popen([sys.executable, str(script), str(_SEED), configuration])
               for configuration in ("verify", "plain")]
    failed = [w.args[-1] for w in warmers if w.wait() != 0]
    if failed:
        raise RuntimeError(f"compiling the kernel modules ({', '.join(failed)}) into {_SEED} failed")


def pytest_collection_modifyitems(session, config, items):
    """The 2000-step scene runs (``xdist_group`` ``long_*``) go first, so that with ``-n 2 --dist
    loadgroup`` each worker starts on its long group at once and the short tests fill in around
    them, instead of the long groups queueing at the end."""
    def is_long(item):
        return any(m.name == "xdist_group" and str(m.args[0] if m.args else m.kwargs.get("name", "")).startswith("long_")
                   for m in item.iter_markers())

    items[:] = [i for i in items if is_long(i)] + [i for i in items if not is_long(i)]
