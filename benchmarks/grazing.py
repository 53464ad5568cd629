"""Gradient across a grazing contact (a true double root): the paper's mollified derivative against
``-1/p'(t*)``.

    python benchmarks/grazing.py [--points 41] [--out benchmarks/results/grazing.png]

Runs the sweep of the ``grazing`` scene (:mod:`scenes.grazing`: a particle aimed ever closer to a
tangential touch of a tilting flap, where the coplanarity cubic of the substep has a double root)
and writes a log-log PNG of ``|d z(T) / d v_z|`` over the free-flight gradient against the
relative aim offset: mollified (``M = 1000``, and ``M = 10`` for the scaling with ``M``),
unmollified, and central finite differences of the forward where they converge (two steps
agreeing to 1e-4); the miss side (aims shallower by the same offsets) is the free-flight gradient.
Prints the table.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

FD_STEPS = (1e-3, 2.5e-4)  # relative to the offset
FD_AGREE = 1e-4


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=41, help="aims in the sweep, offsets 1e-1 .. 1e-11 "
                        "(default %(default)s)")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "grazing.png"), help="PNG path")
    args = parser.parse_args(argv)
    if args.points < 2:
        parser.error("--points must be >= 2")

    import warp as wp

    wp.config.quiet = True
    from scenes.grazing import MISS_OFFSETS, predicted_plateau, sweep

    offsets = np.logspace(-1.0, -11.0, args.points)
    r = sweep(offsets, 1000.0, other_max_derivatives=(10.0,), fd_steps=FD_STEPS, miss_offsets=MISS_OFFSETS)
    free = r["free"]
    fd, fd_alt = r["fd"][1], r["fd"][0]
    converged = np.abs(fd - fd_alt) <= FD_AGREE * np.abs(fd)
    m10 = r["by_max_derivative"][10.0]
    print(f"free-flight gradient d z(T) / d v_z = {free:.6f} s; grazing aim v_z* = {r['threshold']:.6f} m/s")
    print("gradients in units of the free-flight gradient; FD: central differences of the forward, "
          "step 2.5e-4 x offset ('*': steps 1e-3 and 2.5e-4 agree to 1e-4)")
    print(f"{'offset':>9s} {'contacts':>8s} {'M=1000':>12s} {'M=10':>9s} {'unmollified':>13s} {'FD':>13s} "
          f"{'|unm/FD-1|':>10s}")
    for i, k in enumerate(r["offsets"]):
        star = "*" if converged[i] else " "
        print(f"{k:9.2e} {r['contacts'][i]:8d} {r['mollified'][i] / free:+12.4f} {m10[i] / free:+9.4f} "
              f"{r['unmollified'][i] / free:+13.4f} {fd[i] / free:+13.4f}{star} "
              f"{abs(r['unmollified'][i] / fd[i] - 1):10.1e}")
    for k, g, c in zip(r["miss_offsets"], r["miss_gradients"], r["miss_contacts"]):
        print(f"miss side, offset -{k:8.2e}: {c} contacts, gradient {g / free:+.12f} x free flight")
    near = r["offsets"] <= 1e-6
    slope = np.polyfit(np.log(r["offsets"][near]), np.log(np.abs(r["unmollified"][near])), 1)[0]
    print(f"largest |gradient| / free flight: mollified M=1000 {np.abs(r['mollified']).max() / abs(free):.1f} "
          f"(first-order prediction {predicted_plateau(1000.0):.1f}), M=10 {np.abs(m10).max() / abs(free):.2f} "
          f"({predicted_plateau(10.0):.2f}), unmollified {np.abs(r['unmollified']).max() / abs(free):.1f}; "
          f"unmollified slope (offsets <= 1e-6) {slope:.4f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = r["offsets"]
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    ax.loglog(k, np.abs(r["unmollified"]) / abs(free), "o-", ms=3, color="tab:red",
              label=r"unmollified $-1/p'(t^*)$")
    ax.loglog(k, np.abs(r["mollified"]) / abs(free), "s-", ms=3, color="tab:blue", label="mollified, M = 1000")
    ax.loglog(k, np.abs(m10) / abs(free), "^-", ms=3, color="tab:cyan", label="mollified, M = 10")
    ax.loglog(k[converged], np.abs(fd[converged]) / abs(free), "kx", ms=6, label="central differences (converged)")
    ax.loglog(r["miss_offsets"], np.abs(r["miss_gradients"]) / abs(free), "D", color="gray", ms=5,
              label="misses (shallower by the offset)")
    ax.axhline(1.0, color="gray", ls="--", lw=1, label="free flight")
    ref = k[near]
    ax.loglog(ref, 3.0 * np.abs(r["unmollified"][near][0]) / abs(free) * (ref / ref[0]) ** -0.5, ":",
              color="tab:red", lw=1, label=r"$\propto$ offset$^{-1/2}$")
    ax.invert_xaxis()
    ax.set_xlabel("relative aim offset from the grazing aim (right: closer to the tangency)")
    ax.set_ylabel(r"$|\partial z(T) / \partial v_{z,0}|$ / free flight")
    ax.set_title("Particle grazing a tilting flap (double root): gradient vs aim offset")
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(True, which="both", alpha=0.3)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
