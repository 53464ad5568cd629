"""Billiards beside DiffTaichi: from its own start and from misses, in one run.

    python benchmarks/billiards.py [--iters 200] [--gd-iters 700] [--seeds 20] [--breaks 10000] [--rows 4,6,8,10,13]
                                   [--parts shots,gradients,scale,breaks] [--out benchmarks/results/billiards]

* **shots**: DiffTaichi's method (:mod:`difftaichi_anchor`: Taichi, float32, CPU, one thread,
  plain gradient descent, learning rate 0.01) and the scene's methods (:mod:`scenes.billiards`,
  float64): ``proposed`` with plain gradient descent and with Adam, ``baseline`` (gradient descent
  through the real contacts), ``cma`` (CMA-ES at the same rollout budget), from DiffTaichi's start,
  the two named misses and the seeded misses ``0 .. seeds-1``; from DiffTaichi's start the
  gradient-descent runs (DiffTaichi's, ``proposed/gd``, ``baseline/gd``) have ``--gd-iters``
  steps, the others ``--iters``. Every run stops once the target is
  within 5 mm of the goal, or at an exactly zero gradient (every later gradient-descent iterate
  would be the same). Per method and start: reached, rollouts to the goal, final loss and
  distance, seconds per iteration (forward + backward) and wall time. The runs are saved as they
  finish (``<out>_runs.json``), and a rerun skips the ones already there.
* **gradients**: at DiffTaichi's start, each simulator's gradient against central differences
  of its own forward; a grazing sweep (closest approach 0.9 - 1.1 x 2 r) of ours, its largest
  gradient against the free flight's.
* **timing**: seconds per iteration of both from DiffTaichi's start, each in its own loop (run it
  alone).
* **scale**: racks of more rows (up to 13: 92 balls): seconds per forward rollout and per
  backward against the ball count, and the fitted exponent.
* **breaks**: random breaks (cue speed 0.5 - 3 m/s at the rack): the deepest overlap of any pair
  at any step and the momentum drift.

Writes ``<out>.md``, ``<out>.json`` and ``<out>.png`` (loss curves from DiffTaichi's start and
one miss). Needs taichi (``pip install -e '.[difftaichi]'``, which ``make bench`` does).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

from benchmarks.report import RESULTS, atomic_write, save_figure, table, write  # noqa: E402

TOLERANCE = 0.005  # [m]


def _starts(seeds: int, model) -> dict[str, tuple]:
    from scenes import billiards as B

    out = dict(B.STARTS)
    for seed in range(seeds):
        out[f"seed {seed}"] = B.seeded_start(model, seed)
    return out


def _anchor_run(anchor, shot, iters: int) -> dict:
    r = anchor.optimise(shot[:2], shot[2:], iters=iters, tolerance=TOLERANCE, stop_at_zero_gradient=True)
    seconds = r["seconds"]
    return {"reached_target": r["reached"] is not None, "iterations_to_target": r["reached"],
            "final_loss": r["losses"][-1], "target_distance": r["distances"][-1], "rollouts": len(r["losses"]),
            "seconds_per_iteration": float(np.mean(seconds[1:] if len(seconds) > 1 else seconds)),
            "wall_time": float(np.sum(seconds)), "loss_curve": r["losses"], "zero_gradient_at": r["zero_gradient_at"]}


def _our_run(model, shot, iters: int, method: str, optimizer: str) -> dict:
    from scenes import billiards as B

    r = B.optimise(model, shot, iters, method, optimizer)
    h = r.pop("history")
    r["loss_curve"] = h["loss"]
    r["first_hit"] = next((i for i, hit in enumerate(h["hit"]) if hit), None)
    return r


RUNS = (("difftaichi", None), ("proposed", "gd"), ("proposed", "adam"), ("baseline", "gd"), ("cma", None))


def shots(args, model, runs_path: str) -> dict:
    """Every (run, start) pair, resumed from ``runs_path``."""
    from benchmarks.difftaichi_anchor import DiffTaichiBilliards

    done = json.load(open(runs_path)) if os.path.exists(runs_path) else {}
    anchor = DiffTaichiBilliards()
    anchor.loss_and_grad((0.1, 0.5), (0.3, 0.0))  # compile before any clock starts
    from scenes import billiards as B

    B.simulate(model, B.STARTS["default"], grad=True)[1].body_q.sum().backward()
    for name, shot in _starts(args.seeds, model).items():
        for method, optimizer in RUNS:
            if optimizer == "gd" and method == "proposed" and name != "default":
                continue  # plain gradient descent from the misses: proposed with Adam only
            key = f"{method}{'/' + optimizer if optimizer else ''} | {name}"
            if key in done:
                continue
            t0 = time.perf_counter()
            descent = method == "difftaichi" or optimizer == "gd"
            iters = args.gd_iters if descent and name == "default" else args.iters
            result = _anchor_run(anchor, shot, iters) if method == "difftaichi" \
                else _our_run(model, shot, iters, method, optimizer or "gd")
            result["shot"] = list(shot)
            done[key] = result
            atomic_write(runs_path, json.dumps(done) + "\n")
            print(f"[billiards] {key}: reached {result['reached_target']} in {result['rollouts']} rollouts, "
                  f"distance {result['target_distance']:.4g} m, {time.perf_counter() - t0:.1f} s", flush=True)
    return done


def gradients(model) -> dict:
    import torch

    from benchmarks.difftaichi_anchor import DiffTaichiBilliards
    from scenes import billiards as B
    from scenes.optim import central_difference_check

    shot = np.asarray(B.STARTS["default"])
    ours = B.gradient_check(model, shot)
    anchor = DiffTaichiBilliards()
    _, grad = anchor.loss_and_grad(shot[:2], shot[2:])
    fd = {str(step): central_difference_check(grad, lambda s: anchor.loss_and_grad(s[:2], s[2:])[0], shot,
                                              step)["numeric"] for step in (1e-2, 1e-3)}
    # grazing sweep: a ball struck at closest approaches 0.9 .. 1.1 x 2 r; the gradient of its
    # final position w.r.t. the cue's velocity, against the free flight's (1 s: the time)
    from sim.builder import ModelBuilder
    from sim.rollout import rollout

    sweep = []
    for ratio in np.linspace(0.9, 1.1, 41):
        b = ModelBuilder(gravity=0.0)
        b.set_contact(restitution=0.8, friction=0.0)
        b.add_sphere(B.RADIUS, mass=1.0, pos=(0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
        b.add_sphere(B.RADIUS, mass=1.0, pos=(0.2, ratio * 2 * B.RADIUS, 0.0))
        m = b.finalize()
        bqd = torch.from_numpy(m.body_qd.numpy().copy()).requires_grad_()
        res = rollout(m, 300, 0.003, 1, body_qd=bqd)
        res.body_q[-1, 1, :2].sum().backward()
        sweep.append({"ratio": float(ratio), "gradient_norm": float(bqd.grad[0].norm()),
                      "finite": bool(torch.isfinite(bqd.grad).all())})
    free_flight = 300 * 0.003 * math.sqrt(2.0)  # |d (x + y) / d (vx, vy)| of a ball in free flight
    return {"ours": ours, "difftaichi": {"autodiff": grad.tolist(), "central_differences": fd},
            "grazing": sweep, "free_flight_gradient": free_flight}


def timing(model, rounds: int = 15) -> dict:
    """Seconds per iteration (forward + backward) from DiffTaichi's start, each simulator
    ``rounds`` times in a loop of its own, compiled first: the medians (run it on a quiet
    machine)."""
    from benchmarks.difftaichi_anchor import DiffTaichiBilliards
    from scenes import billiards as B

    anchor = DiffTaichiBilliards()
    shot = B.STARTS["default"]
    anchor.loss_and_grad(shot[:2], shot[2:])
    B.evaluate(model, shot, "proposed", grad=True)[2].backward()
    ours, theirs = [], []
    # each in a loop of its own (alternating them slowed DiffTaichi's iterations 3.5x here)
    for _ in range(rounds):
        t0 = time.perf_counter()
        anchor.loss_and_grad(shot[:2], shot[2:])
        theirs.append(time.perf_counter() - t0)
    for _ in range(rounds):
        t0 = time.perf_counter()
        z, _, loss, _, _ = B.evaluate(model, shot, "proposed", grad=True)
        loss.backward()
        ours.append(time.perf_counter() - t0)
    return {"ours": float(np.median(ours)), "difftaichi": float(np.median(theirs)), "rounds": rounds,
            "ratio": float(np.median(ours) / np.median(theirs))}


def scale(rows_list) -> list[dict]:
    from scenes import billiards as B

    out = []
    for rows in rows_list:
        model = B.build(rows=rows)
        shot = (0.1, 0.5, 2.0, 0.0)
        B.simulate(model, shot, grad=True)[1].body_q.sum().backward()  # compile, warm
        forward, backward = [], []
        for _ in range(3):
            t0 = time.perf_counter()
            z, res = B.simulate(model, shot, grad=True)
            t1 = time.perf_counter()
            res.body_q[-1, :, :2].sum().backward()
            forward.append(t1 - t0)
            backward.append(time.perf_counter() - t1)
        out.append({"rows": rows, "balls": model.body_count, "pairs": model.body_count * (model.body_count - 1) // 2,
                    "forward": float(np.median(forward)), "backward": float(np.median(backward)),
                    "moved": int(B.moved(res).sum())})
        print(f"[billiards] scale {model.body_count} balls: forward {out[-1]['forward']:.3f} s, "
              f"backward {out[-1]['backward']:.3f} s", flush=True)
    return out


def breaks(count: int, seed: int = 0) -> dict:
    from scenes import billiards as B

    model = B.build()
    rng = np.random.default_rng(seed)
    deepest, drift, overlapping = 0.0, 0.0, 0
    t0 = time.perf_counter()
    for k in range(count):
        y, speed = rng.uniform(0.4, 0.6), rng.uniform(0.5, 3.0)
        angle = math.atan2(0.55 - y, 0.5) + rng.uniform(-0.1, 0.1)
        _, res = B.simulate(model, (0.1, y, speed * math.cos(angle), speed * math.sin(angle)))
        q, qd = res.body_q.numpy()[:, :, :2], res.body_qd.numpy()[:, :, 3:5]
        gaps = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1) - 2 * B.RADIUS
        n = q.shape[1]
        gaps[:, np.arange(n), np.arange(n)] = np.inf
        depth = float(max(-gaps.min(), 0.0))
        deepest = max(deepest, depth)
        overlapping += depth > 1e-12
        momentum = qd.sum(axis=1)
        drift = max(drift, float(np.abs(momentum - momentum[0]).max()))
        if (k + 1) % 500 == 0:
            print(f"[billiards] breaks {k + 1}/{count}: deepest overlap {deepest:.3g} m", flush=True)
    return {"breaks": count, "deepest_overlap": deepest, "breaks_with_overlap": overlapping,
            "momentum_drift": drift, "seconds": time.perf_counter() - t0}


def _summary(done: dict) -> tuple[list[str], dict]:
    lines = ["## From DiffTaichi's start", "",
             "Plain gradient descent (learning rate 0.01) unless marked Adam; every run stops at the goal (5 mm). "
             "A run that does not reach it plays its whole budget: rollouts = steps + 1.", ""]
    rows = []
    for key, r in done.items():
        if key.endswith("| default"):
            rows.append([key.split(" | ")[0], r["reached_target"], r["iterations_to_target"], r["final_loss"],
                         r["target_distance"], r["rollouts"], r["seconds_per_iteration"]])
    lines += table(["method", "reached", "iteration at the goal", "final loss [m^2]", "distance [m]", "rollouts",
                    "s / iteration"], rows)
    lines += ["", "## From misses", ""]
    per_method: dict[str, list] = {}
    for key, r in done.items():
        method, start = key.split(" | ")
        if start != "default":
            per_method.setdefault(method, []).append((start, r))
    rows = []
    for method, runs in per_method.items():
        reached = [r for _, r in runs if r["reached_target"]]
        rows.append([method, f"{len(reached)} / {len(runs)}",
                     float(np.median([r["iterations_to_target"] for r in reached])) if reached else None,
                     float(np.median([r["target_distance"] for _, r in runs])),
                     float(np.median([r["seconds_per_iteration"] for _, r in runs]))])
    lines += table(["method", "reached the goal", "median iterations (reached)", "median final distance [m]",
                    "median s / iteration"], rows)
    lines += ["", "Per start:", ""]
    starts = sorted({key.split(" | ")[1] for key in done if not key.endswith("| default")},
                    key=lambda s: (s.startswith("seed"), int(s.split()[1]) if s.startswith("seed") else 0, s))
    methods = list(per_method)
    rows = []
    for start in starts:
        row = [start]
        for method in methods:
            r = done.get(f"{method} | {start}")
            row.append("—" if r is None else (f"{r['iterations_to_target']}" if r["reached_target"]
                                               else f"no ({r['target_distance']:.3g} m)"))
        rows.append(row)
    lines += table(["start"] + [f"{m}: iteration at the goal" for m in methods], rows)
    return lines, {"runs": done}


def _plot(done: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scenes.optim import draw_loss_curves

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, start in zip(axes, ("default", "seed 0")):
        curves = {key.split(" | ")[0]: r["loss_curve"] for key, r in done.items() if key.split(" | ")[1] == start}
        draw_loss_curves(ax, curves, "loss (squared distance [m^2]; a miss: the method's own loss)")
        ax.set_title(f"billiards from '{start}'")
    save_figure(fig, path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iters", type=int, default=200, help="optimiser steps per run at most: N + 1 rollouts (default 200)")
    parser.add_argument("--gd-iters", type=int, default=700,
                        help="gradient-descent steps from DiffTaichi's start (plain descent on the true gradient "
                             "is slow there; default 700)")
    parser.add_argument("--seeds", type=int, default=20, help="seeded misses 0 .. N-1 (default 20)")
    parser.add_argument("--breaks", type=int, default=10000, help="random breaks (default 10000)")
    parser.add_argument("--rows", default="4,6,8,10,13", help="rack rows of the scale part (default 4,6,8,10,13)")
    parser.add_argument("--parts", default="shots,gradients,timing,scale,breaks", help="which parts run")
    parser.add_argument("--out", default=os.path.join(RESULTS, "billiards"))
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from scenes import billiards as B

    parts = set(args.parts.split(","))
    data_path = args.out + ".json"
    data = json.load(open(data_path)) if os.path.exists(data_path) else {}
    model = B.build()
    if "shots" in parts:
        data["shots"] = shots(args, model, args.out + "_runs.json")
    if "gradients" in parts:
        data["gradients"] = gradients(model)
    if "timing" in parts:
        data["timing"] = timing(model)
    if "scale" in parts:
        data["scale"] = scale([int(r) for r in args.rows.split(",")])
    if "breaks" in parts:
        data["breaks"] = breaks(args.breaks)
    lines = []
    if "shots" in data:
        more, _ = _summary(data["shots"])
        lines += more
        _plot(data["shots"], args.out + ".png")
    if "gradients" in data:
        g = data["gradients"]
        grazing = g["grazing"]
        lines += ["", "## Gradients at DiffTaichi's start", "",
                  f"- ours (float64) against central differences (step 1e-6): relative error "
                  f"{g['ours']['relative_error']:.2g}; gradient {np.round(g['ours']['analytic'], 4).tolist()}",
                  f"- DiffTaichi's autodiff (float32): {np.round(g['difftaichi']['autodiff'], 4).tolist()}; "
                  f"central differences of its own forward: step 1e-2 "
                  f"{np.round(g['difftaichi']['central_differences']['0.01'], 4).tolist()}, step 1e-3 "
                  f"{np.round(g['difftaichi']['central_differences']['0.001'], 4).tolist()}",
                  f"- grazing sweep (41 closest approaches, 0.9 - 1.1 x 2 r): all finite: "
                  f"{all(s['finite'] for s in grazing)}; largest gradient norm "
                  f"{max(s['gradient_norm'] for s in grazing):.3g} against the free flight's "
                  f"{g['free_flight_gradient']:.3g}"]
    if "timing" in data:
        t = data["timing"]
        lines += ["", "## Seconds per iteration (forward + backward, DiffTaichi's start, alone on the machine)", "",
                  f"ours {t['ours']:.3f} s (float64), DiffTaichi {t['difftaichi']:.3f} s (float32): "
                  f"ratio {t['ratio']:.2f} (medians of {t['rounds']} rounds each)."]
    if "scale" in data:
        sc = data["scale"]
        balls = np.array([s["balls"] for s in sc], dtype=np.float64)
        fwd = np.array([s["forward"] for s in sc])
        bwd = np.array([s["backward"] for s in sc])
        ef = float(np.polyfit(np.log(balls), np.log(fwd), 1)[0]) if len(sc) > 1 else None
        eb = float(np.polyfit(np.log(balls), np.log(bwd), 1)[0]) if len(sc) > 1 else None
        lines += ["", "## Scale (1023 steps, cue at 2 m/s into the rack)", ""]
        lines += table(["rows", "balls", "pairs", "balls moved", "forward [s]", "backward [s]"],
                       [[s["rows"], s["balls"], s["pairs"], s["moved"], s["forward"], s["backward"]] for s in sc])
        lines += ["", f"Growth exponents (time ~ balls^k): forward {ef:.2f}, backward {eb:.2f}."
                  if ef is not None else ""]
        data["scale_exponents"] = {"forward": ef, "backward": eb}
    if "breaks" in data:
        b = data["breaks"]
        lines += ["", "## Random breaks", "",
                  f"{b['breaks']} breaks: deepest overlap of any pair at any step {b['deepest_overlap']:.3g} m "
                  f"({b['breaks_with_overlap']} breaks overlap beyond 1e-12 m); momentum drift "
                  f"{b['momentum_drift']:.3g} kg m/s; {b['seconds']:.0f} s."]
    write(args.out, "Billiards beside DiffTaichi", lines, data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
