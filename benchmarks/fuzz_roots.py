"""Large fuzz run of the root solver (the default test suite runs a 1e5 slice).

    python benchmarks/fuzz_roots.py [--n 1000000] [--chunk 200000] [--seed 0] [--degree 3|2|both]

Inputs from ``tests/groundtruth.fuzz_inputs`` (uniform, log-uniform denormal..1e308, special
values, sparse zeros, exact/nudged repeated roots at 2^+-1000, equal magnitudes, raw float64 bit
patterns). Prints, per degree, the counts of: non-finite roots, roots outside the t_max box,
non-finite Jacobian entries, Jacobian entries above 5 M, slot-structure violations, and the time
spent in the solver and in the Jacobian. Exits 1 if any count is non-zero.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import groundtruth as gt  # noqa: E402

from collision.roots import cubic_root_jacobian, quadratic_root_jacobian, solve_cubic, solve_quadratic  # noqa: E402

T_MAX = 1e150
M = 1000.0


def structure_violations(z, deg):
    real = z.imag == 0
    if deg == 2:
        conj = (z[:, 0] == np.conj(z[:, 1])) & (z.imag[:, 0] != 0)
        return ~(real.all(axis=1) | conj)
    asc = (z.real[:, 0] <= z.real[:, 1]) & (z.real[:, 1] <= z.real[:, 2])
    pair_lo = real[:, 2] & (z[:, 0] == np.conj(z[:, 1])) & (z.imag[:, 1] > 0)
    pair_hi = real[:, 0] & (z[:, 1] == np.conj(z[:, 2])) & (z.imag[:, 2] > 0)
    return ~np.where(real.all(axis=1), asc, pair_lo | pair_hi)


def run(deg: int, n: int, chunk: int, seed: int) -> int:
    solve = solve_cubic if deg == 3 else solve_quadratic
    jac_fn = cubic_root_jacobian if deg == 3 else quadratic_root_jacobian
    rng = np.random.default_rng(seed + deg)
    solve(np.ones((1, deg + 1)))  # warm-up (kernel compile/load)
    jac_fn(np.ones((1, deg + 1)))
    counts = dict(nonfinite_roots=0, roots_outside_tmax=0, nonfinite_jacobian=0, jacobian_above_5M=0, slot_structure=0)
    examples = {}
    t_solve = t_jac = 0.0
    max_j = 0.0
    done = 0
    while done < n:
        k = min(chunk, n - done)
        p = gt.fuzz_inputs(rng, k, deg + 1)
        t0 = time.perf_counter()
        z = solve(p)
        t1 = time.perf_counter()
        j = jac_fn(p)
        t2 = time.perf_counter()
        t_solve += t1 - t0
        t_jac += t2 - t1
        masks = {
            "nonfinite_roots": ~np.isfinite(z).all(axis=1),
            "roots_outside_tmax": (np.abs(np.nan_to_num(z.real)) > T_MAX).any(axis=1)
            | (np.abs(np.nan_to_num(z.imag)) > T_MAX).any(axis=1),
            "nonfinite_jacobian": ~np.isfinite(j).all(axis=(1, 2, 3)),
            "jacobian_above_5M": (np.abs(np.nan_to_num(j)) > 5 * M).any(axis=(1, 2, 3)),
            "slot_structure": structure_violations(z, deg),
        }
        max_j = max(max_j, float(np.max(np.abs(np.nan_to_num(j)))))
        for key, mask in masks.items():
            counts[key] += int(mask.sum())
            if mask.any() and key not in examples:
                i = int(np.nonzero(mask)[0][0])
                examples[key] = (p[i].tolist(), z[i].tolist())
        done += k
    print(f"\ndegree {deg}: {n} inputs, solve {t_solve:.2f} s ({n / t_solve:.3g}/s), "
          f"roots+Jacobian {t_jac:.2f} s ({n / t_jac:.3g}/s), max |J| {max_j:.6g}")
    for key, v in counts.items():
        print(f"  {key:22s} {v}")
    for key, (p, z) in examples.items():
        print(f"  first {key}: p={p!r} -> {z!r}")
    return sum(counts.values())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--chunk", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--degree", choices=["2", "3", "both"], default="both")
    args = ap.parse_args()
    degs = [3, 2] if args.degree == "both" else [int(args.degree)]
    t0 = time.perf_counter()
    bad = sum(run(d, args.n, args.chunk, args.seed) for d in degs)
    print(f"\ntotal wall time {time.perf_counter() - t0:.1f} s; violations {bad}")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
