"""Reusable Warp arrays filled from host (numpy) data (:class:`Staging`: named buffers) or handed
out per call (:class:`Arena`), so that a stepping loop allocates nothing per substep, and
reusable kernel launches (:class:`RecordedLaunches`).

On the CPU a Warp array and its ``numpy()`` view share memory: :func:`upload` writes the view in
place (no temporary Warp array, no copy launch). On other devices it copies through
``wp.array.assign`` (a host staging copy is unavoidable there).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.warp_adapter import (cpu_capture_active, cpu_launch, cpu_launch_arguments, host_view,
                                packed_argument)


def host(arr: wp.array) -> np.ndarray:
    """The host values of ``arr``: on the CPU its numpy view, made once and kept on the array
    (``numpy()`` costs microseconds per call, and a substep reads the same buffers many
    times); elsewhere a fresh copy."""
    if not arr.device.is_cpu:
        return arr.numpy()
    return host_view(arr)


PEEK = True
"""Whether :func:`peek` reads CPU arrays (False: it never does, as on a GPU; for measuring the
device path's host reads on a CPU)."""


def peek(arr: wp.array) -> np.ndarray | None:
    """The values of ``arr`` where reading them costs no synchronisation: on the CPU (launches
    run to completion before they return) its host view, except under a graph capture, whose
    replay would not repeat the read; None elsewhere (a GPU's copy would wait for the device),
    so a caller then keeps the decision on the device."""
    if PEEK and arr.device.is_cpu and not cpu_capture_active(arr.device):
        return host_view(arr)
    return None


def upload(dst: wp.array, src: np.ndarray) -> wp.array:
    """Writes host data ``src`` into the first ``len(src)`` rows of ``dst`` (same dtype layout,
    e.g. (n, 3) float64 into a vec3d array) and returns ``dst``."""
    n = len(src)
    if n == 0:
        return dst
    if dst.device.is_cpu:
        view = host(dst)
        if type(src) is np.ndarray and src.shape[1:] == view.shape[1:]:
            view[:n] = src  # rows of the buffer's shape: no reshape (a substep uploads ~20 small arrays)
        else:
            view[:n] = np.asarray(src).reshape((n,) + view.shape[1:])
    elif n == dst.shape[0]:
        dst.assign(np.ascontiguousarray(src))
    else:
        wp.copy(dst, wp.array(np.ascontiguousarray(src), dtype=dst.dtype, device="cpu"), count=n)
    return dst


def grown_capacity(rows: int, current: int, minimum: int = 16) -> int:
    """The one growth policy of the reused device buffers (:class:`Staging`, the contact set's
    rows, the narrow and broad phases' outputs): at least ``rows``, at least twice the current
    capacity (n appends cost O(n) copies in all), at least ``minimum``."""
    return max(int(rows), 2 * int(current), int(minimum))


def rows(a, tail: tuple, dtype=np.float64) -> np.ndarray:
    """``a`` (a Warp array, a tensor, array-like or None) as a numpy array of rows of shape
    ``tail``: (n, *tail) of ``dtype``; None gives zero rows."""
    if a is None:
        return np.zeros((0, *tail), dtype=dtype)
    return np.asarray(a.numpy() if hasattr(a, "numpy") else a, dtype=dtype).reshape(-1, *tail)


def read_only(*arrays: np.ndarray) -> tuple:
    """``arrays``, made read-only (results shared between calls: writing one raises)."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


def zero(arr: wp.array) -> wp.array:
    """Sets ``arr`` to zeros: on the CPU through its host view (a counter reset per launch costs
    a microsecond less than ``zero_()``), except under a CPU graph capture, which must record it."""
    if arr.device.is_cpu and not cpu_capture_active(arr.device):
        host(arr).fill(0)
    else:
        arr.zero_()
    return arr


_zero_array = zero  # for Arena.take, whose argument ``zero`` hides the function


class Staging:
    """Named Warp arrays that grow to the largest size asked for and are then reused.

    ``put(name, data, dtype)`` returns an array of at least ``max(len(data), 1)`` rows whose first
    ``len(data)`` rows hold ``data`` (the rest is stale: pass the count to the kernel).
    ``empty(name, rows, dtype)`` returns one without filling it. ``zeros(name, rows, dtype)``
    returns one that holds zeros (for constant zero inputs; nothing may write it).
    """

    def __init__(self, device) -> None:
        self.device = wp.get_device(device)
        self._arrays: dict[str, wp.array] = {}

    def empty(self, name: str, rows: int, dtype) -> wp.array:
        a = self._arrays.get(name)
        if a is None or a.shape[0] < max(rows, 1) or a.dtype != dtype:
            size = grown_capacity(rows, a.shape[0] if a is not None else 0)
            a = wp.zeros(size, dtype=dtype, device=self.device)
            self._arrays[name] = a
        return a

    def zeros(self, name: str, rows: int, dtype) -> wp.array:
        # a new array is allocated zero-filled and, under its own name space, never written
        return self.empty("zeros:" + name, rows, dtype)

    def put(self, name: str, data: np.ndarray, dtype) -> wp.array:
        return upload(self.empty(name, len(data), dtype), data)



class Arena:
    """Arrays handed out one per request within a call and all reused by the next call.

    ``take(shape, dtype)`` (``shape`` an int or a square ``(n, n)``) returns a view of the next
    array of this call whose size class (the power of two >= n) and dtype match; ``begin()``
    starts a new call, after which the previous call's arrays may be handed out again (the
    caller must be done with them). Once the largest sizes and counts of a run have been met,
    taking allocates no memory (a view is a new array object, not new memory).
    """

    def __init__(self, device) -> None:
        self.device = device
        self._pools: dict = {}  # (dtype, square, size) -> arrays
        self._taken: dict = {}  # (dtype, square, size) -> how many this call has taken
        self._views: dict = {}  # (pool key, slot, rows) -> the view handed out

    def begin(self) -> None:
        self._taken.clear()

    def take(self, shape, dtype, zero: bool = True) -> wp.array:
        """The next array of ``shape`` / ``dtype`` of this call, zeroed unless ``zero`` is False."""
        square = isinstance(shape, tuple)
        n = shape[0] if square else int(shape)
        size = 1 << max(n - 1, 0).bit_length()  # the power of two >= n
        key = (dtype, square, size)
        k = self._taken.get(key, 0)
        self._taken[key] = k + 1
        pool = self._pools.setdefault(key, [])
        if k == len(pool):
            pool.append(wp.zeros((size, size) if square else size, dtype=dtype, device=self.device))
        # the view of this slot and size, made once (slicing a Warp array costs ~20 us of Python)
        view_key = (key, k, n)
        out = self._views.get(view_key)
        if out is None:
            out = self._views[view_key] = pool[k][:n, :n] if square else pool[k][:n]
        if zero:
            _zero_array(out)
        return out

    def mark(self) -> dict:
        """How many square arrays this call has taken so far (for :meth:`release_squares`)."""
        return {key: k for key, k in self._taken.items() if key[1]}

    def release_squares(self, mark: dict) -> None:
        """Hands the square arrays taken since ``mark`` out again (the scratch matrices of a
        finished solve: the caller keeps none of them)."""
        for key in self._taken:
            if key[1]:
                self._taken[key] = mark.get(key, 0)

class RecordedLaunches:
    """Kernel launches recorded on the first call with a key and replayed after that.

    ``launch(key, kernel, dim, args)`` is ``wp.launch(kernel, dim, inputs=args)``, through a
    command recorded with ``record_cmd=True``. Replaying it skips Warp's per-launch argument
    packing (tens of microseconds, more than most collision kernels take on a few hundred
    elements); only the launch size and the arguments that changed since the key's last launch
    (another array object, another scalar value) are set again. A reused buffer whose contents
    changed needs nothing: the command holds its address. Pass scalars as Python numbers (they
    are compared by value). A replayed command is not recorded by a ``wp.Tape``: use it for
    launches that stay off the tape.

    On the CPU the command's argument structure is kept too and only its changed fields are
    rewritten: Warp's own replay (``Launch.launch``) builds the structure afresh, field by field,
    on every launch (about 5-8 microseconds for a collision kernel's 15-20 arguments, a substep
    replays about a dozen). The structure is the one Warp's CPU ``invoke`` builds (the kernel's
    arguments in order, each of its packed type); under a CPU graph capture, and for launches in
    blocks, the command's own ``launch()`` runs instead. An array argument replaced by a plain
    array of the same dtype, dimensions and device (the states a stepping loop alternates) only
    has its descriptor written into that structure (Warp's checks of it cost microseconds, and
    the array it replaces passed them); the command's own copy of such arguments is brought up to
    date before its ``launch()`` runs or its structure is rebuilt.
    """

    def __init__(self, device) -> None:
        self.device = device
        self._cmds: dict = {}

    def launch(self, key, kernel, dim: int, args: list) -> None:
        entry = self._cmds.get(key)
        if entry is None:  # recorded, not run (record_cmd)
            cmd = wp.launch(kernel, dim=dim, inputs=args, device=self.device, record_cmd=True)
            self._cmds[key] = entry = [cmd, list(args), dim, cpu_launch_arguments(cmd), set()]
        cmd, last, last_dim, cpu, stale = entry
        if dim != last_dim:
            cmd.set_dim(dim)
            entry[2] = dim
        for i, (new, old) in enumerate(zip(args, last)):
            if new is not old and (isinstance(new, wp.array) or new != old):
                if cpu is not None and _same_kind_of_array(new, old):
                    # another array like the last one (the states a stepping loop alternates):
                    # its descriptor goes into the structure; the command's own copy of the
                    # argument is brought up to date only if its launch() runs (Warp's checks
                    # of an array argument cost microseconds, and the last array passed them)
                    setattr(cpu[0], cpu[1][i], new.__ctype__())
                    stale.add(i)
                else:
                    cmd.set_param_at_index(i, new)
                    stale.discard(i)
                    if cpu is not None:
                        packed = packed_argument(cmd, i)
                        if type(packed) is cpu[2][i]:
                            setattr(cpu[0], cpu[1][i], packed)
                        else:  # packed as another ctypes class (a value argument given another way)
                            cpu = entry[3] = cpu_launch_arguments(cmd, last, stale)
                last[i] = new
        if cpu is None or cpu_capture_active(cmd.device):
            for i in stale:
                cmd.set_param_at_index(i, last[i])
            stale.clear()
            cmd.launch()
        else:
            cpu_launch(cmd, cpu[0])


def _same_kind_of_array(new, old) -> bool:
    """Whether ``new`` is a plain Warp array of the same dtype, dimensions and device as
    ``old`` (which a launch accepted): Warp would accept it for the same argument."""
    return type(new) is wp.array and type(old) is wp.array and new.dtype is old.dtype \
        and new.ndim == old.ndim and new.device is old.device \
        and wp.config.launch_array_access_mode == wp.config.LaunchArrayAccessMode.RELAXED


def copy_rows(dst: wp.array, src: wp.array, n: int) -> wp.array:
    """Copies the first ``n`` rows of ``src`` into ``dst`` (same dtype) and returns ``dst``: on
    the CPU through the arrays' host views (no launch), elsewhere by ``wp.copy``."""
    if n:
        if dst.device.is_cpu and src.device.is_cpu and not cpu_capture_active(dst.device):
            host(dst)[:n] = host(src)[:n]
        else:
            wp.copy(dst, src, count=n)
    return dst
