"""The speed/accuracy trade of the simulation settings: wall time against accuracy, per scene.

    python benchmarks/trade.py [--quick | --full] [--out benchmarks/results/trade]

For each simulation scene (``cloth_drop``, ``rigid_toss``, ``cloth_rigid``) every setting of a
grid runs the scene for the same simulated time and is compared with a *reference* run of the
same scene at many more substeps (semi-implicit, Gauss-Seidel response, everything else at the
defaults). The grid: substeps x integrator (semi-implicit / implicit), plus one-factor changes at
the default 8 substeps: the contact thickness (x0.1, x10), the collision rounds per substep, the
response (replayed exact solve instead of Gauss-Seidel), CG's tolerance (implicit), and the narrow
phase that decides the CCD contacts: float32, its error bounds' tolerance scale, its root solver's
iteration cap (``--ccd-precision``, ``--ccd-tolerance-scale``, ``--root-max-iterations``).

Accuracy, per run (all from the run itself or the reference run, never from the settings):

* ``penetrations``: most intersecting primitive pairs on any frame (independent checker,
  :class:`sim.penetration.PenetrationChecker`), and their largest depth: missed collisions;
* ``deviation``: largest distance of a particle or body origin from the reference run's at the
  end, over the scene's size (the diagonal of its initial bounding box);
* ``energy gain``: most total energy on any frame over the initial (> 1: energy was created);
* ``fail-safe``: substeps that needed rigid impact zones.

Speed: mean wall time of a step (forces, integration, collision handling; not the checker),
after the kernels are loaded. A setting is *acceptable* when it has no penetration, did not
diverge and gains at most :data:`ENERGY_GAIN_LIMIT`; the Pareto front is taken over the
acceptable settings in (ms/step, deviation), and the *recommended* setting is the fastest point
of the front within :data:`DEVIATION_GOAL` of the reference (marked ★).

``M`` (the robust division's bound) does not change a forward simulation at all; it shapes the
gradients. Its trade is measured on the inverse scene ``tunnel`` (final loss and success of the
proposed method's Adam runs for several ``M``, same seeds and budget). Precision: the scenes step
in float64 only (``--precision float32`` is not offered); float32 enters through the CCD
decisions here, and the float32 root solver and CCD on their own are measured in the roots and
CCD benchmarks.

Writes ``<out>.md``, ``<out>.json`` and ``<out>.png`` (one panel per scene: ms/step against
deviation, the front, the recommended setting).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)  # before this folder: benchmarks/sim.py must not shadow the sim package

from benchmarks import report  # noqa: E402

SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid")
ENERGY_GAIN_LIMIT = 1.01
"""An acceptable run never holds more than 1 % above its initial energy (the scenes only lose
energy to contacts and damping, or exchange it with gravity)."""
DEVIATION_GOAL = 0.01
"""The recommended setting ends within 1 % of the scene's size of the reference run."""

CONFIGS = {
    # steps, reference substeps, substeps of the grid, one-factor changes at 8 substeps
    "quick": dict(steps=30, reference=32, substeps=(4, 8, 16), tunnel_seeds=(0,), tunnel_iters=30,
                  max_derivatives=(10.0, 1000.0, 1.0e6),
                  variants=({"thickness_factor": 10.0}, {"collision_rounds": 2}, {"response": "replayed"},
                            {"ccd_precision": "float32"})),
    "default": dict(steps=90, reference=64, substeps=(2, 4, 8, 16, 32), tunnel_seeds=(0, 1), tunnel_iters=100,
                    max_derivatives=(10.0, 100.0, 1000.0, 1.0e4, 1.0e6),
                    variants=({"thickness_factor": 0.1}, {"thickness_factor": 10.0}, {"collision_rounds": 1},
                              {"collision_rounds": 2}, {"response": "replayed"},
                              {"integrator": "implicit", "cg_tolerance": 1e-4}, {"ccd_precision": "float32"},
                              {"ccd_tolerance_scale": 0.1}, {"root_max_iterations": 4})),
    "full": dict(steps=180, reference=128, substeps=(2, 4, 8, 16, 32, 64), tunnel_seeds=(0, 1, 2, 3),
                 tunnel_iters=300, max_derivatives=(1.0, 10.0, 100.0, 1000.0, 1.0e4, 1.0e6),
                 variants=({"thickness_factor": 0.1}, {"thickness_factor": 10.0}, {"collision_rounds": 1},
                           {"collision_rounds": 2}, {"collision_rounds": 4}, {"response": "replayed"},
                           {"integrator": "implicit", "response": "replayed"},
                           {"integrator": "implicit", "cg_tolerance": 1e-4},
                           {"integrator": "implicit", "cg_tolerance": 1e-12}, {"ccd_precision": "float32"},
                           {"ccd_precision": "float32", "ccd_tolerance_scale": 10.0},
                           {"ccd_tolerance_scale": 0.1}, {"ccd_tolerance_scale": 10.0},
                           {"root_max_iterations": 2}, {"root_max_iterations": 4})),
}


def _scene_module(name: str):
    import importlib

    return importlib.import_module(f"scenes.{name}")


def _positions(final: dict[str, np.ndarray]) -> np.ndarray:
    parts = [np.asarray(final["particle_q"]).reshape(-1, 3)]
    if np.asarray(final["body_q"]).size:
        parts.append(np.asarray(final["body_q"]).reshape(-1, 7)[:, :3])
    return np.concatenate(parts)


def _scene_scale(module) -> tuple[float, float]:
    """(size [m]: the diagonal of the scene's initial bounding box; the contact thickness the
    collision handler uses at the scene's defaults [m])."""
    from collision.response import ImpulseCollisionHandler
    from scenes.sim_common import build_model, default_args

    model = build_model(module.build, default_args())
    pts = _positions(model.state().numpy())
    size = float(np.linalg.norm(pts.max(0) - pts.min(0))) or 1.0
    return size, float(ImpulseCollisionHandler(model).separation)


def setting_label(s: dict[str, Any]) -> str:
    """Short text of a setting (what differs from the defaults)."""
    parts = [f"{s['substeps']} sub", "impl" if s["integrator"] == "implicit" else "semi"]
    if s.get("response", "gauss-seidel") != "gauss-seidel":
        parts.append(s["response"])
    if s.get("thickness_factor", 1.0) != 1.0:
        parts.append(f"thick x{s['thickness_factor']:g}")
    if s.get("collision_rounds", 8) != 8:
        parts.append(f"{s['collision_rounds']} rounds")
    if s.get("cg_tolerance") is not None:
        parts.append(f"cg {s['cg_tolerance']:g}")
    if s.get("ccd_precision", "float64") != "float64":
        parts.append(f"ccd {s['ccd_precision']}")
    if s.get("ccd_tolerance_scale", 1.0) != 1.0:
        parts.append(f"ccd tol x{s['ccd_tolerance_scale']:g}")
    if s.get("root_max_iterations") is not None:
        parts.append(f"{s['root_max_iterations']} root its")
    return ", ".join(parts)


def run_setting(module, setting: dict[str, Any], steps: int, thickness: float) -> dict[str, Any]:
    """One run of ``module`` with ``setting``: the summary's figures and the end positions (or
    the divergence)."""
    from scenes.sim_common import SimulationDiverged, default_args, simulate

    args = default_args(steps=steps, substeps=setting["substeps"], integrator=setting["integrator"],
                        response=setting.get("response", "gauss-seidel"),
                        collision_rounds=setting.get("collision_rounds", 8),
                        cg_tolerance=setting.get("cg_tolerance"),
                        thickness=thickness * setting.get("thickness_factor", 1.0),
                        ccd_precision=setting.get("ccd_precision", "float64"),
                        ccd_tolerance_scale=setting.get("ccd_tolerance_scale", 1.0),
                        root_max_iterations=setting.get("root_max_iterations"))
    try:
        summary, final = simulate(module.build, args, None, name=module.NAME, progress=False)
    except SimulationDiverged as exc:
        return {"diverged": str(exc).split(":")[1].strip() if ":" in str(exc) else str(exc)}
    return {"diverged": None, "summary": summary, "positions": _positions(final)}


def _pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both coordinates (lower is better)."""
    front = []
    for i, (a, b) in enumerate(points):
        dominated = any((c <= a and d <= b) and (c < a or d < b) for j, (c, d) in enumerate(points) if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


def scene_trade(name: str, config: dict[str, Any], progress) -> dict[str, Any]:
    module = _scene_module(name)
    size, thickness = _scene_scale(module)
    steps = config["steps"]
    grid = [{"substeps": n, "integrator": kind} for kind in ("semi_implicit", "implicit") for n in config["substeps"]]
    for v in config["variants"]:
        grid.append({"substeps": 8, "integrator": "semi_implicit", **v})
    # kernels load at their first launch: one short run per integrator x response first, so
    # that no timed run pays for it
    for kind in ("semi_implicit", "implicit"):
        for response in ("gauss-seidel", "replayed"):
            run_setting(module, {"substeps": 8, "integrator": kind, "response": response}, 2, thickness)
    for v in config["variants"]:  # generated narrow-phase variants compile at their first launch too
        if any(key in v for key in ("ccd_precision", "ccd_tolerance_scale", "root_max_iterations")):
            run_setting(module, {"substeps": 8, "integrator": "semi_implicit", **v}, 2, thickness)
    reference = run_setting(module, {"substeps": config["reference"], "integrator": "semi_implicit"}, steps, thickness)
    if reference["diverged"]:
        raise RuntimeError(f"{name}: the reference run diverged: {reference['diverged']}")
    rows = []
    for setting in grid:
        progress(f"{name}: {setting_label(setting)}")
        r = run_setting(module, setting, steps, thickness)
        row = {"setting": setting, "label": setting_label(setting), "diverged": r["diverged"]}
        if not r["diverged"]:
            s = r["summary"]
            row.update(
                ms_per_step=s["step_ms_mean"], penetrations=s["penetrations"],
                max_depth=s["max_penetration_depth"], energy_gain=s["energy_max_ratio"],
                energy_drift=s["energy_drift"], failsafe=s["failsafe_count"], contacts=s["contacts"],
                deviation=float(np.max(np.linalg.norm(r["positions"] - reference["positions"], axis=1))) / size,
            )
            gain = row["energy_gain"] if row["energy_gain"] is not None else 1.0
            row["acceptable"] = row["penetrations"] == 0 and gain <= ENERGY_GAIN_LIMIT
        else:
            row["acceptable"] = False
        rows.append(row)
    ok = [i for i, r in enumerate(rows) if r["acceptable"]]
    front = [ok[k] for k in _pareto([(rows[i]["ms_per_step"], rows[i]["deviation"]) for i in ok])]
    for i, r in enumerate(rows):
        r["pareto"] = i in front
    close = [i for i in front if rows[i]["deviation"] <= DEVIATION_GOAL]
    # none within the goal: the most accurate acceptable setting (the front's slowest)
    recommended = close[0] if close else (front[-1] if front else None)
    for i, r in enumerate(rows):
        r["recommended"] = i == recommended
    ref = reference["summary"]
    return {"scene": name, "size": size, "thickness": thickness, "steps": steps, "goal_met": bool(close),
            "reference": {"substeps": config["reference"], "ms_per_step": ref["step_ms_mean"],
                          "penetrations": ref["penetrations"], "energy_gain": ref["energy_max_ratio"]},
            "rows": rows}


def tunnel_trade(config: dict[str, Any], progress) -> list[dict[str, Any]]:
    """The proposed method on ``tunnel`` for each ``M`` (same seeds, same Adam budget)."""
    from scenes import tunnel

    out = []
    problems = {seed: tunnel.make_problem(seed) for seed in config["tunnel_seeds"]}
    for m in config["max_derivatives"]:
        progress(f"tunnel: M = {m:g}")
        losses, reached, walls, rollouts = [], 0, 0.0, 0
        for seed, problem in problems.items():
            r = tunnel.optimise(problem, config["tunnel_iters"], "proposed", max_derivative=m)
            losses.append(r["final_loss"])
            reached += bool(r["reached_target"])
            walls += r["wall_time"]
            rollouts += r["rollouts"]
        finite = [x for x in losses if x is not None and np.isfinite(x)]
        out.append({"max_derivative": m, "seeds": len(problems), "reached": reached,
                    "median_final_loss": float(np.median(finite)) if finite else None,
                    "ms_per_rollout": 1e3 * walls / max(rollouts, 1), "wall_s": walls})
    return out


def _plot(results: list[dict[str, Any]], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.2), squeeze=False)
    for ax, res in zip(axes[0], results):
        rows = [r for r in res["rows"] if not r["diverged"]]
        for kind, marker in (("semi_implicit", "o"), ("implicit", "s")):
            good = [r for r in rows if r["setting"]["integrator"] == kind and r["acceptable"]]
            bad = [r for r in rows if r["setting"]["integrator"] == kind and not r["acceptable"]]
            floor = 1e-12  # a deviation of exactly 0 (the reference's own setting) on a log axis
            ax.scatter([r["ms_per_step"] for r in good], [max(r["deviation"], floor) for r in good], marker=marker,
                       label=f"{kind}", alpha=0.8)
            if bad:
                ax.scatter([r["ms_per_step"] for r in bad], [max(r["deviation"], floor) for r in bad], marker="x",
                           color="red", label=f"{kind}: penetrates / gains energy")
        front = sorted([r for r in rows if r["pareto"]], key=lambda r: r["ms_per_step"])
        if front:
            ax.plot([r["ms_per_step"] for r in front], [max(r["deviation"], 1e-12) for r in front], "k--", lw=1,
                    label="Pareto front")
        for r in rows:
            if r["recommended"]:
                ax.scatter([r["ms_per_step"]], [max(r["deviation"], 1e-12)], marker="*", s=260, color="gold",
                           edgecolor="k", zorder=5, label=f"recommended: {r['label']}")
        ax.axhline(DEVIATION_GOAL, color="grey", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time per step [ms]")
        ax.set_ylabel("end deviation from the reference / scene size")
        ax.set_title(f"{res['scene']} ({res['steps']} steps)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    report.save_figure(fig, path)
    plt.close(fig)


def main(argv=None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    report.add_size_arguments(parser, SCENES, "trade", "a small grid and short runs (a few minutes)",
                              "the largest grid and longest runs")
    parser.add_argument("--skip-tunnel", action="store_true", help="leave out the M sweep on the tunnel scene")
    parser.add_argument("--tunnel-iters", type=int, default=None, help="override the Adam iterations per tunnel run")
    args = parser.parse_args(argv)
    config, scenes = report.chosen(parser, args, CONFIGS, SCENES)
    if args.tunnel_iters is not None:
        if args.tunnel_iters < 1:
            parser.error("--tunnel-iters must be >= 1")
        config["tunnel_iters"] = args.tunnel_iters

    import warp as wp

    wp.config.quiet = True
    start = time.perf_counter()

    def progress(text: str) -> None:
        print(f"[trade {time.perf_counter() - start:6.0f} s] {text}", file=sys.stderr, flush=True)

    results = [scene_trade(name, config, progress) for name in scenes]
    tunnel = [] if args.skip_tunnel else tunnel_trade(config, progress)

    lines = [f"Each scene runs {config['steps']} steps of 1/60 s per setting; the reference is "
             f"{config['reference']} substeps (semi-implicit, Gauss-Seidel). deviation: largest end distance "
             "from the reference over the scene size; pen.: most intersecting pairs on a frame (depth [m]); "
             f"energy gain: most energy on a frame over the initial (acceptable <= {ENERGY_GAIN_LIMIT}). "
             f"★ recommended: the fastest Pareto setting within {DEVIATION_GOAL:g} of the reference; "
             "P: on the Pareto front of the acceptable settings.", ""]
    for res in results:
        ref = res["reference"]
        lines += [f"## {res['scene']}", "",
                  f"Scene size {res['size']:.3g} m, default thickness {res['thickness']:.3g} m; reference "
                  f"{ref['ms_per_step']:.1f} ms/step, {ref['penetrations']} penetrations."
                  + ("" if res["goal_met"] else f" No acceptable setting of the grid ends within {DEVIATION_GOAL:g} of "
                     "the reference: ★ marks the most accurate one of the front."), ""]
        body = []
        for r in sorted(res["rows"], key=lambda r: (r["diverged"] is not None, r.get("ms_per_step", 0.0))):
            mark = "★" if r["recommended"] else ("P" if r["pareto"] else "")
            if r["diverged"]:
                body.append([r["label"], "diverged", None, None, None, None, None, r["diverged"][:60]])
                continue
            body.append([r["label"], r["ms_per_step"], r["deviation"], f"{r['penetrations']} ({fmt_depth(r['max_depth'])})",
                         r["energy_gain"], r["failsafe"], r["contacts"], mark])
        lines += report.table(["setting", "ms/step", "deviation", "pen. (depth)", "energy gain", "fail-safe",
                               "contacts", ""], body)
        lines.append("")
    if tunnel:
        lines += ["## M on the inverse scene `tunnel`", "",
                  f"The proposed method (mollified derivatives bounded by M), {config['tunnel_iters']} Adam "
                  f"iterations per seed, seeds {', '.join(str(s) for s in config['tunnel_seeds'])}:", ""]
        lines += report.table(["M", "reached target", "median final loss", "ms/rollout"],
                              [[t["max_derivative"], f"{t['reached']}/{t['seeds']}", t["median_final_loss"],
                                t["ms_per_rollout"]] for t in tunnel])
        lines.append("")
    lines += ["Precision: the scenes step in float64 only (`--precision float32` is not offered). The float32 "
              "root solver and CCD are measured in `roots.md` and `ccd.md`.", ""]
    _plot(results, args.out + ".png")
    report.write(args.out, "Speed/accuracy trade of the simulation settings", lines,
                 {"config": {k: v for k, v in config.items()}, "scenes": results, "tunnel": tunnel})
    print(f"wrote {args.out}.md, .json, .png", file=sys.stderr)
    return {"scenes": results, "tunnel": tunnel}


def fmt_depth(depth: float) -> str:
    return "0" if not depth else f"{depth:.2g}"


if __name__ == "__main__":
    main()
