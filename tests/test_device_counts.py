"""The collision stage's counts stay on the device: a CCD round's detection (for the
Gauss-Seidel response the whole round) brings its counts to the host in one read
(:meth:`sim.contact.detect.ContactDetection.read_counts`), and the launches over bounds that a
GPU runs (no peeking at the counts, :data:`core.buffers.PEEK`) give the same trajectories, bit
for bit, as the CPU's launches over the exact counts, with either response."""

import importlib

import numpy as np
import pytest

import core.buffers as buffers
import sim.contact.detect as detect
from scenes.sim_common import default_args, simulate

SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid")


def _run(name: str, steps: int, response: str = "gauss-seidel") -> str:
    module = importlib.import_module(f"scenes.{name}")
    summary, _ = simulate(module.build, default_args(steps=steps, response=response), None, name=name,
                          progress=False)
    return summary["state_sha256"]


@pytest.mark.parametrize("name,response", [(name, "gauss-seidel") for name in SCENES]
                         + [("rigid_toss", "replayed"), ("cloth_rigid", "replayed")])
def test_launches_over_bounds_give_the_same_trajectory(name, response, monkeypatch):
    """The device path (every pass launched over its bound, the counts read by the kernels) and
    the CPU path (launches over the peeked counts) end in the same state, bit for bit, after
    steps with resting and impact contacts. (The replayed response shares the detection; its
    cloth is ``cloth_rigid``'s: ``cloth_drop``'s resting cloth costs 30 s per pair of runs.)"""
    steps = {"cloth_drop": 40, "rigid_toss": 40, "cloth_rigid": 60}[name]
    peeked = _run(name, steps, response)
    monkeypatch.setattr(buffers, "PEEK", False)
    assert _run(name, steps, response) == peeked


@pytest.mark.parametrize("response,counted", [("gauss-seidel", "ccd_round"), ("replayed", "ccd_detect")])
def test_a_ccd_round_reads_the_host_once(response, counted, monkeypatch):
    """Inside each CCD round of ``rigid_toss`` (a box bouncing and coming to rest) the stage
    calls ``host`` once, on the device path: the round's counts, the broad-phase cover tested on
    the device, no per-contact or per-stage read and no end position on the host. For
    Gauss-Seidel the whole round (``ccd_round``); the replayed response's rounds detect their
    hits the same way (``ccd_detect``; their solves then read their sizes). A round whose motion
    left the cover (rare) is run again with the host's test."""
    monkeypatch.setattr(buffers, "PEEK", False)
    reads, rounds = [0], []
    original_host, original_round = detect.host, getattr(detect.ContactDetection, counted)
    counting = [False]

    def counting_host(arr):
        reads[0] += counting[0]
        return original_host(arr)

    def counting_round(self, *args):
        counting[0], reads[0] = True, 0
        host_tested = self.host_tested_rounds
        try:
            return original_round(self, *args)
        finally:
            counting[0] = False
            rounds.append((reads[0], self.host_tested_rounds - host_tested))

    import collision.broad_phase as broad_phase
    import collision.narrow_phase as narrow_phase

    for module in (detect, narrow_phase, broad_phase):
        monkeypatch.setattr(module, "host", counting_host)
    monkeypatch.setattr(detect.ContactDetection, counted, counting_round)
    _run("rigid_toss", 30, response)
    rounds = np.array(rounds)
    assert len(rounds) > 100
    on_device = rounds[rounds[:, 1] == 0, 0]
    assert (on_device == 1).all(), np.unique(on_device, return_counts=True)
    assert len(on_device) > 0.9 * len(rounds)
