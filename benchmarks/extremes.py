"""Stability at the extremes: each row holds or fails with a clear error inside its time limit.

    python benchmarks/extremes.py [--rows NAME,...] [--limit SECONDS] [--out benchmarks/results/extremes]

Each row runs one simulation scene (:func:`scenes.sim_common.simulate`, the scenes' defaults
otherwise) with one setting pushed to an extreme: the step ``dt`` from 1e-5 to 1 s, the springs'
stiffness x1e3 and x1e6, a body's mass x1e-6 and x1e6, a body thrown at 1e3 m/s, contact
thickness 0, the scene scaled by 1e-3 and 1e3, float32 CCD decisions. Every row runs in its own
process under a wall-time limit (``--limit``, default 120 s, kernel cache warm). Its outcome is
**holds** (the run ends with 0 penetrations on every frame and an energy peak of at most 1.01x
the initial), **clear error** (the run stops with :class:`sim.stability.SimulationDiverged`
inside the limit: a refusal, the divergence guard or a contact limit, its one-line message
shown), or a **failure** (penetrations, energy growth, another exception, or the time limit).

Writes ``<out>.md`` and ``<out>.json`` (``rows``: ``name``, ``scene``, ``setting``, ``outcome``,
``seconds``, ``penetrations``, ``energy_peak``, ``message``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)  # before this folder: benchmarks/sim.py must not shadow the sim package

from benchmarks import report  # noqa: E402

ENERGY_LIMIT = 1.01
SIMULATED = 0.5
"""Simulated time [s] of a row (at most 2000 steps, at least 2)."""


def _scale_springs(factor: float):
    def prepare(model):
        import warp as wp

        k = model.spring_stiffness.numpy() * factor
        model.spring_stiffness = wp.array(k, dtype=wp.float64, device=model.device)
        return model

    return prepare


def _scale_body_mass(factor: float, body: int = 0):
    def prepare(model):
        import numpy as np
        import warp as wp

        def scaled(arr, f, dtype):
            a = arr.numpy().copy()
            a[body] = a[body] * f
            return wp.array(a, dtype=dtype, device=model.device)

        model.body_mass = scaled(model.body_mass, factor, wp.float64)
        model.body_inv_mass = scaled(model.body_inv_mass, 1.0 / factor, wp.float64)
        model.body_inertia = scaled(model.body_inertia, factor, wp.mat33d)
        model.body_inv_inertia = scaled(model.body_inv_inertia, 1.0 / factor, wp.mat33d)
        assert np.isfinite(model.body_inv_mass.numpy()).all()
        return model

    return prepare


def _throw_body(speed: float, body: int = 0):
    def prepare(model):
        import numpy as np
        import warp as wp

        qd = model.body_qd.numpy().reshape(-1, 6).copy()
        v = qd[body, 3:]
        direction = v / np.linalg.norm(v) if np.linalg.norm(v) > 0 else np.array([1.0, 0.0, 0.0])
        qd[body, 3:] = speed * direction
        model.body_qd = wp.array(qd, dtype=wp.spatial_vectord, device=model.device)
        return model

    return prepare


ROWS: dict[str, tuple[str, dict[str, Any], Any]] = {
    **{f"dt {dt:g} s": ("cloth_drop", {"dt": dt}, None) for dt in (1e-5, 1e-3, 1.0 / 60.0, 0.1, 1.0)},
    **{f"dt {dt:g} s, rigid": ("rigid_toss", {"dt": dt}, None) for dt in (1e-5, 0.1, 1.0)},
    "dt 1 s, implicit": ("cloth_drop", {"dt": 1.0, "integrator": "implicit"}, None),
    "stiffness x1e3": ("cloth_drop", {}, ("springs", 1e3)),
    "stiffness x1e6": ("cloth_drop", {}, ("springs", 1e6)),
    "stiffness x1e3, implicit": ("cloth_drop", {"integrator": "implicit"}, ("springs", 1e3)),
    "mass ratio 1e-6": ("rigid_toss", {}, ("mass", 1e-6)),
    "mass ratio 1e6": ("rigid_toss", {}, ("mass", 1e6)),
    "speed 1e3 m/s": ("rigid_toss", {}, ("speed", 1e3)),
    "thickness 0": ("cloth_drop", {"thickness": 0.0}, None),
    "scale 1e-3": ("cloth_rigid", {"scale": 1e-3}, None),
    "scale 1e3": ("cloth_rigid", {"scale": 1e3}, None),
    "float32 CCD": ("cloth_rigid", {"ccd_precision": "float32"}, None),
}
"""name -> (scene, option overrides, model change: None or (kind, factor))."""


def run_row(name: str) -> dict[str, Any]:
    """Runs one row in this process: ``outcome`` "holds", "clear error" or "fails"."""
    import importlib

    from scenes.sim_common import SimulationDiverged, default_args, simulate

    scene, overrides, change = ROWS[name]
    module = importlib.import_module(f"scenes.{scene}")
    dt = float(overrides.get("dt", 1.0 / 60.0))
    steps = int(min(2000, max(2, round(SIMULATED / dt))))
    args = default_args(steps=steps, **overrides)
    prepare = None
    if change is not None:
        kind, factor = change
        prepare = {"springs": _scale_springs, "mass": _scale_body_mass, "speed": _throw_body}[kind](factor)
    start = time.perf_counter()
    row = {"name": name, "scene": scene, "setting": {**overrides, "steps": steps}, "change": change}
    try:
        summary, _ = simulate(module.build, args, None, name=scene, progress=False, prepare=prepare)
    except SimulationDiverged as exc:
        return {**row, "outcome": "clear error", "seconds": time.perf_counter() - start, "message": str(exc),
                "penetrations": None, "energy_peak": None}
    peak = summary["energy_max_ratio"]
    holds = summary["penetrations"] == 0 and summary["energy_finite"] and (peak is None or peak <= ENERGY_LIMIT)
    return {**row, "outcome": "holds" if holds else "fails", "seconds": time.perf_counter() - start,
            "message": "" if holds else f"penetrations {summary['penetrations']}, energy peak {peak}",
            "penetrations": summary["penetrations"], "energy_peak": peak}


def run_isolated(name: str, limit: float) -> dict[str, Any]:
    """:func:`run_row` in a fresh process under ``limit`` seconds of wall time."""
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--row", name], cwd=ROOT,
                              capture_output=True, text=True, timeout=limit)
    except subprocess.TimeoutExpired:
        return {"name": name, "scene": ROWS[name][0], "outcome": "fails", "seconds": limit,
                "message": f"no result within the {limit:g} s limit", "penetrations": None, "energy_peak": None}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"name": name, "scene": ROWS[name][0], "outcome": "fails", "seconds": time.perf_counter() - start,
                "message": f"exit {proc.returncode}: {tail}", "penetrations": None, "energy_peak": None}
    return json.loads(lines[-1])


def main(argv=None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default=None, help="comma-separated row names (default all)")
    parser.add_argument("--limit", type=float, default=120.0, help="wall-time limit per row [s] (default 120)")
    parser.add_argument("--row", default=None, help=argparse.SUPPRESS)  # one row, in this process, JSON out
    parser.add_argument("--out", default=os.path.join(report.RESULTS, "extremes"), help="output prefix")
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    if args.row is not None:
        if args.row not in ROWS:
            parser.error(f"--row: unknown {args.row!r}")
        print(json.dumps(run_row(args.row)), flush=True)
        return []
    names = [s.strip() for s in args.rows.split(",")] if args.rows else list(ROWS)
    bad = [n for n in names if n not in ROWS]
    if bad:
        parser.error(f"--rows: unknown {bad}; choose from {', '.join(ROWS)}")
    rows = []
    for name in names:
        print(f"[extremes] {name}", file=sys.stderr, flush=True)
        rows.append(run_isolated(name, args.limit))
    lines = [f"Each row: one scene for {SIMULATED:g} s of simulated time (2 to 2000 steps), one setting at an "
             f"extreme, in its own process with a {args.limit:g} s limit. holds: 0 penetrations on every frame and "
             f"an energy peak <= {ENERGY_LIMIT}x; clear error: stopped by a refusal, the divergence guard or a "
             "contact limit, with the message shown.", ""]
    lines += report.table(["row", "scene", "outcome", "seconds", "penetrations", "energy peak", "message"],
                          [[r["name"], r["scene"], r["outcome"], r["seconds"], r["penetrations"], r["energy_peak"],
                            (r["message"] or "")[:160]] for r in rows])
    report.write(args.out, "Stability at the extremes", lines, {"rows": rows, "limit_s": args.limit})
    return rows


if __name__ == "__main__":
    main()
