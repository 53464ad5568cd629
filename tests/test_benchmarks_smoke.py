"""Smoke tests of ``python -m benchmarks``: a tiny configuration of each benchmark runs and
writes its tables, so the command cannot silently rot. (The numbers themselves are measured by
the command; here only their sanity is checked.)"""

from __future__ import annotations

import json
import math

import pytest

pytestmark = pytest.mark.xdist_group("benchmarks")


def _read(prefix):
    with open(str(prefix) + ".md") as fh:
        md = fh.read()
    assert md.startswith("# ") and "Machine:" in md
    return md


def test_roots_tiny(tmp_path):
    from benchmarks import roots

    data = roots.main(["--n", "2000", "--n-roots", "100", "--n-accuracy", "3", "--out", str(tmp_path / "roots")])
    md = _read(tmp_path / "roots")
    assert "float32" in md and "eigvals" in md
    assert json.loads((tmp_path / "roots.json").read_text())["settings"]["n"] == 2000
    assert data["speed"]


def test_ccd_tiny(tmp_path):
    from ccd_queries import available

    if not available():
        pytest.skip("the CCD sample queries are not on this machine (../shared/data/ccd-sample-queries)")
    from benchmarks import ccd

    ccd.main(["--quick", "--tolerance-scales", "1", "--out", str(tmp_path / "ccd")])
    md = _read(tmp_path / "ccd")
    assert "float32" in md and "ipctk" in md.lower()


def test_sim_tiny(tmp_path, capsys):
    from benchmarks import sim as sim_bench

    sim_bench.main(["--dims", "8", "--frames", "1", "--repeats", "1", "--scene-steps", "2", "--sizes", "8",
                    "--size-steps", "2", "--newton-sizes", "--alone-repeats", "0"])
    out = capsys.readouterr().out
    for name in ("NpIntegrator", "cloth_drop", "rigid_toss", "cloth_rigid"):
        assert name in out
    # a replayed run alone (the table runs it in fresh processes: here in this one)
    assert 0.0 < sim_bench._alone_ms_per_step("rigid_toss", True, 2) < 60_000.0


def test_gradients_tiny(tmp_path):
    """A rollout with no contact yet: the gradient must match central differences closely."""
    from benchmarks import gradients

    res = gradients.main(["--scenes", "cloth_drop", "--steps", "3", "--out", str(tmp_path / "gradients")])
    _read(tmp_path / "gradients")
    row = res["rows"][0]
    assert row["finite"] and row["contact_substeps"] == 0
    assert row["best_error"] < 1e-5, row["relative_error"]
    assert row["forward_ms_per_step"] > 0 and row["ratio"] > 0
    # the horizon sweep: one horizon (3 steps) per substep setting, smooth before any contact
    assert [(h["substeps"], h["steps"]) for h in res["horizons"]] == [(8, 3), (16, 3)]
    for h in res["horizons"]:
        assert h["finite"] and h["smooth"] and h["worst_error"] < 1e-5
    assert [s["amplified_from"] for s in res["horizon_summary"]] == [None, None]


def test_gradient_horizon_sweep_through_the_tunnel_hit():
    """The tunnel (seed 0) from the velocity that hits its face at about step 20: at a horizon
    of 25 steps (past the hit, 8 substeps) the rollout's directional derivatives match central
    differences (measured 1.2e-8), and the loss is smooth at their scale."""
    from benchmarks import gradients

    (row,) = gradients.horizon_sweep("tunnel", [25], [8])
    assert row["finite"] and row["smooth"] and row["worst_error"] < 1e-6, row


def test_trade_tiny(tmp_path):
    from benchmarks import trade

    res = trade.main(["--quick", "--scenes", "rigid_toss", "--steps", "3", "--tunnel-iters", "1",
                      "--out", str(tmp_path / "trade")])
    md = _read(tmp_path / "trade")
    assert "rigid_toss" in md and "tunnel" in md
    assert (tmp_path / "trade.png").stat().st_size > 1000
    rows = res["scenes"][0]["rows"]
    assert len(rows) == 2 * len(trade.CONFIGS["quick"]["substeps"]) + len(trade.CONFIGS["quick"]["variants"])
    for r in rows:
        if r["diverged"] is None:
            assert r["ms_per_step"] > 0 and math.isfinite(r["deviation"]) and r["deviation"] >= 0
            assert set(r["errors"]) == set(trade.OBSERVABLES) == set(r["within_noise"])
            # within noise means at most the floor of that observable
            floor = res["scenes"][0]["end_floor"]
            assert all(r["errors"][o] <= floor[o] for o in trade.OBSERVABLES if r["within_noise"][o])
    assert sum(r["recommended"] for r in rows) <= 1
    assert all(r["acceptable"] for r in rows if r["pareto"])
    scene = res["scenes"][0]
    assert scene["observables"] == list(trade.OBSERVABLES)
    assert [h["steps"] for h in scene["noise_floor"]] and all(h["spread"] >= 0 for h in scene["noise_floor"])
    assert [t["max_derivative"] for t in res["tunnel"]] == list(trade.CONFIGS["quick"]["max_derivatives"])


def test_pareto_front():
    from benchmarks.trade import _pareto

    pts = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (4.0, 1.0), (2.0, 3.0)]
    # (3, 4) is beaten by (2, 3); the two equal points do not beat each other
    assert _pareto(pts) == [0, 1, 4, 3]


def test_command_reports_a_failed_section(tmp_path, monkeypatch, capsys):
    import benchmarks.__main__ as cmd

    ran = []

    def fake(name, full, out_dir):
        ran.append(name)
        if name == "roots":
            raise RuntimeError("boom")

    monkeypatch.setattr(cmd, "section", fake)
    assert cmd.main(["--only", "roots,trade", "--out-dir", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert ran == ["roots", "trade"] and "FAILED" in out
    with pytest.raises(SystemExit) as exc:
        cmd.main(["--only", "nope"])
    assert exc.value.code == 2


def test_host_reads_tiny(tmp_path):
    """benchmarks/host_reads.py counts the collision stage's reads per substep for every scene and
    response, writes its table, and leaves core.buffers.host as it found it."""
    import core.buffers as buffers
    from benchmarks import host_reads

    host = buffers.host
    rows = host_reads.main(["--steps", "2", "--out", str(tmp_path / "host_reads")])
    assert buffers.host is host
    assert {(r["scene"], r["response"]) for r in rows} == {(s, r) for s in host_reads.SCENES for r in host_reads.RESPONSES}
    assert all(r["host_per_substep"] > 0 and math.isfinite(r["numpy_per_substep"]) for r in rows)
    assert "| cloth_drop | replayed |" in _read(tmp_path / "host_reads")
    assert len(json.load(open(tmp_path / "host_reads.json"))["rows"]) == 6


def test_capture_tiny(tmp_path):
    """benchmarks/capture.py times a scene with its CCD rounds launched and as graphs, and finds
    the two runs bit-identical (every scene: tests/test_capture.py), and reports what a reused
    graph could save per launch."""
    from benchmarks import capture

    rows = capture.main(["--steps", "3", "--repeats", "1", "--scenes", "rigid_toss", "--out", str(tmp_path / "c")])
    assert [r["scene"] for r in rows] == ["rigid_toss"]
    assert all(r["bit_identical"] and len(r["captured_ms"]) == 1 for r in rows)
    assert "| rigid_toss |" in _read(tmp_path / "c")
    assert "runs to repay the recording" in _read(tmp_path / "c")  # the launch costs' table
    with pytest.raises(SystemExit):
        capture.main(["--scenes", "nope"])


def test_tunnel_seeds_tiny_and_resumes(tmp_path, monkeypatch):
    """One seed, two iterations: the report counts it; a second call finds it done (no rerun)."""
    from benchmarks import tunnel_seeds

    out = str(tmp_path / "ts")
    assert tunnel_seeds.main(["--first", "0", "--last", "1", "--iters", "2", "--out", out]) == 0
    rows = json.loads((tmp_path / "ts.json").read_text())["rows"]
    assert [r["seed"] for r in rows] == [0] and not rows[0]["reached"]
    assert "**0 / 1**" in (tmp_path / "ts.md").read_text()
    (tmp_path / "ts.md").unlink()
    monkeypatch.setattr(tunnel_seeds, "run_seed", None)  # a rerun would fail: the seed comes from the file
    assert tunnel_seeds.main(["--first", "0", "--last", "1", "--iters", "2", "--out", out]) == 0
    assert json.loads((tmp_path / "ts.json").read_text())["rows"] == rows and (tmp_path / "ts.md").exists()


def test_cloth_toss_rounding_counts_the_rollouts_where_the_copies_agree():
    """``benchmarks/cloth_toss_rounding.py``'s summary: the first rollouts on which every copy's
    loss has the same 3 significant digits (the run itself is the benchmark's, minutes long)."""
    from benchmarks.cloth_toss_rounding import agreeing_rollouts

    rows = [{"losses": [0.3071, 0.2254, 0.1640, 0.1118, 0.111]},
            {"losses": [0.3072, 0.2251, 0.1641, 0.1111, 0.0379]},
            {"losses": [0.3074, 0.2252, 0.1643, 0.1112, 0.0340]}]
    assert agreeing_rollouts(rows) == 3  # 0.112 against 0.111 at the 4th
    assert agreeing_rollouts(rows, digits=2) == 4
    assert agreeing_rollouts(rows[:1]) == 5
