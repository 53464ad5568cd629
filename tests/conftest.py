"""Test-session set-up: one Warp kernel cache for the test run, and Warp's check that no array a
tape read is written before its backward pass.

The pytest-xdist workers and the scene subprocesses they start (which inherit the environment)
share one kernel cache, ``.warp_cache/tests`` in the repository. The subprocesses compile the
kernels without the tape check (part of a module's hash) and load what another of them compiled
(about a minute of CPU for the project's kernels); the workers, with the check on, compile every
module they use once each (Warp 1.19 skips the cache in that mode), unless one of them, or an
earlier run, has already built it (:func:`core.warp_adapter.reuse_cached_binaries_while_verifying`
copies the binary). Sharing is safe: Warp compiles into a folder of its own process and renames
it into the cache, and ``kernels/variants.py`` writes its generated sources by atomic renames.
Set before any test module imports warp.
"""

import os
from pathlib import Path

os.environ["WARP_CACHE_PATH"] = str(Path(__file__).resolve().parent.parent / ".warp_cache" / "tests")

import warp as wp  # noqa: E402  (after the cache path)

# every taped launch marks the arrays it reads; a later write to one of them by a launch or a
# copy (which would corrupt the backward pass silently) is an error (pyproject's filterwarnings)
wp.config.verify_autograd_array_access = True

from core.warp_adapter import reuse_cached_binaries_while_verifying  # noqa: E402

# the check makes Warp compile every module again: a module that another worker or an earlier
# run has built is copied from the cache instead, once its source is generated
reuse_cached_binaries_while_verifying()


def pytest_collection_modifyitems(session, config, items):
    """The 2000-step scene runs (``xdist_group`` ``long_*``) go first, so that with ``-n 2 --dist
    loadgroup`` each worker starts on its long group at once and the short tests fill in around
    them, instead of the long groups queueing at the end."""
    def is_long(item):
        return any(m.name == "xdist_group" and str(m.args[0] if m.args else m.kwargs.get("name", "")).startswith("long_")
                   for m in item.iter_markers())

    items[:] = [i for i in items if is_long(i)] + [i for i in items if not is_long(i)]
