"""CCD accuracy and speed: our batched narrow phase against ipctk's Tight Inclusion CCD, per
precision and CCD tolerance setting.

    python benchmarks/ccd.py [--quick] [--out benchmarks/results/ccd] [--precisions float64,float32]
                             [--tolerance-scales 0.01,1,100] [--max-iterations 10000000]
                             [--ipctk-sample N] [--repeats 3] [--generated] [--toi] [--mesh] [--peer-only]

Queries: every sample query under the data root (tests/ccd_queries.py: the shared
ccd-sample-queries, or $TUNNELSIM_CCD_QUERIES), vertex-face and edge-edge, against the data set's
ground truth. FN = truth 1 reported as a miss, FP = truth 0 reported as a hit.

Ours: ``collision.ccd.point_triangle_ccd`` / ``edge_edge_ccd`` on the whole (N, 3)-argument batch
(best of --repeats after one warm-up call that compiles/loads the Warp kernels); time per query =
batch time / N. One row per precision (``float32``: the narrow phase and root solver generated in
float32 by :mod:`kernels.variants`, positions rounded to float32 before the kernel, the rounding
inside the timed call) and ``tolerance_scale`` (the multiplier on the coefficient and distance
error bounds that decide a hit; 1 = the kernels' 64 u / 256 u). ipctk: ``ipctk.tight_inclusion.point_triangle_ccd`` / ``edge_edge_ccd`` (the raw
Tight Inclusion solver, tolerance 1e-6, max_iterations ipctk's default 1e7) called once per query
from Python (benchmarks/ipctk_peer.py); its time per query includes the Python call overhead, as
the batched call's does. Bar: ours >= 10x faster per query than ipctk.

With the default 1e7 iterations the ipctk pass alone takes about 4 minutes (measured: 18.7 ms per
vertex-face and 46.9 ms per edge-edge query; a few edge-edge unit tests run for seconds each);
``--max-iterations 1000000`` is ~8x faster (2.3 / 5.2 ms) with the same FN/FP on these queries, ``--ipctk-sample N`` times ipctk on a random N per kind (FN/FP then
over that sample only).

--generated  also run the exact-by-construction touching queries and near misses
             (tests/ccd_generated.py): FN / FP and |toi - exact|.
--toi        time-of-impact error of both against the exact earliest contact (tests/exact_ccd.py)
             on the sample queries whose truth is 1 (a few seconds of exact arithmetic).
--mesh       the mesh-level comparison (cloth sheet dropped on a ground quad): ipctk's
             compute_collision_free_stepsize; our side is still a placeholder.
--peer-only  skip our CCD (to measure ipctk before collision.ccd exists); without it a missing
             collision.ccd is an error.
--quick      a subset of the sample queries (every true contact plus 300 random non-contacts per
             kind), ipctk with max_iterations 1e6, tolerance scales 1 and 100, best of 1 (< 60 s
             once the kernels are compiled; each new variant compiles in ~7 s).

Writes ``<out>.md`` (the tables) and ``<out>.json`` and prints the tables (the --generated,
--toi and --mesh sections are printed only).
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

import ccd_queries  # noqa: E402

from benchmarks import ipctk_peer, report  # noqa: E402

SPEED_BAR = 10.0  # ours must be >= 10x faster per query than ipctk (milestone bar)
KINDS = ("vertex-face", "edge-edge")
DEFAULT_OUT = os.path.join(HERE, "results", "ccd")
QUICK_NEGATIVES = 300


def import_ours():
    """(point_triangle_ccd, edge_edge_ccd) from collision.ccd, or exit with a clear message."""
    try:
        from collision.ccd import edge_edge_ccd, point_triangle_ccd
    except ModuleNotFoundError as e:
        if e.name in ("collision.ccd", "collision"):
            raise SystemExit(
                "benchmarks/ccd.py: collision/ccd.py does not exist yet (the batched narrow phase "
                "point_triangle_ccd / edge_edge_ccd has not landed). Run with --peer-only to "
                "measure ipctk alone."
            ) from None
        raise
    except ImportError as e:
        raise SystemExit(
            f"benchmarks/ccd.py: collision.ccd does not provide point_triangle_ccd and edge_edge_ccd yet ({e})"
        ) from None
    return point_triangle_ccd, edge_edge_ccd


def ours_setting(ours, kind, precision="float64", tolerance_scale=1.0):
    """Our batched function for ``kind`` with the precision / tolerance settings bound."""
    fn = ours[0] if kind == "vertex-face" else ours[1]
    if precision == "float64" and tolerance_scale == 1.0:
        return fn
    return lambda *a: fn(*a, precision=precision, tolerance_scale=tolerance_scale)


def run_ours(fn, points, repeats):
    """Batched call: (hit, toi, best seconds for the batch)."""
    args = [np.ascontiguousarray(points[:, j, :]) for j in range(8)]
    fn(*[a[: min(len(a), 16)] for a in args])  # warm-up (kernel compile / load)
    best, out = float("inf"), None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    hit, toi = out
    hit = np.asarray(hit, dtype=bool).reshape(-1)
    toi = np.asarray(toi, dtype=np.float64).reshape(-1)
    if hit.shape != (len(points),) or toi.shape != (len(points),):
        raise SystemExit(f"collision.ccd returned shapes {hit.shape}, {toi.shape} for {len(points)} queries")
    return hit, toi, best


def fn_fp(hit, truth):
    return int((truth & ~hit).sum()), int((~truth & hit).sum())


def fmt_ms(s):
    return f"{s * 1e3:9.4f}" if np.isfinite(s) else f"{'-':>9s}"


def exact_tois(qs, idx):
    """Exact earliest contact (float, correctly rounded) of queries idx (truth 1)."""
    from exact_ccd import exact_ccd

    out = np.full(len(idx), np.nan)
    for k, i in enumerate(idx):
        r = exact_ccd(qs.exact(int(i)), qs.kind)
        out[k] = r.toi_float
    return out


def toi_report(name, toi, hit, ref):
    """|toi - exact| over the true hits a method reports; 'late' = toi after the exact earliest
    contact (a conservative CCD never is; 1e-12 allows for the float rounding of the exact toi)."""
    m = hit & np.isfinite(ref)
    if not m.any():
        return f"{name}: no common hits"
    err = toi[m] - ref[m]
    late = int((err > 1e-12).sum())
    early = int((err < -1e-3).sum())
    return (
        f"{name}: max |toi - exact| {np.abs(err).max():.3g}, median {np.median(np.abs(err)):.3g}; "
        f"late by > 1e-12: {late} (max {max(err.max(), 0.0):.3g}); early by > 1e-3: {early} (of {int(m.sum())})"
    )


def sample_queries(args, ours):
    """The sample-query table: FN / FP and time per query of every (precision, tolerance_scale)
    of ours and of ipctk, per kind, split into the unit-test and erleben scenes. Returns the
    markdown lines and the JSON data."""
    root = ccd_queries.queries_root()
    print(f"Sample queries from {root}")
    settings = [(p, ts) for p in args.precisions for ts in args.tolerance_scales] if ours is not None else []
    rng = np.random.default_rng(args.seed)
    rows, data, verdicts, notes = [], [], [], []
    for kind in KINDS:
        qs = ccd_queries.load_queries(kind)
        rep = ccd_queries.representability(kind)
        notes.append(f"{kind}: {rep['queries']} queries, {rep['inexact_coordinates']} of {rep['coordinates']} "
                     "coordinates not exactly representable in float64")
        use = np.arange(len(qs.truth))
        if args.quick:
            neg = np.flatnonzero(~qs.truth)
            use = np.sort(np.concatenate([np.flatnonzero(qs.truth),
                                          rng.choice(neg, min(QUICK_NEGATIVES, len(neg)), replace=False)]))
        pts, truth, scenes = qs.points[use], qs.truth[use], qs.scenes()[use]
        n = len(truth)
        subsets = [("unit", scenes == "unit-tests"), ("erleben", scenes != "unit-tests"), ("all", np.ones(n, dtype=bool))]
        results = []  # (method, precision, tolerance_scale, hit, toi, seconds per query (mean), timed mask)
        for prec, ts in settings:
            hit, toi, secs = run_ours(ours_setting(ours, kind, prec, ts), pts, args.repeats)
            results.append(("ours", prec, ts, hit, toi, secs / n, np.ones(n, dtype=bool)))
        if not args.skip_ipctk:
            sel = np.arange(n)
            if args.ipctk_sample and args.ipctk_sample < n:
                sel = np.sort(rng.choice(n, args.ipctk_sample, replace=False))
            r = ipctk_peer.tight_inclusion_queries(pts[sel], kind, max_iterations=args.max_iterations)
            i_hit, i_toi, i_sec = np.zeros(n, dtype=bool), np.full(n, np.nan), np.full(n, np.nan)
            i_hit[sel], i_toi[sel], i_sec[sel] = r.hit, r.toi, r.seconds
            timed = np.zeros(n, dtype=bool)
            timed[sel] = True
            results.append(("ipctk", "float64", None, i_hit, i_toi, float(np.nanmean(i_sec)), timed))
        ipctk_s = next((r[5] for r in results if r[0] == "ipctk"), None)
        if args.toi:
            idx = np.flatnonzero(truth)
            ref = exact_tois(qs, use[idx])  # exact earliest contacts of the true hits
        for method, prec, ts, hit, toi, per_query, timed in results:
            cells = [kind, method, prec, ts if ts is not None else "tol 1e-6", int(timed.sum()), int(truth[timed].sum())]
            rec = {"kind": kind, "method": method, "precision": prec, "tolerance_scale": ts,
                   "queries": int(timed.sum()), "positives": int(truth[timed].sum())}
            for name, mask in subsets:
                m = mask & timed
                fn_, fp_ = fn_fp(hit[m], truth[m])
                cells += [fn_, fp_]
                rec[f"fn_{name}"], rec[f"fp_{name}"] = fn_, fp_
            speedup = ipctk_s / per_query if (ipctk_s is not None and method == "ours") else None
            cells += [per_query * 1e6, speedup]
            rec["us_per_query"], rec["ipctk_over_ours"] = per_query * 1e6, speedup
            rows.append(cells)
            data.append(rec)
            if method == "ours" and prec == "float64" and ts == 1.0 and speedup is not None:
                verdicts.append((kind, speedup))
            if args.toi:
                label = f"{method} {prec} ts={ts}" if method == "ours" else "ipctk"
                j = timed[idx]
                notes.append(f"{kind} " + toi_report(label, toi[idx][j], hit[idx][j], ref[j]))
    subset_note = (f"a subset: every true contact plus {QUICK_NEGATIVES} random non-contacts per kind (seed {args.seed})"
                   if args.quick else "all queries")
    lines = [
        f"## Sample queries ({subset_note})",
        "",
        f"Data: {root}. FN = truth 1 reported as a miss, FP = truth 0 reported as a hit (truth of the exact "
        "rationals; float32 rounds the positions first). ipctk: Tight Inclusion, tolerance "
        f"{ipctk_peer.TOLERANCE:g}, max_iterations {args.max_iterations:g}, one Python call per query; ours: "
        f"best of {args.repeats} batched calls, time per query = batch time / N (one thread). "
        "*ts*: tolerance_scale (multiplier on the 64 u / 256 u error bounds).",
        "",
        *report.table(["kind", "method", "precision", "ts", "N", "pos", "FN unit", "FP unit", "FN erleben",
                       "FP erleben", "FN", "FP", "µs/query", "ipctk / ours"], rows),
        "",
        *[f"- {x}" for x in notes],
        "",
    ]
    for kind, ratio in verdicts:
        lines.append(f"Speed bar {kind}: ours (float64) {ratio:.1f}x faster per query than ipctk "
                     f"(bar {SPEED_BAR:g}x: {'met' if ratio >= SPEED_BAR else 'NOT met'}).")
    return lines + [""], {"subset": subset_note, "rows": data}


def generated_queries(args, ours):
    import ccd_generated

    print("\nGenerated queries (exact by construction, tests/ccd_generated.py): touching + near misses (gap 2^-30)")
    touch = ccd_generated.generate_queries(n_per_case=args.n_generated, seed=args.seed)
    miss = ccd_generated.generate_near_misses(n_per_case=max(1, args.n_generated - 1), seed=args.seed + 1)
    head = f"{'kind':12s} {'set':6s} {'N':>5s} | {'ours FN/FP':>10s} {'max|dtoi|':>10s} | {'ipctk FN/FP':>11s} {'max|dtoi|':>10s}"
    print(head)
    print("-" * len(head))
    worst = {}
    for kind in KINDS:
        for name, g in (("touch", touch), ("miss", miss)):
            pts, tois, labels = g.select(kind)
            truth = np.array([t is not None for t in tois])
            ref = np.array([float(t) if t is not None else np.nan for t in tois])
            cells = f"{kind:12s} {name:6s} {len(pts):5d} |"
            results = []
            if ours is not None:
                h, t, _ = run_ours(ours_setting(ours, kind), pts, 1)
                results.append(("ours", h, t))
            else:
                cells += f" {'-':>10s} {'-':>10s} |"
            if not args.skip_ipctk:
                r = ipctk_peer.tight_inclusion_queries(pts, kind, max_iterations=args.max_iterations)
                results.append(("ipctk", r.hit, r.toi))
            for who, h, t in results:
                fn_, fp_ = fn_fp(h, truth)
                m = h & truth
                d = np.abs(t[m] - ref[m]) if m.any() else np.zeros(1)
                cells += f" {f'{fn_}/{fp_}':>{10 if who == 'ours' else 11}s} {d.max():10.3g} |"
                bad = [labels[i] for i in np.flatnonzero(truth != h)]
                if bad:
                    worst.setdefault(who, []).extend(bad[:5])
            print(cells)
    for who, bad in worst.items():
        print(f"  {who} wrong on (first few per set): {', '.join(bad)}")


# ------------------------------------------------------------------------------ mesh level


def cloth_drop_scene(n: int = 32, seed: int = 0, height: float = 0.1, drop: float = 0.3):
    """A wavy n x n cloth sheet (unit square, a few mm of random height noise) at ``height``
    above a ground quad (2 triangles, z = 0), moved down by ``drop`` (+ noise) in one step.
    Returns V0, V1, F (cloth then ground), and the exact first contact of the step: every cloth
    vertex is above the ground's interior, so the earliest contact is the first cloth vertex to
    reach z = 0, min_i z0_i / (z0_i - z1_i) (a cloth edge or face is never lower than its lowest
    vertex)."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    Z = height + 0.005 * rng.standard_normal(X.shape)
    cloth = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    Fc = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    ground = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [2.0, 2.0, 0.0], [-1.0, 2.0, 0.0]])
    Fg = np.array([[0, 1, 2], [0, 2, 3]]) + len(cloth)
    V0 = np.vstack([cloth, ground])
    V1 = V0.copy()
    V1[: len(cloth), 2] -= drop + 0.01 * rng.random(len(cloth))
    F = np.concatenate([Fc, Fg]).astype(np.int32)
    z0, z1 = V0[: len(cloth), 2], V1[: len(cloth), 2]
    t_exact = float(np.min(z0 / (z0 - z1)))
    return V0, V1, F, t_exact


def mesh_level(args, ours):
    print("\nMesh level: one cloth step against the ground, largest collision-free step fraction")
    V0, V1, F, t_exact = cloth_drop_scene(args.mesh_n, args.seed)
    E = ipctk_peer.ipctk.edges(np.asfortranarray(F))
    print(f"  scene: {len(V0)} vertices, {len(E)} edges, {len(F)} faces; exact first contact t = {t_exact:.9f}")
    mesh = ipctk_peer.collision_mesh(V0, E, F)
    ipctk_best = float("inf")
    for name, bp in (("default", None), ("HashGrid", ipctk_peer.ipctk.HashGrid()), ("LBVH", ipctk_peer.ipctk.LBVH())):
        ipctk_peer.ipctk_stepsize(V0, V1, mesh=mesh, broad_phase=bp)  # warm-up
        best, step = float("inf"), None
        for _ in range(max(1, args.repeats)):
            step, secs = ipctk_peer.ipctk_stepsize(V0, V1, mesh=mesh, broad_phase=bp)
            best = min(best, secs)
        ipctk_best = min(ipctk_best, best)
        print(
            f"  ipctk compute_collision_free_stepsize ({name} broad phase, {ipctk_peer.ipctk.get_num_threads()} threads): "
            f"step {step:.9f} (exact contact - step = {t_exact - step:.3g}) in {best * 1e3:.2f} ms"
        )
    if ours is None:
        return
    from collision.broad_phase import BroadPhase
    from collision.ccd import mesh_ccd

    # the whole mesh is one self-colliding body, as in ipctk's CollisionMesh
    mesh_ccd(V0, V1, F)  # warm-up (kernel compilation)
    rows = []
    for label, make in (("fresh broad phase", lambda: None), ("reused BroadPhase", lambda: bp_reused)):
        bp_reused = BroadPhase(F, num_vertices=len(V0)) if label.startswith("reused") else None
        if bp_reused is not None:
            mesh_ccd(V0, V1, F, broad_phase=bp_reused)
        best, result = float("inf"), None
        for _ in range(max(1, args.repeats)):
            t = time.perf_counter()
            result = mesh_ccd(V0, V1, F, broad_phase=make())
            best = min(best, time.perf_counter() - t)
        rows.append((label, result, best))
    for label, result, best in rows:
        print(
            f"  ours mesh_ccd ({label}, 1 thread): earliest toi {result.time_of_impact:.9f} "
            f"(exact contact - toi = {t_exact - result.time_of_impact:.3g}; {len(result.vf)} vf + {len(result.ee)} ee "
            f"candidates, {result.num_contacts} contacts) in {best * 1e3:.2f} ms; ipctk best / ours = {ipctk_best / best:.1f}x"
        )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max-iterations", type=int, default=None,
                    help=f"ipctk max_iterations (default {ipctk_peer.MAX_ITERATIONS:g}; --quick: 1e6)")
    ap.add_argument("--ipctk-sample", type=int, default=0, help="time ipctk on a random N queries per kind (0: all)")
    ap.add_argument("--repeats", type=int, default=None, help="best of this many batched calls (ours; default 3, --quick 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--precisions", default="float64,float32", help="comma-separated: float64,float32")
    ap.add_argument("--tolerance-scales", default=None, help="comma-separated tolerance_scale values (default 0.01,1,100; --quick 1,100)")
    ap.add_argument("--quick", action="store_true", help="a subset of the queries, ipctk at 1e6 iterations")
    ap.add_argument("--out", default=DEFAULT_OUT, help="output prefix: writes <out>.md and <out>.json")
    ap.add_argument("--generated", action="store_true", help="also the exact-by-construction queries")
    ap.add_argument("--n-generated", type=int, default=3, help="instances per generated case")
    ap.add_argument("--toi", action="store_true", help="toi error against the exact contact time")
    ap.add_argument("--mesh", action="store_true", help="mesh-level comparison (ipctk side)")
    ap.add_argument("--mesh-n", type=int, default=32, help="cloth grid resolution for --mesh")
    ap.add_argument("--peer-only", action="store_true", help="ipctk only (before collision.ccd exists)")
    ap.add_argument("--skip-ipctk", action="store_true", help="ours only")
    args = ap.parse_args(argv)
    if args.max_iterations is None:
        args.max_iterations = 1_000_000 if args.quick else ipctk_peer.MAX_ITERATIONS
    if args.repeats is None:
        args.repeats = 1 if args.quick else 3
    if args.tolerance_scales is None:
        args.tolerance_scales = "1,100" if args.quick else "0.01,1,100"
    args.precisions = [x.strip() for x in args.precisions.split(",") if x.strip()]
    for prec in args.precisions:
        if prec not in ("float64", "float32"):
            ap.error(f"--precisions: unknown precision {prec!r}")
    try:
        args.tolerance_scales = [float(x) for x in args.tolerance_scales.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--tolerance-scales: expected comma-separated numbers, got {args.tolerance_scales!r}")
    if any(not (np.isfinite(x) and x > 0) for x in args.tolerance_scales):
        ap.error("--tolerance-scales: every value must be positive and finite")
    ipctk_peer.quiet()
    ours = None if args.peer_only else import_ours()
    t0 = time.perf_counter()
    lines, sample = sample_queries(args, ours)
    if args.generated:
        generated_queries(args, ours)
    if args.mesh:
        mesh_level(args, ours)
    lines.append(f"Total {time.perf_counter() - t0:.1f} s.")
    data = {"settings": {"quick": args.quick, "precisions": args.precisions, "tolerance_scales": args.tolerance_scales,
                         "ipctk_max_iterations": args.max_iterations, "repeats": args.repeats, "seed": args.seed},
            "sample_queries": sample}
    report.write(args.out, "Narrow-phase CCD on the sample queries: precision and tolerance against Tight Inclusion",
                 lines, data)
    return data


if __name__ == "__main__":
    main()
