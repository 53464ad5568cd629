"""The one module that reaches past Warp's public API.

Everything here depends on Warp internals of the version in :data:`WARP_VERSION` (pinned in
``constraints.txt``; :func:`check_warp_version` and ``tests/test_layers.py`` fail clearly on
another one):

* the runtime's current tape (``warp._src.context.runtime.tape``), which the tape helpers
  (:mod:`core.tape`) read and swap to keep trial launches off a recording tape;
* whether a CPU graph capture is recording (launches must then go through Warp's own path);
* per-array marks kept on ``wp.array`` objects (a cached host view, a "frozen copy" flag);
* the argument structure of a recorded CPU launch (:class:`core.buffers.RecordedLaunches`
  rewrites only the changed fields of it instead of Warp rebuilding it per launch);
* the CPU compile step, for the tests' tape check, which would otherwise compile every module
  again in each process (:func:`reuse_cached_binaries_while_verifying`).
"""

from __future__ import annotations

import ctypes

import numpy as np
import warp as wp
import warp._src.context as _warp_context

WARP_VERSION = "1.19.0"
"""The Warp release this adapter was written for (``constraints.txt`` pins it)."""


def check_warp_version() -> None:
    """Raises ``RuntimeError`` naming both versions when the installed Warp is not
    :data:`WARP_VERSION`: the internals used here may have moved."""
    if wp.__version__ != WARP_VERSION:
        raise RuntimeError(f"tunnelsim's Warp adapter (core/warp_adapter.py) was written for warp-lang "
                           f"{WARP_VERSION}, but {wp.__version__} is installed: install the version pinned in "
                           f"constraints.txt (pip install -c constraints.txt -e .)")


def current_tape():
    """The ``wp.Tape`` recording launches now (None outside ``with tape:``)."""
    runtime = _warp_context.runtime
    return runtime.tape if runtime is not None else None


def set_current_tape(tape) -> None:
    """Makes ``tape`` (or None: no recording) the tape Warp records launches on."""
    _warp_context.runtime.tape = tape


def cpu_capture_active(device) -> bool:
    """Whether a Warp graph capture records launches on ``device`` (then launches and copies must
    go through Warp's own path, which records them)."""
    runtime = _warp_context.runtime
    capture = getattr(runtime, "_apic_capture", None) if runtime is not None else None
    return capture is not None and capture.device == device


def host_view(arr: wp.array) -> np.ndarray:
    """The numpy view of a CPU array, made once and kept on the array (``numpy()`` costs
    microseconds per call, and a substep reads the same buffers many times)."""
    view = getattr(arr, "_host_view", None)
    if view is None:
        view = arr._host_view = arr.numpy()
    return view


def mark_frozen(arr: wp.array) -> wp.array:
    """Marks ``arr`` as a copy of its own that no later call overwrites (see :func:`is_frozen`)."""
    arr._frozen = True
    return arr


def is_frozen(arr: wp.array) -> bool:
    """Whether :func:`mark_frozen` marked ``arr``."""
    return getattr(arr, "_frozen", False)


def cpu_launch_arguments(cmd, last=None, stale=()):
    """(argument structure, field names, packed types) of a recorded CPU launch ``cmd``
    (``wp.launch(..., record_cmd=True)``): the structure Warp's CPU ``invoke`` builds, the
    kernel's arguments in order, each of its packed type. None where the command's own
    ``launch()`` must run (launch in blocks, an adjoint, or a Warp without the hooks this relies
    on). ``stale``: indices of array arguments ``last`` that the command's own copy lacks (set
    on it first)."""
    if not cmd.device.is_cpu or cmd.block_dim > 1 or cmd.adjoint or getattr(cmd, "hooks", None) is None \
            or getattr(cmd.hooks, "forward", None) is None:
        return None
    for i in stale:
        cmd.set_param_at_index(i, last[i])
    if stale:
        stale.clear()
    names = [arg.label for arg in cmd.kernel.adj.args]
    types = [type(cmd.params[1 + i]) for i in range(len(names))]
    struct = type("RecordedArgs", (ctypes.Structure,), {"_fields_": list(zip(names, types))})()
    for i, name in enumerate(names):
        setattr(struct, name, cmd.params[1 + i])
    return struct, names, types


def packed_argument(cmd, index: int):
    """The packed (ctypes) value of a recorded command's argument ``index``."""
    return cmd.params[1 + index]


def cpu_launch(cmd, struct) -> None:
    """Runs a recorded CPU command's forward function on the argument structure ``struct`` of
    :func:`cpu_launch_arguments`."""
    cmd.hooks.forward(ctypes.byref(cmd.params[0]), ctypes.byref(struct))


def reuse_cached_binaries_while_verifying() -> dict:
    """Lets a process that checks tapes (``wp.config.verify_autograd_array_access``) load the CPU
    binaries of its kernel cache instead of compiling them again.

    Warp recompiles every module in that mode: the check needs the code generator's record of
    which arrays each kernel reads and writes, made while the module's source is generated.
    Generation still runs (the record is made); only the native compile, the bulk of a module's
    build (about 45 of the 55 s of CPU a simulation scene's modules take), is replaced by a copy
    of the binary already cached under the same module hash, which covers the source and the
    build options, this mode included. Warp builds into ``<cache entry>_p<pid>_t<thread>`` and
    renames the finished entry into place, so an entry's binary is complete once it exists.

    Returns:
        This process's counts, kept up to date: ``{"compiled": modules compiled, "copied":
        modules whose binary came from the cache}``.
    """
    import os
    import re
    import shutil

    import warp._src.build as _warp_build

    compile_cpu = _warp_build.build_cpu
    counts = getattr(compile_cpu, "reuse_counts", None)
    if counts is not None:  # already in place
        return counts
    counts = {"compiled": 0, "copied": 0}

    def build_cpu(obj_path, *args, **kwargs):
        build_dir, name = os.path.split(obj_path)
        entry = re.sub(r"_p\d+_t\d+$", "", build_dir)
        cached = os.path.join(entry, name)
        # only the tape check's forced rebuild of an entry of the kernel cache: a rebuild asked
        # for (cache_kernels off) and a build into a folder without the module hash compile
        if (wp.config.verify_autograd_array_access and wp.config.cache_kernels and entry != build_dir
                and os.path.dirname(os.path.abspath(entry)) == os.path.abspath(wp.config.kernel_cache_dir)
                and os.path.exists(cached)):
            shutil.copyfile(cached, obj_path)
            counts["copied"] += 1
            return
        compile_cpu(obj_path, *args, **kwargs)
        counts["compiled"] += 1

    build_cpu.reuse_counts = counts
    _warp_build.build_cpu = build_cpu
    return counts
