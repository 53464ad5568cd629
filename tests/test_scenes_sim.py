"""Simulation scenes ``cloth_drop``, ``rigid_toss``, ``cloth_rigid``: in-process runs and the CLI.

Each scene runs in-process twice for :data:`STEPS` steps (no recording): the summary's fields,
zero penetrations from the independent checker, finite energy, contacts, and bit-identical final
states (determinism). Each also runs once through ``python -m scenes NAME --steps 10`` into a
temporary ``.rrd``: exactly one JSON line on stdout with the summary fields, and the recording
reads back with ``rerun.chunk.RrdReader`` holding ``/world`` entities and per-frame metrics.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scenes import cloth_drop, cloth_rigid, rigid_toss, sim_common

REPO = Path(__file__).resolve().parents[1]
STEPS = 20
"""In-process steps: enough for first contact in every scene (cloth_drop touches the sphere
after ~15 steps, the ball reaches the cloth after ~4, box B rests on the ground from step 1)."""
CLI_STEPS = 10
SCENES = {"cloth_drop": cloth_drop, "rigid_toss": rigid_toss, "cloth_rigid": cloth_rigid}
SUMMARY_FIELDS = (
    "steps", "dt", "substeps", "stepping_seconds", "steps_per_second", "contacts", "penetrations",
    "max_penetration_depth", "energy_drift", "energy_max_ratio", "failsafe_count",
)
COMPONENTS = {
    "cloth_drop": ["cloth", "static"],
    "rigid_toss": ["rigid", "static"],
    "cloth_rigid": ["cloth", "rigid", "static"],
}


def simulate(name: str, steps: int = STEPS):
    module = SCENES[name]
    return sim_common.simulate(module.build, sim_common.default_args(steps=steps), None, name=name, progress=False)


@pytest.fixture(scope="module", params=sorted(SCENES))
def run_once(request):
    name = request.param
    summary, final = simulate(name)
    return name, summary, final


def test_summary_fields_and_no_penetrations(run_once):
    name, s, _ = run_once
    for key in SUMMARY_FIELDS:
        assert key in s, key
    assert s["steps"] == STEPS
    assert s["dt"] == pytest.approx(1.0 / 60.0)
    assert s["substeps"] == 8
    assert s["components"] == COMPONENTS[name]
    assert s["penetrations"] == 0
    assert s["max_penetration_depth"] == 0.0
    assert s["contacts"] > 0
    assert s["energy_finite"]
    assert math.isfinite(s["energy_drift"]) and math.isfinite(s["energy_final"])
    # no energy from nowhere beyond a modest margin (impulses and friction only dissipate)
    assert s["energy_max_ratio"] < 1.5
    json.dumps(s, allow_nan=False)


def test_deterministic(run_once):
    name, _, final = run_once
    _, again = simulate(name)
    for key in ("particle_q", "particle_qd", "body_q", "body_qd"):
        a, b = np.asarray(final[key]), np.asarray(again[key])
        assert a.shape == b.shape
        assert np.all(np.isfinite(a))
        assert a.tobytes() == b.tobytes(), f"{name}: {key} differs between two runs"


def read_rrd(path: Path) -> dict[str, int]:
    """Rows per entity path (static and temporal together)."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


@pytest.mark.parametrize("name", sorted(SCENES))
def test_cli(name, tmp_path):
    out = tmp_path / f"{name}.rrd"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-m", "scenes", name, "--out", str(out), "--steps", str(CLI_STEPS)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert len(lines) == 1, proc.stdout[:500]
    s = json.loads(lines[0])
    for key in (*SUMMARY_FIELDS, "wall_time_s", "out"):
        assert key in s, key
    assert s["steps"] == CLI_STEPS
    assert s["penetrations"] == 0
    assert s["energy_finite"]
    assert out.is_file()
    rows = read_rrd(out)
    world = [e for e in rows if e.startswith("/world")]
    assert world, sorted(rows)
    if name != "rigid_toss":
        assert rows.get("/world/cloth", 0) >= CLI_STEPS
    if name != "cloth_drop":
        assert rows.get("/world/bodies/0", 0) >= CLI_STEPS
    if name != "cloth_rigid":
        assert any(e.startswith("/world/static/") for e in rows)
    assert rows.get("/metrics/energy/total", 0) == CLI_STEPS
    assert rows.get("/metrics/penetrations", 0) == CLI_STEPS


def test_cli_options():
    """--dt/--substeps/--device parse with the documented defaults; --precision float32 is refused."""
    import argparse

    parser = argparse.ArgumentParser()
    cloth_drop.add_arguments(parser)
    args = parser.parse_args([])
    assert args.dt == pytest.approx(1 / 60) and args.substeps == 8 and args.device == "cpu"
    assert cloth_drop.SUPPORTS_STEPS and cloth_drop.PRECISIONS == ("float64",)
    with pytest.raises(SystemExit):
        parser.parse_args(["--substeps", "0"])
    with pytest.raises(SystemExit):  # not a Warp device (and no GPU is needed to say so)
        parser.parse_args(["--device", "tpu:7"])
    with pytest.raises(SystemExit):
        parser.parse_args(["--scale", "0"])
    assert parser.parse_args(["--scale", "1e-3"]).scale == 1e-3
    assert sim_common.ccd_options(args) == {}  # the defaults run the narrow phase as written
    knobs = parser.parse_args(["--ccd-precision", "float32", "--ccd-tolerance-scale", "0.5",
                               "--root-max-iterations", "6", "--root-tolerance", "1e-9"])
    assert sim_common.ccd_options(knobs) == {"precision": "float32", "tolerance_scale": 0.5, "max_iterations": 6,
                                             "tolerance": 1e-9}
    for bad in (["--ccd-precision", "float16"], ["--ccd-tolerance-scale", "0"], ["--root-max-iterations", "0"],
                ["--root-tolerance", "nan"]):
        with pytest.raises(SystemExit):
            parser.parse_args(bad)


@pytest.mark.parametrize("flags, named", [(["--root-tolerance", "1e-45"], "--root-tolerance"),
                                           (["--ccd-tolerance-scale", "1e-44"], "--ccd-tolerance-scale")])
def test_ccd_knobs_float32_cannot_hold_are_refused_before_the_run(tmp_path, capsys, flags, named):
    """Values each flag takes alone but float32 cannot represent are refused when the options are
    read (exit code 2, the flag named), not by an error once the scene is running, and nothing
    is written; with float64 the same value runs."""
    from scenes.__main__ import main

    out = tmp_path / "x.rrd"
    with pytest.raises(SystemExit) as exc:
        main(["rigid_toss", "--out", str(out), "--steps", "1", "--ccd-precision", "float32", *flags])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert named in err and "float32" in err
    assert not out.exists()
    assert main(["rigid_toss", "--out", str(out), "--steps", "1", *flags]) == 0 and out.exists()


def test_bad_scene_input_writes_no_file(tmp_path, monkeypatch):
    """A scene whose geometry is bad (a NaN vertex) fails while it is built, before the first
    frame: exit code 1, an error naming the argument, and no recording left behind."""
    from scenes.__main__ import main

    def bad_build(builder, args):
        from sim.mesh_io import box_mesh

        v, t = box_mesh(0.1)
        v[3, 2] = np.nan
        builder.add_static_mesh(v, t)

    monkeypatch.setattr(cloth_drop, "build", bad_build)
    out = tmp_path / "bad.rrd"
    assert main(["cloth_drop", "--out", str(out), "--steps", "2"]) == 1
    assert not out.exists()
    assert not list(tmp_path.iterdir())  # no temporary file either


def test_interrupted_run_keeps_a_readable_partial_recording(tmp_path, monkeypatch, capsys):
    """Ctrl-C during stepping: exit code 130 and the frames recorded so far stay readable."""
    from scenes.__main__ import main
    from sim.integrators.semi_implicit import SemiImplicitIntegrator

    real_step = SemiImplicitIntegrator.step
    calls = {"n": 0}

    def step(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real_step(self, *a, **k)

    monkeypatch.setattr(SemiImplicitIntegrator, "step", step)
    out = tmp_path / "run.rrd"
    out.write_bytes(b"an earlier recording")
    assert main(["rigid_toss", "--out", str(out), "--steps", "50"]) == 130
    err = capsys.readouterr().err
    assert f"the frames recorded so far are in {tmp_path / 'run.partial.rrd'}" in err
    assert f"{out} is untouched" in err
    assert out.read_bytes() == b"an earlier recording"  # a failed run never replaces a finished one
    rows = read_rrd(tmp_path / "run.partial.rrd")
    assert rows.get("/metrics/energy/total", 0) == 3
    assert rows.get("/status", 0) >= 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.partial.rrd", "run.rrd"]


def test_too_few_substeps_stop_with_a_clear_error():
    """Explicit springs blow up when the substep is too long for their stiffness: the run stops
    within seconds with an error that names the setting to change, instead of grinding through
    an exploding cloth."""
    with pytest.raises(sim_common.SimulationDiverged, match="--substeps"):
        sim_common.simulate(cloth_drop.build, sim_common.default_args(steps=60, substeps=3), None,
                            name="cloth_drop", progress=False)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_replayed_response_keeps_scenes_penetration_free(name):
    """``--response replayed`` (the exact solve that rollouts differentiate) on every scene:
    contacts happen, the independent checker finds no penetration on any frame, energy bounded,
    and :func:`sim.rollout.rollout` of the same model reproduces the run bit for bit.
    The replayed response restores the separation at the position level (the push lifts resting
    cloth without a velocity), which adds potential energy: cloth_drop peaks at 1.012x its
    initial energy in its first 20 steps (measured), hence 1.02."""
    module = SCENES[name]
    args = sim_common.default_args(steps=STEPS, response="replayed")
    summary, _ = sim_common.simulate(module.build, args, None, name=name, progress=False)
    assert summary["contacts"] > 0
    assert summary["penetrations"] == 0 and summary["penetration_frames"] == 0
    assert summary["energy_finite"] and summary["energy_max_ratio"] <= 1.02
    # one forward function: the differentiable rollout of the same model ends in the same bits
    # (the summary's state_sha256 hashes the final positions and velocities)
    from sim.rollout import rollout

    res = rollout(sim_common.build_model(module.build, args), STEPS, args.dt, args.substeps)
    final = {key: getattr(res, key)[-1].detach().numpy()
             for key in ("particle_q", "particle_qd", "body_q", "body_qd")}
    assert sim_common.state_sha256(final) == summary["state_sha256"], "the scene run and rollout() differ"


def test_grazing_scene_cli(tmp_path):
    """``python -m scenes grazing``: JSON summary with both gradient curves, and the recording."""
    out = tmp_path / "g.rrd"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-m", "scenes", "grazing", "--out", str(out), "--points", "3"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.splitlines()[-1])
    assert summary["free_flight_gradient"] == pytest.approx(1 / 60.0, rel=1e-12)
    assert len(summary["mollified"]) == len(summary["unmollified"]) == 3
    assert summary["offsets"] == pytest.approx([1e-1, 1e-6, 1e-11])
    assert summary["contacts"] == [1, 1, 1]
    assert summary["miss_gradients"] == pytest.approx([summary["free_flight_gradient"]] * 3, rel=1e-12)
    # a true double root: the mollified gradient (M = 1000) bounded, the unmollified one blowing up
    assert summary["max_mollified_over_free"] <= 1.2 * 1000 + 2  # tests/test_rollout.py mollified_bound
    assert summary["max_unmollified_over_free"] >= 10 * summary["max_mollified_over_free"]
    from rerun.chunk import RrdReader

    entities = {chunk.entity_path for chunk in RrdReader(out).stream().to_chunks()}
    assert "/metrics/gradient/mollified" in entities and "/metrics/gradient/unmollified" in entities


def test_grazing_scene_rejects_a_one_point_sweep(tmp_path):
    out = tmp_path / "g.rrd"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-m", "scenes", "grazing", "--out", str(out), "--points", "1"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "--points" in proc.stderr
    assert not out.exists()


def test_float32_ccd_decisions_keep_rigid_toss_penetration_free():
    """``--ccd-precision float32 --root-max-iterations 8``: the contacts are decided by the
    float32 narrow phase (the summary says so), the independent float64 checker finds no
    penetration, and energy stays bounded."""
    args = sim_common.default_args(steps=STEPS, ccd_precision="float32", root_max_iterations=8)
    summary, _ = sim_common.simulate(rigid_toss.build, args, None, name="rigid_toss", progress=False)
    assert summary["ccd_options"] == {"precision": "float32", "max_iterations": 8}
    # and the handler's narrow phase really runs the float32 variant
    from sim.contact.response import ImpulseCollisionHandler
    from scenes.sim_common import build_model, ccd_options

    narrow = ImpulseCollisionHandler(build_model(rigid_toss.build, args), ccd_options=ccd_options(args)).detect.narrow
    assert narrow._float32 and narrow.settings.max_iterations == 8
    assert summary["contacts"] > 0
    assert summary["penetrations"] == 0 and summary["penetration_frames"] == 0
    assert summary["energy_finite"] and summary["energy_max_ratio"] <= 1.01
