"""RecordedLaunches (core/buffers.py): a replayed launch computes what wp.launch does with
the same arguments, whatever changed since the key's last launch, and a CPU graph capture still
records it."""

import numpy as np
import pytest
import warp as wp

from core.buffers import RecordedLaunches
from core.device import init_warp

init_warp()


@wp.kernel
def _axpy(a: wp.float64, shift: int, x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64),
          out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = a * x[i] + y[i] + wp.float64(shift)


def _expected(a, shift, x, y, n):
    return a * x.numpy()[:n] + y.numpy()[:n] + shift


def test_replayed_launches_match_fresh_launches_after_every_kind_of_change():
    """Same key, changing in turn: nothing, the launch size, a scalar (float and int), the
    contents of an input (same array object), another input array object, another output array
    object: each replay writes exactly what a fresh wp.launch writes."""
    rng = np.random.default_rng(0)
    x = wp.array(rng.normal(size=16), dtype=wp.float64)
    y = wp.array(rng.normal(size=16), dtype=wp.float64)
    y2 = wp.array(rng.normal(size=16), dtype=wp.float64)
    out = wp.zeros(16, dtype=wp.float64)
    out2 = wp.zeros(16, dtype=wp.float64)
    launches = RecordedLaunches("cpu")
    calls = [
        (2.0, 0, x, y, out, 16),
        (2.0, 0, x, y, out, 16),  # unchanged
        (2.0, 0, x, y, out, 5),  # smaller launch
        (-1.5, 0, x, y, out, 16),  # float scalar
        (-1.5, 7, x, y, out, 16),  # int scalar
        ("contents", 7, x, y, out, 16),  # x's contents, same object
        (-1.5, 7, x, y2, out, 16),  # another input array
        (0.25, 3, x, y2, out2, 11),  # another output array, scalars and size
    ]
    for a, shift, xa, ya, oa, n in calls:
        if a == "contents":
            x.assign(rng.normal(size=16))
            a = -1.5
        oa.zero_()
        launches.launch("axpy", _axpy, n, [a, shift, xa, ya, oa])
        got = oa.numpy().copy()
        np.testing.assert_array_equal(got[:n], _expected(a, shift, xa, ya, n))
        np.testing.assert_array_equal(got[n:], 0.0)  # nothing past the launch size
        fresh = wp.zeros(16, dtype=wp.float64)
        wp.launch(_axpy, dim=n, inputs=[a, shift, xa, ya, fresh], device="cpu")
        np.testing.assert_array_equal(got, fresh.numpy())
    # on the CPU the kept argument structure serves the replays
    assert launches._cmds["axpy"][3] is not None


def test_replayed_launch_is_recorded_by_a_cpu_graph_capture():
    """Under wp.ScopedCapture on the CPU the launch goes through Warp's own path, which records
    it: replaying the graph later recomputes the output."""
    x = wp.array(np.arange(8.0), dtype=wp.float64)
    y = wp.ones(8, dtype=wp.float64)
    out = wp.zeros(8, dtype=wp.float64)
    launches = RecordedLaunches("cpu")
    launches.launch("axpy", _axpy, 8, [2.0, 0, x, y, out])
    with wp.ScopedCapture(device="cpu") as capture:
        launches.launch("axpy", _axpy, 4, [3.0, 1, x, y, out])
    out.zero_()
    wp.capture_launch(capture.graph)
    np.testing.assert_array_equal(out.numpy(), np.concatenate([_expected(3.0, 1, x, y, 4), np.zeros(4)]))


@wp.kernel
def _vector_sum(v: wp.vec3d, out: wp.array(dtype=wp.float64)):
    out[0] = v[0] + v[1] + v[2]


def test_replayed_launch_takes_a_value_argument_packed_as_another_class():
    """A vector value given first as a tuple, then as an instance of another vector class of the
    same layout (packed as another ctypes class): the replay rebuilds its argument structure
    instead of failing, and computes what wp.launch does."""
    other = wp.types.vector(3, wp.float64)
    out = wp.zeros(1, dtype=wp.float64)
    launches = RecordedLaunches("cpu")
    for value, want in (((1.0, 2.0, 3.0), 6.0), (other(1.0, 1.0, 1.0), 3.0), ((2.0, 2.0, 2.0), 6.0)):
        launches.launch("sum", _vector_sum, 1, [value, out])
        assert out.numpy()[0] == want


def test_alternating_arrays_stay_right_on_both_launch_paths():
    """Input arrays alternating between launches (as a stepping loop's states do) take the
    cheap path (the descriptor only, the command's copy updated lazily); a CPU graph capture in
    between launches the latest arrays, as does the cheap path after it; an array of another
    dtype is still refused by Warp's own checks."""
    rng = np.random.default_rng(1)
    xs = [wp.array(rng.normal(size=8), dtype=wp.float64) for _ in range(3)]
    y = wp.array(rng.normal(size=8), dtype=wp.float64)
    out = wp.zeros(8, dtype=wp.float64)
    launches = RecordedLaunches("cpu")
    for step in range(7):
        x = xs[step % 3]
        if step == 4:  # captured: Warp's own path, which must see the lazily kept arrays
            with wp.ScopedCapture(device="cpu") as capture:
                launches.launch("axpy", _axpy, 8, [2.0, 0, x, y, out])
            out.zero_()
            wp.capture_launch(capture.graph)
        else:
            launches.launch("axpy", _axpy, 8, [2.0, 0, x, y, out])
        np.testing.assert_array_equal(out.numpy(), _expected(2.0, 0, x, y, 8))
        if step in (1, 2, 6):  # another x like the last: the cheap path, Warp's copy not yet updated
            assert launches._cmds["axpy"][4] == {2}
        if step == 4:
            assert not launches._cmds["axpy"][4]  # brought up to date for the capture
    wrong = wp.array(rng.normal(size=8), dtype=wp.float32)
    with pytest.raises(RuntimeError, match="dtype"):
        launches.launch("axpy", _axpy, 8, [2.0, 0, wrong, y, out])


def test_zero_clears_through_the_host_view_and_is_recorded_by_a_cpu_capture():
    """zero(): on the CPU the array reads zeros right after; under a CPU graph capture the
    clearing is recorded (replaying the graph clears the array again)."""
    from core.buffers import zero

    counter = wp.array(np.array([5, -3], dtype=np.int32), dtype=wp.int32)
    zero(counter)
    np.testing.assert_array_equal(counter.numpy(), [0, 0])
    with wp.ScopedCapture(device="cpu") as capture:
        zero(counter)
    counter.assign(np.array([7, 7], dtype=np.int32))
    wp.capture_launch(capture.graph)
    np.testing.assert_array_equal(counter.numpy(), [0, 0])


def test_arena_hands_released_squares_out_again_and_keeps_the_vectors():
    """A solve's dense matrices are scratch: after ``release_squares(mark)`` the next square
    take of the call gets the same memory (a cloth's active-set repairs kept over a gigabyte of
    matrices to the end of each call before), while vectors taken since the mark stay the
    caller's."""
    from core.buffers import Arena

    arena = Arena("cpu")
    arena.begin()
    kept = arena.take(5, wp.float64)
    mark = arena.mark()
    first = arena.take((6, 6), wp.float64)
    vector = arena.take(5, wp.float64)
    arena.release_squares(mark)
    again = arena.take((7, 7), wp.float64)  # the same size class (8)
    assert again.ptr == first.ptr
    assert arena.take(5, wp.float64).ptr not in (kept.ptr, vector.ptr)
    arena.begin()
    assert arena.take(5, wp.float64).ptr == kept.ptr
