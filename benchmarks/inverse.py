"""Inverse control with lifted events: the ``tunnel`` scene over many seeds, proposed vs baseline.

    python benchmarks/inverse.py [--seeds 50] [--iters 500] [--jobs 2] [--scenes tunnel,bank_shot]
                                 [--bank-iters 300] [--bank-seeds 5] [--out benchmarks/results/inverse_tunnel]

``bank_shot`` (:mod:`scenes.bank_shot`, Newton's ``diffsim_ball`` problem): both starts with the
proposed method, the baseline and CMA-ES, then Newton 1.8's own example (:mod:`newton_ball`,
penalty contact, float32, gradient descent) from both starts, each simulator's gradient against
central differences of its own forward, in one run: ``<out>_bank_shot.md/.json/.png``.

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
    from scenes.tunnel import METHODS, make_problem, optimise

    t0 = time.perf_counter()
    problem = make_problem(seed)
    make_time = time.perf_counter() - t0
    out = {"seed": seed, "make_time": make_time, "t_target": problem.t_target}
    for method in METHODS:
        r = optimise(problem, iters, method)
        h = r.pop("history")
        grads = [g for g in h["grad_norm"] if g > 0.0]
        r["median_grad_norm"] = float(np.median(grads)) if grads else 0.0
        r["seconds_per_rollout"] = r["wall_time"] / max(r["rollouts"], 1)
        r["loss_curve"] = [None if not np.isfinite(x) else x for x in h["loss"]]
        r["hit_curve"] = h["hit"]
        out[method] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()}
    return out


def run_bank_shot(args):
    """One (start, method) of ``bank_shot`` (a worker process): figures and curves."""
    start, method, iters = args
    import warp as wp

    wp.config.quiet = True
    from scenes import bank_shot as B

    model = B.build()
    velocity = B.seeded_start(model, int(start[len("seed "):])) if start.startswith("seed ") else B.STARTS[start]
    r = B.optimise(model, velocity, iters, method)
    r["start_velocity"] = list(velocity)
    h = r.pop("history")
    r["seconds_per_rollout"] = r["wall_time"] / max(r["rollouts"], 1)
    r["distance_curve"] = h["distance"]
    grads = [g for g in h["grad_norm"] if g > 0.0]
    r["median_grad_norm"] = float(np.median(grads)) if grads else 0.0
    return {"start": start, "method": method, **r}


def bank_shot(args) -> dict:
    """``bank_shot`` from both starts with the three methods, Newton's ``diffsim_ball`` from both
    starts, and each simulator's gradient against central differences of its own forward."""
    import multiprocessing as mp

    from scenes import bank_shot as B

    B.build()
    starts = ["newton", "miss"] + [f"seed {k}" for k in range(args.bank_seeds)]
    tasks = [(start, method, args.bank_iters) for start in starts for method in B.METHODS]
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        ours = list(pool.imap(run_bank_shot, tasks))
    profile = fresh_profile("bank_shot")
    # Newton after the pool, alone on the machine (its wall time is not shared with our workers)
    from benchmarks import newton_ball  # the package path: `python -m benchmarks` has no benchmarks/ on sys.path

    newton = []
    for start in ("newton", "miss"):
        r = newton_ball.optimise(args.bank_iters, B.STARTS[start], B.TARGET_TOLERANCE)
        r["seconds_per_rollout"] = r["wall_time"] / max(r["rollouts"], 1)
        newton.append({"start": start, "method": "newton (penalty, GD)", **r})
    model = B.build()
    shifted = np.asarray(B.STARTS["newton"]) + np.array([0.003, 0.007, -0.005])
    checks = {
        "tunnelsim at Newton's start + (3, 7, -5) mm/s, step 1e-6": B.gradient_check(model, shifted),
        "tunnelsim at Newton's start exactly, step 1e-6": B.gradient_check(model, B.STARTS["newton"]),
        "Newton at its start, step 1e-3 (its example's check)": newton_ball.NewtonBall().check_grad(1e-3),
    }
    lines = [
        f"# bank_shot (Newton's diffsim_ball problem): {args.bank_iters} iterations per method",
        "",
        "Success: the end point within 1 cm of the target after bouncing off the floor and the wall.",
        "tunnelsim: exact CCD impulses, float64, Adam; Newton 1.8: penalty contact, float32, gradient",
        "descent (rate 0.02), both on the CPU. Rollouts: simulations run (CMA-ES: forward only).",
        "",
        "| start | method | reached | rollouts to target | final distance [m] | floor/wall bounces | wall time [s] | s per rollout |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in ours + newton:
        bounces = f"{r.get('floor_bounces', '-')}/{r.get('wall_bounces', '-')}"
        lines.append(f"| {r['start']} | {r['method']} | {r['reached_target']} | {r['iterations_to_target']} | "
                     f"{r['final_distance']:.4f} | {bounces} | {r['wall_time']:.1f} | {r['seconds_per_rollout']:.3f} |")
    seeded = [r for r in ours if r["start"].startswith("seed ")]
    if seeded:
        caption = (f"Seeded misses (`--start seeded --seed 0..{args.bank_seeds - 1}`, drawn by "
                   "`bank_shot.seeded_start`):")
        lines += ["", caption, "", "| method | reached | median rollouts to target |", "|---|---|---|"]
        for method in B.METHODS:
            runs = [r for r in seeded if r["method"] == method]
            hits = [r["iterations_to_target"] for r in runs if r["reached_target"]]
            median = f"{np.median(hits):.0f}" if hits else "-"
            lines.append(f"| {method} | {len(hits)}/{len(runs)} | {median} |")
    lines += _profile_lines(profile, "One rollout from Newton's start (36 frames x 8 substeps, the proposed method's "
                            "lifted events included), alone in a fresh worker:", 3)
    lines += ["", "| gradient check | analytic | central differences | relative error |", "|---|---|---|---|"]
    for name, c in checks.items():
        lines.append(f"| {name} | {np.round(c['analytic'], 4).tolist()} | {np.round(c['numeric'], 4).tolist()} | "
                     f"{c['relative_error']:.2e} |")
    out = _scene_prefix(args, "bank_shot")
    plt = _write_outputs(out, lines, {"iters": args.bank_iters, "runs": ours + newton, "gradient_checks": checks,
                                      "profile": profile})

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, start in zip(axes, ("newton", "miss")):
        for r in ours + newton:
            if r["start"] == start:
                ax.semilogy(np.arange(len(r["distance_curve"])), r["distance_curve"], label=r["method"])
        ax.axhline(B.TARGET_TOLERANCE, color="grey", ls=":")
        ax.set_title(f"start: {start} {B.STARTS[start]} m/s")
        ax.set_xlabel("rollout")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("distance to the target [m]")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out + ".png", dpi=120)
    print(f"wrote {out}.md, .json, .png")
    return {"runs": ours + newton, "gradient_checks": checks}


def _write_outputs(out: str, lines: list[str], data: dict):
    """Prints the table ``lines``, writes ``<out>.md`` and ``<out>.json`` (``data``); returns
    ``matplotlib.pyplot`` (Agg backend) for the caller's ``<out>.png``."""
    table = "\n".join(lines)
    print()
    print(table)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out + ".md", "w") as f:
        f.write(table + "\n")
    with open(out + ".json", "w") as f:
        json.dump(data, f)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _scene_prefix(args, scene: str) -> str:
    """Output prefix of ``scene``: ``--out`` (tunnel's, default ``results/inverse_tunnel``) with
    its ``_tunnel`` suffix replaced by the scene's name."""
    base = args.out.removesuffix("_tunnel")
    return f"{base}_{scene}"


def _profile_lines(profile: dict, caption: str, digits: int) -> list[str]:
    """The table rows of :func:`profile_rollout`'s figures."""
    f = f".{digits}f"
    return ["", caption, "",
            "| forward [s] | forward with tape [s] | backward [s] | mesh-contact substeps | CCD events | peak memory [MiB] |",
            "|---|---|---|---|---|---|",
            (f"| {profile['forward_s']:{f}} | {profile['forward_taped_s']:{f}} | {profile['backward_s']:{f}} | "
             f"{profile['contact_substeps']} | {profile['ccd_events']} | {profile['peak_rss_mib']:.0f} |")]


def _median(values):
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else float("nan")


def run_cloth(args):
    """One (seed, method) of ``cloth_toss`` (a worker process): figures and the loss curve."""
    seed, method, iters = args
    import warp as wp

    wp.config.quiet = True
    from scenes import cloth_toss as C

    r = C.optimise(C.build(seed), iters, method)
    h = r.pop("history")
    r["loss_curve"] = h["loss"]
    grads = [g for g in h["grad_norm"] if g > 0.0]
    r["median_grad_norm"] = float(np.median(grads)) if grads else 0.0
    r["seconds_per_rollout"] = r["wall_time"] / max(r["rollouts"], 1)
    return {"seed": seed, "method": method, **r}


def fresh_profile(scene: str) -> dict:
    """:func:`profile_rollout` in a process of its own (its peak memory is that rollout's alone)."""
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(profile_rollout, (scene,))


def profile_rollout(scene: str) -> dict:
    """Forward (no tape), forward with tape and backward time [s] of one rollout of ``scene`` at
    its seed-0 start, its mesh-contact substeps, and the process' peak resident memory [MiB]
    (a fresh worker process, so the peak is this rollout's)."""
    import resource

    import torch
    import warp as wp

    wp.config.quiet = True
    if scene == "cloth_toss":
        from scenes import cloth_toss as C

        problem = C.build(0)

        def forward(grad):
            u, res = C.simulate(problem, problem.u0, grad=grad)
            return u, res, C.drape_loss(problem, res)
    elif scene == "bank_shot":
        from scenes import bank_shot as B

        model = B.build()

        def forward(grad):
            v, res = B.simulate(model, B.STARTS["newton"], events=B.events_of(model), grad=grad)
            return v, res, B.distance_loss(res) + res.event_roots.sum()
    elif scene == "tunnel":
        from scenes import tunnel as T

        problem = T.make_problem(0)
        event = T.face_event(problem.face, problem.window)

        def forward(grad):
            v, res = T.tunnel_rollout(problem, problem.v_star, events=[event], grad=grad)
            return v, res, (res.particle_qd[-1, 0] ** 2).sum() + res.event_roots.sum()
    else:
        raise ValueError(scene)
    forward(True)[2].backward()  # compiles, warms the caches
    times = {"forward_s": [], "forward_taped_s": [], "backward_s": []}
    for _ in range(3):
        t0 = time.perf_counter()
        with torch.no_grad():
            forward(False)
        times["forward_s"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _, res, loss = forward(True)
        t1 = time.perf_counter()
        loss.backward()
        times["forward_taped_s"].append(t1 - t0)
        times["backward_s"].append(time.perf_counter() - t1)
    out = {k: float(np.median(v)) for k, v in times.items()}
    out["contact_substeps"] = int(res.stats["contact_substeps"])
    out["ccd_events"] = int(res.stats.get("ccd_events", 0))  # approaching CCD hits in the rollout
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def cloth_toss(args) -> dict:
    """``cloth_toss`` over seeds 0 .. cloth_seeds-1 with the three methods, same rollout budget."""
    import multiprocessing as mp

    from scenes import cloth_toss as C

    C.build(0)
    tasks = [(seed, method, args.cloth_iters) for seed in range(args.cloth_seeds) for method in C.METHODS]
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        runs = list(pool.imap(run_cloth, tasks))
    total = time.perf_counter() - t0
    profile = fresh_profile("cloth_toss")
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {args.jobs} worker(s)"
    lines = [
        f"# cloth_toss: seeds 0-{args.cloth_seeds - 1}, {args.cloth_iters} optimiser steps per method "
        f"({args.cloth_iters + 1} rollouts)",
        "",
        f"Machine: {machine}; total wall time {total:.0f} s. Loss: the drape loss [m^2] (scenes/cloth_toss.py);",
        f"success: the best iterate's loss cut by {100 * C.TARGET_CUT:.0f}% from the start's (a throw that lands beside the sphere).",
        "",
        "| seed | method | start loss | best loss | cut | rollouts to a 90% cut | wall time [s] | s per rollout | median grad norm | median contact substeps | fail-safe rollouts |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        lines.append(f"| {r['seed']} | {r['method']} | {r['initial_loss']:.4f} | {r['final_loss']:.4f} | "
                     f"{100 * r['loss_cut']:.1f}% | {'-' if r['iterations_to_target'] is None else r['iterations_to_target'] + 1} | "
                     f"{r['wall_time']:.0f} | {r['seconds_per_rollout']:.2f} | {r['median_grad_norm']:.3g} | "
                     f"{r['median_contact_substeps']:.0f} | {r['failsafe_rollouts']} |")
    lines += ["", "| method | seeds with a 90% cut | median cut | median rollouts to a 90% cut |", "|---|---|---|---|"]
    summary = {}
    for method in C.METHODS:
        mine = [r for r in runs if r["method"] == method]
        done = [r["iterations_to_target"] + 1 for r in mine if r["reached_target"]]
        summary[method] = {"successes": len(done), "seeds": len(mine),
                           "median_cut": float(np.median([r["loss_cut"] for r in mine])),
                           "median_rollouts_to_target": _median(done)}
        lines.append(f"| {method} | {len(done)}/{len(mine)} | {100 * summary[method]['median_cut']:.1f}% | "
                     f"{'-' if not done else format(summary[method]['median_rollouts_to_target'], '.0f')} |")
    lines += _profile_lines(profile, "One rollout at seed 0's start (median of 3, a fresh worker):", 2)
    out = _scene_prefix(args, "cloth_toss")
    plt = _write_outputs(out, lines, {"machine": machine, "iters": args.cloth_iters, "summary": summary,
                                      "profile": profile, "runs": runs})

    fig, axes = plt.subplots(1, len(C.METHODS), figsize=(15, 4), sharey=True)
    for ax, method in zip(axes, C.METHODS):
        for r in runs:
            if r["method"] == method:
                curve = np.asarray(r["loss_curve"]) / r["initial_loss"]
                ax.semilogy(np.arange(len(curve)), curve, label=f"seed {r['seed']}")
        ax.axhline(1.0 - C.TARGET_CUT, color="grey", ls=":")
    _label_panels(fig, axes, C.METHODS, "drape loss / start's",
                  "cloth_toss: initial linear and angular velocity of a cloth, draped over a sphere")
    fig.savefig(out + ".png", dpi=120)
    print(f"wrote {out}.md, .json, .png")
    return {"runs": runs, "summary": summary}


def plot_tunnel_curves(plt, rows, iters: int):
    """The loss curves of ``rows`` (runs of :func:`run_seed`), one panel per method; a
    method without any finite loss (the baseline from a miss) is drawn flat. Returns the figure."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4), sharey=True)
    for ax, method in zip(axes, ("proposed", "baseline", "cma")):
        flat = False
        for k, row in enumerate(rows):
            curve = np.array([np.nan if x is None else x for x in row[method]["loss_curve"]], dtype=float)
            if not np.isfinite(curve).any():
                # no real root at a miss: no loss and a zero gradient, so the shot never changes;
                # drawn at the lifted loss of that same shot (the proposed method's first value)
                start = row["proposed"]["loss_curve"][0]
                ax.semilogy([0, iters], [start, start], color=f"C{k}", linestyle="--", label=f"seed {row['seed']}")
                flat = True
                continue
            ax.semilogy(np.arange(len(curve)), curve, color=f"C{k}", label=f"seed {row['seed']}")
        if flat:
            ax.text(0.03, 0.04, "dashed: a miss has no real root, so no loss and a zero\ngradient: "
                    "the shot never moves (drawn at its lifted loss)", transform=ax.transAxes, fontsize=8)
    _label_panels(fig, axes, ("proposed", "baseline", "cma"), "loss (miss phase: lifted event; hit phase: time + velocity)",
                  "tunnel: from a miss (complex wanted root) to the target hit")
    return fig


def _label_panels(fig, axes, methods, ylabel: str, title: str) -> None:
    """Titles, axis labels, grids and the legend of a row of per-method loss panels."""
    for ax, method in zip(axes, methods):
        ax.set_title(method)
        ax.set_xlabel("rollout")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(ylabel)
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50, help="tunnel: N seeds from --first-seed (default %(default)s)")
    parser.add_argument("--first-seed", type=int, default=0, help="tunnel: the first seed (default %(default)s)")
    parser.add_argument("--iters", type=int, default=500, help="Adam iterations per method (default %(default)s)")
    parser.add_argument("--jobs", type=int, default=max(1, min(os.cpu_count() or 1, 8)),
                        help="worker processes (default: the CPU count, at most 8)")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "inverse_tunnel"),
                        help="path prefix of the .md, .json and .png outputs")
    parser.add_argument("--curves", type=int, default=5, help="seeds whose loss curves the PNG shows")
    parser.add_argument("--scenes", default="tunnel,bank_shot,cloth_toss",
                        help="comma-separated scenes to run: tunnel, bank_shot, cloth_toss (default all)")
    parser.add_argument("--cloth-seeds", type=int, default=5, help="cloth_toss: seeds 0 .. N-1 (default %(default)s)")
    parser.add_argument("--cloth-iters", type=int, default=40,
                        help="cloth_toss: optimiser steps per method, N + 1 rollouts (default %(default)s)")
    parser.add_argument("--bank-seeds", type=int, default=5,
                        help="bank_shot: seeded misses (--start seeded --seed 0..N-1) beside the two fixed starts (default %(default)s)")
    parser.add_argument("--bank-iters", type=int, default=300,
                        help="bank_shot: iterations per method, Newton's included (default %(default)s)")
    args = parser.parse_args(argv)
    for name in ("seeds", "iters", "jobs", "bank_iters", "cloth_seeds", "cloth_iters"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.bank_seeds < 0:
        parser.error("--bank-seeds must be >= 0")
    scenes = [x.strip() for x in args.scenes.split(",") if x.strip()]
    if not scenes or any(x not in ("tunnel", "bank_shot", "cloth_toss") for x in scenes):
        parser.error(f"--scenes must be a comma-separated subset of tunnel,bank_shot,cloth_toss, got {args.scenes!r}")
    if "tunnel" in scenes:
        tunnel(args)
    if "bank_shot" in scenes:
        bank_shot(args)
    if "cloth_toss" in scenes:
        cloth_toss(args)


def tunnel(args) -> None:

    import multiprocessing as mp

    import warp as wp

    wp.config.quiet = True
    from scenes.tunnel import make_problem

    make_problem(0)  # compiles every kernel once, before the workers share the cache
    t0 = time.perf_counter()
    tasks = [(seed, args.iters) for seed in range(args.first_seed, args.first_seed + args.seeds)]
    rows = []
    header = (f"{'seed':>4s} | {'proposed':>8s} {'iters':>5s} {'1st hit':>7s} {'|dt| [s]':>9s} {'dv rel':>9s} "
              f"{'wall [s]':>8s} | {'baseline':>8s} {'stalled':>7s} | {'cma':>5s} {'rollouts':>8s} {'wall [s]':>8s}")
    print(header)
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for row in pool.imap(run_seed, tasks):
            rows.append(row)
            p, b, c = row["proposed"], row["baseline"], row["cma"]
            te = p["time_error"]
            ve = p["velocity_error"]
            print(f"{row['seed']:>4d} | {p['reached_target']!s:>8s} {p['iterations']:>5d} "
                  f"{p['first_hit_iteration']!s:>7s} {abs(te) if te is not None else float('nan'):>9.2e} "
                  f"{ve if ve is not None else float('nan'):>9.2e} {p['wall_time']:>8.1f} | "
                  f"{b['reached_target']!s:>8s} {b['stalled']!s:>7s} | "
                  f"{c['reached_target']!s:>5s} {c['rollouts']:>8d} {c['wall_time']:>8.1f}", flush=True)
    total = time.perf_counter() - t0
    profile = fresh_profile("tunnel")

    summary = {}
    for method in ("proposed", "baseline", "cma"):
        runs = [r[method] for r in rows]
        reached = [r for r in runs if r["reached_target"]]
        summary[method] = {
            "success_rate": len(reached) / len(runs),
            "successes": len(reached),
            "left_the_miss": sum(r["first_hit_iteration"] is not None for r in runs) / len(runs),
            "median_iterations_to_target": _median([r["iterations_to_target"] for r in reached]),
            "max_iterations_to_target": max((r["iterations_to_target"] for r in reached), default=None),
            "median_rollouts_to_target": _median([r["rollouts_to_target"] for r in reached]),
            "median_wall_time_to_target_s": _median([r["wall_time"] for r in reached]),
            "median_first_hit": _median([r["first_hit_iteration"] for r in runs]),
            "median_wall_time_s": _median([r["wall_time"] for r in runs]),
            "median_seconds_per_rollout": _median([r["seconds_per_rollout"] for r in runs]),
            "median_grad_norm": _median([r["median_grad_norm"] for r in runs]),
            "stalled": sum(bool(r["stalled"]) for r in runs),
        }
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {args.jobs} worker(s)"
    lines = [
        f"# tunnel: {args.seeds} seeds from {args.first_seed}, {args.iters} iterations per method "
        f"(CMA-ES: {args.iters} rollouts)",
        "",
        f"Machine: {machine}; total wall time {total:.0f} s. Success: |t - t_target| < 1e-6 s and final",
        "velocity within 1e-3 relative. Iterations are Adam steps (CMA-ES: rollouts); rollouts count every",
        "simulation (phase one: the ghost's event rollout, plus the real one when the ghost is ready).",
        "",
        ("| method | success | left the miss | median iterations to target | max | median rollouts to target | "
         "median first hit | median wall time to target [s] | s per rollout | median grad norm | stalled (zero gradient) |"),
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def fmt(x, spec):
        return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)

    for method, s in summary.items():
        lines.append(
            f"| {method} | {s['successes']}/{len(rows)} ({100 * s['success_rate']:.0f}%) | {100 * s['left_the_miss']:.0f}% | "
            f"{fmt(s['median_iterations_to_target'], '.0f')} | {fmt(s['max_iterations_to_target'], 'd')} | "
            f"{fmt(s['median_rollouts_to_target'], '.0f')} | {fmt(s['median_first_hit'], '.0f')} | "
            f"{fmt(s['median_wall_time_to_target_s'], '.1f')} | {s['median_seconds_per_rollout']:.3f} | "
            f"{s['median_grad_norm']:.3g} | {s['stalled']} |")
    failed = [r["seed"] for r in rows if not r["proposed"]["reached_target"]]
    lines += ["", f"Seeds the proposed method did not solve: {failed if failed else 'none'}."]
    lines += _profile_lines(profile, "One rollout at seed 0's aimed shot with its event (median of 3, a fresh worker):", 3)
    plt = _write_outputs(args.out, lines, {"machine": machine, "seeds": args.seeds, "iters": args.iters,
                                           "summary": summary, "profile": profile, "runs": rows})

    plot_tunnel_curves(plt, rows[: args.curves], args.iters).savefig(args.out + ".png", dpi=120)
    print(f"wrote {args.out}.md, .json, .png")


if __name__ == "__main__":
    main()
