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
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch is imported lazily (fast CLI usage errors and --list)
    import torch

# Scene attributes read by the CLI, shared by the paper scenes (float64 only; --iters, not --steps):
from scenes.paper_common import PRECISIONS as PRECISIONS, SUPPORTS_STEPS as SUPPORTS_STEPS
from scenes.paper_common import (
    DEFAULT_LR,
    DEFAULT_MAX_DERIVATIVE,
    T_MAX,
    AdamRun,
    ProposedRecord,
    RobustRoots,
    Start,
    add_scene_arguments,
    root_loss,
    roots_as_complex,
    run_scene,
    run_starts,
    start,
)

NAME = "paper_quadratic"
DESCRIPTION = "Paper quadratic examples (tables bad_a/bad_ab/bad_abc, Figure example-3): Adam on [a,b,c], proposed vs autograd baseline"
DEFAULT_ITERS = 4000
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


class ProposedLoss(RobustRoots):
    """Eq. ``lossagainwitht`` on slot ``t+`` of the robust solver, mollified backward.

    Args:
        max_derivative: ``M`` of the robust division.
        t_max: Root clamp.
    """

    def __init__(self, max_derivative: float = DEFAULT_MAX_DERIVATIVE, t_max: float = T_MAX) -> None:
        from collision.roots import quadratic_roots  # imported lazily: starts Warp

        super().__init__(quadratic_roots, max_derivative, t_max)

    def __call__(self, p: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, np.ndarray]]:
        """Loss ``(B,)`` and extras ``roots`` (complex ``(B, 2)``, slots ``(t-, t+)``)."""
        roots = self.solve(p)  # (B, 2, 2)
        loss = root_loss(roots[:, T_PLUS, 0], roots[:, T_PLUS, 1])
        return loss, {"roots": roots_as_complex(roots)}


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
    t_max: float = T_MAX,
) -> AdamRun:
    """Adam with the proposed method on all ``starts`` (used by the scene and the table tests).

    Arguments as :func:`scenes.paper_common.run_starts`, plus ``max_derivative`` (``M``) and
    ``t_max`` (the root clamp: escaping roots sit at ``+-t_max``; the paper's 1e150).

    Returns:
        History; ``extras["roots"]`` is complex ``(iters+1, B, 2)``.
    """
    return run_starts(starts, ProposedLoss(max_derivative, t_max), iters, lr, progress)


def run_baseline(
    starts: tuple[Start, ...] = STARTS, iters: int = DEFAULT_ITERS, lr: float = DEFAULT_LR, progress=None
) -> AdamRun:
    """Adam with the autograd-through-the-formula baseline on all ``starts``.

    Arguments as :func:`scenes.paper_common.run_starts`.

    Returns:
        History; ``extras["t_plus"]`` is real ``(iters+1, B)``.
    """
    return run_starts(starts, BaselineLoss(), iters, lr, progress, ignore_fp_errors=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Scene options (``--iters``, ``--lr``, ``--max-derivative``, ``--t-max``)."""
    add_scene_arguments(parser, DEFAULT_ITERS)


def proposed_record(run: AdamRun, row: int) -> ProposedRecord:
    """Logged roots (both slots) and the summary's ``final_t_plus`` of one start's proposed run."""
    roots = run.extras["roots"][:, row, :]
    t_final = roots[-1, T_PLUS]
    return ProposedRecord(
        roots={slot: roots[:, j] for j, slot in enumerate(SLOTS)},
        summary={"final_t_plus": [t_final.real, t_final.imag]},
    )


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene, logs it and returns the JSON summary (see :func:`scenes.paper_common.run_scene`)."""
    return run_scene(
        args, log, name=NAME, starts=STARTS, param_names=PARAM_NAMES,
        run_proposed=run_proposed, run_baseline=run_baseline,
        proposed_roots=SLOTS, proposed_record=proposed_record,
        baseline_root="t_plus", baseline_key="t_plus",
        baseline_description="torch autograd through the real quadratic formula (eq. quadform)",
    )
