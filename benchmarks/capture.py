"""The Gauss-Seidel response's CCD rounds recorded as a Warp graph, against the same rounds launched
one by one, on the three simulation scenes.

    python benchmarks/capture.py [--steps N] [--repeats R] [--scenes A,B] [--out benchmarks/results/capture]

Per scene (defaults, ``--response gauss-seidel``), the scene run of :func:`scenes.sim_common.simulate`
with the handler's ``capture_rounds`` off and on (interleaved, ``--repeats`` times each, after a
warm-up run that compiles and loads every kernel): ms per step, the SHA-256 of the final state
(the two must match bit for bit), and the graphs launched. With ``capture_rounds`` each substep's
CCD rounds after its first contact are recorded (``wp.ScopedCapture`` with ``wp.capture_while``
and ``wp.capture_if``) and the graph launched once: the host reads the counts once for all the
rounds, instead of once per round. A graph is recorded for each substep that has contacts: it
holds that substep's arrays and launch sizes.

Also what a graph could save if it were reused (:func:`launch_costs`): per launch of one
collision kernel (``cover_check_kernel`` over 64 vertices), the stage's recorded launches
(:class:`core.buffers.RecordedLaunches`) against the launch of a recorded graph of the same
launches, and what recording that graph costs; their ratio is how many times a graph would have to
run unchanged to repay its recording.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from benchmarks import report  # noqa: E402

SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid")


def run(name: str, steps: int, capture: bool) -> dict[str, Any]:
    """One scene run with the Gauss-Seidel response (``capture``: its rounds as graphs)."""
    from scenes.sim_common import default_args, simulate

    module = importlib.import_module(f"scenes.{name}")
    start = time.perf_counter()
    summary, _ = simulate(module.build, default_args(steps=steps, response="gauss-seidel", capture_rounds=capture),
                          None, name=name, progress=False)
    return {"seconds": time.perf_counter() - start, "ms_per_step": summary["step_ms_mean"],
            "sha256": summary["state_sha256"], "graphs": summary.get("captured_round_graphs", 0)}


def launch_costs(launches: int = 15, vertices: int = 64, repeats: int = 2000) -> dict[str, float]:
    """Per launch [us]: ``launches`` recorded launches of :func:`kernels.broad_phase.cover_check_kernel`
    (each its own command) run one by one, and the same launches as one recorded graph; and the
    recording of that graph [ms] (``wp.ScopedCapture``), averaged over ``repeats`` (recording: a
    tenth as many)."""
    import numpy as np
    import warp as wp

    from core.buffers import RecordedLaunches
    from kernels.broad_phase import cover_check_kernel

    rng = np.random.default_rng(0)
    arrays = [wp.array(rng.normal(size=(vertices, 3)), dtype=wp.vec3d) for _ in range(4)]
    radius, counts = wp.zeros(vertices, dtype=wp.float64), wp.zeros(2, dtype=wp.int32)
    uncovered, beyond = counts[0:1], counts[1:2]  # views made once, as the stage's counters are
    recorded = RecordedLaunches(wp.get_device("cpu"))

    def sequence():
        for i in range(launches):
            recorded.launch(("cover", i), cover_check_kernel, vertices,
                            [*arrays, 0.001 * (i + 1), radius, 1, uncovered, beyond])

    sequence()  # loads the kernel and records the commands
    start = time.perf_counter()
    for _ in range(repeats):
        sequence()
    one_by_one = (time.perf_counter() - start) / (repeats * launches)
    start = time.perf_counter()
    for _ in range(repeats // 10):
        with wp.ScopedCapture(device="cpu") as capture:
            sequence()
    recording = (time.perf_counter() - start) / (repeats // 10)
    start = time.perf_counter()
    for _ in range(repeats):
        wp.capture_launch(capture.graph)
    graph = (time.perf_counter() - start) / (repeats * launches)
    return {"launches": launches, "recorded_us": one_by_one * 1e6, "graph_us": graph * 1e6,
            "recording_ms": recording * 1e3, "break_even_runs": recording / (launches * (one_by_one - graph))}


def main(argv=None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150, help="steps per run (default 150)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per setting, interleaved (default 2)")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated (default {','.join(SCENES)})")
    parser.add_argument("--out", default=os.path.join(report.RESULTS, "capture"))
    args = parser.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown or not scenes:
        parser.error(f"--scenes: expected some of {', '.join(SCENES)}, got {args.scenes!r}")
    import warp as wp

    wp.config.quiet = True
    rows = []
    for name in scenes:
        run(name, 3, True)  # compiles and loads every kernel of both settings
        runs: dict[bool, list] = {False: [], True: []}
        for _ in range(args.repeats):
            for capture in (False, True):
                runs[capture].append(run(name, args.steps, capture))
        hashes = {r["sha256"] for rs in runs.values() for r in rs}
        rows.append({"scene": name,
                     "uncaptured_ms": [r["ms_per_step"] for r in runs[False]],
                     "captured_ms": [r["ms_per_step"] for r in runs[True]],
                     "graphs": runs[True][0]["graphs"], "bit_identical": len(hashes) == 1})
        if len(hashes) != 1:
            raise SystemExit(f"{name}: the captured and uncaptured runs end in different states: {sorted(hashes)}")
    lines = [f"Gauss-Seidel response, {args.steps} steps of each scene from the start (1/60 s, 8 substeps), "
             f"ms per step of the whole step, {args.repeats} runs per setting interleaved; captured: each "
             "substep's CCD rounds after its first contact recorded as one Warp graph (capture_while / "
             "capture_if) and launched.", ""]
    lines += report.table(["scene", "uncaptured ms/step", "captured ms/step", "graphs (captured run)",
                           "final states bit-identical"],
                          [[r["scene"], ", ".join(report.fmt(v) for v in r["uncaptured_ms"]),
                            ", ".join(report.fmt(v) for v in r["captured_ms"]), r["graphs"],
                            "yes" if r["bit_identical"] else "no"] for r in rows])
    costs = launch_costs()
    lines += ["", f"What reusing a graph could save, per launch of `cover_check_kernel` over 64 vertices: "
              f"{costs['launches']} recorded launches run one by one, against one recorded graph of them.", ""]
    lines += report.table(["recorded launch (us)", "launch in a graph (us)",
                           f"recording the graph of {costs['launches']} (ms)", "runs to repay the recording"],
                          [[costs["recorded_us"], costs["graph_us"], costs["recording_ms"], costs["break_even_runs"]]])
    report.write(args.out, "CCD rounds as graphs", lines, {"steps": args.steps, "rows": rows, "launch_costs": costs})
    return rows


if __name__ == "__main__":
    main()
