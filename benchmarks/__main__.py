"""One command for every benchmark: ``python -m benchmarks`` (quick, minutes) or ``--full``.

    python -m benchmarks [--full] [--only roots,ccd,sim,gradients,trade,physics,convergence] [--out-dir benchmarks/results]

Run from the repository root after ``make test`` (which builds ``.venv``):
``.venv/bin/python -m benchmarks``. Each benchmark prints its tables and writes
``<out-dir>/<name>.md`` (and ``.json`` / ``.png`` where it has them); every ratio in a table is
measured in the same run as its peer. The sections:

* ``roots``: throughput and accuracy per coefficient category, float64 and float32, against
  numpy's batched ``eigvals``, ``numpy.roots`` and mpmath (:mod:`benchmarks.roots`);
* ``ccd``: false negatives / positives and time per query against ipctk's Tight Inclusion on the
  sample queries, per precision and CCD tolerance (:mod:`benchmarks.ccd`; needs the sample
  queries: ``../shared/data/ccd-sample-queries`` or ``$TUNNELSIM_CCD_QUERIES``);
* ``sim``: steps per second of the force step against Warp's numpy / torch / Warp cloth
  variants, per scene with collisions, and per cloth size (:mod:`benchmarks.sim`);
* ``gradients``: rollout gradients against finite differences, forward + backward cost
  (:mod:`benchmarks.gradients`);
* ``trade``: wall time against accuracy over substeps x integrator x thickness x rounds x
  response x the CCD decisions' precision / tolerance / root iteration cap per scene, ``M`` on the inverse scene, Pareto table and plot with the recommended
  setting (:mod:`benchmarks.trade`);
* ``physics``: the physics validation suite, classic checks against closed forms for both
  collision responses (:mod:`benchmarks.physics`; quick: 8 substeps, full: 4, 8, 16 and 32);
* ``convergence``: error against closed forms (ballistic flight, a bounce, sliding to rest, an
  elastic hit on a free box, free rotation) as the substeps double, with the fitted order
  (:mod:`benchmarks.convergence`; quick: 8, 16 and 32 substeps, full: 4 to 64);
* ``--full`` adds ``extremes`` (settings at their extremes: each holds or fails with a clear
  error inside a time limit, :mod:`benchmarks.extremes`), ``grazing`` (gradients across a grazing contact, plot), ``implicit``
  (implicit-integrator accuracy), ``rollout`` (time and memory of long rollouts) and ``inverse``
  (the inverse scenes over seeds, against CMA-ES and Newton).

Exit code 0 when every section ran; 1 when one failed (the others still run; the failure is
printed and listed at the end).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import time
import traceback

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from benchmarks import report  # noqa: E402

QUICK = ("roots", "ccd", "sim", "gradients", "trade", "physics", "convergence")
FULL = QUICK + ("extremes", "grazing", "implicit", "rollout", "inverse")


class _Tee(io.TextIOBase):
    """Writes to the terminal and keeps a copy (for the benchmarks that only print)."""

    def __init__(self, stream) -> None:
        self.stream, self.parts = stream, []

    def write(self, text: str) -> int:
        self.stream.write(text)
        self.parts.append(text)
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def _printed(name: str, title: str, out: str, run) -> None:
    """Runs ``run()`` (a benchmark that prints its tables) and writes what it printed to
    ``<out>.md`` as a preformatted block."""
    tee = _Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        run()
    report.write(out, title, ["```", "".join(tee.parts).rstrip(), "```"], echo=False)


def section(name: str, full: bool, out_dir: str) -> None:
    out = os.path.join(out_dir, name)
    if name == "roots":
        from benchmarks import roots

        roots.main(([] if full else ["--quick"]) + ["--out", out])
    elif name == "ccd":
        from benchmarks import ccd

        ccd.main(([] if full else ["--quick"]) + ["--out", out])
    elif name == "sim":
        from benchmarks import sim as sim_bench

        argv = [] if full else ["--dims", "16", "32", "--frames", "4", "--repeats", "1", "--scene-steps", "60",
                                "--sizes", "16", "32", "64", "--size-steps", "10", "--newton-sizes"]
        _printed(name, "Simulation speed", out, lambda: sim_bench.main(argv))
    elif name == "gradients":
        from benchmarks import gradients

        gradients.main((["--full"] if full else []) + ["--out", out])
    elif name == "trade":
        from benchmarks import trade

        trade.main((["--full"] if full else []) + ["--out", out])
    elif name == "physics":
        from benchmarks import physics

        physics.main(([] if full else ["--quick"]) + ["--out-dir", out_dir])
    elif name == "convergence":
        from benchmarks import convergence

        convergence.main(([] if full else ["--quick"]) + ["--out", out])
    elif name == "extremes":
        from benchmarks import extremes

        extremes.main(["--out", out])
    elif name == "grazing":
        from benchmarks import grazing

        grazing.main(["--out", out + ".png"])
    elif name == "implicit":
        from benchmarks import implicit_accuracy

        implicit_accuracy.main(["--out", os.path.join(out_dir, "implicit_accuracy")])
    elif name == "rollout":
        from benchmarks import rollout

        _printed(name, "Rollout cost: time and memory", out, lambda: rollout.main([]))
    elif name == "inverse":
        from benchmarks import inverse

        inverse.main(["--seeds", "10", "--out", os.path.join(out_dir, "inverse_tunnel")])
    else:  # pragma: no cover - argparse restricts the names
        raise ValueError(name)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true",
                        help="every benchmark at its full size (hours); default: the quick set (minutes)")
    parser.add_argument("--only", default=None,
                        help=f"comma-separated sections (from {', '.join(FULL)}); default: all of the chosen set")
    parser.add_argument("--out-dir", default=report.RESULTS, help="folder of the tables and plots (default %(default)s)")
    args = parser.parse_args(argv)
    names = list(FULL if args.full else QUICK)
    if args.only is not None:
        names = [s.strip() for s in args.only.split(",") if s.strip()]
        bad = [s for s in names if s not in FULL]
        if bad or not names:
            parser.error(f"--only: unknown section(s) {bad}; choose from {', '.join(FULL)}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(args.out_dir)) or "."):
        parser.error(f"--out-dir: the parent of {args.out_dir!r} does not exist")
    os.makedirs(args.out_dir, exist_ok=True)

    import warp as wp

    wp.config.quiet = True
    print(f"Machine: {report.machine()}", flush=True)
    failed, times = [], {}
    for name in names:
        print(f"\n===== {name} =====", flush=True)
        t0 = time.perf_counter()
        try:
            section(name, args.full, args.out_dir)
        except (Exception, SystemExit) as exc:  # one broken section must not hide the others
            if isinstance(exc, SystemExit) and exc.code in (0, None):
                pass
            else:
                traceback.print_exc()
                failed.append(name)
        times[name] = time.perf_counter() - t0
    print("\n===== done =====")
    for name in names:
        state = "FAILED" if name in failed else "ok"
        print(f"{name:10s} {state:6s} {times[name]:8.1f} s")
    print(f"tables and plots in {args.out_dir}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
