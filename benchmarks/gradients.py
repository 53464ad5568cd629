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
        kw = {}
        if P:
            kw["particle_qd"] = torch.tensor(v, requires_grad=grad)
        if B:
            kw["body_qd"] = torch.tensor(w, requires_grad=grad)
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


def main(argv=None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    report.add_size_arguments(parser, SCENES, "gradients", "short rollouts (seconds)",
                              "long rollouts, four finite-difference steps")
    args = parser.parse_args(argv)
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
    report.write(args.out, "Gradients through rollouts with contacts", lines, {"config": config, "rows": rows})
    return {"rows": rows}


if __name__ == "__main__":
    main()
