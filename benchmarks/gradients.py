"""Gradients through whole rollouts with contacts: error against finite differences, and cost.

    python benchmarks/gradients.py [--quick | --full] [--out benchmarks/results/gradients]

For each simulation scene (``cloth_drop``, ``rigid_toss``, ``cloth_rigid``, at its defaults) a
:func:`sim.rollout.rollout` of ``steps`` steps from the scene's initial velocities; the loss is a
fixed random weighting of the final particle positions and body origins. The gradient w.r.t. the
initial particle velocities and body twists (torch autograd through the Warp tape: mollified
root derivatives, replayed impulse solves) is projected on a random unit direction and compared
with the central difference of the same rollout's forward, ``(L(v + e d) - L(v - e d)) / 2e``, for
two step sizes ``e`` (their disagreement shows how smooth the loss is there: a contact that
appears or vanishes between ``v - e d`` and ``v + e d`` breaks a central difference, not the
gradient). Cost: wall time of the forward alone (no tape), of the taped forward + backward, and
their ratio, per step.

Horizon sweep (the simulation scenes and ``bank_shot`` from its "newton" start): per substep
setting and horizon, the gradient norm and two random directional derivatives against central
differences, and the horizon from which the loss is not smooth at the differences' scale (the
gradient is then dominated by the physical amplification of perturbations: a horizon to stay
below when optimising through long contact).
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
CONFIGS = {"quick": dict(steps=12, eps=(1e-5, 1e-7)), "default": dict(steps=40, eps=(1e-5, 1e-7, 1e-9)),
           "full": dict(steps=90, eps=(1e-5, 1e-6, 1e-7, 1e-8, 1e-9))}
"""Central-difference steps: a contact that switches inside the stencil breaks the larger ones
(the loss is smooth only between switches), rounding (~1e-16 |L| / e) the smaller ones."""


def _velocities(v: np.ndarray, w: np.ndarray, grad: bool) -> dict:
    """``rollout``'s initial-velocity arguments: particle velocities ``v`` (P, 3) and body
    twists ``w`` (B, 6) as tensors (left out where there are none)."""
    import torch

    kw = {}
    if len(v):
        kw["particle_qd"] = torch.tensor(v, requires_grad=grad)
    if len(w):
        kw["body_qd"] = torch.tensor(w, requires_grad=grad)
    return kw


def scene_gradient(name: str, steps: int, eps_list, seed: int = 0) -> dict[str, Any]:
    import importlib

    import torch

    from scenes.sim_common import build_model, default_args
    from sim.rollout import rollout

    module = importlib.import_module(f"scenes.{name}")
    args = default_args()
    model = build_model(module.build, args)
    P, B = int(model.particle_count), int(model.body_count)
    rng = np.random.default_rng(seed)
    wp_ = torch.tensor(rng.standard_normal((P, 3)))
    wb = torch.tensor(rng.standard_normal((B, 3)))
    dp = rng.standard_normal((P, 3))
    db = rng.standard_normal((B, 6))
    norm = np.sqrt((dp ** 2).sum() + (db ** 2).sum())
    dp, db = dp / norm, db / norm
    v0 = model.particle_qd.numpy().reshape(-1, 3) if P else np.zeros((0, 3))
    w0 = model.body_qd.numpy().reshape(-1, 6) if B else np.zeros((0, 6))

    def loss_of(res):
        total = (res.particle_q[-1] * wp_).sum() if P else torch.zeros((), dtype=torch.float64)
        if B:
            total = total + (res.body_q[-1, :, :3] * wb).sum()
        return total

    def run(v, w, grad: bool):
        kw = _velocities(v, w, grad)
        return kw, rollout(model, steps, args.dt, args.substeps, **kw)

    run(v0, w0, False)  # kernel load
    t0 = time.perf_counter()
    _, res = run(v0, w0, False)
    forward = time.perf_counter() - t0
    t0 = time.perf_counter()
    kw, res_g = run(v0, w0, True)
    loss_of(res_g).backward()
    both = time.perf_counter() - t0
    directional = 0.0
    if P:
        directional += float((kw["particle_qd"].grad.numpy() * dp).sum())
    if B:
        directional += float((kw["body_qd"].grad.numpy() * db).sum())
    finite = bool(all(np.isfinite(k.grad.numpy()).all() for k in kw.values()))
    fd = {}
    with torch.no_grad():
        for e in eps_list:
            lp = float(loss_of(run(v0 + e * dp, w0 + e * db, False)[1]))
            lm = float(loss_of(run(v0 - e * dp, w0 - e * db, False)[1]))
            fd[e] = (lp - lm) / (2 * e)
    errors = {e: abs(directional - f) / max(abs(f), abs(directional), 1e-300) for e, f in fd.items()}
    values = list(fd.values())
    # how far the central differences of the largest and smallest steps disagree with each other:
    # large where the loss is not smooth at the scale of e (a contact switches inside the stencil)
    fd_spread = abs(values[0] - values[-1]) / max(abs(values[0]), abs(values[-1]), 1e-300)
    return {"scene": name, "steps": steps, "substeps": args.substeps, "particles": P, "bodies": B,
            "contact_substeps": int(res.stats["contact_substeps"]), "directional": directional, "fd": fd,
            "relative_error": errors, "fd_spread": fd_spread, "best_error": min(errors.values()), "finite": finite,
            "forward_ms_per_step": 1e3 * forward / steps, "backward_ms_per_step": 1e3 * both / steps,
            "ratio": both / forward}


HORIZONS = {"quick": dict(horizons=(5, 10, 20), substeps=(8,)),
            "default": dict(horizons=(5, 10, 20, 40, 80), substeps=(8, 16)),
            "full": dict(horizons=(5, 10, 20, 40, 80, 160), substeps=(8, 16, 32))}
"""The horizon sweep's horizons [steps] and substep settings per mode."""
HORIZON_EPS = (1e-6, 1e-8)
"""Its two central-difference steps."""
DIRECTIONS = 2
"""Random directions per horizon."""
SMOOTH = 1e-2
"""Two central differences that disagree by more than this (relative) mean the loss is not
smooth at their scale: perturbations are amplified faster than the finite difference resolves."""
HORIZON_SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid", "bank_shot", "tunnel")
INVERSE_SCENES = ("bank_shot", "tunnel")
"""The inverse scenes the horizon sweep adds to the default scenes."""


def _horizon_problem(name: str):
    """(model, dt, initial particle velocities (P, 3), body twists (B, 6)) of a scene at its
    start: the simulation scenes at their defaults; ``bank_shot`` from its "newton" start;
    ``tunnel`` (seed 0) from the velocity that hits its designated face of the spinning
    tetrahedron at about 0.5 s."""
    import importlib

    if name == "tunnel":
        from scenes import tunnel

        problem = tunnel.make_problem(0)
        model = problem.model
        return model, tunnel.DT, np.array([problem.v_star], dtype=np.float64), model.body_qd.numpy().reshape(-1, 6)
    if name == "bank_shot":
        from scenes import bank_shot

        model = bank_shot.build()
        return model, bank_shot.DT, np.array([bank_shot.STARTS["newton"]], dtype=np.float64), np.zeros((0, 6))
    from scenes.sim_common import build_model, default_args

    module = importlib.import_module(f"scenes.{name}")
    args = default_args()
    model = build_model(module.build, args)
    P, B = int(model.particle_count), int(model.body_count)
    v0 = model.particle_qd.numpy().reshape(-1, 3) if P else np.zeros((0, 3))
    w0 = model.body_qd.numpy().reshape(-1, 6) if B else np.zeros((0, 6))
    return model, float(args.dt), v0, w0


def horizon_sweep(name: str, horizons, substeps_list, seed: int = 0) -> list[dict[str, Any]]:
    """Per substep setting and horizon: the gradient norm of a random weighting of the end
    positions w.r.t. the initial velocities, and :data:`DIRECTIONS` directional derivatives
    against central differences at :data:`HORIZON_EPS`."""
    import torch

    from sim.rollout import rollout

    model, dt, v0, w0 = _horizon_problem(name)
    P, B = len(v0), len(w0)
    rng = np.random.default_rng(seed)
    weights_p = torch.tensor(rng.standard_normal((P, 3)))
    weights_b = torch.tensor(rng.standard_normal((B, 3)))
    out = []
    for substeps in substeps_list:
        for steps in horizons:
            def loss(v, w, grad: bool):
                kw = _velocities(v, w, grad)
                res = rollout(model, steps, dt, substeps, **kw)
                total = (res.particle_q[-1] * weights_p).sum() if P else torch.zeros((), dtype=torch.float64)
                if B:
                    total = total + (res.body_q[-1, :, :3] * weights_b).sum()
                return kw, total

            kw, total = loss(v0, w0, True)
            total.backward()
            gp = kw["particle_qd"].grad.numpy() if P else np.zeros((0, 3))
            gb = kw["body_qd"].grad.numpy() if B else np.zeros((0, 6))
            norm = float(np.sqrt((gp ** 2).sum() + (gb ** 2).sum()))
            checks = []
            for _ in range(DIRECTIONS):
                dp, db = rng.standard_normal((P, 3)), rng.standard_normal((B, 6))
                scale = np.sqrt((dp ** 2).sum() + (db ** 2).sum())
                dp, db = dp / scale, db / scale
                directional = float((gp * dp).sum() + (gb * db).sum())
                fd = []
                with torch.no_grad():
                    for e in HORIZON_EPS:
                        lp = float(loss(v0 + e * dp, w0 + e * db, False)[1])
                        lm = float(loss(v0 - e * dp, w0 - e * db, False)[1])
                        fd.append((lp - lm) / (2 * e))
                spread = abs(fd[0] - fd[-1]) / max(abs(fd[0]), abs(fd[-1]), 1e-300)
                error = min(abs(directional - f) / max(abs(f), abs(directional), 1e-300) for f in fd)
                checks.append({"directional": directional, "fd": fd, "fd_spread": spread, "error": error})
            out.append({"scene": name, "substeps": substeps, "steps": steps, "gradient_norm": norm,
                        "finite": bool(np.isfinite(norm)), "checks": checks,
                        "worst_error": max(c["error"] for c in checks),
                        "smooth": all(c["fd_spread"] <= SMOOTH for c in checks)})
    return out


def amplified_horizon(rows: list[dict[str, Any]]) -> int | None:
    """The first horizon [steps] of a scene and setting from which the loss is not smooth at
    the differences' scale (:data:`SMOOTH`) at every longer horizon; None if it stays smooth."""
    rows = sorted(rows, key=lambda r: r["steps"])
    for i, r in enumerate(rows):
        if all(not q["smooth"] for q in rows[i:]):
            return r["steps"]
    return None


def main(argv=None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    report.add_size_arguments(parser, SCENES, "gradients", "short rollouts (seconds)",
                              "long rollouts, four finite-difference steps")
    args = parser.parse_args(argv)
    args.scenes_default = args.scenes == ",".join(SCENES)  # the horizon sweep adds the inverse scenes then
    config, scenes = report.chosen(parser, args, CONFIGS, SCENES)
    import warp as wp

    wp.config.quiet = True
    rows = []
    for name in scenes:
        print(f"[gradients] {name}", file=sys.stderr, flush=True)
        rows.append(scene_gradient(name, config["steps"], config["eps"]))
    eps = config["eps"]
    lines = [f"Rollouts of {config['steps']} steps of 1/60 s (8 substeps) from each scene's start; directional "
             "derivative of a random weighting of the end positions along a random unit direction of the "
             "initial velocities (particles) and twists (bodies), against central differences with step e.", ""]
    lines += report.table(
        ["scene", "contact substeps", "gradient", *[f"rel. error (e={e:g})" for e in eps], "FD spread", "finite",
         "forward ms/step", "fwd+bwd ms/step", "fwd+bwd / fwd"],
        [[r["scene"], r["contact_substeps"], r["directional"], *[r["relative_error"][e] for e in eps], r["fd_spread"], r["finite"],
          r["forward_ms_per_step"], r["backward_ms_per_step"], r["ratio"]] for r in rows])
    lines += ["", "FD spread: relative disagreement of the central differences of the largest and the smallest e "
              "with each other. Where it is large the loss is not smooth at that scale (a contact appears or "
              "vanishes between v - e d and v + e d), and the finite differences are no reference there; the "
              "gradient is then the mollified one of the contacts this rollout made."]
    sweep_config = HORIZONS["quick" if args.quick else "full" if args.full else "default"]
    horizons = [h for h in sweep_config["horizons"] if args.steps is None or h <= max(args.steps, 1)] or [args.steps]
    sweep_scenes = [n for n in HORIZON_SCENES if n in scenes or (n in INVERSE_SCENES and args.scenes_default)]
    sweep = []
    for name in sweep_scenes:
        print(f"[gradients] horizons: {name}", file=sys.stderr, flush=True)
        sweep += horizon_sweep(name, horizons, sweep_config["substeps"])
    summary = []
    for name in sweep_scenes:
        for sub in sweep_config["substeps"]:
            sel = [r for r in sweep if r["scene"] == name and r["substeps"] == sub]
            summary.append({"scene": name, "substeps": sub, "amplified_from": amplified_horizon(sel)})
    lines += ["", "## Gradient accuracy against the horizon", "",
              f"A random weighting of the end positions after each horizon; {DIRECTIONS} random directions of the "
              f"initial velocities; central differences at e = {', '.join(f'{e:g}' for e in HORIZON_EPS)}. error: "
              "the directional derivative's relative difference from the nearer central difference (worst "
              f"direction); smooth: the two differences agree within {SMOOTH:g} for every direction (else "
              "perturbations are amplified faster than the differences resolve, and they are no reference).", ""]
    lines += report.table(["scene", "substeps", "steps", "gradient norm", "worst error", "smooth", "FD spread (max)"],
                          [[r["scene"], r["substeps"], r["steps"], r["gradient_norm"], r["worst_error"],
                            "yes" if r["smooth"] else "no", max(c["fd_spread"] for c in r["checks"])] for r in sweep])
    lines += ["", "Horizon from which the loss stays non-smooth (gradients dominated by the physical "
              "amplification; a user optimising through contact should stay below it):", ""]
    lines += report.table(["scene", "substeps", "non-smooth from [steps]"],
                          [[s["scene"], s["substeps"], s["amplified_from"] if s["amplified_from"] else
                            f"smooth to {max(horizons)}"] for s in summary])
    report.write(args.out, "Gradients through rollouts with contacts", lines,
                 {"config": config, "rows": rows, "horizons": sweep, "horizon_summary": summary})
    return {"rows": rows, "horizons": sweep, "horizon_summary": summary}


if __name__ == "__main__":
    main()
