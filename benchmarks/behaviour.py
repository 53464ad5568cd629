"""Behaviour fingerprint: what a change of layout must keep, bit for bit where the arithmetic is
unchanged.

    python benchmarks/behaviour.py [--out FILE.json] [--compare BASELINE.json] [--iters N]

Records, on the current code:

* the three simulation scenes (``cloth_drop``, ``rigid_toss``, ``cloth_rigid``) over 300 steps at
  their defaults, for both collision responses: the summary's ``state_sha256`` (the final
  positions and velocities, bytes) and its centre of mass;
* :func:`scenes.tunnel.optimise` for seeds 0-3 and :func:`scenes.bank_shot.optimise` from each
  named start, ``--iters`` iterations (default 3): every iteration's loss, velocity and gradient
  norm (the rollout outputs and the gradients through them).

``--compare`` prints, per item, ``identical`` or the largest relative difference from the
baseline, and exits 1 when an item differs (the differences are then to be explained, and
compared with the noise floors of ``benchmarks/trade.py``). ``benchmarks/results/behaviour.json``
is the fingerprint of the code as committed: a change meant to keep the arithmetic runs
``python benchmarks/behaviour.py --compare benchmarks/results/behaviour.json``, and a change of
the arithmetic rewrites it (``--out``) after its differences are explained.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

SCENES = ("cloth_drop", "rigid_toss", "cloth_rigid")
RESPONSES = ("replayed", "gauss-seidel")
SCENE_STEPS = 300
TUNNEL_SEEDS = (0, 1, 2, 3)


def _digest(values: dict[str, list[float]]) -> str:
    digest = hashlib.sha256()
    for key in sorted(values):
        digest.update(key.encode())
        digest.update(np.ascontiguousarray(np.asarray(values[key], dtype=np.float64)).tobytes())
    return digest.hexdigest()


def scene_items() -> dict[str, dict[str, Any]]:
    """``state_sha256`` and the centre of mass of each scene and response after 300 steps."""
    import importlib

    from scenes.sim_common import default_args, simulate

    items = {}
    for name in SCENES:
        module = importlib.import_module(f"scenes.{name}")
        for response in RESPONSES:
            print(f"[behaviour] {name} ({response})", file=sys.stderr, flush=True)
            summary, final = simulate(module.build, default_args(steps=SCENE_STEPS, response=response), None,
                                      name=name, progress=False)
            values = {key: np.asarray(final[key], dtype=np.float64).reshape(-1).tolist()
                      for key in ("particle_q", "particle_qd", "body_q", "body_qd")}
            items[f"{name}/{response}"] = {"sha256": summary["state_sha256"], "values": values}
    return items


def _history_values(history: dict[str, list]) -> dict[str, list[float]]:
    values = {}
    for key in ("loss", "grad_norm", "velocity"):
        values[key] = np.asarray(history[key], dtype=np.float64).reshape(-1).tolist()
    return values


def optimisation_items(iters: int) -> dict[str, dict[str, Any]]:
    """Loss, velocity and gradient norm of every iteration of the inverse scenes' optimisers."""
    from scenes import bank_shot, tunnel

    items = {}
    for seed in TUNNEL_SEEDS:
        print(f"[behaviour] tunnel seed {seed}", file=sys.stderr, flush=True)
        result = tunnel.optimise(tunnel.make_problem(seed), iters)
        values = _history_values(result["history"])
        items[f"tunnel/{seed}"] = {"sha256": _digest(values), "values": values}
    model = bank_shot.build()
    for start in sorted(bank_shot.STARTS):
        print(f"[behaviour] bank_shot {start}", file=sys.stderr, flush=True)
        result = bank_shot.optimise(model, bank_shot.STARTS[start], iters)
        values = _history_values(result["history"])
        items[f"bank_shot/{start}"] = {"sha256": _digest(values), "values": values}
    return items


def compare(items: dict[str, dict[str, Any]], baseline: dict[str, dict[str, Any]]) -> list[tuple[str, str]]:
    """Per item: "identical", "missing", or the largest relative difference per value key."""
    rows = []
    for key in sorted(set(items) | set(baseline)):
        if key not in items or key not in baseline:
            rows.append((key, "missing here" if key not in items else "missing in the baseline"))
            continue
        if items[key]["sha256"] == baseline[key]["sha256"]:
            rows.append((key, "identical"))
            continue
        parts = []
        for name, now in items[key]["values"].items():
            old = np.asarray(baseline[key]["values"].get(name, []), dtype=np.float64)
            now = np.asarray(now, dtype=np.float64)
            if old.shape != now.shape:
                parts.append(f"{name}: shape {old.shape} -> {now.shape}")
                continue
            if old.size == 0 or np.array_equal(old, now, equal_nan=True):
                continue
            scale = max(float(np.nanmax(np.abs(old))), 1e-300)
            parts.append(f"{name}: {float(np.nanmax(np.abs(now - old))) / scale:.2e}")
        rows.append((key, "differs (" + ", ".join(parts) + ")"))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="write the fingerprint to this JSON file")
    parser.add_argument("--compare", default=None, help="a fingerprint JSON to compare with")
    parser.add_argument("--iters", type=int, default=3, help="optimiser iterations per inverse run (default 3)")
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    t0 = time.perf_counter()
    items = scene_items()
    items.update(optimisation_items(args.iters))
    print(f"[behaviour] {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"iters": args.iters, "items": items}, fh)
    if args.compare:
        with open(args.compare) as fh:
            baseline = json.load(fh)
        if baseline.get("iters") != args.iters:
            parser.error(f"the baseline ran {baseline.get('iters')} iterations, this run {args.iters}")
        rows = compare(items, baseline["items"])
        width = max(len(k) for k, _ in rows)
        for key, verdict in rows:
            print(f"{key:<{width}}  {verdict}")
        return 0 if all(v == "identical" for _, v in rows) else 1
    for key, item in items.items():
        print(f"{key}  {item['sha256'][:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
