"""Scene CLI tests for ``paper_quadratic`` and ``paper_cubic`` (subprocess, headless).

Each scene runs once (module fixture) through ``python -m scenes`` with a small ``--iters``: the
JSON line, the summary's bookkeeping, the baselines' immediate failures and the .rrd contents are
checked on it. Convergence of the proposed method needs far more Adam steps (measured: quadratic
440-2750, cubic 130-1730 per start), so it is checked in-process with the scenes' own
``run_proposed`` (the exact code path the CLI runs, minus the baseline and the logging) to keep
this file fast. The paper states that the proposed approach recovers and converges from every one
of these starts; its baselines (plain autograd, real roots only) fail where the paper says they
must (``a = 0`` in the quadratic formula, ``f' = 0`` for Newton, a root that has to pass through
the complex plane).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scenes import paper_cubic, paper_quadratic
from scenes.paper_common import start

REPO = Path(__file__).resolve().parents[1]
CLI_ITERS = 30
QUADRATIC_CONVERGENCE_ITERS = 3500
"""Slowest measured start: ``[0, -5.1, 5]`` (table bad_a), loss < 1e-10 after ~2750 steps."""
CUBIC_CONVERGENCE_ITERS = 2500
"""Slowest measured start: ``[1, 0, -7.1, 6]`` with q, a fixed, loss < 1e-10 after 1730-1850 steps
(the count moves with the last bits of the solver: margin kept on purpose)."""


def run_cli(*args: str, cwd: Path | None = None, code: str | None = None) -> subprocess.CompletedProcess:
    """Runs ``python -m scenes ARGS`` (or ``python -c CODE ARGS``) from the repository root."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", "scenes", *args]
    return subprocess.run(cmd, cwd=cwd or REPO, env=env, capture_output=True, text=True, timeout=300)


def summary_of(proc: subprocess.CompletedProcess) -> dict:
    """The run's JSON summary: stdout must be exactly one JSON line."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert len(lines) == 1, f"stdout must be exactly one line, got {len(lines)}: {proc.stdout[:500]!r}"
    return json.loads(lines[0])


@pytest.fixture(scope="module")
def quadratic(tmp_path_factory):
    out = tmp_path_factory.mktemp("quadratic") / "q.rrd"
    proc = run_cli("paper_quadratic", "--out", str(out), "--iters", str(CLI_ITERS))
    return summary_of(proc), out


@pytest.fixture(scope="module")
def cubic(tmp_path_factory):
    out = tmp_path_factory.mktemp("cubic") / "c.rrd"
    proc = run_cli("paper_cubic", "--out", str(out), "--iters", str(CLI_ITERS))
    return summary_of(proc), out


def read_rrd(path: Path, *, blueprint: bool = True) -> tuple[dict[str, int], dict[str, set[str]]]:
    """Rows and timelines per entity path of a recording, via ``rerun.chunk.RrdReader``."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    timelines: dict[str, set[str]] = {}
    reader = RrdReader(path)
    assert reader.recordings(), "no recording store in the file"
    if blueprint:
        assert reader.blueprints(), "no default blueprint in the file"
    for chunk in reader.stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        timelines.setdefault(chunk.entity_path, set()).update(chunk.timeline_names)
    return rows, timelines


def check_common_summary(summary: dict, scene, iters: int) -> None:
    assert summary["scene"] == scene.NAME
    assert summary["iters"] == iters
    assert summary["lr"] == 0.1 and summary["max_derivative"] == 1000.0 and summary["t_max"] == 1e150
    assert set(summary["starts"]) == {s.name for s in scene.STARTS}
    for name, entry in summary["starts"].items():
        for method in ("proposed", "baseline"):
            m = entry[method]
            assert set(m) >= {"iters_to_converge", "converged", "final_loss"}, (name, method)
            assert m["converged"] == (m["iters_to_converge"] is not None)
            if m["converged"]:
                assert 0 <= m["iters_to_converge"] <= iters
    assert summary["wall_time_s"] > 0


def check_rrd(path: Path, scene, iters: int, proposed_slots: tuple[str, ...], baseline_slots: tuple[str, ...]) -> None:
    rows, timelines = read_rrd(path)
    root = f"/{scene.NAME}"
    expected = []
    for s in scene.STARTS:
        for method, slots in (("proposed", proposed_slots), ("baseline", baseline_slots)):
            base = f"{root}/{s.name}/{method}"
            expected += [f"{base}/loss"] + [f"{base}/params/{p}" for p in scene.PARAM_NAMES]
            expected += [f"{base}/roots/{slot}/{part}" for slot in slots for part in ("re", "im")]
    missing = [e for e in expected if e not in rows]
    assert not missing, f"missing entities: {missing[:10]}"
    for e in expected:
        assert rows[e] == iters + 1, f"{e}: {rows[e]} rows, expected {iters + 1} (iterates 0..{iters})"
        assert {"iteration", "frame"} <= timelines[e], (e, timelines[e])
        assert not {"log_time", "log_tick"} & timelines[e], "recordings must be deterministic"
    assert "/summary" in rows


# ------------------------------------------------------------------------------------ quadratic


def test_quadratic_summary(quadratic):
    summary, _ = quadratic
    check_common_summary(summary, paper_quadratic, CLI_ITERS)


def test_quadratic_proposed_converges_from_every_start():
    """Tables bad_a/bad_ab/bad_abc and Figure example-3: the proposed approach recovers and converges."""
    from scenes.paper_common import convergence_summary

    run = paper_quadratic.run_proposed(iters=QUADRATIC_CONVERGENCE_ITERS)
    report = {s.name: convergence_summary(run.loss[:, i]) for i, s in enumerate(paper_quadratic.STARTS)}
    assert all(r["converged"] and r["nonfinite_at"] is None for r in report.values()), report
    t_plus = run.extras["roots"][:, :, paper_quadratic.T_PLUS]
    hit = [r["iters_to_converge"] for r in report.values()]
    np.testing.assert_allclose(t_plus[hit, range(len(hit))], 0.5, atol=1.5e-5)


def test_quadratic_baseline_fails(quadratic):
    """Autograd through the real formula: a = 0 divides by zero at once; the Figure example-3 start
    must cross the complex region (sqrt of a negative discriminant) and never converges."""
    summary, _ = quadratic
    for name, entry in summary["starts"].items():
        assert not entry["baseline"]["converged"], name
        assert entry["baseline"]["nonfinite_at"] is not None, name
        if entry["p0"][0] == 0.0:
            assert entry["baseline"]["nonfinite_at"] == 0, name
            assert entry["baseline"]["final_loss"] is None, name


def test_quadratic_rrd(quadratic):
    _, out = quadratic
    check_rrd(out, paper_quadratic, CLI_ITERS, paper_quadratic.SLOTS, ("t_plus",))
    assert not [p for p in out.parent.iterdir() if p.name != out.name], "temporary files left behind"


# ---------------------------------------------------------------------------------------- cubic


def test_cubic_summary(cubic):
    summary, _ = cubic
    check_common_summary(summary, paper_cubic, CLI_ITERS)
    for name, entry in summary["starts"].items():
        assert entry["proposed"]["final_slot"] in paper_cubic.SLOTS, name


def test_cubic_proposed_converges_from_every_start():
    """Every cubic example of the paper "eventually converges" with the proposed approach."""
    from scenes.paper_common import convergence_summary

    run = paper_cubic.run_proposed(iters=CUBIC_CONVERGENCE_ITERS)
    report = {s.name: convergence_summary(run.loss[:, i]) for i, s in enumerate(paper_cubic.STARTS)}
    assert all(r["converged"] and r["nonfinite_at"] is None for r in report.values()), report
    hit = [r["iters_to_converge"] for r in report.values()]
    rows = range(len(hit))
    tracked = run.extras["roots"][hit, rows, run.extras["slot"][hit, rows]]
    np.testing.assert_allclose(tracked, 0.5, atol=1.5e-5)


def test_cubic_baseline_fails_where_the_paper_says(cubic):
    """Newton with autograd: f' = 0 for q = a = b = 0 (nothing or everything is a root) gives
    NaN at once (Section "Differentiating Newton's Method": "backpropagating through Newton's
    method assuredly fails in this a = 0 case")."""
    summary, _ = cubic
    starts = summary["starts"]
    for name in ("q0_a0_b0_c6", "q0_a0_b0_c-6", "q0_a0_b0_c0"):
        assert starts[name]["baseline"]["nonfinite_at"] == 0, name
        assert starts[name]["baseline"]["final_loss"] is None, name
        assert not starts[name]["baseline"]["converged"], name
    finite = [n for n, e in starts.items() if e["baseline"]["nonfinite_at"] is None]
    assert len(finite) == len(starts) - 3, "bounded starts keep a finite Newton baseline"


def test_cubic_rrd(cubic):
    _, out = cubic
    check_rrd(out, paper_cubic, CLI_ITERS, paper_cubic.SLOTS + ("tracked",), ("tracked",))
    rows, _ = read_rrd(out)
    assert rows[f"/paper_cubic/{paper_cubic.STARTS[0].name}/proposed/tracked_slot"] == CLI_ITERS + 1


# ------------------------------------------------------------------------------------ CLI errors


def test_list():
    proc = run_cli("--list")
    assert proc.returncode == 0, proc.stderr
    names = [line.split("\t")[0] for line in proc.stdout.splitlines()]
    assert {"paper_quadratic", "paper_cubic"} <= set(names)


def test_unknown_scene(tmp_path):
    out = tmp_path / "x.rrd"
    proc = run_cli("no_such_scene", "--out", str(out))
    assert proc.returncode == 2
    assert "unknown scene 'no_such_scene'" in proc.stderr
    assert "paper_quadratic" in proc.stderr and "paper_cubic" in proc.stderr
    assert proc.stdout == ""
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(("scene", "iters"), [("paper_quadratic", "0"), ("paper_cubic", "-3"), ("paper_cubic", "abc")])
def test_bad_iters(tmp_path, scene, iters):
    out = tmp_path / "x.rrd"
    proc = run_cli(scene, "--out", str(out), f"--iters={iters}")
    assert proc.returncode == 2
    assert "--iters" in proc.stderr and "positive integer" in proc.stderr
    assert proc.stdout == ""
    assert not list(tmp_path.iterdir()), "nothing may be written on a usage error"


def test_precision_and_steps_rejected(tmp_path):
    """The paper scenes are float64 optimisation scenes: --precision float32 and --steps are usage errors."""
    for extra in (["--precision", "float32"], ["--steps", "10"]):
        proc = run_cli("paper_quadratic", "--out", str(tmp_path / "x.rrd"), *extra)
        assert proc.returncode == 2, extra
        assert extra[0] in proc.stderr
    assert not list(tmp_path.iterdir())


def test_t_max_moves_the_escaping_root_and_its_gradient():
    """``t_max`` is the proposed solver's clamp: for ``[0, -1, 0, 1]`` (the paper's text:
    ``t+`` escapes, ``dt+/dq = -M`` by the clamp) ``t+`` sits at ``t_max`` and ``dL/dq`` is
    ``-(t_max - 1/2) M`` for any ``t_max`` (closed form), the bounded roots ``-1, 1`` stay."""
    s = start([0.0, -1.0, 0.0, 1.0], "qabc")
    for t_max in (1e3, 1e6, 1e150):
        run = paper_cubic.run_proposed((s,), iters=0, t_max=t_max)
        np.testing.assert_allclose(run.extras["roots"][0, 0], [-1.0, 1.0, t_max], rtol=1e-15)
        assert run.grads[0, 0, 0] == pytest.approx(-(t_max - 0.5) * 1000.0, rel=1e-12)
    run = paper_quadratic.run_proposed((start([0.0, 1.0, -1.0], "abc"),), iters=0, t_max=1e6)  # a = 0: t = 1 and one escaping root
    assert sorted(np.abs(run.extras["roots"][0, 0])) == [1.0, 1e6]


def test_t_max_option(tmp_path):
    """``--t-max`` reaches the summary (and the run); values outside [1, 1e150], NaN or text are
    usage errors naming the flag, with nothing written."""
    out = tmp_path / "c.rrd"
    summary = summary_of(run_cli("paper_cubic", "--out", str(out), "--iters", "2", "--t-max", "1e6"))
    assert summary["t_max"] == 1e6 and out.exists()
    out.unlink()
    for bad in ("0.5", "1e151", "nan", "inf", "big"):
        proc = run_cli("paper_quadratic", "--out", str(tmp_path / "x.rrd"), "--t-max", bad)
        assert proc.returncode == 2, bad
        assert "--t-max" in proc.stderr, (bad, proc.stderr[-500:])
        assert proc.stdout == ""
    assert not list(tmp_path.iterdir())


def test_missing_output_folder(tmp_path):
    proc = run_cli("paper_quadratic", "--out", str(tmp_path / "nope" / "x.rrd"), "--iters", "1")
    assert proc.returncode == 2
    assert "does not exist" in proc.stderr
    assert not list(tmp_path.iterdir())


FAILING_RUN = """
import sys
import scenes.paper_quadratic as scene
from scenes.__main__ import main

def failing_run(args, log):
    log.log_scalars("/partial", [1.0, 2.0, 3.0])
    log.stream.flush()
    raise RuntimeError("injected failure after logging")

scene.run = failing_run
sys.exit(main(sys.argv[1:]))
"""


def test_a_failed_run_keeps_its_frames_beside_the_output_and_never_replaces_it(tmp_path):
    """A scene failing after it started writing leaves no NAME.rrd and no temporary file: its
    frames go to NAME.partial.rrd (readable, /status says why), which the message names; an
    existing NAME.rrd is left untouched."""
    out = tmp_path / "x.rrd"
    partial = tmp_path / "x.partial.rrd"
    proc = run_cli("paper_quadratic", "--out", str(out), "--iters", "1", code=FAILING_RUN)
    assert proc.returncode == 1
    assert "injected failure after logging" in proc.stderr
    assert f"the frames recorded so far are in {partial}" in proc.stderr and f"no {out} written" in proc.stderr
    assert proc.stdout == ""
    assert [p.name for p in tmp_path.iterdir()] == ["x.partial.rrd"]
    rows, _ = read_rrd(partial, blueprint=False)
    assert rows.get("/partial") == 3 and rows.get("/status") == 1

    out.write_bytes(b"previous recording")
    proc = run_cli("paper_quadratic", "--out", str(out), "--iters", "1", code=FAILING_RUN)
    assert proc.returncode == 1
    assert out.read_bytes() == b"previous recording"
    assert f"{out} is untouched" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.partial.rrd", "x.rrd"]


def test_divergent_optimiser_is_reported_not_raised():
    """An absurd learning rate drives coefficients to inf: NaN roots and loss, no exception."""
    from scenes.paper_common import convergence_summary

    run = paper_cubic.run_proposed(paper_cubic.STARTS[:3], iters=3, lr=1e308)
    assert not np.isfinite(run.loss[-1]).any()
    for row in range(3):
        s = convergence_summary(run.loss[:, row])
        assert not s["converged"] and s["nonfinite_at"] is not None and s["final_loss"] is None


def test_logger_removes_temporary_file_on_exception(tmp_path):
    from sim.logging import RerunLogger

    out = tmp_path / "y.rrd"
    with pytest.raises(ValueError, match="boom"):
        with RerunLogger(out, recording_name="test") as log:
            log.log_scalars("/x", np.arange(3.0))
            raise ValueError("boom")
    assert not list(tmp_path.iterdir())
    with RerunLogger(out, recording_name="test") as log:
        log.log_scalars("/x", np.arange(3.0), sim_time=[0.0, 0.1, 0.2])
    rows, timelines = read_rrd(out, blueprint=False)
    assert rows["/x"] == 3 and timelines["/x"] == {"frame", "sim_time"}
