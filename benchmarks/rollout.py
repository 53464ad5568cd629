"""Cost of differentiating a rollout (``sim.rollout.rollout``): time and memory.

    python benchmarks/rollout.py [--steps 300] [--memory-substeps 1000] [--skip-memory]

1. ``cloth_rigid`` at its defaults (dt 1/60 s, 8 substeps): wall time of the forward alone (no
   tape) and of forward + backward (taped forward, then the backward of a scalar loss on the final
   positions), over ``--steps`` steps.
2. Peak memory (resident set above the built model, sampled every 20 ms in a fresh subprocess
   each) of ``--memory-substeps``
   substeps of a 32 x 32-cell cloth dropped on a box, forward + backward, with the whole tape
   kept and with checkpointing every ``sqrt(steps)`` steps; the forward alone for reference.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
sys.path.insert(0, ROOT)

MEMORY_CHILD = r"""
import json, math, sys, threading, time
import numpy as np, psutil, torch, warp as wp
wp.config.quiet = True
from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh
from sim.rollout import rollout
mode, substeps_total = sys.argv[1], int(sys.argv[2])
b = ModelBuilder()
n = 32
b.add_cloth_grid((-0.4, -0.4, 0.3), None, n, n, 0.8 / n, 0.8 / n, density=0.5, stretch_stiffness=5.0,
                 shear_stiffness=1.0, bend_stiffness=0.1, damping=0.002)
b.add_static_mesh(*box_mesh((0.2, 0.2, 0.1)))
b.set_contact(restitution=0.0, friction=0.3)
m = b.finalize()
substeps = 10
steps = max(1, substeps_total // substeps)
proc = psutil.Process()
base = proc.memory_info().rss
peak = [base]
done = threading.Event()
def sample():  # the resident set above the built model, sampled every 20 ms
    while not done.is_set():
        peak[0] = max(peak[0], proc.memory_info().rss)
        time.sleep(0.02)
threading.Thread(target=sample, daemon=True).start()
v = torch.zeros((m.particle_count, 3), dtype=torch.float64, requires_grad=mode != "forward")
t0 = time.perf_counter()
kw = {"checkpoint_every": max(1, int(math.sqrt(steps)))} if mode == "checkpoint" else {}
res = rollout(m, steps, 1 / 60, substeps, particle_qd=v, **kw)
if mode != "forward":
    res.particle_q[-1, :, 2].sum().backward()
done.set()
peak[0] = max(peak[0], proc.memory_info().rss)
print(json.dumps({"mode": mode, "steps": steps, "substeps": substeps, "seconds": time.perf_counter() - t0,
                  "peak_mib": (peak[0] - base) / 2.0**20,
                  "contact_substeps": res.stats["contact_substeps"], "min_z": float(res.particle_q[-1, :, 2].min())}))
"""


def timing(steps: int) -> None:
    import torch
    import warp as wp

    wp.config.quiet = True
    from scenes import cloth_rigid
    from scenes.sim_common import build_model, default_args
    from sim.rollout import rollout

    args = default_args()
    model = build_model(cloth_rigid.build, args)
    rollout(model, 2, args.dt, args.substeps)  # kernel load
    t0 = time.perf_counter()
    res = rollout(model, steps, args.dt, args.substeps)
    forward = time.perf_counter() - t0
    v = torch.tensor(model.particle_qd.numpy(), requires_grad=True)
    w = torch.tensor(model.body_qd.numpy(), requires_grad=True)
    t0 = time.perf_counter()
    res_g = rollout(model, steps, args.dt, args.substeps, particle_qd=v, body_qd=w)
    taped = time.perf_counter() - t0
    (res_g.particle_q[-1].sum() + res_g.body_q[-1, :, :3].sum()).backward()
    total = time.perf_counter() - t0
    print(f"cloth_rigid, {steps} steps of 1/60 s in {args.substeps} substeps "
          f"({res.stats['contact_substeps']} substeps with contact, largest impulse system "
          f"{res.stats['largest_system']} unknowns, fail-safe {res.stats['failsafe_substeps']}):")
    print(f"{'forward (no tape)':>28s} {forward:8.2f} s")
    print(f"{'forward (taped)':>28s} {taped:8.2f} s")
    print(f"{'forward + backward':>28s} {total:8.2f} s   ratio to the forward alone: {total / forward:.2f}x")
    print(f"{'|d loss / d v_ball|':>28s} {float(w.grad[0].norm()):8.4f}  (finite: {bool(torch.isfinite(w.grad).all())})")


def memory(substeps_total: int) -> None:
    print(f"\nPeak memory, 32 x 32-cell cloth (1089 particles) dropped on a box, {substeps_total} substeps "
          "(10 per step), each in a fresh process:")
    print(f"{'mode':>12s} {'seconds':>8s} {'peak MiB':>9s} {'contact substeps':>16s}")
    for mode in ("forward", "full_tape", "checkpoint"):
        out = subprocess.run([sys.executable, "-c", MEMORY_CHILD, mode, str(substeps_total)], cwd=ROOT,
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{mode:>12s} {r['seconds']:8.1f} {r['peak_mib']:9.1f} {r['contact_substeps']:16d}")
    print("checkpoint: segments of sqrt(steps) steps recomputed in the backward; full_tape: every "
          "substep's arrays kept until the backward.")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--memory-substeps", type=int, default=1000)
    parser.add_argument("--skip-memory", action="store_true")
    args = parser.parse_args(argv)
    timing(args.steps)
    if not args.skip_memory:
        memory(args.memory_substeps)


if __name__ == "__main__":
    main()
