"""Host reads of the collision stage per substep: how often a substep brings device data to the
host (``core.buffers.host``: a counter, a flag or positions; ``wp.array.numpy``).

    python benchmarks/host_reads.py [--steps N] [--out benchmarks/results/host_reads]

Each read is a synchronisation point: a step that reads a count between two launches cannot be
recorded as one graph (``wp.ScopedCapture``) and, on a GPU, waits for the device each time. On the
CPU a ``host`` view costs no copy, so these counts say how far the stage is from a capturable
substep, not what it costs here. The run takes the device's path (:data:`core.buffers.PEEK` off:
no look at a count that a GPU would have to copy). Per scene (defaults, both responses,
``--steps`` steps from the start), also per CCD round's detection
(:meth:`sim.contact.detect.ContactDetection.ccd_detect`: for the Gauss-Seidel response the
whole round; the replayed round then reads its approaching hits' count and the grown contact
set's, and its solves read their sizes) and how many rounds left the broad-phase cover's room,
which the host then tests.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import os
import sys
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from benchmarks import report  # noqa: E402

SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid")
RESPONSES = ("replayed", "gauss-seidel")
READERS = ("sim.contact.detect", "sim.contact.response", "sim.contact.replayed",
           "sim.contact.contacts", "sim.contact.record", "collision.narrow_phase", "collision.broad_phase")
"""The modules of the collision stage that read device data through ``host`` (imported by name
from :mod:`core.buffers`); the buffers' own writes through it (``upload``, ``zero``) are not
reads and are not counted."""


def count_reads(steps: int) -> list[dict[str, Any]]:
    """Per scene and response: the ``host()`` and ``wp.array.numpy()`` calls made inside the
    collision stage's calls (``ImpulseCollisionHandler.__call__``), per substep, over ``steps``
    steps (on a GPU ``host`` calls ``numpy``: a read counts in both columns there)."""
    import warp as wp

    import core.buffers as buffers
    from sim.contact.detect import ContactDetection
    from sim.contact.response import ImpulseCollisionHandler

    counts: collections.Counter = collections.Counter()
    inside = [0]
    original_host, original_numpy, original_call = buffers.host, wp.array.numpy, ImpulseCollisionHandler.__call__
    original_round, original_host_round, original_peek = (ContactDetection.ccd_detect,
                                                          ContactDetection._host_tested_round, buffers.PEEK)
    in_round = [False]
    in_host = [False]  # numpy() inside host() (its view of a CPU array) is that read, not another
    context = [None]  # "start" (the substep's cover and proximity pass) or "query" (a fresh broad-phase query)
    starts = {name: getattr(ContactDetection, name) for name in ("cover", "proximity", "proximity_hits")}
    original_fresh = ContactDetection._fresh_cover

    def counting_host(arr):
        counts["host"] += inside[0] > 0
        counts["round_host"] += in_round[0]
        counts[f"{context[0]}_host"] += context[0] is not None
        in_host[0] = True
        try:
            return original_host(arr)
        finally:
            in_host[0] = False

    def in_context(name, method):
        def counted(self, *args, **kwargs):
            outer, context[0] = context[0], (context[0] if context[0] == "query" else name)
            counts[name] += name == "query"
            try:
                return method(self, *args, **kwargs)
            finally:
                context[0] = outer
        return counted

    def counting_round(self, *args):
        counts["rounds"] += 1
        in_round[0] = True
        try:
            return original_round(self, *args)
        finally:
            in_round[0] = False

    def counting_host_round(self, *args):
        counts["host_tested"] += 1
        return original_host_round(self, *args)

    core_dir = os.path.join(ROOT, "core") + os.sep

    def counting_numpy(self):
        # not the buffers' own host views (core: a CPU zero fill or upload writes through one)
        counts["numpy"] += inside[0] > 0 and not in_host[0] and not sys._getframe(1).f_code.co_filename.startswith(core_dir)
        return original_numpy(self)

    def counting_call(self, *args):
        inside[0] += 1
        try:
            return original_call(self, *args)
        finally:
            inside[0] -= 1

    modules = [importlib.import_module(name) for name in READERS]
    missing = [m.__name__ for m in modules if getattr(m, "host", None) is not original_host]
    if missing:
        raise RuntimeError(f"these modules no longer read through core.buffers.host: {missing}")
    for m in modules:
        m.host = counting_host
    wp.array.numpy = counting_numpy
    ImpulseCollisionHandler.__call__ = counting_call
    ContactDetection.ccd_detect = counting_round
    ContactDetection._host_tested_round = counting_host_round
    for name, method in starts.items():
        setattr(ContactDetection, name, in_context("start", method))
    ContactDetection._fresh_cover = in_context("query", original_fresh)
    buffers.PEEK = False
    rows = []
    try:
        from scenes.sim_common import default_args, simulate

        for name in SCENES:
            module = importlib.import_module(f"scenes.{name}")
            for response in RESPONSES:
                counts.clear()
                summary, _ = simulate(module.build, default_args(steps=steps, response=response), None,
                                      name=name, progress=False)
                substeps = steps * summary["substeps"]
                rounds = counts["rounds"]
                rows.append({"scene": name, "response": response, "substeps": substeps,
                             "host_per_substep": counts["host"] / substeps,
                             "numpy_per_substep": counts["numpy"] / substeps,
                             "ccd_rounds_per_substep": rounds / substeps if rounds else None,
                             "host_per_ccd_round": counts["round_host"] / rounds if rounds else None,
                             "host_at_start_per_substep": counts["start_host"] / substeps,
                             "fresh_queries_per_substep": counts["query"] / substeps,
                             "host_per_fresh_query": counts["query_host"] / counts["query"] if counts["query"] else None,
                             "host_tested_rounds": counts["host_tested"]})
    finally:
        for m in modules:
            m.host = original_host
        wp.array.numpy = original_numpy
        ImpulseCollisionHandler.__call__ = original_call
        ContactDetection.ccd_detect = original_round
        ContactDetection._host_tested_round = original_host_round
        for name, method in starts.items():
            setattr(ContactDetection, name, method)
        ContactDetection._fresh_cover = original_fresh
        buffers.PEEK = original_peek
    return rows


def main(argv=None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60, help="steps per scene (default 60)")
    parser.add_argument("--out", default=os.path.join(report.RESULTS, "host_reads"))
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    rows = count_reads(args.steps)
    lines = [f"Host reads inside the collision stage's calls, per substep, {args.steps} steps of each scene from "
             "the start (defaults: 1/60 s, 8 substeps), on the device's path (no look at a count that a GPU would "
             "copy): `host()` calls, and the other `numpy()` calls (not the buffers' own views, through which a CPU "
             "zero fill or upload writes). Split into the substep's start "
             "(the broad-phase cover's test and the proximity pass: one read, which also settles the cover; a "
             "second when the kept cover failed and the pass ran again), each CCD round's detection (for the "
             "Gauss-Seidel response the whole round; the replayed round then reads its approaching hits' count "
             "and the grown contact set's, and its exact solves read their sizes and decisions), and the fresh "
             "broad-phase queries (the positions and the candidates' counts read), with the rounds whose motion "
             "left the cover, which the host then tests.", ""]
    lines += report.table(["scene", "response", "host() per substep", "numpy() per substep", "host() at the start",
                           "CCD rounds per substep", "host() per CCD detection", "fresh queries per substep",
                           "host() per fresh query", "rounds tested on the host"],
                          [[r["scene"], r["response"], r["host_per_substep"], r["numpy_per_substep"],
                            r["host_at_start_per_substep"],
                            "-" if r["ccd_rounds_per_substep"] is None else r["ccd_rounds_per_substep"],
                            "-" if r["host_per_ccd_round"] is None else r["host_per_ccd_round"],
                            r["fresh_queries_per_substep"],
                            "-" if r["host_per_fresh_query"] is None else r["host_per_fresh_query"],
                            r["host_tested_rounds"] if r["ccd_rounds_per_substep"] else "-"] for r in rows])
    report.write(args.out, "Host reads per substep", lines, {"steps": args.steps, "rows": rows})
    return rows


if __name__ == "__main__":
    main()
