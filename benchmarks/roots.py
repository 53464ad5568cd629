"""Speed and accuracy of the robust root solver against numpy, in float64 and float32.

    python benchmarks/roots.py [--quick] [--out benchmarks/results/roots] [--n 200000]
                               [--n-roots 20000] [--n-accuracy 200] [--skip-accuracy]
                               [--precisions float64,float32]

Speed (best of 3 with time.perf_counter, after a warm-up call that compiles/loads the Warp
kernels): polynomials per second of ``solve_cubic`` / ``cubic_root_jacobian`` / ``solve_quadratic``
/ ``quadratic_root_jacobian`` on N uniform random inputs, per precision (``precision="float32"``:
the same kernels generated in float32 by :mod:`kernels.variants`; the API call includes rounding
the float64 input to float32 and widening the output, the "kernel only" rows time the launch on
arrays already in the kernel's precision), against batched companion-matrix eigenvalues on
(N, 3, 3) (building the companion matrices is part of their time): float64 ``np.linalg.eigvals``,
float32 ``torch.linalg.eigvals`` (one thread; numpy's linalg computes float32 input in double, so
it is no float32 peer), and a per-polynomial ``numpy.roots`` loop (fewer samples). The bars
reported against (float64): solving >= 5x eigvals, Jacobian >= 3x eigvals.

Accuracy: per category of tests/groundtruth.py (the same inputs as tests/test_roots_accuracy.py),
max / median relative forward error of ours and of ``numpy.roots`` against the exact roots
(mpmath or the exact construction), over the roots both return (``groundtruth.evaluate``), and
our max backward error in ulp of the precision. float32 rows: the coefficients are rounded to
float32 first; the errors are measured against the exact roots of the *rounded* polynomial (the
solver's own accuracy; the peer is :func:`roots_float32`, numpy.roots' algorithm with the
companion eigenvalues in float32 LAPACK via torch), and "e2e max" is our error against the exact
roots of the original float64 input (what a float32 pipeline delivers, input rounding included).
Categories whose inputs overflow float32, or underflow to the zero polynomial, are marked n/a.

``--quick``: 20000 / 2000 / 30 samples (well under 30 s once the kernels are compiled).
Writes ``<out>.md`` (the tables) and ``<out>.json`` and prints the tables.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)  # first: benchmarks/sim.py must not shadow the sim package

import groundtruth as gt  # noqa: E402

from benchmarks import report  # noqa: E402
from collision import roots as croots  # noqa: E402
from collision.roots import (  # noqa: E402
    FLOAT32_T_MAX,
    cubic_root_jacobian,
    quadratic_root_jacobian,
    solve_cubic,
    solve_quadratic,
)

SOLVE_BAR = 5.0
JACOBIAN_BAR = 3.0
ULP = {"float64": 2.0**-52, "float32": 2.0**-23}
T_MAX = {"float64": 1e150, "float32": FLOAT32_T_MAX}
NP_DTYPE = {"float64": np.float64, "float32": np.float32}
DEFAULT_OUT = os.path.join(HERE, "results", "roots")


def best_of(fn, repeats=3):
    best = float("inf")
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def companion(p):
    """(N, 3, 3) companion matrices of the (N, 4) cubics ``p`` (in p's dtype)."""
    comp = np.zeros((len(p), 3, 3), dtype=p.dtype)
    comp[:, 0, :] = -p[:, 1:] / p[:, :1]
    comp[:, 1, 0] = 1.0
    comp[:, 2, 1] = 1.0
    return comp


def companion_eigvals(p):
    """All roots of each cubic by eigenvalues of its companion matrix (numpy, in p's dtype)."""
    return np.linalg.eigvals(companion(p))


def torch_eigvals(p):
    """Companion eigenvalues of (N, 4) float32 cubics with torch (single-precision LAPACK)."""
    import torch

    return torch.linalg.eigvals(torch.from_numpy(companion(p))).numpy()


def roots_float32(row):
    """``numpy.roots`` computed in float32: leading zeros dropped, trailing zeros as zero roots,
    the companion matrix's eigenvalues by torch in single precision (numpy.linalg would compute
    float32 input in double). None when the companion matrix overflows."""
    import torch

    c = np.asarray(row, dtype=np.float32)
    nz = np.flatnonzero(c)
    if len(nz) == 0:
        return []
    trailing = len(c) - 1 - nz[-1]
    c = c[nz[0]: nz[-1] + 1]
    d = len(c) - 1
    out = []
    if d > 0:
        comp = np.zeros((d, d), dtype=np.float32)
        with np.errstate(all="ignore"):
            comp[0] = -c[1:] / c[0]
        if not np.isfinite(comp).all():
            return None
        comp[np.arange(1, d), np.arange(d - 1)] = 1.0
        out = [complex(z) for z in torch.linalg.eigvals(torch.from_numpy(comp)).numpy()]
    return out + [0j] * trailing


def numpy_roots_loop(p):
    return [np.roots(row) for row in p]


def _kernel_only(precision, p, cubic: bool):
    """A closure launching the solve kernel of ``precision`` on arrays already in its dtype."""
    import warp as wp

    k = croots.root_kernels(precision, None, None)
    arr = np.ascontiguousarray(p, dtype=NP_DTYPE[precision])
    v3, v4, scalar = (wp.vec3d, wp.vec4d, wp.float64) if precision == "float64" else (wp.vec3f, wp.vec4f, wp.float32)
    if cubic:
        return lambda: croots.launch_root_kernel(k.solve_cubic_kernel, arr, v4, [T_MAX[precision]], [k.vec6d], scalar)
    return lambda: croots.launch_root_kernel(k.solve_quadratic_kernel, arr, v3, [T_MAX[precision]], [v4], scalar)


def speed(n: int, n_roots: int, precisions):
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (n, 4))
    p2 = rng.uniform(-1, 1, (n, 3))
    import torch

    torch.set_num_threads(1)  # one thread, as the Warp CPU kernels
    rows = []  # (method, precision, N, seconds)
    t, _ = best_of(lambda: companion_eigvals(p))
    rows.append(("np.linalg.eigvals (N,3,3 companion)", "float64", n, t))
    t, _ = best_of(lambda: numpy_roots_loop(p[:n_roots]))
    rows.append(("numpy.roots (python loop)", "float64", n_roots, t))
    for prec in ("float64", "float32"):
        pp = p.astype(NP_DTYPE[prec])
        t, _ = best_of(lambda pp=pp: torch_eigvals(pp))
        rows.append(("torch.linalg.eigvals (N,3,3 companion)", prec, n, t))
    for prec in precisions:
        kw = {"precision": prec}
        # warm-up: compiles (first run) or loads the cached Warp module
        solve_cubic(p[:16], **kw)
        cubic_root_jacobian(p[:16], **kw)
        solve_quadratic(p2[:16], **kw)
        quadratic_root_jacobian(p2[:16], **kw)
        for name, fn, arg in (
            ("solve_cubic", solve_cubic, p),
            ("solve_cubic (kernel only)", None, p),
            ("cubic_root_jacobian (roots + Jacobian)", cubic_root_jacobian, p),
            ("solve_quadratic", solve_quadratic, p2),
            ("solve_quadratic (kernel only)", None, p2),
            ("quadratic_root_jacobian", quadratic_root_jacobian, p2),
        ):
            call = _kernel_only(prec, arg, arg.shape[1] == 4) if fn is None else (lambda fn=fn, arg=arg, kw=kw: fn(arg, **kw))
            t, _ = best_of(call)
            rows.append((name, prec, n, t))
    # the batched eigenvalue peer of each precision: numpy (float64), torch (float32)
    eig = {"float64": next(c / t for m, pr, c, t in rows if m.startswith("np.linalg")),
           "float32": next(c / t for m, pr, c, t in rows if m.startswith("torch") and pr == "float32")}
    f64 = {m: c / t for m, pr, c, t in rows if pr == "float64"}
    table = []
    data = []
    for m, prec, count, t in rows:
        rate = count / t
        ratio = rate / f64[m] if prec == "float32" and m in f64 else None
        table.append([m, prec, count, t, rate, rate / eig[prec], ratio])
        data.append({"method": m, "precision": prec, "n": count, "best_s": t, "per_second": rate,
                     "vs_batched_eigvals": rate / eig[prec], "float32_over_float64": ratio})
    r_solve = f64["solve_cubic"] / eig["float64"]
    r_jac = f64["cubic_root_jacobian (roots + Jacobian)"] / eig["float64"]
    lines = [
        f"## Speed: {n} uniform random cubics / quadratics (numpy.roots: {n_roots}), best of 3, one thread",
        "",
        "*vs eigvals*: throughput over the batched companion eigenvalues of the same precision (float64: "
        "np.linalg.eigvals, float32: torch.linalg.eigvals); *float32 / float64*: the same method's throughput ratio.",
        "",
        *report.table(["method", "precision", "N", "best s", "per second", "vs eigvals", "float32 / float64"], table),
        "",
        f"Bars (float64): solve_cubic {r_solve:.2f}x eigvals (bar {SOLVE_BAR:g}x: "
        f"{'met' if r_solve >= SOLVE_BAR else 'NOT met'}); cubic_root_jacobian {r_jac:.2f}x "
        f"(bar {JACOBIAN_BAR:g}x: {'met' if r_jac >= JACOBIAN_BAR else 'NOT met'}).",
        "",
    ]
    return lines, {"rows": data, "bars": {"solve_vs_eigvals": r_solve, "jacobian_vs_eigvals": r_jac}}


def _peer_errors(p, truth, t_max, precision):
    """Forward errors of the peer (numpy.roots in float64, :func:`roots_float32` in float32)
    matched to the exact roots."""
    out = {}
    for i in range(len(p)):
        if truth[i] is None:
            continue
        if precision == "float64":
            nz = gt.numpy_roots(p[i])
        else:
            nz = roots_float32(p[i])
            if nz is None:  # companion matrix overflowed (a tiny leading coefficient): no roots
                continue
        clamped = [gt.clamp_root(t, t_max) for t in truth[i]]
        for k, j in gt.match_roots(nz, clamped):
            if not gt.beyond(truth[i][j], t_max):
                out[(i, j)] = gt.forward_error(complex(nz[k]), truth[i][j])
    return out


def _truths(p, exact):
    out = []
    for i in range(len(p)):
        if exact[i] is not None:
            out.append(exact[i])
        else:
            out.append(gt.true_roots(p[i])[0])
    return out


def accuracy(n: int, precisions):
    rows, data = [], []
    for kind, cats, gen, solve in (
        ("cubic", gt.CUBIC_CATEGORIES, gt.cubic_category, solve_cubic),
        ("quadratic", gt.QUADRATIC_CATEGORIES, gt.quadratic_category, solve_quadratic),
    ):
        for name in cats:
            p, exact = gen(name, n)
            for prec in precisions:
                t_max = T_MAX[prec]
                ulp = ULP[prec]
                rec = {"kind": kind, "category": name, "precision": prec}
                if prec == "float32":
                    with np.errstate(over="ignore", under="ignore"):
                        p_in = p.astype(np.float32).astype(np.float64)
                    if not np.isfinite(p_in).all():
                        rows.append([kind, name, prec, "n/a: inputs overflow float32"] + [None] * 7)
                        data.append({**rec, "status": "overflow"})
                        continue
                    if not p_in.any(axis=1).any() and p.any():
                        rows.append([kind, name, prec, "n/a: inputs underflow to 0 in float32"] + [None] * 7)
                        data.append({**rec, "status": "underflow"})
                        continue
                    # exact roots survive only where rounding changed nothing
                    exact_in = [e if np.array_equal(a, b) else None for e, a, b in zip(exact, p, p_in)]
                else:
                    p_in, exact_in = p, exact
                ours = solve(p, precision=prec)
                truth = _truths(p_in, exact_in)
                res = gt.evaluate(p_in, truth, ours, t_max, with_numpy=False)
                nperr = _peer_errors(p_in, truth, t_max, prec)
                # our forward errors, paired with numpy's where numpy returned the root too
                ours_err, both = [], []
                for i in range(len(p_in)):
                    if truth[i] is None or len(truth[i]) > ours.shape[1]:
                        continue
                    clamped = [gt.clamp_root(t, t_max) for t in truth[i]]
                    for s, j in gt.match_roots([complex(z) for z in ours[i]], clamped):
                        if gt.beyond(truth[i][j], t_max):
                            continue
                        f = gt.forward_error(ours[i][s], truth[i][j])
                        ours_err.append(f)
                        if (i, j) in nperr:
                            both.append((f, nperr[(i, j)]))
                f = np.array(ours_err) if ours_err else np.zeros(1)
                g = np.array([y for _, y in both]) if both else np.zeros(1)
                bw = max((b for _, _, b in res["backward"]), default=0.0) / ulp
                e2e = None
                if prec == "float32":
                    t64 = _truths(p, exact)
                    r64 = gt.evaluate(p, t64, ours, t_max, with_numpy=False)
                    e2e = max((x for _, _, x, _ in r64["forward"]), default=0.0)
                else:
                    e2e = float(f.max())
                rows.append([kind, name, prec, len(ours_err), float(f.max()), float(np.median(f)), float(g.max()),
                             float(np.median(g)), bw, e2e, len(res["unmatched"])])
                data.append({**rec, "status": "ok", "roots": len(ours_err), "ours_max": float(f.max()),
                             "ours_median": float(np.median(f)), "peer_max": float(g.max()),
                             "peer_median": float(np.median(g)), "backward_max_ulp": bw, "end_to_end_max": e2e,
                             "unmatched": len(res["unmatched"])})
    lines = [
        f"## Accuracy: relative forward error vs exact roots (mpmath / exact construction), {n} samples per category",
        "",
        "*peer*: numpy.roots (float64 rows) / numpy.roots' algorithm in float32 with torch's single-precision "
        "eigenvalues (float32 rows). float32 rows: inputs rounded to float32; errors against the exact roots of the "
        "rounded polynomial; *e2e max*: ours against the exact roots of the float64 input; "
        "backward error in ulp of the precision (2^-52 / 2^-23); roots beyond t_max (1e150 / float32(1e18)) excluded.",
        "",
        *report.table(["kind", "category", "precision", "roots", "ours max", "ours med", "peer max",
                       "peer med", "bw max ulp", "e2e max", "unmatched"], rows),
        "",
    ]
    return lines, data


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200_000, help="batched sample count")
    ap.add_argument("--n-roots", type=int, default=20_000, help="numpy.roots loop sample count")
    ap.add_argument("--n-accuracy", type=int, default=200, help="samples per accuracy category")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--precisions", default="float64,float32", help="comma-separated: float64,float32")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (20000 / 2000 / 30 samples)")
    ap.add_argument("--out", default=DEFAULT_OUT, help="output prefix: writes <out>.md and <out>.json")
    args = ap.parse_args(argv)
    precisions = [s.strip() for s in args.precisions.split(",") if s.strip()]
    for prec in precisions:
        if prec not in croots.PRECISIONS:
            ap.error(f"--precisions: unknown precision {prec!r} (one of {croots.PRECISIONS})")
    if args.quick:
        args.n, args.n_roots, args.n_accuracy = 20_000, 2_000, 30
    t0 = time.perf_counter()
    lines, speed_data = speed(args.n, args.n_roots, precisions)
    data = {"settings": {"n": args.n, "n_roots": args.n_roots, "n_accuracy": args.n_accuracy,
                         "precisions": precisions, "quick": args.quick}, "speed": speed_data}
    if not args.skip_accuracy:
        acc_lines, acc_data = accuracy(args.n_accuracy, precisions)
        lines += acc_lines
        data["accuracy"] = acc_data
    lines.append(f"Total {time.perf_counter() - t0:.1f} s.")
    report.write(args.out, "Root solver: speed and accuracy, float64 and float32", lines, data)
    return data


if __name__ == "__main__":
    main()
