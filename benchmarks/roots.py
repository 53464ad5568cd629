"""Speed and accuracy of the robust cubic solver against numpy.

    python benchmarks/roots.py [--n 200000] [--n-roots 20000] [--n-accuracy 200] [--skip-accuracy]

Speed (best of 3 with time.perf_counter, after a warm-up call that compiles/loads the Warp
kernels): cubics per second of ``solve_cubic`` and ``cubic_root_jacobian`` on N uniform random
cubics, against numpy's batched companion-matrix ``np.linalg.eigvals`` on (N, 3, 3) (building the
companion matrices is part of its time) and a per-polynomial ``numpy.roots`` loop (fewer
samples). The bars reported against: solving >= 5x eigvals, Jacobian >= 3x eigvals.

Accuracy: per category of tests/groundtruth.py (the same inputs as tests/test_roots_accuracy.py),
max / median relative forward error of ours and of numpy.roots against the exact roots, over the
roots both return (see ``groundtruth.evaluate``), and our max backward error in ulp.
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

SOLVE_BAR = 5.0
JACOBIAN_BAR = 3.0
ULP = 2.0**-52


def best_of(fn, repeats=3):
    best = float("inf")
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def companion_eigvals(p):
    """All roots of each cubic by eigenvalues of its (N, 3, 3) companion matrix."""
    n = len(p)
    comp = np.zeros((n, 3, 3))
    comp[:, 0, :] = -p[:, 1:] / p[:, :1]
    comp[:, 1, 0] = 1.0
    comp[:, 2, 1] = 1.0
    return np.linalg.eigvals(comp)


def numpy_roots_loop(p):
    return [np.roots(row) for row in p]


def speed(n: int, n_roots: int):
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (n, 4))
    p2 = rng.uniform(-1, 1, (n, 3))
    # warm-up: compiles (first run) or loads the cached Warp module
    solve_cubic(p[:16])
    cubic_root_jacobian(p[:16])
    solve_quadratic(p2[:16])
    quadratic_root_jacobian(p2[:16])

    rows = []
    t, _ = best_of(lambda: companion_eigvals(p))
    rows.append(("np.linalg.eigvals (N,3,3 companion)", n, t))
    t_eig = t
    t, _ = best_of(lambda: numpy_roots_loop(p[:n_roots]))
    rows.append(("numpy.roots (python loop)", n_roots, t))
    t, _ = best_of(lambda: solve_cubic(p))
    rows.append(("solve_cubic", n, t))
    t_solve = t
    t, _ = best_of(lambda: cubic_root_jacobian(p))
    rows.append(("cubic_root_jacobian (roots + Jacobian)", n, t))
    t_jac = t
    t, _ = best_of(lambda: solve_quadratic(p2))
    rows.append(("solve_quadratic", n, t))
    t, _ = best_of(lambda: quadratic_root_jacobian(p2))
    rows.append(("quadratic_root_jacobian", n, t))

    eig_rate = n / t_eig
    print(f"\nSpeed: {n} uniform random cubics (numpy.roots: {n_roots}), best of 3, {os.cpu_count()} CPUs")
    print(f"{'method':42s} {'N':>8s} {'best s':>9s} {'per second':>12s} {'vs eigvals':>10s}")
    for name, count, t in rows:
        rate = count / t
        print(f"{name:42s} {count:8d} {t:9.4f} {rate:12.4g} {rate / eig_rate:9.2f}x")
    r_solve = (n / t_solve) / eig_rate
    r_jac = (n / t_jac) / eig_rate
    print(
        f"bars: solve_cubic {r_solve:.2f}x eigvals (bar {SOLVE_BAR:g}x: {'met' if r_solve >= SOLVE_BAR else 'NOT met'}); "
        f"cubic_root_jacobian {r_jac:.2f}x (bar {JACOBIAN_BAR:g}x: {'met' if r_jac >= JACOBIAN_BAR else 'NOT met'})"
    )
    return r_solve, r_jac


def accuracy(n: int):
    print(f"\nAccuracy: relative forward error vs exact roots (mpmath / exact construction), {n} samples per category")
    print("  over roots both return (numpy.roots drops leading zeros; roots beyond t_max excluded)")
    head = f"{'kind':9s} {'category':16s} {'roots':>6s} {'ours max':>10s} {'numpy max':>10s} {'ours med':>10s} {'numpy med':>10s} {'bw max ulp':>10s}  verdict"
    print(head)
    worse = []
    for kind, cats, gen, solve in (
        ("cubic", gt.CUBIC_CATEGORIES, gt.cubic_category, solve_cubic),
        ("quadratic", gt.QUADRATIC_CATEGORIES, gt.quadratic_category, solve_quadratic),
    ):
        for name in cats:
            p, exact = gen(name, n)
            res = gt.evaluate(p, exact, solve(p))
            both = [(f, g) for _, _, f, g in res["forward"] if g is not None]
            f = np.array([x for x, _ in both]) if both else np.zeros(1)
            g = np.array([y for _, y in both]) if both else np.zeros(1)
            bw = max((b for _, _, b in res["backward"]), default=0.0) / ULP
            ok = f.max() <= g.max() + 2 * ULP and np.median(f) <= np.median(g) + 2 * ULP and bw <= 8
            if not ok:
                worse.append(f"{kind}/{name}")
            print(
                f"{kind:9s} {name:16s} {len(both):6d} {f.max():10.2e} {g.max():10.2e} {np.median(f):10.2e} "
                f"{np.median(g):10.2e} {bw:10.3g}  {'ok' if ok else 'WORSE/over bound'}"
            )
    print("categories failing 'never worse than numpy.roots' or the 8-ulp backward bound: " + (", ".join(worse) or "none"))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200_000, help="batched sample count")
    ap.add_argument("--n-roots", type=int, default=20_000, help="numpy.roots loop sample count")
    ap.add_argument("--n-accuracy", type=int, default=200, help="samples per accuracy category")
    ap.add_argument("--skip-accuracy", action="store_true")
    args = ap.parse_args()
    speed(args.n, args.n_roots)
    if not args.skip_accuracy:
        accuracy(args.n_accuracy)


if __name__ == "__main__":
    main()
