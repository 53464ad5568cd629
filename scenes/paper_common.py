"""Shared machinery of the paper example scenes (``paper_quadratic``, ``paper_cubic``).

The paper (Johnson & Fedkiw, subsections "Examples" of "Proposed Approach for Quadratic Equations"
and of "Proposed Approach for the Cubic Equation") minimises

    L(p) = 1/2 || t_root(p) - t_root,L ||^2 = 1/2 (Re t - 1/2)^2 + 1/2 (Im t)^2     (eq. lossagainwitht)

with Adam (lr 0.1 here, torch defaults otherwise) over the polynomial coefficients ``p``, starting
on the ``t+`` branch, with the robust solver and the mollified implicit derivative (``M = 1000``,
``t_max = 1e150``). Side by side we run the paper's *baseline*: plain torch autograd through a
real-valued formula or Newton iteration, no complex roots, no mollification.

This module holds the one Adam loop (:func:`run_adam`, batched over a scene's starts by
:func:`run_starts`), used by both scenes and by ``tests/test_paper_tables.py``, the loss, the
robust-solver call of the proposed losses (:class:`RobustRoots`), convergence bookkeeping, the
rerun logging of a run and the scene driver itself (:func:`run_scene`: progress bar, logging of
every start and the JSON summary). A scene module keeps only what is its own: its starts, its
proposed and baseline losses, its branch tracking and names.

All optimisation problems of one scene are batched in one ``(B, P)`` parameter tensor. Adam is
element-wise (its moments are per entry), so this is exactly equivalent to ``B`` independent
optimisers; rows never mix (every objective below is row-wise, a NaN in one row stays there).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from scenes import interrupts

if TYPE_CHECKING:  # torch is imported lazily so that the CLI's --list/--help/usage errors stay fast
    import torch

TARGET = 0.5
"""Target root ``t_root,L = 0.5 + 0i`` of eq. ``lossagainwitht`` (all the paper's examples)."""
CONVERGENCE_TOL = 1e-10
"""An optimisation has converged once its loss drops below this (the brief's criterion)."""
DEFAULT_LR = 0.1
"""Adam learning rate of the paper's tables (the first step moves every coefficient by 0.1)."""
DEFAULT_MAX_DERIVATIVE = 1000.0
"""``M`` of the robust division: the paper's value for the tables and the cubic examples."""
T_MAX = 1e150
"""Root clamp ``t_max`` (the paper's value)."""
T_MAX_RANGE = (1.0, 1e150)
"""``--t-max`` accepted: at least 1 (the target root 0.5 lies inside), at most the paper's 1e150
(the loss at an escaping root is ``(t_max - 0.5)^2 / 2`` and its gradient ``t_max M``: float64
overflows by 1.3e154). The solver clamps *every* root beyond ``t_max``, bounded ones too: the
cubic start ``[1, 0, -7.1, 6]`` has real roots -3.02, 0.98 and 2.04, so a ``t_max`` below 3.02
changes its problem."""
PRECISIONS = ("float64",)
"""Scene attribute: the paper's examples (t_max = 1e150, gradients up to 1e153) need float64."""
SUPPORTS_STEPS = False
"""Scene attribute: an optimisation scene takes ``--iters``, not ``--steps``."""


@dataclass(frozen=True)
class Start:
    """One starting point of a paper example.

    Attributes:
        name: Entity-path friendly name, e.g. ``a0_b-5.1_c5``.
        p0: Initial coefficients (highest degree first).
        trainable: Per coefficient, whether Adam may change it (``False`` = held fixed).
        note: Where the start comes from in the paper.
    """

    name: str
    p0: tuple[float, ...]
    trainable: tuple[bool, ...]
    note: str = ""


def start(p0: Sequence[float], letters: str, fixed: str = "", note: str = "") -> Start:
    """Builds a :class:`Start` named after its coefficients.

    Args:
        p0: Initial coefficients.
        letters: One letter per coefficient, e.g. ``"abc"`` or ``"qabc"``.
        fixed: Letters of the coefficients held fixed.
        note: Provenance in the paper.

    Returns:
        The start, named like ``a0_b-5.1_c5`` (``a1fixed_b-5.1_c5`` for fixed coefficients).
    """
    if len(p0) != len(letters):
        raise ValueError("one letter per coefficient")
    parts = [f"{ch}{v:g}{'fixed' if ch in fixed else ''}" for ch, v in zip(letters, p0)]
    trainable = tuple(ch not in fixed for ch in letters)
    return Start("_".join(parts), tuple(float(v) for v in p0), trainable, note)


@dataclass
class AdamRun:
    """History of a batched Adam run: entry ``k`` is iterate ``k`` (after ``k`` steps).

    Attributes:
        params: ``(K+1, B, P)`` coefficients at each iterate.
        grads: ``(K+1, B, P)`` gradient dL/dp evaluated at each iterate (the one Adam then used;
            zero for held-fixed coefficients).
        loss: ``(K+1, B)`` loss at each iterate.
        extras: Objective-specific records, each ``(K+1, B, ...)`` (roots, tracked slot, ...).
    """

    params: np.ndarray
    grads: np.ndarray
    loss: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def iterations(self) -> int:
        """Number of Adam steps taken (``K``)."""
        return self.loss.shape[0] - 1


Objective = Callable[["torch.Tensor"], tuple["torch.Tensor", Mapping[str, np.ndarray]]]
"""``objective(p) -> (loss (B,), extras)``; extras are numpy arrays with leading dimension B."""


def run_adam(
    p0: np.ndarray | Sequence[Sequence[float]],
    objective: Objective,
    iters: int,
    *,
    lr: float = DEFAULT_LR,
    trainable: np.ndarray | Sequence[Sequence[bool]] | None = None,
    progress: Callable[[int], Any] | None = None,
) -> AdamRun:
    """Runs ``iters`` steps of ``torch.optim.Adam`` on a batch of coefficient vectors.

    At every iterate ``k = 0..iters`` the objective and its gradient are evaluated and recorded;
    Adam then steps (except after the last). Held-fixed coefficients get a zero gradient, which
    leaves them exactly where they are (Adam's moments stay zero).

    Args:
        p0: ``(B, P)`` starting coefficients (float64).
        objective: Row-wise loss, see :data:`Objective`. It may be stateful (branch tracking): it
            is called exactly once per iterate, in order.
        iters: Number of Adam steps (>= 0).
        lr: Adam learning rate (other Adam settings are torch's defaults, as in the paper).
        trainable: ``(B, P)`` booleans, ``False`` = coefficient held fixed. Default: all free.
        progress: Called with the iterate index after each evaluation (e.g. a tqdm update).

    Returns:
        The recorded history.
    """
    import torch

    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    p = torch.tensor(np.asarray(p0, dtype=np.float64), dtype=torch.float64, requires_grad=True)
    if p.ndim != 2:
        raise ValueError(f"p0 must be (B, P), got shape {tuple(p.shape)}")
    mask = None
    if trainable is not None:
        mask = torch.as_tensor(np.asarray(trainable, dtype=bool))
        if mask.shape != p.shape:
            raise ValueError(f"trainable has shape {tuple(mask.shape)}, expected {tuple(p.shape)}")
    opt = torch.optim.Adam([p], lr=lr)
    n_rec = iters + 1
    params = np.empty((n_rec, *p.shape))
    grads = np.empty((n_rec, *p.shape))
    losses = np.empty((n_rec, p.shape[0]))
    extras: dict[str, np.ndarray] = {}
    for k in range(n_rec):
        opt.zero_grad(set_to_none=False)
        loss, extra = objective(p)
        loss.sum().backward()
        if mask is not None:
            with torch.no_grad():
                # where(), not a product: a NaN gradient of a fixed coefficient must not leak.
                p.grad.copy_(torch.where(mask, p.grad, torch.zeros_like(p.grad)))
        params[k] = p.detach().numpy()
        grads[k] = p.grad.detach().numpy()
        losses[k] = loss.detach().numpy()
        for key, val in extra.items():
            val = np.asarray(val)
            if key not in extras:
                extras[key] = np.empty((n_rec, *val.shape), dtype=val.dtype)
            extras[key][k] = val
        if progress is not None:
            progress(k)
        if k < iters:
            opt.step()
    return AdamRun(params, grads, losses, extras)


def run_starts(
    starts: Sequence[Start],
    objective: Objective,
    iters: int,
    lr: float = DEFAULT_LR,
    progress: Callable[[int], Any] | None = None,
    *,
    ignore_fp_errors: bool = False,
) -> AdamRun:
    """:func:`run_adam` on a scene's starts: one batch row per start, its fixed coefficients held.

    Args:
        starts: Starting points (row ``i`` of the history is ``starts[i]``).
        objective: Row-wise loss, see :data:`Objective`.
        iters: Adam steps.
        lr: Learning rate.
        progress: Optional per-iterate callback.
        ignore_fp_errors: Silence numpy floating-point warnings during the run (the baselines,
            whose inf/NaN are expected).

    Returns:
        The recorded history.
    """
    with np.errstate(all="ignore") if ignore_fp_errors else contextlib.nullcontext():
        return run_adam(
            [s.p0 for s in starts],
            objective,
            iters,
            lr=lr,
            trainable=[s.trainable for s in starts],
            progress=progress,
        )


def solve_finite_rows(solver: Callable[..., torch.Tensor], p: torch.Tensor, **kwargs: Any) -> torch.Tensor:
    """Calls a torch root solver on the rows of ``p`` that are finite; other rows get NaN roots.

    The solver API rejects non-finite coefficients (a ``ValueError``, by contract). An optimiser
    that diverged (e.g. an absurd ``--lr``) must be reported as "not converged", not crash the
    scene, so rows with NaN/inf coefficients are solved as zeros and their roots replaced by NaN.

    Args:
        solver: :func:`collision.roots.quadratic_roots` or :func:`collision.roots.cubic_roots`.
        p: ``(B, P)`` coefficients.
        **kwargs: Passed to ``solver``.

    Returns:
        The solver's output, NaN in the non-finite rows.
    """
    import torch

    finite = torch.isfinite(p).all(dim=-1)
    if bool(finite.all()):
        return solver(p, **kwargs)
    out = solver(torch.where(finite[:, None], p, torch.zeros_like(p)), **kwargs)
    mask = finite.reshape(-1, *([1] * (out.ndim - 1)))
    return torch.where(mask, out, torch.full_like(out, float("nan")))


class RobustRoots:
    """Base of the proposed losses: the robust torch root solver with ``M`` and ``t_max``.

    Args:
        solver: :func:`collision.roots.quadratic_roots` or :func:`collision.roots.cubic_roots`
            (imported lazily by the subclass: it starts Warp).
        max_derivative: ``M`` of the robust division.
        t_max: Root clamp.
    """

    def __init__(self, solver: Callable[..., torch.Tensor], max_derivative: float, t_max: float) -> None:
        self._roots = solver
        self.max_derivative = float(max_derivative)
        self.t_max = float(t_max)

    def solve(self, p: torch.Tensor) -> torch.Tensor:
        """Roots ``(B, S, 2)`` (Re, Im per slot) of the rows of ``p``, NaN for non-finite rows."""
        return solve_finite_rows(self._roots, p, t_max=self.t_max, max_derivative=self.max_derivative)


def roots_as_complex(roots: torch.Tensor) -> np.ndarray:
    """Solver output ``(..., 2)`` (Re, Im) as a detached complex numpy array ``(...)``."""
    r = roots.detach().numpy()
    return r[..., 0] + 1j * r[..., 1]


def real_root(values: np.ndarray) -> np.ndarray:
    """A real baseline root as complex: imaginary part 0 where finite, else NaN."""
    v = np.asarray(values, dtype=np.float64)
    return v + 1j * np.where(np.isfinite(v), 0.0, np.nan)


def root_loss(re: torch.Tensor, im: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. ``lossagainwitht``: ``1/2 (Re t - 0.5)^2 + 1/2 (Im t)^2`` (row-wise).

    Args:
        re: Real part of the tracked root, shape ``(B,)``.
        im: Imaginary part (``None`` for real-only baselines).

    Returns:
        Loss, shape ``(B,)``.
    """
    loss = 0.5 * (re - TARGET) ** 2
    if im is not None:
        loss = loss + 0.5 * im**2
    return loss


def convergence_summary(loss: np.ndarray, tol: float = CONVERGENCE_TOL) -> dict[str, Any]:
    """Convergence figures of one loss history.

    Args:
        loss: ``(K+1,)`` loss per iterate.
        tol: Convergence threshold.

    Returns:
        ``iters_to_converge`` (first iterate with loss < tol, ``None`` if never),
        ``converged`` (it happened), ``final_loss`` (``None`` if not finite),
        ``nonfinite_at`` (first iterate whose loss is NaN/inf, ``None`` if never).
    """
    loss = np.asarray(loss, dtype=np.float64)
    finite = np.isfinite(loss)
    hit = np.flatnonzero(finite & (loss < tol))
    bad = np.flatnonzero(~finite)
    final = float(loss[-1])
    return {
        "iters_to_converge": int(hit[0]) if hit.size else None,
        "converged": bool(hit.size),
        "final_loss": final if math.isfinite(final) else None,
        "nonfinite_at": int(bad[0]) if bad.size else None,
    }


def log_method(
    log: Any,
    prefix: str,
    run: AdamRun,
    row: int,
    param_names: Sequence[str],
    roots: Mapping[str, np.ndarray],
    extra_series: Mapping[str, np.ndarray] | None = None,
) -> None:
    """Logs one method of one start: parameters, roots (Re, Im) and loss on timeline ``iteration``.

    Entities (``rr.Scalars``): ``<prefix>/params/<name>``, ``<prefix>/roots/<slot>/re`` and
    ``/im``, ``<prefix>/loss`` and any ``extra_series`` as ``<prefix>/<name>``.

    Args:
        log: An open :class:`sim.logging.RerunLogger`.
        prefix: Entity prefix, e.g. ``/paper_quadratic/a0_b0_c5/proposed``.
        run: The run history.
        row: Batch row of this start.
        param_names: Coefficient names.
        roots: Slot name -> complex ``(K+1,)`` root history (NaN allowed).
        extra_series: Further ``(K+1,)`` series.
    """
    n = run.loss.shape[0]
    seq = {"iteration": np.arange(n), "frame": np.arange(n)}
    for j, name in enumerate(param_names):
        log.log_scalars(f"{prefix}/params/{name}", run.params[:, row, j], sequence=seq)
    for slot, values in roots.items():
        values = np.asarray(values)
        log.log_scalars(f"{prefix}/roots/{slot}/re", values.real, sequence=seq)
        log.log_scalars(f"{prefix}/roots/{slot}/im", values.imag, sequence=seq)
    log.log_scalars(f"{prefix}/loss", run.loss[:, row], sequence=seq)
    for name, values in (extra_series or {}).items():
        log.log_scalars(f"{prefix}/{name}", np.asarray(values, dtype=np.float64), sequence=seq)


def views_for_start(
    root: str, start_name: str, slots: Mapping[str, Sequence[str]]
) -> dict[str, list[str]]:
    """Time-series views (loss / params / Re roots / Im roots) of one start, all methods.

    Args:
        root: Scene entity root, e.g. ``/paper_quadratic``.
        start_name: Start name.
        slots: Method name -> root slot names logged for it.

    Returns:
        View name -> entity path expressions, for :func:`sim.logging.time_series_blueprint`.
    """
    base = f"{root}/{start_name}"
    return {
        "loss": [f"{base}/{m}/loss" for m in slots],
        "params": [f"{base}/{m}/params/**" for m in slots],
        "Re roots": [f"{base}/{m}/roots/{s}/re" for m, ss in slots.items() for s in ss],
        "Im roots": [f"{base}/{m}/roots/{s}/im" for m, ss in slots.items() for s in ss],
    }


def add_scene_arguments(parser: argparse.ArgumentParser, default_iters: int) -> None:
    """A paper scene's options (``--iters``, ``--lr``, ``--max-derivative``, ``--t-max``), paper
    defaults.

    Args:
        parser: Parser to extend.
        default_iters: The scene's default number of Adam steps.
    """
    from scenes.registry import add_optimisation_arguments, float_in

    add_optimisation_arguments(parser, default_iters=default_iters, default_lr=DEFAULT_LR,
                               default_max_derivative=DEFAULT_MAX_DERIVATIVE)
    parser.add_argument("--t-max", type=float_in(*T_MAX_RANGE), default=T_MAX, dest="t_max",
                        help=f"root clamp t_max of the proposed solver: escaping roots sit at +-t_max, and "
                             f"any root beyond it is clamped to it (in [{T_MAX_RANGE[0]:g}, {T_MAX_RANGE[1]:g}]; "
                             f"default the paper's {T_MAX:g})")


@dataclass(frozen=True)
class ProposedRecord:
    """What a scene logs and summarises of the proposed method for one start.

    Attributes:
        roots: Root name -> complex ``(K+1,)`` history, logged as ``.../roots/<name>/{re,im}``.
        series: Further ``(K+1,)`` series, logged as ``.../<name>``.
        summary: Entries appended to the start's ``proposed`` summary (after ``final_params``).
    """

    roots: Mapping[str, np.ndarray]
    series: Mapping[str, np.ndarray] = field(default_factory=dict)
    summary: Mapping[str, Any] = field(default_factory=dict)


def run_scene(
    args: argparse.Namespace,
    log: Any,
    *,
    name: str,
    starts: Sequence[Start],
    param_names: Sequence[str],
    run_proposed: Callable[..., AdamRun],
    run_baseline: Callable[..., AdamRun],
    proposed_roots: Sequence[str],
    proposed_record: Callable[[AdamRun, int], ProposedRecord],
    baseline_root: str,
    baseline_key: str,
    baseline_description: str,
) -> dict[str, Any]:
    """Runs a paper scene (proposed and baseline on all starts), logs it, returns the JSON summary.

    Entities: ``/<name>/<start>/{proposed,baseline}/...`` as written by :func:`log_method`.

    Args:
        args: Parsed CLI arguments (``iters``, ``lr``, ``max_derivative``; ``t_max``,
            default :data:`T_MAX`).
        log: An open :class:`sim.logging.RerunLogger`.
        name: Scene name (entity root ``/<name>``).
        starts: The scene's starts.
        param_names: Coefficient names.
        run_proposed: ``run_proposed(starts, iters, lr, max_derivative, t_max=..., progress=...)``.
        run_baseline: ``run_baseline(starts, iters, lr, progress=...)``.
        proposed_roots: Root names the proposed records log (for the blueprint views).
        proposed_record: ``(history, row) -> ProposedRecord`` of the proposed method.
        baseline_root: Root name under which the baseline's real root is logged.
        baseline_key: ``extras`` key of the baseline's root in its history.
        baseline_description: The summary's ``baseline`` text.

    Returns:
        Summary: per start, ``proposed`` and ``baseline`` convergence figures.
    """
    from tqdm import tqdm

    from sim.logging import time_series_blueprint

    t_max = float(getattr(args, "t_max", T_MAX))
    root = f"/{name}"
    slots = {"proposed": tuple(proposed_roots), "baseline": (baseline_root,)}
    log.send_blueprint(time_series_blueprint({s.name: views_for_start(root, s.name, slots) for s in starts}))
    with tqdm(total=2 * (args.iters + 1), desc=name, unit="it", file=sys.stderr,
              disable=None, leave=False) as bar:
        def tick(_k: int) -> None:
            interrupts.raise_pending()
            bar.update(1)

        prop = run_proposed(starts, args.iters, args.lr, args.max_derivative, t_max=t_max, progress=tick)
        base = run_baseline(starts, args.iters, args.lr, progress=tick)

    starts_summary: dict[str, Any] = {}
    for i, s in enumerate(starts):
        prefix = f"{root}/{s.name}"
        rec = proposed_record(prop, i)
        log_method(log, f"{prefix}/proposed", prop, i, param_names, rec.roots, extra_series=rec.series)
        log_method(log, f"{prefix}/baseline", base, i, param_names,
                   {baseline_root: real_root(base.extras[baseline_key][:, i])})
        starts_summary[s.name] = {
            "p0": list(s.p0),
            "fixed": [n for n, t in zip(param_names, s.trainable) if not t],
            "note": s.note,
            "proposed": {**convergence_summary(prop.loss[:, i]),
                         "final_params": prop.params[-1, i].tolist(),
                         **rec.summary},
            "baseline": {**convergence_summary(base.loss[:, i]),
                         "final_params": base.params[-1, i].tolist()},
        }
    return {
        "scene": name,
        "iters": args.iters,
        "lr": args.lr,
        "max_derivative": args.max_derivative,
        "t_max": t_max,
        "target": TARGET,
        "tol": CONVERGENCE_TOL,
        "baseline": baseline_description,
        "proposed_converged": sum(v["proposed"]["converged"] for v in starts_summary.values()),
        "baseline_converged": sum(v["baseline"]["converged"] for v in starts_summary.values()),
        "final_loss_max": float(np.max(prop.loss[-1])),  # the largest over the starts
        "starts": starts_summary,
    }
