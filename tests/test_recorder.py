"""sim.recorder.SimRecorder: entity tree, static topology logged once, per-frame values read back
with ``rerun.chunk.RrdReader``, timelines, determinism and the interrupted-run outcome."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from sim.builder import ModelBuilder
from sim.logging import RerunLogger
from sim.mesh_io import box_mesh
from sim.recorder import Contacts, SimRecorder

CLOTH = dict(density=0.2, stretch_stiffness=1e3, shear_stiffness=1e2, bend_stiffness=10.0, damping=0.1)
FRAMES = 6
DT = 0.01


@pytest.fixture(scope="module")
def model():
    """4 x 4 cloth grid, one rigid box, one static box, a ground plane."""
    b = ModelBuilder()
    b.add_cloth_grid((-0.5, -0.5, 1.0), None, 4, 4, 0.25, 0.25, **CLOTH)
    b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(0.0, 0.0, 0.5))
    b.add_static_mesh(*box_mesh(0.2), pos=(1.0, 0.0, 0.2))
    b.add_ground_plane()
    return b.finalize("cpu")


def _angle_quat(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def _frame_state(model, k: int, as_state: bool):
    """Hand-made state of frame k: cloth falls and waves, the box drops and spins."""
    s = model.state()
    q = s.particle_q.numpy()
    q[:, 2] -= 0.05 * k
    q[:, 0] += 0.01 * k * np.sin(q[:, 1])
    bq = s.body_q.numpy()
    bq[0, 2] -= 0.03 * k
    bq[0, 3:] = _angle_quat(0.2 * k)
    if as_state:
        s.particle_q = wp.array(q, dtype=wp.vec3d)
        s.body_q = wp.array(bq, dtype=wp.transformd)
        return s, q, bq
    return {"particle_q": q, "body_q": bq}, q, bq


def _contacts(k: int, q: np.ndarray):
    if k % 2:
        return None
    n = k // 2 + 1
    return Contacts(points=q[:n], normals=np.tile([0.0, 0.0, 2.0], (n, 1)), toi=np.linspace(0.1, 0.9, n))


def _write(path: Path, model, frames: int = FRAMES, fail_at: int | None = None, seed: int = 3):
    logged = []
    with SimRecorder(path, model, application_id="test_recorder", seed=seed) as rec:
        for k in range(frames):
            if k == fail_at:
                raise RuntimeError("injected failure")
            state, q, bq = _frame_state(model, k, as_state=bool(k % 2))
            metrics = {"energy": 1.0 / (k + 1), "solver/iters": k}
            rec.record(k, k * DT, state, contacts=_contacts(k, q), metrics=metrics)
            logged.append((q, bq))
    return logged


def read(path: Path):
    """Per entity: static rows, temporal rows, columns (static / temporal), and the temporal data
    sorted by frame as {column: [values...]} (python objects via pyarrow)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    info = {
        "recordings": reader.recordings(),
        "blueprints": reader.blueprints(),
        "static_rows": defaultdict(int),
        "rows": defaultdict(int),
        "static_cols": defaultdict(set),
        "cols": defaultdict(set),
        "timelines": defaultdict(set),
        "static_data": defaultdict(dict),
        "data": defaultdict(lambda: defaultdict(list)),
    }
    for chunk in reader.stream().to_chunks():
        e = chunk.entity_path
        rb = chunk.to_record_batch()
        names = [f.name for f in rb.schema if not f.name.startswith("rerun.")]
        comps = {n for n in names if ":" in n}
        if chunk.is_static:
            info["static_rows"][e] += chunk.num_rows
            info["static_cols"][e] |= comps
            for n in comps:
                info["static_data"][e][n] = rb.column(n).to_pylist()[-1]
        else:
            info["rows"][e] += chunk.num_rows
            info["cols"][e] |= comps
            info["timelines"][e] |= set(chunk.timeline_names)
            frames = rb.column("frame").to_pylist()
            for n in comps | ({"sim_time"} & set(chunk.timeline_names)):
                for f, v in zip(frames, rb.column(n).to_pylist()):
                    info["data"][e][n].append((f, v))
    for e in info["data"]:
        for n in info["data"][e]:
            info["data"][e][n].sort(key=lambda fv: fv[0])
    return info


def status(info) -> str:
    (text,) = info["static_data"]["/status"]["TextDocument:text"]
    return text


@pytest.fixture(scope="module")
def recording(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "run.rrd"
    logged = _write(path, model)
    return path, logged, read(path)


def test_file_has_the_expected_entities(recording):
    path, _, info = recording
    assert [p.name for p in path.parent.iterdir()] == ["run.rrd"], "temporary file left behind"
    assert info["recordings"] and info["blueprints"], "recording and default blueprint"
    static = {"/world", "/world/cloth", "/world/bodies/0", "/world/static/0", "/world/planes/0", "/status"}
    assert static <= set(info["static_rows"])
    temporal = {
        "/world/cloth",
        "/world/bodies/0",
        "/world/contacts/points",
        "/world/contacts/normals",
        "/metrics/energy",
        "/metrics/solver/iters",
        "/metrics/contacts/count",
        "/metrics/contacts/time_of_impact",
    }
    assert temporal <= set(info["rows"])
    assert "/world/particles" not in info["rows"]  # every particle is in a triangle


def test_frames_and_timelines(recording):
    _, _, info = recording
    for e in ("/world/cloth", "/world/bodies/0", "/metrics/energy", "/world/contacts/points"):
        assert info["rows"][e] == FRAMES, e
        assert info["timelines"][e] == {"frame", "sim_time"}, (e, info["timelines"][e])
        frames = [f for f, _ in info["data"][e]["sim_time"]]
        assert frames == list(range(FRAMES))
        times = [t for _, t in info["data"][e]["sim_time"]]
        assert np.allclose([t.total_seconds() if hasattr(t, "total_seconds") else t * 1e-9 for t in times],
                           DT * np.arange(FRAMES))  # fmt: skip
    # contacts only on even frames; time of impact is the frame's earliest
    assert info["rows"]["/metrics/contacts/time_of_impact"] == len(range(0, FRAMES, 2))


def test_static_topology_logged_once(recording, model):
    _, _, info = recording
    assert info["static_rows"]["/world/cloth"] == 1
    assert "Mesh3D:triangle_indices" in info["static_cols"]["/world/cloth"]
    assert "Mesh3D:vertex_positions" not in info["static_cols"]["/world/cloth"]  # would shadow frames
    assert info["cols"]["/world/cloth"] == {"Mesh3D:vertex_positions"}  # per frame: positions only
    tris = np.array(info["static_data"]["/world/cloth"]["Mesh3D:triangle_indices"])
    assert np.array_equal(tris, model.tri_indices.numpy())
    for e in ("/world/bodies/0", "/world/static/0", "/world/planes/0"):
        assert info["static_rows"][e] == 1
        assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices"} <= info["static_cols"][e]
    assert info["cols"]["/world/bodies/0"] == {"Transform3D:translation", "Transform3D:quaternion"}
    # body mesh in body frame (centred at the com), static box in world frame
    bv = np.array(info["static_data"]["/world/bodies/0"]["Mesh3D:vertex_positions"])
    assert np.allclose(bv, model.shape_vertices.numpy(), atol=1e-7)
    sv = np.array(info["static_data"]["/world/static/0"]["Mesh3D:vertex_positions"])
    assert np.allclose(sv, model.static_vertices.numpy(), atol=1e-7)
    plane = np.array(info["static_data"]["/world/planes/0"]["Mesh3D:vertex_positions"])
    assert np.allclose(plane[:, 2], 0.0) and np.ptp(plane[:, 0]) >= 20.0


def test_per_frame_values_read_back(recording):
    _, logged, info = recording
    cloth = info["data"]["/world/cloth"]["Mesh3D:vertex_positions"]
    trans = info["data"]["/world/bodies/0"]["Transform3D:translation"]
    quat = info["data"]["/world/bodies/0"]["Transform3D:quaternion"]
    for k, (q, bq) in enumerate(logged):
        assert np.allclose(np.array(cloth[k][1]), q, atol=1e-6)
        assert np.allclose(np.array(trans[k][1]).reshape(-1), bq[0, :3], atol=1e-6)
        assert np.allclose(np.array(quat[k][1]).reshape(-1), bq[0, 3:], atol=1e-6)
    energy = [v for _, v in info["data"]["/metrics/energy"]["Scalars:scalars"]]
    assert np.allclose(np.array(energy).reshape(-1), 1.0 / np.arange(1, FRAMES + 1))
    pts = info["data"]["/world/contacts/points"]["Points3D:positions"]
    assert [len(v) for _, v in pts] == [1, 0, 2, 0, 3, 0]  # odd frames cleared
    arrows = info["data"]["/world/contacts/normals"]["Arrows3D:vectors"]
    vec = np.array(arrows[4][1])  # normals (0, 0, 2) drawn unit-direction, contact_normal_length long
    assert vec.shape == (3, 3) and np.allclose(vec[:, :2], 0.0) and np.all(vec[:, 2] > 0)
    assert np.allclose(vec[:, 2], vec[0, 2])
    toi = [v for _, v in info["data"]["/metrics/contacts/time_of_impact"]["Scalars:scalars"]]
    assert np.allclose(np.array(toi).reshape(-1), 0.1)
    assert status(info) == f"complete: {FRAMES} frames"


def test_deterministic(model, tmp_path, recording):
    _, _, ref = recording
    path = tmp_path / "again.rrd"
    _write(path, model)
    info = read(path)
    assert info["recordings"][0].recording_id == ref["recordings"][0].recording_id
    for e in ref["data"]:
        for col, values in ref["data"][e].items():
            assert info["data"][e][col] == values, (e, col)
    for e in ref["rows"]:
        assert not {"log_time", "log_tick"} & info["timelines"][e]


def test_exception_mid_run_keeps_a_readable_file_of_the_frames_so_far(model, tmp_path):
    path = tmp_path / "broken.rrd"
    with pytest.raises(RuntimeError, match="injected failure"):
        _write(path, model, frames=FRAMES, fail_at=3)
    assert [p.name for p in tmp_path.iterdir()] == ["broken.partial.rrd"], "no temporary file may remain"
    info = read(tmp_path / "broken.partial.rrd")
    assert info["recordings"] and info["blueprints"]
    assert info["rows"]["/world/cloth"] == 3 and info["rows"]["/world/bodies/0"] == 3
    assert info["static_rows"]["/world/cloth"] == 1
    assert status(info) == (
        "interrupted after 3 frames: RuntimeError: injected failure"
    )


def test_keyboard_interrupt_also_finalises(model, tmp_path):
    path = tmp_path / "ctrl_c.rrd"
    with pytest.raises(KeyboardInterrupt):
        with SimRecorder(path, model, application_id="t", seed=0) as rec:
            rec.record(0, 0.0, model.state())
            raise KeyboardInterrupt
    assert not path.exists()
    info = read(tmp_path / "ctrl_c.partial.rrd")
    assert info["rows"]["/world/cloth"] == 1
    assert status(info).startswith("interrupted after 1 frames: KeyboardInterrupt")


def test_bad_arguments_leave_no_file(model, tmp_path):
    with pytest.raises(ValueError, match="contact_normal_length"):
        SimRecorder(tmp_path / "x.rrd", model, application_id="t", seed=0, contact_normal_length=-1.0)
    with pytest.raises(FileNotFoundError):
        SimRecorder(tmp_path / "missing" / "x.rrd", model, application_id="t", seed=0)
    assert not list(tmp_path.iterdir())
    path = tmp_path / "y.rrd"
    with SimRecorder(path, model, application_id="t", seed=0) as rec:
        with pytest.raises(ValueError, match="particles"):
            rec.record(0, 0.0, {"particle_q": np.zeros((3, 3)), "body_q": np.zeros((1, 7))})
        with pytest.raises(ValueError, match="frame"):
            rec.record(0.5, 0.0, model.state())
        with pytest.raises(ValueError, match="metric"):
            rec.record(0, 0.0, model.state(), metrics={"/abs": 1.0})
        with pytest.raises(ValueError, match="normals"):
            rec.record(0, 0.0, model.state(), contacts={"points": np.zeros((2, 3)), "normals": np.zeros((1, 3))})
    info = read(path)
    assert "/world/cloth" not in info["rows"]  # rejected frames logged nothing
    assert status(info) == "complete: 0 frames"
    with pytest.raises(RuntimeError, match="closed"):
        rec.record(1, 0.0, model.state())


def test_on_logger_and_loose_particles(tmp_path):
    b = ModelBuilder()
    b.add_particle((0.0, 0.0, 1.0))
    b.add_particle((0.5, 0.0, 1.0))
    b.add_ground_plane()
    m = b.finalize()
    path = tmp_path / "scene.rrd"
    with RerunLogger(path, application_id="t", recording_name="scene") as log:
        rec = SimRecorder.on_logger(log, m)
        for k in range(4):
            rec.record(k, k * 0.1, m.state(), metrics={"k": k})
        rec.close()
        log.log_scalars("/summary/x", [1.0])
    info = read(path)
    assert info["rows"]["/world/particles"] == 4 and "/world/cloth" not in info["rows"]
    assert info["rows"]["/metrics/k"] == 4 and "/summary/x" in info["rows"]
    assert status(info) == "complete: 4 frames"
    # the caller's logger owns the file: its error policy (no file) applies
    path2 = tmp_path / "scene2.rrd"
    with pytest.raises(RuntimeError):
        with RerunLogger(path2, application_id="t") as log:
            rec = SimRecorder.on_logger(log, m)
            rec.record(0, 0.0, m.state())
            raise RuntimeError("boom")
    assert not path2.exists()
