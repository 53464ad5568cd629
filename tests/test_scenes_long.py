"""Every simulation scene for 2000 steps: no interpenetration, bounded energy, bit-identical reruns.

Per scene, one in-process run (no recording) of :data:`LONG_STEPS` steps at the scene's defaults
(dt 1/60 s, 8 substeps), with the independent checker of :mod:`sim.penetration` evaluated on
every frame's end state (``penetrations`` is the worst frame, ``penetration_frames`` the count of
frames with any). Then the scene's first :data:`RERUN_STEPS` steps (its landing and first contacts
included) again through ``python -m scenes NAME --steps 200 --out X.rrd`` in a fresh process: its
final state must hash to the same SHA-256 as the long run's state at that step (bit for bit: the
response is sequential and every reduction has a fixed order), and the recording must read back
with ``rerun.chunk.RrdReader`` holding every frame.

What each scene shows is checked on the final state: the cloth settles on the sphere and the box
(cloth_drop), box A knocks box B along the ground and both come to rest on it (rigid_toss), the
ball is caught and slowed by the cloth and ends on the floor (cloth_rigid).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scenes import cloth_drop, cloth_rigid, rigid_toss, sim_common

REPO = Path(__file__).resolve().parents[1]
LONG_STEPS = 2000
RERUN_STEPS = 200
"""The fresh-process rerun's length (3.3 s of simulated time): past every scene's first contacts
(asserted), at a tenth of the long run's cost."""
SCENES = {"cloth_drop": cloth_drop, "rigid_toss": rigid_toss, "cloth_rigid": cloth_rigid}
ENERGY_GROWTH_LIMIT = 1.01
"""Total energy may never exceed its initial value by more than 1 %: gravity, springs and
impulses without restitution only dissipate; the proximity push that keeps resting contacts
apart (a tenth of the missing separation per substep) adds at most a few parts in 10^4."""


def _read_rrd(path: Path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def _check_outcome(name: str, final: dict) -> None:
    x, v = final["particle_q"], final["particle_qd"]
    bq, bv = final["body_q"], final["body_qd"]
    if name == "cloth_drop":
        # settled: slow, above the ground, draped over the sphere (top at z = 0.4) and the box.
        # The median particle: a few particles of the resting cloth still jitter (measured over
        # the last 500 of 2000 steps: the median particle's speed at most 0.006 m/s, the fastest
        # particle's up to 0.25 m/s in single frames, above 0.05 m/s in a quarter of them)
        speed = np.linalg.norm(v, axis=1)
        assert np.median(speed) < 0.02 and speed.max() < 0.5, (np.median(speed), speed.max())
        assert x[:, 2].min() >= -1e-9
        centre = np.array(cloth_drop.SPHERE_CENTRE)
        near_top = np.linalg.norm(x[:, :2] - centre[:2], axis=1) < 0.05
        assert near_top.any() and x[near_top, 2].min() > 0.39
    elif name == "rigid_toss":
        # box B was knocked along +x, and both boxes rest on the ground (centres 0.1 m up)
        assert bq[1, 0] > rigid_toss.REST_POS[0] + 0.05, bq[1]
        assert np.all(np.abs(bq[:, 2] - rigid_toss.BOX_HALF) < 0.01), bq[:, 2]
        assert np.abs(bv).max() < 0.1, bv
    elif name == "cloth_rigid":
        # the ball ends on the floor (centre one radius up), at rest or rolling slowly
        assert abs(bq[0, 2] - cloth_rigid.BALL_RADIUS) < 0.01, bq[0]
        assert np.linalg.norm(bv[0, 3:]) < 2.0, bv[0]


# the longest run gets a worker of its own; the other two share the second (make test: -n 2
# --dist loadgroup), so the three never queue behind each other on one worker
WORKER_GROUP = {"cloth_drop": "long_a", "rigid_toss": "long_b", "cloth_rigid": "long_b"}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.xdist_group(WORKER_GROUP[n])) for n in sorted(SCENES)]
)
def test_2000_steps_no_penetration_bounded_energy_bit_identical_rerun(name, tmp_path):
    module = SCENES[name]
    at_rerun = {}

    def observe(step, state, info):
        at_rerun["contacts"] = at_rerun.get("contacts", 0) + len(info["contacts"]["points"])
        if step == RERUN_STEPS:
            at_rerun.update(state_sha256=sim_common.state_sha256(state.numpy()),
                            energy_final=info["kinetic"] + info["potential"], total_contacts=at_rerun["contacts"])

    summary, final = sim_common.simulate(
        module.build, sim_common.default_args(steps=LONG_STEPS), None, name=name, progress=False, observer=observe)
    assert summary["steps"] == LONG_STEPS
    assert summary["penetrations"] == 0 and summary["penetration_frames"] == 0, summary
    assert summary["max_penetration_depth"] == 0.0
    assert summary["energy_finite"]
    assert summary["energy_max_ratio"] <= ENERGY_GROWTH_LIMIT, summary["energy_max_ratio"]
    assert summary["contacts"] > 0
    _check_outcome(name, final)

    out = tmp_path / f"{name}.rrd"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-m", "scenes", name, "--out", str(out), "--steps", str(RERUN_STEPS)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rerun = json.loads(proc.stdout.splitlines()[-1])
    assert rerun["steps"] == RERUN_STEPS
    assert rerun["state_sha256"] == at_rerun["state_sha256"]
    assert rerun["contacts"] == at_rerun["total_contacts"] > 0
    assert rerun["energy_final"] == at_rerun["energy_final"]
    assert rerun["penetrations"] == 0
    assert rerun["failsafe_count"] <= summary["failsafe_count"]  # the counter only grows
    rows = _read_rrd(out)
    assert rows.get("/metrics/energy/total", 0) == RERUN_STEPS
    assert rows.get("/metrics/penetrations", 0) == RERUN_STEPS
    if "cloth" in summary["components"]:
        assert rows.get("/world/cloth", 0) >= RERUN_STEPS
    if "rigid" in summary["components"]:
        assert rows.get("/world/bodies/0", 0) >= RERUN_STEPS
