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
    report.write(args.out, "CCD rounds as graphs", lines, {"steps": args.steps, "rows": rows})
    return rows


if __name__ == "__main__":
    main()
