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


@pytest.mark.parametrize("name,response", [("rigid_toss", "gauss-seidel"), ("cloth_rigid", "gauss-seidel"),
                                           ("rigid_toss", "replayed")])
def test_a_substep_start_reads_the_host_once_unless_its_cover_is_queried_afresh(name, response, monkeypatch):
    """The start of each substep (the broad-phase cover's test and the proximity pass's
    detection; for Gauss-Seidel the whole pass) calls ``host`` once on the device path: the
    pass's counts, which settle the cover's test (a kernel) and the pairs kept for the rounds; no
    position is read. A substep whose motion left
    the kept cover queries afresh (the positions read, and its pass then runs again) and reads
    more; those are counted apart."""
    monkeypatch.setattr(buffers, "PEEK", False)
    starts, context, depth = [], [None], [0]
    original_host = detect.host

    def counting_host(arr):
        if context[0] is not None:
            context[0][0 if context[0][2] == 0 else 1] += 1
        return original_host(arr)

    originals = {m: getattr(detect.ContactDetection, m) for m in ("cover", "proximity", "proximity_hits",
                                                                    "_fresh_cover")}

    def start_stage(method):
        def counted(self, *args, **kwargs):
            if method == "cover":  # a substep starts: [reads, reads in fresh queries, inside a query]
                context[0] = [0, 0, 0]
                starts.append(context[0])
            if method == "_fresh_cover":
                context[0][2] += 1
            depth[0] += 1
            try:
                return originals[method](self, *args, **kwargs)
            finally:
                depth[0] -= 1
                if method == "_fresh_cover":
                    context[0][2] -= 1
                    context[0].append("fresh")
                elif method != "cover" and depth[0] == 0:
                    context[0] = None  # the pass's detection ends (the replayed response's solve follows)
        return counted

    import collision.broad_phase as broad_phase
    import collision.narrow_phase as narrow_phase

    for module in (detect, narrow_phase, broad_phase):
        monkeypatch.setattr(module, "host", counting_host)
    for method in originals:
        monkeypatch.setattr(detect.ContactDetection, method, start_stage(method))

    _run(name, 30, response)
    kept = [s[0] for s in starts if "fresh" not in s]
    fresh = [s for s in starts if "fresh" in s]
    assert len(starts) == 240 and len(kept) >= 100, (len(starts), len(kept))
    assert set(kept) == {1}, np.unique(kept, return_counts=True)
    # a fresh query reads the positions (2) and the broad phase's counts; its pass reads its
    # counts once (none without a candidate), twice when a kept cover failed first
    assert all(s[1] >= 2 and s[0] <= 2 for s in fresh), fresh
