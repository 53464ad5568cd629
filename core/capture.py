"""Launch sequences recorded once as a Warp graph and replayed (``wp.ScopedCapture``).

A stage list (:class:`Launch`, :class:`Zero`) says what a step launches; :class:`Graphs` runs it
either launch by launch or, from the second time the same list comes (the same kernels, launch
sizes, arrays and scalar values), as one recorded graph. Warp records CPU launches too and replays
them in C++: a replayed graph skips Python's per-launch argument packing (about 10-20 us a launch
on the CPU), and gives the same bits as the launches (the same kernels on the same arguments).

A graph holds the arrays' addresses and the scalars' values it was recorded with, so the key is
all of them; an array replaced by another (or a changed scalar) selects another graph. The
stage list is kept with its graph, so that no array the graph writes is freed and its address
given to another array while the graph lives. Launches in a graph are not recorded by a
``wp.Tape``: callers run graphs only when no tape records (nor is paused).
"""

from __future__ import annotations

import ctypes
from collections import OrderedDict
from typing import NamedTuple

import numpy as np
import warp as wp


class Launch(NamedTuple):
    """One kernel launch: ``wp.launch(kernel, dim, inputs, outputs, record_tape=record_tape)``."""

    kernel: object
    dim: int
    inputs: tuple
    outputs: tuple = ()
    record_tape: bool = True

    def run(self, device) -> None:
        wp.launch(self.kernel, dim=self.dim, inputs=list(self.inputs), outputs=list(self.outputs), device=device,
                  record_tape=self.record_tape)

    def key(self) -> tuple:
        # the kernel object, not its name: two kernels may share a name
        return (self.kernel, self.dim, tuple(map(argument_key, self.inputs)),
                tuple(map(argument_key, self.outputs)))


class Zero(NamedTuple):
    """Zeroes ``array`` (a recorded memset under a capture)."""

    array: wp.array

    def run(self, device) -> None:
        self.array.zero_()

    def key(self) -> tuple:
        return ("zero", argument_key(self.array))


def argument_key(value) -> object:
    """What a recorded graph holds of a launch argument: an array's address and shape (a
    launch accepts only one dtype per argument); a float's bits (-0.0 is not 0.0 to a graph, a
    NaN matches itself); a Warp scalar's value; a vector's bytes; anything else as it is."""
    kind = type(value)
    if kind is wp.array:
        return value.ptr, value.shape
    if isinstance(value, (float, np.floating)):
        return float(value).hex()
    if kind is int or kind is bool:
        return value
    if isinstance(value, ctypes.Array):  # wp.vec3d(...) and the like: its bytes
        return kind, bytes(value)
    if isinstance(value, wp.array):
        return value.ptr, value.shape, kind
    if hasattr(value, "value"):  # wp.float64(...) and the like
        return kind, argument_key(value.value)
    return value


def run_stages(stages, device) -> None:
    """Runs ``stages`` launch by launch."""
    for stage in stages:
        stage.run(device)


class Graphs:
    """Stage lists run as recorded graphs from their second call on.

    A list seen once runs launch by launch (its kernels load, its scratch arrays exist before a
    capture starts; a run whose arguments never repeat, such as a step size changing every call,
    never records). Seen again, it is recorded (``wp.ScopedCapture``, which on the CPU records
    without running) and the graph is launched; later calls launch the graph.

    Args:
        device: the Warp device of every launch.
        limit: the graphs (and the keys seen once) kept; the oldest goes first.
    """

    def __init__(self, device, limit: int = 16) -> None:
        self.device = wp.get_device(device)
        self.limit = limit
        self._graphs: OrderedDict = OrderedDict()
        self._seen: OrderedDict = OrderedDict()
        self.recorded = 0  # graphs recorded over the object's life (statistics)
        self.replayed = 0  # graph launches

    def run(self, stages) -> None:
        """Runs the stage list ``stages`` (see the class docstring; an empty one runs nothing)."""
        if not stages:
            return
        key = tuple(stage.key() for stage in stages)
        entry = self._graphs.get(key)
        if entry is None:
            if key not in self._seen:
                self._keep(self._seen, key, True)
                run_stages(stages, self.device)
                return
            with wp.ScopedCapture(device=self.device) as capture:
                run_stages(stages, self.device)
            entry = (capture.graph, list(stages))  # the stages keep the graph's arrays alive
            self._keep(self._graphs, key, entry)
            self.recorded += 1
        else:
            self._graphs.move_to_end(key)
        wp.capture_launch(entry[0])
        self.replayed += 1

    def _keep(self, table: OrderedDict, key, value) -> None:
        table[key] = value
        while len(table) > self.limit:
            table.popitem(last=False)
