"""The paper's quadratic example (Table ``exp4``, Figures ``example-18``/``example-20``) with the
root derivatives on offer: iterations to the target for each optimiser, rate and derivative.

    python benchmarks/orthogonal_clamp.py [--iters 3000] [--out benchmarks/results/orthogonal_clamp]

``t^2 + b t + c`` from ``(b, c) = (-3, 9/4 - 1e-12)`` (roots 1.5 +- 1e-6, a near double root),
loss ``0.5 |t+ - 1/2|^2`` on the larger root. Derivatives: the plain implicit one (``M = 1e300``),
the mollified one (robust division bounded by ``M``) and eq. ``orthogonal_clamping_real_side``
(only the part along ``dc~/dp`` clamped to ``M``). Success: ``|t+ - 1/2| < 1e-6`` by the quadratic
formula on the iterate (not the solver). Writes ``<out>.md`` and ``<out>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import numpy as np  # noqa: E402

START = (-3.0, 9.0 / 4.0 - 1e-12)
TARGET = 0.5
CONFIGS = [("plain implicit", "mollified", 1e300), ("mollified", "mollified", 1.0), ("mollified", "mollified", 10.0),
           ("orthogonal", "orthogonal", 1.0), ("orthogonal", "orthogonal", 10.0)]


def run(optimiser: str, rate: float, derivative: str, bound: float, iters: int):
    """Iterations to the target (None if not reached) and the final |t+ - 1/2| (nan: complex)."""
    import torch

    from collision.roots import quadratic_roots

    x = torch.tensor(START, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([x], lr=rate) if optimiser == "SGD" else torch.optim.Adam([x], lr=rate)
    target = torch.tensor([TARGET, 0.0], dtype=torch.float64)
    error = float("nan")
    for it in range(iters + 1):
        b, c = x.detach().numpy()
        disc = b * b / 4.0 - c
        error = abs(-b / 2.0 + np.sqrt(disc) - TARGET) if disc >= 0.0 else float("nan")
        if error < 1e-6:
            return it, error
        if it == iters:
            break
        opt.zero_grad()
        roots = quadratic_roots(torch.cat([torch.ones(1, dtype=torch.float64), x]), max_derivative=bound,
                                derivative=derivative)
        (0.5 * ((roots[1] - target) ** 2).sum()).backward()
        opt.step()
    return None, error


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=3000, help="iterations per run (default %(default)s)")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "orthogonal_clamp"))
    args = parser.parse_args(argv)
    if args.iters < 1:
        parser.error("--iters must be >= 1")
    rows = []
    lines = [f"# The paper's quadratic example: iterations to |t+ - 1/2| < 1e-6 (of {args.iters})", "",
             "| optimiser | rate | derivative | M | iterations | final error |", "|---|---|---|---|---|---|"]
    for optimiser in ("SGD", "Adam"):
        for rate in (0.01, 0.1):
            for name, derivative, bound in CONFIGS:
                it, error = run(optimiser, rate, derivative, bound, args.iters)
                rows.append({"optimiser": optimiser, "rate": rate, "derivative": name, "M": bound,
                             "iterations": it, "final_error": None if not np.isfinite(error) else error})
                m = "-" if bound >= 1e300 else f"{bound:g}"
                err = "complex" if not np.isfinite(error) else f"{error:.1e}"
                lines.append(f"| {optimiser} | {rate} | {name} | {m} | {'-' if it is None else it} | {err} |")
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out + ".md", "w") as f:
        f.write(text)
    with open(args.out + ".json", "w") as f:
        json.dump({"start": START, "target": TARGET, "iters": args.iters, "runs": rows}, f, indent=1)


if __name__ == "__main__":
    main()
