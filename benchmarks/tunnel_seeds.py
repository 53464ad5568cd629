"""The ``tunnel`` scene's proposed method over a range of seeds (success rate, failures).

Runs :func:`scenes.tunnel.optimise` (``proposed``, 500 iterations) on seeds ``--first`` ..
``--last - 1``, one process, and writes ``benchmarks/results/tunnel_seeds_<first>_<last-1>.md``
and ``.json``. The per-seed rows are kept in the ``.json`` as they finish, so an interrupted sweep
resumes where it stopped. ``benchmarks/inverse.py --scenes tunnel`` compares the three methods on
seeds 0-49; this one measures the proposed method alone on seeds nobody tuned on.

Usage::

    python benchmarks/tunnel_seeds.py --first 50 --last 150
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from benchmarks.report import atomic_write  # noqa: E402


def run_seed(seed: int, iters: int) -> dict:
    from scenes.tunnel import make_problem, optimise

    t0 = time.perf_counter()
    r = optimise(make_problem(seed), iters, "proposed")
    hits = r["history"]["hit"]
    return {"seed": seed, "reached": r["reached_target"], "iterations_to_target": r["iterations_to_target"],
            "first_hit": next((i for i, h in enumerate(hits) if h), None),
            "time_error": r["time_error"], "velocity_error": r["velocity_error"], "wall": time.perf_counter() - t0}


def report(rows: list[dict], first: int, last: int, iters: int) -> list[str]:
    reached = [r for r in rows if r["reached"]]
    iterations = sorted(r["iterations_to_target"] for r in reached)
    lines = [f"# tunnel, proposed method, seeds {first}-{last - 1}, {iters} iterations", "",
             f"Reached the target (|t - t_target| < 1e-6 s, final velocity within 1e-3 relative): "
             f"**{len(reached)} / {len(rows)}**.",
             f"Median iterations to the target {iterations[len(iterations) // 2] if iterations else '-'}, "
             f"max {iterations[-1] if iterations else '-'}.", "", "Failures:", "",
             "| seed | first hit of the face | time error [s] | velocity error |", "|---|---|---|---|"]
    for r in rows:
        if not r["reached"]:
            lines.append(f"| {r['seed']} | {r['first_hit'] if r['first_hit'] is not None else 'never'} | "
                         f"{r['time_error']:.3g} | {r['velocity_error']:.3g} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--first", type=int, default=50, help="first seed (default %(default)s)")
    parser.add_argument("--last", type=int, default=150, help="one past the last seed (default %(default)s)")
    parser.add_argument("--iters", type=int, default=500, help="iterations per seed (default %(default)s)")
    parser.add_argument("--out", default=None, help="output prefix (default benchmarks/results/tunnel_seeds_F_L)")
    args = parser.parse_args(argv)
    out = args.out or os.path.join(HERE, "results", f"tunnel_seeds_{args.first}_{args.last - 1}")
    data = json.load(open(out + ".json")) if os.path.exists(out + ".json") else {"iters": args.iters, "rows": []}
    done = {r["seed"] for r in data["rows"]}
    from tqdm import tqdm

    for seed in tqdm(range(args.first, args.last), desc="tunnel seeds", file=sys.stderr, disable=None):
        if seed in done:
            continue
        data["rows"].append(run_seed(seed, args.iters))
        atomic_write(out + ".json", json.dumps(data) + "\n")
    rows = sorted(data["rows"], key=lambda r: r["seed"])
    atomic_write(out + ".md", "\n".join(report(rows, args.first, args.last, args.iters)) + "\n")
    print(f"wrote {out}.md, .json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
