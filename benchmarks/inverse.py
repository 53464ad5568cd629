"""Inverse control with lifted events: the ``tunnel`` scene over many seeds, proposed vs baseline.

    python benchmarks/inverse.py [--seeds 50] [--iters 500] [--jobs 2]
                                 [--out benchmarks/results/inverse_tunnel]

For each seed ``0 .. seeds-1`` it draws the ``tunnel`` problem (:mod:`scenes.tunnel`: a miss
whose wanted root is complex, targets from a shot that really hits), runs the proposed method
(lifted roots, mollified derivatives) and the baseline (real roots only, unmollified ``-1/p'(t*)``)
with the same Adam budget, and prints one row per seed and a summary table: success rate
(``|t - t_target| < 1e-6 s`` and final velocity within 1e-3 relative), rollouts to the target,
the first hit, wall time, gradient norms and the time per rollout (forward + backward). Writes
``<out>.md`` (the tables), ``<out>.json`` (every figure) and ``<out>.png`` (loss curves of the
first seeds). Every number comes from this run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))


def run_seed(args):
    """Both methods on one seed (a worker process): figures and loss histories."""
    seed, iters = args
    import warp as wp

    wp.config.quiet = True
    from scenes.tunnel import make_problem, optimise

    t0 = time.perf_counter()
    problem = make_problem(seed)
    make_time = time.perf_counter() - t0
    out = {"seed": seed, "make_time": make_time, "t_target": problem.t_target}
    for method in ("proposed", "baseline"):
        r = optimise(problem, iters, method)
        h = r.pop("history")
        grads = [g for g in h["grad_norm"] if g > 0.0]
        r["median_grad_norm"] = float(np.median(grads)) if grads else 0.0
        r["seconds_per_rollout"] = r["wall_time"] / max(r["rollouts"], 1)
        r["loss_curve"] = [None if not np.isfinite(x) else x for x in h["loss"]]
        r["hit_curve"] = h["hit"]
        out[method] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()}
    return out


def _median(values):
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else float("nan")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50, help="seeds 0 .. N-1 (default %(default)s)")
    parser.add_argument("--iters", type=int, default=500, help="Adam iterations per method (default %(default)s)")
    parser.add_argument("--jobs", type=int, default=max(1, min(os.cpu_count() or 1, 8)),
                        help="worker processes (default: the CPU count, at most 8)")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "inverse_tunnel"),
                        help="path prefix of the .md, .json and .png outputs")
    parser.add_argument("--curves", type=int, default=5, help="seeds whose loss curves the PNG shows")
    args = parser.parse_args(argv)
    for name in ("seeds", "iters", "jobs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")

    import multiprocessing as mp

    import warp as wp

    wp.config.quiet = True
    from scenes.tunnel import make_problem

    make_problem(0)  # compiles every kernel once, before the workers share the cache
    t0 = time.perf_counter()
    tasks = [(seed, args.iters) for seed in range(args.seeds)]
    rows = []
    header = (f"{'seed':>4s} | {'proposed':>8s} {'rollouts':>8s} {'1st hit':>7s} {'|dt| [s]':>9s} {'dv rel':>9s} "
              f"{'wall [s]':>8s} | {'baseline':>8s} {'stalled':>7s} {'1st hit':>7s}")
    print(header)
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for row in pool.imap(run_seed, tasks):
            rows.append(row)
            p, b = row["proposed"], row["baseline"]
            te = p["time_error"]
            ve = p["velocity_error"]
            print(f"{row['seed']:>4d} | {p['reached_target']!s:>8s} {p['rollouts']:>8d} "
                  f"{p['first_hit_iteration']!s:>7s} {abs(te) if te is not None else float('nan'):>9.2e} "
                  f"{ve if ve is not None else float('nan'):>9.2e} {p['wall_time']:>8.1f} | "
                  f"{b['reached_target']!s:>8s} {b['stalled']!s:>7s} "
                  f"{b['first_hit_iteration']!s:>7s}", flush=True)
    total = time.perf_counter() - t0

    summary = {}
    for method in ("proposed", "baseline"):
        runs = [r[method] for r in rows]
        reached = [r for r in runs if r["reached_target"]]
        summary[method] = {
            "success_rate": len(reached) / len(runs),
            "left_the_miss": sum(r["first_hit_iteration"] is not None for r in runs) / len(runs),
            "median_rollouts_to_target": _median([r["iterations_to_target"] for r in reached]),
            "max_rollouts_to_target": max((r["iterations_to_target"] for r in reached), default=None),
            "median_first_hit": _median([r["first_hit_iteration"] for r in runs]),
            "median_wall_time_s": _median([r["wall_time"] for r in runs]),
            "median_seconds_per_rollout": _median([r["seconds_per_rollout"] for r in runs]),
            "median_grad_norm": _median([r["median_grad_norm"] for r in runs]),
            "stalled": sum(bool(r["stalled"]) for r in runs),
        }
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {args.jobs} worker(s)"
    lines = [
        f"# tunnel: {args.seeds} seeds, {args.iters} Adam iterations per method",
        "",
        f"Machine: {machine}; total wall time {total:.0f} s. Success: |t - t_target| < 1e-6 s and final",
        "velocity within 1e-3 relative. Rollouts count every simulation, rejected hit-phase steps included.",
        "",
        ("| method | success | left the miss | median rollouts to target | max | median first hit | "
         "median wall time [s] | s per rollout (fwd+bwd) | median grad norm | stalled (zero gradient) |"),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method, s in summary.items():
        lines.append(
            f"| {method} | {100 * s['success_rate']:.0f}% | {100 * s['left_the_miss']:.0f}% | "
            f"{s['median_rollouts_to_target']:.0f} | {s['max_rollouts_to_target']} | {s['median_first_hit']:.0f} | "
            f"{s['median_wall_time_s']:.1f} | {s['median_seconds_per_rollout']:.3f} | {s['median_grad_norm']:.3g} | "
            f"{s['stalled']} |")
    failed = [r["seed"] for r in rows if not r["proposed"]["reached_target"]]
    lines += ["", f"Seeds the proposed method did not solve: {failed if failed else 'none'}."]
    table = "\n".join(lines)
    print()
    print(table)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out + ".md", "w") as f:
        f.write(table + "\n")
    with open(args.out + ".json", "w") as f:
        json.dump({"machine": machine, "seeds": args.seeds, "iters": args.iters, "summary": summary, "runs": rows}, f)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, method in zip(axes, ("proposed", "baseline")):
        for row in rows[: args.curves]:
            curve = np.array([np.nan if x is None else x for x in row[method]["loss_curve"]], dtype=float)
            ax.semilogy(np.arange(len(curve)), curve, label=f"seed {row['seed']}")
        ax.set_title(f"{method}")
        ax.set_xlabel("rollout")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("loss (miss phase: lifted event; hit phase: time + velocity)")
    axes[0].legend()
    fig.suptitle("tunnel: from a miss (complex wanted root) to the target hit")
    fig.tight_layout()
    fig.savefig(args.out + ".png", dpi=120)
    print(f"wrote {args.out}.md, .json, .png")


if __name__ == "__main__":
    main()
