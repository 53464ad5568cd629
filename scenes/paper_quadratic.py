"""Scene ``paper_quadratic``: the paper's quadratic optimisation examples, proposed vs baseline.

Reproduces the subsection "Examples" of "Proposed Approach for Quadratic Equations" (Johnson &
Fedkiw): Adam (lr 0.1) on the coefficients ``p = [a, b, c]`` of ``a t^2 + b t + c`` minimising
eq. ``lossagainwitht``, ``L = 1/2 (Re t+ - 1/2)^2 + 1/2 (Im t+)^2``, on the ``t+`` branch
(``t+ = (-b + sqrt(b^2 - 4ac)) / 2a``), with the robust root solver and the mollified implicit
derivative (``M = 1000``, ``t_max = 1e150``) of :func:`collision.roots.quadratic_roots`.

Branch: the slot ``t+`` is used throughout, no tracking. The paper (subsection "Branch
Selection" of the quadratic proposed approach) shows the roles of ``t+-`` need not change when
``a`` changes sign, and its tables ``bad_a``/``bad_ab``/``bad_abc`` are all on slot ``t+``.

Baseline (side by side, same Adam settings): plain torch autograd through the real,
de-rationalised quadratic formula of eq. ``quadform``
(``t+ = (-b + sqrt(b^2-4ac)) / 2a`` if ``b <= 0``, else ``2c / (-b - sqrt(b^2-4ac))``), evaluated
with Python branching per start, exactly as a scalar implementation would. It has no complex roots
(``sqrt`` of a negative discriminant is NaN) and no mollification (``a = 0`` divides by zero); a
non-finite loss is recorded as "not converged", never raised.

Starts:

* ``[0, -5.1, 5]``, ``[0, 0, 5]``, ``[0, 0, 0]``: tables ``bad_a``, ``bad_ab``, ``bad_abc``
  (Figure ``example-22-clamping-robust-all``);
* ``[1, -5.1, 5]`` with ``a = 1`` held fixed: the Figure ``example-3`` start. The text states it
  (after eq. ``lossagain``): "In Figure example-3, the initial guess is modified to
  ``(b^0, c^0) = (-5.1, 5)``" in the hat variables ``b^ = b``, ``c^ = ac`` with ``a = 1``; the
  proposed-approach repeat (Figure ``example-22-clamping-normal-final``) holds ``a = 1`` fixed;
* ``[1, -5.1, 5]`` with all three free: Figure ``example-22-clamping-normal`` (same start, ``M = 1000``).

Convergence: ``iters_to_converge`` is the first iterate with ``L < 1e-10``. Adam (lr 0.1) can
leave a converged minimum later: with vanishing gradients its second-moment estimate decays, the
effective step ``lr / sqrt(v)`` outgrows the stability limit of the minimum and the iterate
oscillates out; e.g. ``[0, 0, 5]`` reaches ``L ~ 1e-32`` and ~2000 iterations later climbs back
to ~1e-4. ``final_loss`` reports where the run ended.

Entities (``rr.Scalars`` on timelines ``iteration`` and ``frame``, one row per iterate
``0..iters``): ``/paper_quadratic/<start>/<method>/params/{a,b,c}``,
``.../roots/{t_minus,t_plus}/{re,im}`` (baseline: ``t_plus`` only) and ``.../loss``, with
``<method>`` in ``proposed``, ``baseline``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch is imported lazily (fast CLI usage errors and --list)
    import torch

from scenes.paper_common import (
    CONVERGENCE_TOL,
    DEFAULT_LR,
    DEFAULT_MAX_DERIVATIVE,
    T_MAX,
    TARGET,
    AdamRun,
    Start,
    convergence_summary,
    log_method,
    root_loss,
    run_adam,
    solve_finite_rows,
    start,
    views_for_start,
)

NAME = "paper_quadratic"
DESCRIPTION = "Paper quadratic examples (tables bad_a/bad_ab/bad_abc, Figure example-3): Adam on [a,b,c], proposed vs autograd baseline"
DEFAULT_ITERS = 4000
PRECISIONS = ("float64",)
"""The paper's examples (t_max = 1e150, gradients up to 1e153) need float64."""
SUPPORTS_STEPS = False
"""An optimisation scene: ``--iters``, not ``--steps``."""
PARAM_NAMES = ("a", "b", "c")
SLOTS = ("t_minus", "t_plus")
T_PLUS = 1
"""Index of slot ``t+`` in the solver output ``(t-, t+)``."""

STARTS: tuple[Start, ...] = (
    start([0.0, -5.1, 5.0], "abc", note="table bad_a"),
    start([0.0, 0.0, 5.0], "abc", note="table bad_ab"),
    start([0.0, 0.0, 0.0], "abc", note="table bad_abc"),
    start([1.0, -5.1, 5.0], "abc", fixed="a", note="Figure example-3 start, a = 1 held fixed"),
    start([1.0, -5.1, 5.0], "abc", note="Figure example-3 start, a free (Figure example-22-clamping-normal)"),
)


class ProposedLoss:
    """Eq. ``lossagainwitht`` on slot ``t+`` of the robust solver, mollified backward.

    Args:
        max_derivative: ``M`` of the robust division.
        t_max: Root clamp.
    """

    def __init__(self, max_derivative: float = DEFAULT_MAX_DERIVATIVE, t_max: float = T_MAX) -> None:
        from collision.roots import quadratic_roots  # imported lazily: starts Warp

        self._roots = quadratic_roots
        self.max_derivative = float(max_derivative)
        self.t_max = float(t_max)

    def __call__(self, p: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, np.ndarray]]:
        """Loss ``(B,)`` and extras ``roots`` (complex ``(B, 2)``, slots ``(t-, t+)``)."""
        roots = solve_finite_rows(self._roots, p, t_max=self.t_max, max_derivative=self.max_derivative)  # (B, 2, 2)
        loss = root_loss(roots[:, T_PLUS, 0], roots[:, T_PLUS, 1])
        r = roots.detach().numpy()
        return loss, {"roots": r[..., 0] + 1j * r[..., 1]}


def quadform_t_plus(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``t+`` by the real de-rationalised quadratic formula (eq. ``quadform``), plain autograd.

    Args:
        a: Scalar tensor.
        b: Scalar tensor.
        c: Scalar tensor.

    Returns:
        ``t+`` (NaN for a negative discriminant, inf/NaN for ``a = 0`` where the formula divides
        by zero): the baseline deliberately has no safeguards.
    """
    import torch

    sq = torch.sqrt(b * b - 4.0 * a * c)
    if bool(b <= 0):
        return (-b + sq) / (2.0 * a)
    return 2.0 * c / (-b - sq)


class BaselineLoss:
    """Baseline: eq. ``lossagainwitht`` (real part only) on :func:`quadform_t_plus`."""

    def __call__(self, p: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, np.ndarray]]:
        """Loss ``(B,)`` and extras ``t_plus`` (real ``(B,)``, NaN/inf allowed)."""
        import torch

        t = torch.stack([quadform_t_plus(row[0], row[1], row[2]) for row in p])
        loss = root_loss(t)
        return loss, {"t_plus": t.detach().numpy()}


def run_proposed(
    starts: tuple[Start, ...] = STARTS,
    iters: int = DEFAULT_ITERS,
    lr: float = DEFAULT_LR,
    max_derivative: float = DEFAULT_MAX_DERIVATIVE,
    progress=None,
) -> AdamRun:
    """Adam with the proposed method on all ``starts`` (used by the scene and the table tests).

    Args:
        starts: Starting points.
        iters: Adam steps.
        lr: Learning rate.
        max_derivative: ``M``.
        progress: Optional per-iterate callback.

    Returns:
        History; ``extras["roots"]`` is complex ``(iters+1, B, 2)``.
    """
    return run_adam(
        [s.p0 for s in starts],
        ProposedLoss(max_derivative),
        iters,
        lr=lr,
        trainable=[s.trainable for s in starts],
        progress=progress,
    )


def run_baseline(
    starts: tuple[Start, ...] = STARTS, iters: int = DEFAULT_ITERS, lr: float = DEFAULT_LR, progress=None
) -> AdamRun:
    """Adam with the autograd-through-the-formula baseline on all ``starts``.

    Args:
        starts: Starting points.
        iters: Adam steps.
        lr: Learning rate.
        progress: Optional per-iterate callback.

    Returns:
        History; ``extras["t_plus"]`` is real ``(iters+1, B)``.
    """
    with np.errstate(all="ignore"):
        return run_adam(
            [s.p0 for s in starts],
            BaselineLoss(),
            iters,
            lr=lr,
            trainable=[s.trainable for s in starts],
            progress=progress,
        )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Scene options (``--iters``, ``--lr``, ``--max-derivative``)."""
    from scenes.registry import add_optimisation_arguments

    add_optimisation_arguments(parser, default_iters=DEFAULT_ITERS, default_lr=DEFAULT_LR,
                               default_max_derivative=DEFAULT_MAX_DERIVATIVE)


def _real_root(values: np.ndarray) -> np.ndarray:
    """Baseline roots as complex: imaginary part 0 where finite (the formula is real), else NaN."""
    v = np.asarray(values, dtype=np.float64)
    return v + 1j * np.where(np.isfinite(v), 0.0, np.nan)


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene, logs it and returns the JSON summary.

    Args:
        args: Parsed CLI arguments (``iters``, ``lr``, ``max_derivative``, ``seed``).
        log: An open :class:`sim.logging.RerunLogger`.

    Returns:
        Summary: per start, ``proposed`` and ``baseline`` convergence figures.
    """
    import torch
    from tqdm import tqdm

    from sim.logging import time_series_blueprint

    torch.manual_seed(args.seed)  # nothing is random; kept for the CLI contract
    root = f"/{NAME}"
    log.send_blueprint(
        time_series_blueprint(
            {s.name: views_for_start(root, s.name, {"proposed": SLOTS, "baseline": ("t_plus",)})
             for s in STARTS}
        )
    )
    with tqdm(total=2 * (args.iters + 1), desc=NAME, unit="it", file=sys.stderr,
              disable=None, leave=False) as bar:
        tick = lambda _k: bar.update(1)  # noqa: E731
        prop = run_proposed(STARTS, args.iters, args.lr, args.max_derivative, progress=tick)
        base = run_baseline(STARTS, args.iters, args.lr, progress=tick)

    starts_summary: dict[str, Any] = {}
    for i, s in enumerate(STARTS):
        prefix = f"{root}/{s.name}"
        roots = prop.extras["roots"][:, i, :]
        log_method(log, f"{prefix}/proposed", prop, i, PARAM_NAMES,
                   {slot: roots[:, j] for j, slot in enumerate(SLOTS)})
        log_method(log, f"{prefix}/baseline", base, i, PARAM_NAMES,
                   {"t_plus": _real_root(base.extras["t_plus"][:, i])})
        t_final = roots[-1, T_PLUS]
        starts_summary[s.name] = {
            "p0": list(s.p0),
            "fixed": [n for n, t in zip(PARAM_NAMES, s.trainable) if not t],
            "note": s.note,
            "proposed": {**convergence_summary(prop.loss[:, i]),
                         "final_params": prop.params[-1, i].tolist(),
                         "final_t_plus": [t_final.real, t_final.imag]},
            "baseline": {**convergence_summary(base.loss[:, i]),
                         "final_params": base.params[-1, i].tolist()},
        }
    return {
        "scene": NAME,
        "iters": args.iters,
        "lr": args.lr,
        "max_derivative": args.max_derivative,
        "t_max": T_MAX,
        "target": TARGET,
        "tol": CONVERGENCE_TOL,
        "seed": args.seed,
        "baseline": "torch autograd through the real quadratic formula (eq. quadform)",
        "proposed_converged": sum(v["proposed"]["converged"] for v in starts_summary.values()),
        "baseline_converged": sum(v["baseline"]["converged"] for v in starts_summary.values()),
        "final_loss": float(np.max(prop.loss[-1])),
        "starts": starts_summary,
    }
