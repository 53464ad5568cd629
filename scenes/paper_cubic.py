"""Scene ``paper_cubic``: the paper's cubic optimisation examples, proposed vs baseline.

Reproduces the subsection "Examples" of "Proposed Approach for the Cubic Equation" (Johnson &
Fedkiw): Adam (lr 0.1) on ``p = [q, a, b, c]`` of ``q t^3 + a t^2 + b t + c`` minimising eq.
``lossagainwitht``, ``L = 1/2 (Re t - 1/2)^2 + 1/2 (Im t)^2``, starting on the ``t+`` branch,
with the robust solver and the mollified implicit derivative (``M = 1000``, ``t_max = 1e150``) of
:func:`collision.roots.cubic_roots`.

Branch tracking (documented choice). The paper starts on ``t+`` and then switches slots "in order
to ensure that we are always using the same root": when a root near +-inf changes sign (``q``
crosses 0, ``tM`` and ``t+-`` swap roles), when the reduced ``c^`` changes sign while the single
real root is used (it moves between ``t+`` and ``t-``), and when the tracked root merges or
unmerges, mapping "the larger/smaller real root to the complex root with positive/negative
imaginary part". We implement this with :class:`RootTracker`, applied after every Adam step:

1. by default keep the slot whose new root is nearest the previously tracked root in the
   *chordal metric of the Riemann sphere*, ``d(z, w) = |z - w| / (sqrt(1+|z|^2) sqrt(1+|w|^2))``.
   Unlike ``|z - w|`` it treats ``+t_max`` and ``-t_max`` as neighbours (both are near the point
   at infinity), so a root escaping through infinity and returning with the other sign stays
   tracked; ordinary moves and the ``t+``/``t-`` relabelling of a single real root are followed
   because the root itself barely moves;
2. merge (the tracked root was real and the nearest new root is complex): take the member of the
   new pair with ``Im > 0`` if the tracked root was the larger of the two merging real roots (its
   partner = the other previously real root nearest to it), ``Im < 0`` if it was the smaller;
3. unmerge (tracked root complex, nearest new root real): of the two new real roots nearest the
   old pair, take the larger if the tracked root had ``Im > 0``, else the smaller.

Ties keep the current slot. The loss and its gradient are invariant under conjugation, so rules 2-3
only fix the labelling; rule 1 decides which root is optimised.

Against the paper's narrative (``tests/test_paper_tables.py`` checks the first): for
``[0, -1, 0, 1]`` the tracked ``t+`` merges with ``tM`` at iteration 3, the single real root is
``t+`` exactly in iterations 26-31 without disturbing the tracked complex root, and the tracked
root is ``t+`` (real again) at iteration 41, all as the text states. For ``[0, 0, 7.1, 6]`` the
text has ``t+`` "immediately merge with ``tM``" and unmerge at iteration 87; here the two roots
at ``-t_max`` come back from infinity as a complex pair while the bounded real root moves
continuously (``-0.845 -> -0.803``), so rule 1 keeps tracking that real root (it moves from
slot ``t+`` to ``t-`` as ``c^`` changes sign) and it converges without ever being complex.

Baseline (same Adam settings): plain torch autograd through ``NEWTON_ITERATIONS`` real Newton
iterations ``t <- t - f(t)/f'(t)`` from the fixed start ``t0 = NEWTON_START`` (right of every
bounded root of the examples, so for ``q > 0`` Newton heads for the largest real root, the paper's
``t+``). No complex roots, no safeguards, no mollification: ``f' = 0`` gives inf/NaN, which is
recorded as "not converged", never raised.

Starts (the paper's subsection "Examples" of the cubic proposed approach): ``[1, 0, -7.1, 6]``
(``q, a`` free: Figure ``cubic-example-2-clamping-normal-1000``; also with ``q = 1, a = 0`` held
fixed: Figure ``cubic-example-1-clamping-normal-1000``), ``[1, 0, 0, 0]`` (triple root),
``[0, 1, 0, -1]``, ``[0, -1, 0, 1]``, ``[0, 0, 7.1, 6]``, ``[0, 0, -7.1, 6]``, ``[0, 0, 0, 6]``,
``[0, 0, 0, -6]``, ``[0, 0, 0, 0]``.

Entities (``rr.Scalars`` on timelines ``iteration`` and ``frame``):
``/paper_cubic/<start>/<method>/params/{q,a,b,c}``,
``.../roots/{t_minus,t_mid,t_plus}/{re,im}`` (proposed; the solver's slots),
``.../roots/tracked/{re,im}`` (both methods: the root in the loss), ``.../tracked_slot``
(proposed: 0, 1, 2 = ``t-, tM, t+``) and ``.../loss``.
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

NAME = "paper_cubic"
DESCRIPTION = "Paper cubic examples (degenerate starts q=0, a=0, ...): Adam on [q,a,b,c] with branch tracking, proposed vs Newton-autograd baseline"
DEFAULT_ITERS = 3000
PARAM_NAMES = ("q", "a", "b", "c")
SLOTS = ("t_minus", "t_mid", "t_plus")
T_PLUS = 2
"""Index of slot ``t+`` in the solver output ``(t-, tM, t+)``; every example starts there."""
NEWTON_ITERATIONS = 40
"""Baseline Newton iterations: from ``t0 = 10`` the bounded examples reach full precision in < 30."""
NEWTON_START = 10.0
"""Baseline Newton start ``t0`` (fixed, not differentiated)."""

STARTS: tuple[Start, ...] = (
    start([1.0, 0.0, -7.1, 6.0], "qabc", note="Figure cubic-example-2-clamping-normal-1000 (q, a free)"),
    start([1.0, 0.0, -7.1, 6.0], "qabc", fixed="qa",
          note="Figure cubic-example-1-clamping-normal-1000 (q = 1, a = 0 held fixed)"),
    start([1.0, 0.0, 0.0, 0.0], "qabc", note="triple root (tables triple_root)"),
    start([0.0, 1.0, 0.0, -1.0], "qabc", note="q = 0, t^2 - 1 (tables bad_q)"),
    start([0.0, -1.0, 0.0, 1.0], "qabc", note="q = 0, -t^2 + 1 (tables bad_q_again)"),
    start([0.0, 0.0, 7.1, 6.0], "qabc", note="q = a = 0, 7.1 t + 6 (tables bad_qa_again)"),
    start([0.0, 0.0, -7.1, 6.0], "qabc", note="q = a = 0, -7.1 t + 6 (tables bad_qa)"),
    start([0.0, 0.0, 0.0, 6.0], "qabc", note="q = a = b = 0, c = 6 (tables bad_qab)"),
    start([0.0, 0.0, 0.0, -6.0], "qabc", note="q = a = b = 0, c = -6 (tables bad_qab_again)"),
    start([0.0, 0.0, 0.0, 0.0], "qabc", note="all zero (tables bad_qabc)"),
)


def chordal_distance(z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Chordal distance on the Riemann sphere (up to the usual factor 2), overflow-free.

    Args:
        z: Complex array.
        w: Complex array (broadcast against ``z``).

    Returns:
        ``|z - w| / (sqrt(1+|z|^2) sqrt(1+|w|^2))``; ``+-1e150`` are ~1e-150 apart.
    """
    return np.abs(z - w) / (np.hypot(1.0, np.abs(z)) * np.hypot(1.0, np.abs(w)))


class RootTracker:
    """Chooses, after each step, the slot holding "the same root" (see the module docstring).

    Args:
        batch: Number of problems.
        initial_slot: Slot used at iterate 0 (the paper: ``t+``).
    """

    def __init__(self, batch: int, initial_slot: int = T_PLUS) -> None:
        self.slot = np.full(batch, initial_slot, dtype=np.int64)
        self.prev: np.ndarray | None = None

    def update(self, roots: np.ndarray) -> np.ndarray:
        """Updates and returns the tracked slot per problem.

        Args:
            roots: Complex ``(B, 3)`` roots of the new iterate, slots ``(t-, tM, t+)``.

        Returns:
            ``(B,)`` slot indices.
        """
        if self.prev is not None:
            for i in range(roots.shape[0]):
                self.slot[i] = self._choose(self.prev[i], int(self.slot[i]), roots[i])
        self.prev = roots.copy()
        return self.slot.copy()

    @staticmethod
    def _choose(prev: np.ndarray, slot: int, new: np.ndarray) -> int:
        old = prev[slot]
        d = chordal_distance(new, old)
        best = int(np.argmin(d))
        if d[slot] <= d[best]:
            best = slot  # ties keep the current slot
        old_real = old.imag == 0.0
        new_real = new.imag == 0.0
        if old_real and not new_real[best]:
            # Merge: the larger of the two merging real roots -> Im > 0, the smaller -> Im < 0.
            others = [j for j in range(3) if j != slot and prev[j].imag == 0.0]
            larger = True
            if others:
                partner = min(others, key=lambda j: abs(prev[j].real - old.real))
                larger = old.real >= prev[partner].real
            pair = [j for j in range(3) if not new_real[j]]
            want = [j for j in pair if (new[j].imag > 0) == larger]
            return want[0] if want else best
        if not old_real and new_real[best]:
            # Unmerge: Im > 0 -> the larger of the two new real roots nearest the old pair.
            reals = sorted((j for j in range(3) if new_real[j]), key=lambda j: d[j])[:2]
            if len(reals) == 2:
                lo, hi = sorted(reals, key=lambda j: new[j].real)
                return hi if old.imag > 0 else lo
        return best


class ProposedLoss(RobustRoots):
    """Eq. ``lossagainwitht`` on the tracked root of the robust solver, mollified backward.

    Args:
        batch: Number of problems.
        max_derivative: ``M`` of the robust division.
        t_max: Root clamp.
    """

    def __init__(self, batch: int, max_derivative: float = DEFAULT_MAX_DERIVATIVE, t_max: float = T_MAX) -> None:
        from collision.roots import cubic_roots  # imported lazily: starts Warp

        super().__init__(cubic_roots, max_derivative, t_max)
        self.tracker = RootTracker(batch)

    def __call__(self, p: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, np.ndarray]]:
        """Loss ``(B,)``; extras ``roots`` (complex ``(B, 3)``) and ``slot`` (``(B,)``)."""
        import torch

        roots = self.solve(p)  # (B, 3, 2)
        rc = roots_as_complex(roots)
        slot = self.tracker.update(rc)
        tracked = roots[torch.arange(p.shape[0]), torch.from_numpy(slot)]  # (B, 2)
        loss = root_loss(tracked[:, 0], tracked[:, 1])
        return loss, {"roots": rc, "slot": slot}


def newton_root(p: torch.Tensor, iterations: int = NEWTON_ITERATIONS, t0: float = NEWTON_START) -> torch.Tensor:
    """Baseline root: ``iterations`` plain real Newton steps from ``t0``, differentiable by autograd.

    Args:
        p: ``(B, 4)`` coefficients ``[q, a, b, c]``.
        iterations: Number of Newton steps.
        t0: Fixed start.

    Returns:
        ``(B,)`` last iterate (inf/NaN where ``f'`` vanished: no safeguards by design).
    """
    import torch

    q, a, b, c = p.unbind(-1)
    q3, a2 = 3.0 * q, 2.0 * a
    t = torch.full_like(q, t0)
    for _ in range(iterations):
        # Horner with fused multiply-adds (fewer autograd nodes, same arithmetic)
        f = torch.addcmul(c, torch.addcmul(b, torch.addcmul(a, q, t), t), t)  # q t^3 + a t^2 + b t + c
        df = torch.addcmul(b, torch.addcmul(a2, q3, t), t)  # 3 q t^2 + 2 a t + b
        t = t - f / df
    return t


class BaselineLoss:
    """Baseline: eq. ``lossagainwitht`` (real part only) on :func:`newton_root`."""

    def __call__(self, p: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, np.ndarray]]:
        """Loss ``(B,)``; extras ``t`` (real ``(B,)``)."""
        t = newton_root(p)
        return root_loss(t), {"t": t.detach().numpy()}


def run_proposed(
    starts: tuple[Start, ...] = STARTS,
    iters: int = DEFAULT_ITERS,
    lr: float = DEFAULT_LR,
    max_derivative: float = DEFAULT_MAX_DERIVATIVE,
    progress=None,
    t_max: float = T_MAX,
) -> AdamRun:
    """Adam with the proposed method and branch tracking on all ``starts``.

    Arguments as :func:`scenes.paper_common.run_starts`, plus ``max_derivative`` (``M``) and
    ``t_max`` (the root clamp: escaping roots sit at ``+-t_max``; the paper's 1e150).

    Returns:
        History; ``extras["roots"]`` complex ``(iters+1, B, 3)``, ``extras["slot"]`` ``(iters+1, B)``.
    """
    return run_starts(starts, ProposedLoss(len(starts), max_derivative, t_max), iters, lr, progress)


def run_baseline(
    starts: tuple[Start, ...] = STARTS, iters: int = DEFAULT_ITERS, lr: float = DEFAULT_LR, progress=None
) -> AdamRun:
    """Adam with the autograd-through-Newton baseline on all ``starts``.

    Arguments as :func:`scenes.paper_common.run_starts`.

    Returns:
        History; ``extras["t"]`` real ``(iters+1, B)``.
    """
    return run_starts(starts, BaselineLoss(), iters, lr, progress, ignore_fp_errors=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Scene options (``--iters``, ``--lr``, ``--max-derivative``, ``--t-max``)."""
    add_scene_arguments(parser, DEFAULT_ITERS)


def tracked_events(slots: np.ndarray, roots: np.ndarray) -> dict[str, list[int]]:
    """Iterates at which the tracked root changed slot or merged/unmerged (for the summary).

    Args:
        slots: ``(K+1,)`` tracked slot per iterate.
        roots: Complex ``(K+1, 3)`` roots per iterate.

    Returns:
        ``slot_changes``, ``became_complex`` and ``became_real``: iterate indices.
    """
    tracked = roots[np.arange(len(slots)), slots]
    is_real = tracked.imag == 0.0
    return {
        "slot_changes": (np.flatnonzero(np.diff(slots) != 0) + 1).tolist(),
        "became_complex": (np.flatnonzero(is_real[:-1] & ~is_real[1:]) + 1).tolist(),
        "became_real": (np.flatnonzero(~is_real[:-1] & is_real[1:]) + 1).tolist(),
    }


def proposed_record(run: AdamRun, row: int) -> ProposedRecord:
    """Logged roots (the solver's slots and the tracked root), the ``tracked_slot`` series and the
    summary's ``final_root``, ``final_slot`` and :func:`tracked_events` of one start's proposed run."""
    roots = run.extras["roots"][:, row, :]
    slots = run.extras["slot"][:, row]
    tracked = roots[np.arange(len(slots)), slots]
    return ProposedRecord(
        roots={**{slot: roots[:, j] for j, slot in enumerate(SLOTS)}, "tracked": tracked},
        series={"tracked_slot": slots},
        summary={"final_root": [tracked[-1].real, tracked[-1].imag],
                 "final_slot": SLOTS[int(slots[-1])],
                 **tracked_events(slots, roots)},
    )


def run(args: argparse.Namespace, log: Any) -> dict[str, Any]:
    """Runs the scene, logs it and returns the JSON summary (see :func:`scenes.paper_common.run_scene`)."""
    return run_scene(
        args, log, name=NAME, starts=STARTS, param_names=PARAM_NAMES,
        run_proposed=run_proposed, run_baseline=run_baseline,
        proposed_roots=SLOTS + ("tracked",), proposed_record=proposed_record,
        baseline_root="tracked", baseline_key="t",
        baseline_description=f"torch autograd through {NEWTON_ITERATIONS} real Newton iterations from t0={NEWTON_START:g}",
    )
