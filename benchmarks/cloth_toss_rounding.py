"""How much of a ``cloth_toss`` optimisation is rounding: the proposed method from seed 0's start
and from copies of it whose linear velocity is scaled by ``1 + k * 1e-12``.

The cloth's many contacts amplify rounding, as in a contact-rich forward run, so from a few
rollouts on the optimisation paths of such copies part. This measures where: the loss of every
rollout per start, and whether and when each start reaches the 90 % cut
(:data:`scenes.cloth_toss.TARGET_CUT`). Writes ``benchmarks/results/cloth_toss_rounding.md`` and
``.json``.

Usage::

    python benchmarks/cloth_toss_rounding.py [--starts 4] [--iters 10]
"""

from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from benchmarks.report import RESULTS, write  # noqa: E402

PERTURBATION = 1e-12
"""Relative change of the start's linear velocity per copy (copy k: ``1 + k * PERTURBATION``)."""


def run(starts: int, iters: int, callback=None) -> list[dict]:
    """The proposed method's losses from ``starts`` copies of seed 0's start (``iters`` optimiser
    steps each)."""
    from scenes import cloth_toss

    rows = []
    for k in range(starts):
        problem = cloth_toss.build(0)
        problem.u0[:3] = problem.u0[:3] * (1.0 + k * PERTURBATION)
        result = cloth_toss.optimise(problem, iters, "proposed")
        at = result["iterations_to_target"]  # the rollout's index, from 0
        rows.append({"copy": k, "scale": 1.0 + k * PERTURBATION, "losses": list(result["history"]["loss"]),
                     "reached": result["reached_target"], "rollouts_to_cut": None if at is None else at + 1})
        if callback is not None:
            callback(k)
    return rows


def agreeing_rollouts(rows: list[dict], digits: int = 3) -> int:
    """How many first rollouts give every copy the same loss to ``digits`` significant digits."""
    count = 0
    for losses in zip(*(r["losses"] for r in rows)):
        if len({f"{loss:.{digits - 1}e}" for loss in losses}) > 1:
            break
        count += 1
    return count


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--starts", type=int, default=4, help="copies of the start (default %(default)s)")
    parser.add_argument("--iters", type=int, default=10, help="optimiser steps per copy (default %(default)s)")
    parser.add_argument("--out", default=os.path.join(RESULTS, "cloth_toss_rounding"), help="output prefix")
    args = parser.parse_args(argv)
    from tqdm import tqdm

    with tqdm(total=args.starts, desc="cloth_toss copies", file=sys.stderr, disable=None) as bar:
        rows = run(args.starts, args.iters, callback=lambda _k: bar.update(1))
    agree = agreeing_rollouts(rows)
    reached = sum(r["reached"] for r in rows)
    lines = [f"Seed 0's start and copies of it with the linear velocity scaled by 1 + k * {PERTURBATION:g}; "
             f"the proposed method (Adam, mollified), {args.iters} optimiser steps ({args.iters + 1} rollouts) "
             "each. Loss: the drape loss [m^2].", "",
             f"All copies agree to 3 significant digits over the first **{agree}** rollouts; "
             f"**{reached} / {len(rows)}** reach the 90 % cut.", "",
             "| copy | scale - 1 | reached the cut | rollouts to the cut | losses per rollout |", "|---|---|---|---|---|"]
    for r in rows:
        losses = ", ".join(f"{loss:.3g}" for loss in r["losses"])
        lines.append(f"| {r['copy']} | {r['copy'] * PERTURBATION:.0e} | {'yes' if r['reached'] else 'no'} | "
                     f"{r['rollouts_to_cut'] if r['rollouts_to_cut'] is not None else '-'} | {losses} |")
    write(args.out, "cloth_toss: the optimisation under rounding-level changes of the start", lines,
          {"perturbation": PERTURBATION, "iters": args.iters, "agreeing_rollouts": agree, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
