"""The scene CLI never loses or clobbers a user's file: what ``--out`` accepts, where a failed or
interrupted run's frames go (``NAME.partial.rrd``), SIGTERM, stale temporary files, and the
flags that exist only where they mean something (``--seed``, ``--version``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from scenes.__main__ import main

REPO = Path(__file__).resolve().parents[1]


def _usage_error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


def test_out_refuses_a_device_a_fifo_and_a_folder(tmp_path, capsys):
    err = _usage_error(["rigid_toss", "--out", "/dev/null", "--steps", "1"], capsys)
    assert "--out" in err and "not a regular file" in err
    assert Path("/dev/null").is_char_device()  # not replaced by a regular file
    fifo = tmp_path / "pipe.rrd"
    os.mkfifo(fifo)
    err = _usage_error(["rigid_toss", "--out", str(fifo), "--steps", "1"], capsys)
    assert "--out" in err and "not a regular file" in err
    assert fifo.is_fifo()
    err = _usage_error(["rigid_toss", "--out", str(tmp_path), "--steps", "1"], capsys)
    assert "--out" in err and "is a folder" in err
    err = _usage_error(["rigid_toss", "--out", str(tmp_path / "no" / "x.rrd"), "--steps", "1"], capsys)
    assert "--out" in err and "does not exist" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe.rrd"]


def test_out_follows_a_symbolic_link(tmp_path, capsys):
    target = tmp_path / "recordings" / "real.rrd"
    target.parent.mkdir()
    target.write_bytes(b"old")
    link = tmp_path / "link.rrd"
    link.symlink_to(target)
    assert main(["rigid_toss", "--out", str(link), "--steps", "2"]) == 0
    capsys.readouterr()
    assert link.is_symlink() and link.resolve() == target
    assert target.read_bytes()[:4] != b"old" and target.stat().st_size > 1000


def test_a_stale_temporary_file_of_a_killed_run_is_removed(tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".x.rrd.{dead.pid}.tmp"
    stale.write_bytes(b"frames of a killed run")
    mine = tmp_path / f".x.rrd.{os.getpid()}.tmp.keep"  # not a temporary name: left alone
    mine.write_bytes(b"")
    assert main(["rigid_toss", "--out", str(tmp_path / "x.rrd"), "--steps", "1"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([mine.name, "x.rrd"])


def test_seed_exists_only_where_something_is_random(tmp_path, capsys):
    err = _usage_error(["rigid_toss", "--out", str(tmp_path / "x.rrd"), "--seed", "3"], capsys)
    assert "--seed" in err
    with pytest.raises(SystemExit) as exc:
        main(["billiards", "--help"])
    assert exc.value.code == 0
    assert "--seed" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("tunnelsim ")


def test_sigterm_keeps_the_frames_so_far_like_ctrl_c(tmp_path):
    """SIGTERM mid-run: exit 143, the frames so far in NAME.partial.rrd (readable, with
    /status), an earlier NAME.rrd untouched, no temporary file left."""
    from rerun.chunk import RrdReader

    out = tmp_path / "h.rrd"
    out.write_bytes(b"an earlier recording")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-m", "scenes", "rigid_toss", "--out", str(out), "--steps", "1000000"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    tmp = tmp_path / f".h.rrd.{proc.pid}.tmp"
    deadline = time.monotonic() + 600
    # well past the static meshes and the blueprint (a few kB): stepping has logged many frames
    while time.monotonic() < deadline and proc.poll() is None and not (tmp.exists() and tmp.stat().st_size > 200_000):
        time.sleep(0.2)
    if proc.poll() is not None or time.monotonic() >= deadline:
        proc.kill()
        pytest.fail(f"the run never got to stepping: {proc.communicate()[1][-2000:]}")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    partial = tmp_path / "h.partial.rrd"
    assert f"terminated; the frames recorded so far are in {partial}" in err
    assert out.read_bytes() == b"an earlier recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h.partial.rrd", "h.rrd"]
    rows = {}
    for chunk in RrdReader(partial).stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows.get("/status") == 1 and rows.get("/metrics/energy/total", 0) >= 1


def test_a_signal_whose_exception_a_destructor_swallowed_still_ends_the_run(tmp_path, monkeypatch, capsys):
    """Python drops an exception raised inside ``__del__`` ("Exception ignored in ..."): a SIGTERM
    that lands while a Warp array is freed used to be lost, and the run went on. The noted signal
    ends the run at the next step instead: exit 143, the 4 frames so far kept."""
    from sim.integrators.semi_implicit import SemiImplicitIntegrator

    class FreedDuringTheSignal:
        def __del__(self):
            signal.raise_signal(signal.SIGTERM)  # the handler runs here, and its exception is dropped

    real_step = SemiImplicitIntegrator.step
    calls = {"n": 0}

    def step(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            FreedDuringTheSignal()
        return real_step(self, *a, **k)

    monkeypatch.setattr(SemiImplicitIntegrator, "step", step)
    dropped = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: dropped.append(info.exc_type.__name__))
    out = tmp_path / "run.rrd"
    handlers = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]
    assert main(["rigid_toss", "--out", str(out), "--steps", "50"]) == 143
    err = capsys.readouterr().err
    assert [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)] == handlers  # put back
    assert dropped == ["Terminated"]  # the destructor swallowed it once
    assert f"terminated; the frames recorded so far are in {tmp_path / 'run.partial.rrd'}" in err
    assert calls["n"] == 4
    from rerun.chunk import RrdReader

    rows = {}
    for chunk in RrdReader(tmp_path / "run.partial.rrd").stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows.get("/metrics/energy/total") == 4


def test_the_tunnel_plot_draws_the_baseline_flat_from_a_miss():
    """The baseline from a miss has no finite loss at all: its panel shows a flat, explained line
    at the shot's lifted loss instead of an empty axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.inverse import plot_tunnel_curves

    rows = [{"seed": 0, "proposed": {"loss_curve": [0.5, 0.2, 0.01]}, "baseline": {"loss_curve": [None]},
             "cma": {"loss_curve": [0.5, 0.4]}}]
    fig = plot_tunnel_curves(plt, rows, iters=3)
    baseline = fig.axes[1]
    (line,) = baseline.get_lines()
    assert list(line.get_xdata()) == [0, 3] and list(line.get_ydata()) == [0.5, 0.5]
    assert any("no real root" in t.get_text() for t in baseline.texts)
    plt.close(fig)


@pytest.mark.parametrize("argv, flag", [
    (["bank_shot", "--methods", "foo"], "--methods"),
    (["billiards", "--methods", ""], "--methods"),
    (["cloth_drop", "--cg-tolerance", "1e-6"], "--cg-tolerance"),
    (["rigid_toss", "--integrator", "implicit"], "--integrator"),
    (["paper_cubic", "--seed", "1"], "--seed"),
])
def test_flags_that_do_not_apply_are_usage_errors(tmp_path, capsys, argv, flag):
    """Refused before any set-up (no scene built, nothing written), with exit 2 and the flag named."""
    import scenes.sim_common

    built = []
    real = scenes.sim_common.build_model
    scenes.sim_common.build_model = lambda *a, **k: built.append(1) or real(*a, **k)
    try:
        err = _usage_error([*argv, "--out", str(tmp_path / "x.rrd")], capsys)
    finally:
        scenes.sim_common.build_model = real
    assert flag in err and not built
    assert not list(tmp_path.iterdir())


def test_the_first_compile_is_announced(tmp_path):
    """A cold kernel cache: one line on stderr before Warp compiles (then a line per module); a
    warm one: silence."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    code = "from core.device import init_warp; init_warp()"
    import warp
    for cache, notice in ((tmp_path / "cold", True), (tmp_path / "warm", False)):
        if not notice:
            (cache / warp.config.version / "wp_kernels.roots_0000000").mkdir(parents=True)
        proc = subprocess.run([sys.executable, "-c", code], env={**env, "WARP_CACHE_PATH": str(cache)},
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert ("Warp compiles each kernel module on first use" in proc.stderr) == notice, proc.stderr
        assert proc.stdout == ""


@pytest.fixture(scope="module")
def user_meshes(tmp_path_factory):
    """A unit icosphere as OBJ and a unit box as STL (a user's own files)."""
    from sim.mesh_io import box_mesh, icosphere, save_mesh

    folder = tmp_path_factory.mktemp("meshes")
    save_mesh(folder / "ball.obj", *icosphere(1.0, 2))
    save_mesh(folder / "block.stl", *box_mesh(1.0))
    return folder


@pytest.mark.parametrize("argv, components, bodies", [
    (["cloth_drop", "--cloth-res", "8", "--mesh", "ball.obj", "--mesh-scale", "0.2", "--steps", "24"],
     ["cloth", "static"], 0),
    (["rigid_toss", "--mesh", "block.stl", "--mesh-scale", "0.1", "--mesh-offset", "0.2", "0", "--steps", "30"],
     ["rigid", "static"], 1),
])
def test_a_users_mesh_as_the_obstacle(tmp_path, capsys, user_meshes, argv, components, bodies):
    """The cloth drapes onto, or the tossed box runs into, the user's file, placed on the ground;
    the independent checker finds no penetration on any frame."""
    import json

    argv = [str(user_meshes / a) if a.endswith((".obj", ".stl")) else a for a in argv]
    assert main([*argv, "--out", str(tmp_path / "m.rrd")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["components"] == components and summary["bodies"] == bodies
    assert summary["penetrations"] == 0 and summary["contacts"] > 0


def test_the_users_mesh_is_scaled_and_placed_on_the_ground(user_meshes):
    """--mesh-scale 0.2 of a unit icosphere: a ball of radius 0.2 resting on z = 0, centred
    under the cloth (moved by --mesh-offset), in place of the scene's sphere and box."""
    import numpy as np

    from scenes import cloth_drop
    from scenes.sim_common import build_model, default_args

    args = default_args(mesh=user_meshes / "ball.obj", mesh_scale=0.2, mesh_offset=(0.1, -0.05))
    static = build_model(cloth_drop.build, args).static_vertices.numpy()
    low, high = static.min(axis=0), static.max(axis=0)
    np.testing.assert_allclose(low[2], 0.0, atol=1e-15)
    np.testing.assert_allclose(high - low, [0.4, 0.4, 0.4], rtol=0.06)  # an icosphere's extent
    np.testing.assert_allclose(0.5 * (low[:2] + high[:2]), np.add(cloth_drop.CLOTH_CENTRE_XY, (0.1, -0.05)), atol=1e-12)
    assert len(static) == 162  # the icosphere alone: no sphere and box of the scene's own


@pytest.mark.parametrize("argv, message", [
    (["cloth_drop", "--mesh", "ball.obj"], "reaches into what falls onto it"),
    (["cloth_drop", "--mesh-scale", "2"], "--mesh-scale applies with --mesh only"),
    (["rigid_toss", "--mesh", "missing.obj"], "mesh file not found"),
    (["rigid_toss", "--mesh", "ball.obj", "--mesh-offset", "nan", "0"], "--mesh-offset must be finite"),
])
def test_mesh_usage_errors(tmp_path, capsys, user_meshes, argv, message):
    argv = [str(user_meshes / a) if a.endswith((".obj", ".stl")) else a for a in argv]
    err = _usage_error([*argv, "--out", str(tmp_path / "m.rrd")], capsys)
    assert message in err
    assert not list(tmp_path.iterdir())


def test_a_scenes_loss_plot_draws_a_stopped_method_flat(tmp_path, monkeypatch):
    """billiards --plot: the baseline from a miss stops after one rollout (gradient exactly 0);
    its curve is a dashed line across the plot, not an invisible point."""
    import sim.logging
    from scenes.optim import plot_loss_curves

    figures = []
    monkeypatch.setattr(sim.logging, "save_figure", lambda fig, path: figures.append(fig))
    plot_loss_curves({"baseline": [0.066], "proposed": [0.5, 0.1, 0.01, 0.001]}, str(tmp_path / "l.png"), "t", "loss")
    baseline, proposed = figures[0].axes[0].get_lines()
    assert list(baseline.get_xdata()) == [0, 3] and list(baseline.get_ydata()) == [0.066, 0.066]
    assert baseline.get_linestyle() == "--" and "gradient 0" in baseline.get_label()
    assert len(proposed.get_xdata()) == 4


def test_an_interrupt_during_the_flush_waits_until_the_file_is_in_place(tmp_path, monkeypatch):
    """A SIGTERM that arrives while a finished run's recording is flushed is held back: the
    recording still replaces NAME.rrd whole, no temporary file is left, and the signal's handler
    runs once the logger has exited."""
    from rerun.chunk import RrdReader

    from sim.logging import RerunLogger

    class Stopped(Exception):
        pass

    def handler(signum, frame):
        raise Stopped

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        out = tmp_path / "run.rrd"
        out.write_bytes(b"an earlier recording")
        log = RerunLogger(out, application_id="t")
        flush = None
        with pytest.raises(Stopped):
            with log:
                log.log_text("/status", "done")
                flush = log.rec.flush

                def flush_and_be_terminated(*args, **kwargs):
                    os.kill(os.getpid(), signal.SIGTERM)  # arrives in the middle of the flush
                    time.sleep(0.05)
                    return flush(*args, **kwargs)

                monkeypatch.setattr(log.rec, "flush", flush_and_be_terminated)
        assert log.written == out
        assert sorted(p.name for p in tmp_path.iterdir()) == ["run.rrd"]
        rows = {chunk.entity_path: chunk.num_rows for chunk in RrdReader(out).stream().to_chunks()}
        assert rows.get("/status") == 1
    finally:
        signal.signal(signal.SIGTERM, previous)
