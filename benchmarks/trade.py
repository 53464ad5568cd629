"""The speed/accuracy trade of the simulation settings: wall time against accuracy, per scene.

    python benchmarks/trade.py [--quick | --full] [--out benchmarks/results/trade]

For each simulation scene (``cloth_drop``, ``rigid_toss``, ``cloth_rigid``) every setting of a
grid runs the scene for the same simulated time and is compared with a *reference* run of the
same scene at many more substeps (semi-implicit, the default replayed response, everything else
at the defaults). The grid: substeps x integrator (semi-implicit / implicit), plus one-factor
changes at the default 8 substeps: the contact thickness (x0.1, x10), the collision rounds per
substep, the response (Gauss-Seidel instead of the replayed exact solve), CG's tolerance
(implicit), and the narrow phase that decides the CCD contacts: float32, its error bounds'
tolerance scale, its root solver's iteration cap (``--ccd-precision``, ``--ccd-tolerance-scale``,
``--root-max-iterations``).

**Noise floor.** Contact-rich motion amplifies rounding (a compressed cloth buckles; a box's
tumble depends on which corner lands first), so a setting's end state can differ from the
reference by more than its method error. :data:`ENSEMBLE` copies of the reference run start
with every initial position moved by :data:`PERTURBATION` of the scene's size; their largest
difference from the reference is the floor, per observable and per step (amplification: floor
over perturbation; growth rate: a fit of log floor against time where it rises). A difference
inside the floor is reported as *within noise*, never as error.

**Observables** (:data:`OBSERVABLES`, each at the last step against the reference, with the
tolerance :data:`TOLERANCE` in its unit): the pointwise deviation, the centre of mass and its
velocity, the total energy, and the time of the first contact. Those whose floor is below the
tolerance decide the recommendation.

Hard constraints, per run: ``penetrations`` (most intersecting primitive pairs on any frame,
from the independent checker :class:`sim.penetration.PenetrationChecker`), ``energy gain``
(most total energy on a frame over the initial), ``fail-safe`` (substeps that needed rigid
impact zones).

Speed: mean wall time of a step (forces, integration, collision handling; not the checker),
after the kernels are loaded. A setting is *acceptable* when it has no penetration, did not
diverge and gains at most :data:`ENERGY_GAIN_LIMIT`; the Pareto front is taken over the
acceptable settings in (ms/step, the largest error beyond the floor on a decisive observable),
and the *recommended* setting (★) is the fastest point of the front whose decisive errors are
all within the tolerance or within noise; the table names the observable that decided it.

``M`` (the robust division's bound) does not change a forward simulation at all; it shapes the
gradients. Its trade is measured on the inverse scene ``tunnel`` (final loss and success of the
proposed method's Adam runs for several ``M``, same seeds and budget). Precision: the scenes step
in float64 only (``--precision float32`` is not offered); float32 enters through the CCD
decisions here, and the float32 root solver and CCD on their own are measured in the roots and
CCD benchmarks.

Writes ``<out>.md``, ``<out>.json`` and ``<out>.png`` (a row of panels per scene, one per
observable: error against ms/step, the noise floor as a grey band, the recommended setting).
"""

from __future__ import annotations

import argparse
import math
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
                  variants=({"thickness_factor": 10.0}, {"collision_rounds": 2}, {"response": "gauss-seidel"},
                            {"ccd_precision": "float32"})),
    "default": dict(steps=90, reference=64, substeps=(2, 4, 8, 16, 32), tunnel_seeds=(0, 1), tunnel_iters=100,
                    max_derivatives=(10.0, 100.0, 1000.0, 1.0e4, 1.0e6),
                    variants=({"thickness_factor": 0.1}, {"thickness_factor": 10.0}, {"collision_rounds": 1},
                              {"collision_rounds": 2}, {"response": "gauss-seidel"},
                              {"integrator": "implicit", "cg_tolerance": 1e-4}, {"ccd_precision": "float32"},
                              {"ccd_tolerance_scale": 0.1}, {"root_max_iterations": 4})),
    "full": dict(steps=180, reference=128, substeps=(2, 4, 8, 16, 32, 64), tunnel_seeds=(0, 1, 2, 3),
                 tunnel_iters=300, max_derivatives=(1.0, 10.0, 100.0, 1000.0, 1.0e4, 1.0e6),
                 variants=({"thickness_factor": 0.1}, {"thickness_factor": 10.0}, {"collision_rounds": 1},
                           {"collision_rounds": 2}, {"collision_rounds": 4}, {"response": "gauss-seidel"},
                           {"integrator": "implicit", "response": "gauss-seidel"},
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
    from sim.contact.response import ImpulseCollisionHandler
    from scenes.sim_common import build_model, default_args

    model = build_model(module.build, default_args())
    pts = _positions(model.state().numpy())
    size = float(np.linalg.norm(pts.max(0) - pts.min(0))) or 1.0
    return size, float(ImpulseCollisionHandler(model).separation)


def setting_label(s: dict[str, Any]) -> str:
    """Short text of a setting (what differs from the defaults)."""
    parts = [f"{s['substeps']} sub", "impl" if s["integrator"] == "implicit" else "semi"]
    if s.get("response", "replayed") != "replayed":
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


PERTURBATION = 1e-10
"""The noise floor's perturbation: every initial particle and body position moves by a random
vector of this length times the scene's size."""
ENSEMBLE = 4
"""Perturbed copies of the reference run that measure the noise floor."""
TOLERANCE = 0.01
"""The accuracy goal on every observable, in its unit (:data:`OBSERVABLES`)."""
OBSERVABLES = {
    "pointwise": "largest distance of a particle or body origin from the reference's / scene size",
    "com": "distance of the centre of mass from the reference's / scene size",
    "com_velocity": "difference of the centre of mass' velocity / sqrt(g size)",
    "energy": "difference of the total energy / (total mass g size)",
    "first_contact": "difference of the time of the first contact / dt",
}
"""What each observable measures at the end of a run (against the reference run), in the unit
its tolerance and error use."""


class _Trace:
    """Per-step observables of one run (the :func:`scenes.sim_common.simulate` observer)."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self.positions: list[np.ndarray] = []
        self.com: list[np.ndarray] = []
        self.com_velocity: list[np.ndarray] = []
        self.energy: list[float] = []
        self.first_contact: float | None = None

    def bind(self, model):
        """``prepare`` for :func:`scenes.sim_common.simulate`: takes the masses of the model the
        run steps (returned unchanged)."""
        P, B = int(model.particle_count), int(model.body_count)
        self.masses = np.concatenate([model.particle_mass.numpy()[:P] if P else np.zeros(0),
                                      model.body_mass.numpy()[:B] if B else np.zeros(0)])
        return model

    def __call__(self, step: int, state, info: dict[str, Any]) -> None:
        arrays = state.numpy()
        x = _positions(arrays)
        v = [np.asarray(arrays["particle_qd"]).reshape(-1, 3)]
        if np.asarray(arrays["body_qd"]).size:
            v.append(np.asarray(arrays["body_qd"]).reshape(-1, 6)[:, 3:])
        v = np.concatenate(v)
        m = self.masses
        total = float(np.sum(m)) or 1.0
        self.positions.append(x)
        self.com.append((m[:, None] * x).sum(0) / total)
        self.com_velocity.append((m[:, None] * v).sum(0) / total)
        self.energy.append(float(info["kinetic"] + info["potential"]))
        toi = info["contacts"]["toi"]
        if self.first_contact is None and len(toi):
            self.first_contact = (step - 1) * self.dt + float(np.min(toi))


def _perturbed(scale: float, seed: int):
    """``prepare`` for :func:`scenes.sim_common.simulate`: moves every initial particle and body
    position by a random vector of length ``scale`` [m]."""
    import warp as wp

    def prepare(model):
        rng = np.random.default_rng(seed)

        def shift(n):
            d = rng.normal(size=(n, 3))
            return scale * d / np.linalg.norm(d, axis=1, keepdims=True)

        if model.particle_count:
            x = model.particle_q.numpy().reshape(-1, 3).copy()
            model.particle_q = wp.array(x + shift(len(x)), dtype=wp.vec3d, device=model.device)
        if model.body_count:
            q = model.body_q.numpy().reshape(-1, 7).copy()
            q[:, :3] += shift(len(q))
            model.body_q = wp.array(q, dtype=wp.transformd, device=model.device)
        return model

    return prepare


def run_setting(module, setting: dict[str, Any], steps: int, thickness: float, perturb: float = 0.0,
                seed: int = 0) -> dict[str, Any]:
    """One run of ``module`` with ``setting`` (initial positions perturbed by ``perturb`` [m]):
    the summary's figures and the per-step trace (or the divergence)."""
    from scenes.sim_common import SimulationDiverged, default_args, simulate

    args = default_args(steps=steps, substeps=setting["substeps"], integrator=setting["integrator"],
                        response=setting.get("response", "replayed"),
                        collision_rounds=setting.get("collision_rounds", 8),
                        cg_tolerance=setting.get("cg_tolerance"),
                        thickness=thickness * setting.get("thickness_factor", 1.0),
                        ccd_precision=setting.get("ccd_precision", "float64"),
                        ccd_tolerance_scale=setting.get("ccd_tolerance_scale", 1.0),
                        root_max_iterations=setting.get("root_max_iterations"))
    trace = _Trace(float(args.dt))
    perturbed = _perturbed(perturb, seed) if perturb else None

    def prepare(model):
        return trace.bind(perturbed(model) if perturbed else model)

    try:
        summary, _ = simulate(module.build, args, None, name=module.NAME, progress=False, prepare=prepare,
                              observer=trace)
    except SimulationDiverged as exc:
        text = str(exc)
        return {"diverged": text.split(":", 1)[1].strip() if ":" in text else text}
    return {"diverged": None, "summary": summary, "trace": trace}


def observable_errors(run: _Trace, ref: _Trace, k: int, size: float, g: float, dt: float) -> dict[str, float]:
    """Each observable's difference between ``run`` and ``ref`` after step ``k`` (1-based), in
    the units of :data:`OBSERVABLES` (NaN for a first contact only one of them had)."""
    mass = float(np.sum(ref.masses)) or 1.0
    first = (abs(run.first_contact - ref.first_contact) / dt
             if run.first_contact is not None and ref.first_contact is not None
             else (0.0 if run.first_contact is None and ref.first_contact is None else math.nan))
    return {
        "pointwise": float(np.max(np.linalg.norm(run.positions[k - 1] - ref.positions[k - 1], axis=1))) / size,
        "com": float(np.linalg.norm(run.com[k - 1] - ref.com[k - 1])) / size,
        "com_velocity": float(np.linalg.norm(run.com_velocity[k - 1] - ref.com_velocity[k - 1])) / math.sqrt(g * size),
        "energy": abs(run.energy[k - 1] - ref.energy[k - 1]) / (mass * g * size),
        "first_contact": first,
    }


def noise_floor(reference: _Trace, members: list[_Trace], size: float, g: float, dt: float,
                steps: int) -> dict[str, Any]:
    """The spread of the perturbed runs around the reference: per step, each observable's
    largest difference over the members; the pointwise spread's amplification over the
    perturbation, and its growth rate fitted where it rises."""
    def largest(values):  # NaN (a member's first contact where the reference has none) is maximal noise
        values = list(values)
        return math.nan if any(math.isnan(v) for v in values) else max(values)

    per_step = [
        {name: largest(observable_errors(m, reference, k, size, g, dt)[name] for m in members)
         for name in OBSERVABLES}
        for k in range(1, steps + 1)
    ]
    spread = np.array([max(p["pointwise"], 1e-300) for p in per_step])
    # the window where log spread rises: from the first step 10x above the perturbation to the
    # step where it first reaches 1 % of the scene (or the end)
    start = next((k for k in range(steps) if spread[k] > 10.0 * PERTURBATION), None)
    rate, window = None, None
    if start is not None:
        end = next((k for k in range(start, steps) if spread[k] >= TOLERANCE), steps - 1)
        if end - start >= 2:
            t = (np.arange(start, end + 1) + 1) * dt
            rate = float(np.polyfit(t, np.log(spread[start:end + 1]), 1)[0])
            window = [(start + 1) * dt, (end + 1) * dt]
    horizons = sorted({max(1, round(f * steps)) for f in (0.1, 0.2, 0.3, 0.5, 0.7, 1.0)})
    return {"per_step": per_step,
            "noise_floor": [{"steps": k, "spread": float(spread[k - 1]),
                             "amplification": float(spread[k - 1] / PERTURBATION)} for k in horizons],
            "growth_rate": rate, "growth_window_s": window}


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
    dt = 1.0 / 60.0
    g = 9.81
    grid = [{"substeps": n, "integrator": kind} for kind in ("semi_implicit", "implicit") for n in config["substeps"]]
    for v in config["variants"]:
        grid.append({"substeps": 8, "integrator": "semi_implicit", **v})
    # kernels load at their first launch: one run per integrator x response that reaches
    # contact first, so that no timed run pays for it
    warm = max(2, min(steps, 20))
    for kind in ("semi_implicit", "implicit"):
        for response in ("gauss-seidel", "replayed"):
            run_setting(module, {"substeps": 8, "integrator": kind, "response": response}, warm, thickness)
    for v in config["variants"]:  # generated narrow-phase variants compile at their first launch too
        if any(key in v for key in ("ccd_precision", "ccd_tolerance_scale", "root_max_iterations")):
            run_setting(module, {"substeps": 8, "integrator": "semi_implicit", **v}, warm, thickness)
    ref_setting = {"substeps": config["reference"], "integrator": "semi_implicit"}
    reference = run_setting(module, ref_setting, steps, thickness)
    if reference["diverged"]:
        raise RuntimeError(f"{name}: the reference run diverged: {reference['diverged']}")
    ref = reference["trace"]
    members = []
    for seed in range(1, ENSEMBLE + 1):
        progress(f"{name}: noise floor, perturbed reference {seed}/{ENSEMBLE}")
        r = run_setting(module, ref_setting, steps, thickness, perturb=PERTURBATION * size, seed=seed)
        if r["diverged"]:
            raise RuntimeError(f"{name}: a perturbed reference run diverged: {r['diverged']}")
        members.append(r["trace"])
    floor = noise_floor(ref, members, size, g, dt, steps)
    end_floor = floor["per_step"][-1]
    # the observables that can tell settings apart: their floor below the tolerance
    decisive = [o for o in OBSERVABLES if end_floor[o] <= TOLERANCE]  # a NaN floor is not
    rows = []
    for setting in grid:
        progress(f"{name}: {setting_label(setting)}")
        r = run_setting(module, setting, steps, thickness)
        row = {"setting": setting, "label": setting_label(setting), "diverged": r["diverged"]}
        if not r["diverged"]:
            s = r["summary"]
            errors = observable_errors(r["trace"], ref, steps, size, g, dt)
            row.update(
                ms_per_step=s["step_ms_mean"], penetrations=s["penetrations"],
                max_depth=s["max_penetration_depth"], energy_gain=s["energy_max_ratio"],
                energy_drift=s["energy_drift"], failsafe=s["failsafe_count"], contacts=s["contacts"],
                deviation=errors["pointwise"], errors=errors,
                within_noise={o: bool(errors[o] <= end_floor[o]) for o in OBSERVABLES},
                # the pointwise deviation at the horizons where the floor is below the tolerance
                pointwise_at={str(h["steps"]): float(np.max(np.linalg.norm(
                    r["trace"].positions[h["steps"] - 1] - ref.positions[h["steps"] - 1], axis=1))) / size
                    for h in floor["noise_floor"] if h["spread"] <= TOLERANCE},
            )
            # error beyond the floor, per decisive observable, in units of the tolerance
            # a NaN error (a first contact only one run made) is as bad as it gets
            row["score"] = max([0.0] + [0.0 if row["within_noise"][o] else
                                        (errors[o] / TOLERANCE if math.isfinite(errors[o]) else math.inf)
                                        for o in decisive])
            gain = row["energy_gain"] if row["energy_gain"] is not None else 1.0
            row["acceptable"] = row["penetrations"] == 0 and gain <= ENERGY_GAIN_LIMIT
        else:
            row["acceptable"] = False
        rows.append(row)
    ok = [i for i, r in enumerate(rows) if r["acceptable"]]
    front = [ok[k] for k in _pareto([(rows[i]["ms_per_step"], rows[i]["score"]) for i in ok])]
    for i, r in enumerate(rows):
        r["pareto"] = i in front
    close = [i for i in front if rows[i]["score"] <= 1.0]
    # none within the goal: the most accurate acceptable setting (the front's slowest)
    recommended = close[0] if close else (front[-1] if front else None)
    for i, r in enumerate(rows):
        r["recommended"] = i == recommended
        r["decided_by"] = None
        if r.get("errors"):
            worst = max(decisive, key=lambda o: (r["errors"][o] if math.isfinite(r["errors"][o])
                                                 and not r["within_noise"][o] else -1.0), default=None)
            r["decided_by"] = worst if worst is not None and not r["within_noise"][worst] else None
    refs = reference["summary"]
    return {"scene": name, "size": size, "thickness": thickness, "steps": steps, "goal_met": bool(close),
            "reference": {"substeps": config["reference"], "ms_per_step": refs["step_ms_mean"],
                          "penetrations": refs["penetrations"], "energy_gain": refs["energy_max_ratio"]},
            "noise_floor": floor["noise_floor"], "growth_rate": floor["growth_rate"],
            "growth_window_s": floor["growth_window_s"], "end_floor": end_floor,
            "observables": list(OBSERVABLES), "decisive": decisive, "rows": rows}


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
    """One row per scene, one panel per observable: error against ms/step, the noise floor at
    the end as a grey band, the tolerance dotted, the recommended setting starred."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    names = list(OBSERVABLES)
    fig, axes = plt.subplots(len(results), len(names), figsize=(3.6 * len(names), 3.2 * len(results)), squeeze=False)
    tiny = 1e-14  # an error of exactly 0 on a log axis
    for row_axes, res in zip(axes, results):
        rows = [r for r in res["rows"] if not r["diverged"]]
        for ax, name in zip(row_axes, names):
            for kind, marker in (("semi_implicit", "o"), ("implicit", "s")):
                pts = [(r["ms_per_step"], max(r["errors"][name], tiny)) for r in rows
                       if r["setting"]["integrator"] == kind and math.isfinite(r["errors"][name])]
                if pts:
                    ax.scatter(*zip(*pts), marker=marker, alpha=0.8, label=kind)
            for r in rows:
                if r["recommended"] and math.isfinite(r["errors"][name]):
                    ax.scatter([r["ms_per_step"]], [max(r["errors"][name], tiny)], marker="*", s=220, color="gold",
                               edgecolor="k", zorder=5, label=f"recommended: {r['label']}")
            ax.axhspan(tiny, max(res["end_floor"][name], tiny), color="grey", alpha=0.25, label="noise floor")
            ax.axhline(TOLERANCE, color="k", lw=0.8, ls=":")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # no overlapping minor labels
            ax.set_xlabel("ms per step")
            ax.set_title(f"{res['scene']}: {name}", fontsize=9)
        row_axes[0].set_ylabel(f"error at step {res['steps']}")
        row_axes[0].legend(fontsize=6)
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

    lines = [f"Each scene runs {config['steps']} steps of 1/60 s per setting against a reference of "
             f"{config['reference']} substeps (semi-implicit, replayed response). **Noise floor**: {ENSEMBLE} copies "
             f"of the reference with every initial position moved by {PERTURBATION:g} of the scene's size; their "
             "largest difference from the reference, per observable, is the floor. A setting's error inside the "
             "floor is not error: it is marked ~ (within noise). Observables at the last step, with the tolerance "
             f"{TOLERANCE:g} in each one's unit:", ""]
    lines += [f"* `{k}`: {v}" for k, v in OBSERVABLES.items()]
    lines += ["", "Decisive observables: those whose floor at the last step is below the tolerance. ★ recommended: "
              "the fastest acceptable setting (no penetration, energy gain <= "
              f"{ENERGY_GAIN_LIMIT}) whose error on every decisive observable is within the tolerance or within "
              "noise (else the most accurate); 'decided by': the decisive observable with the largest error beyond "
              "the floor. P: on the Pareto front (ms/step, that error).", ""]
    for res in results:
        ref = res["reference"]
        rate = res["growth_rate"]
        window = res["growth_window_s"]
        lines += [f"## {res['scene']}", "",
                  f"Scene size {res['size']:.3g} m, default thickness {res['thickness']:.3g} m; reference "
                  f"{ref['ms_per_step']:.1f} ms/step, {ref['penetrations']} penetrations.", "",
                  "Noise floor (pointwise spread over the scene size, and its amplification of the perturbation):", ""]
        lines += report.table(["steps", "spread", "amplification"],
                              [[h["steps"], h["spread"], h["amplification"]] for h in res["noise_floor"]])
        lines += ["", (f"Growth rate of the spread: {rate:.3g} 1/s (fitted over t = {window[0]:.3g}-{window[1]:.3g} s, "
                       f"where it rises from 10x the perturbation to {TOLERANCE:g})" if rate is not None else
                       "The spread never rose 10x above the perturbation over 3 steps or more: no growth rate."),
                  "Floor at the last step: " + ", ".join(f"{k} {v:.3g}" for k, v in res["end_floor"].items())
                  + f". Decisive: {', '.join(res['decisive']) or 'none'}."
                  + ("" if res["goal_met"] else " No acceptable setting meets the tolerance on every decisive "
                     "observable: ★ marks the most accurate one of the front."), ""]
        body = []
        for r in sorted(res["rows"], key=lambda r: (r["diverged"] is not None, r.get("ms_per_step", 0.0))):
            mark = "★" if r["recommended"] else ("P" if r["pareto"] else "")
            if r["diverged"]:
                body.append([r["label"], "diverged"] + [None] * (len(OBSERVABLES) + 3) + [r["diverged"][:70]])
                continue
            errs = [(f"{r['errors'][o]:.3g}" + (" ~" if r["within_noise"][o] else "")) if math.isfinite(r["errors"][o])
                    else "n/a" for o in OBSERVABLES]
            body.append([r["label"], r["ms_per_step"], *errs, f"{r['penetrations']} ({fmt_depth(r['max_depth'])})",
                         r["energy_gain"], r["failsafe"], f"{mark} {r['decided_by'] or ''}".strip()])
        lines += report.table(["setting", "ms/step", *OBSERVABLES, "pen. (depth)", "energy gain", "fail-safe",
                               "★ / P, decided by"], body)
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
