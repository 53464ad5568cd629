"""The two-phase optimiser of the inverse scenes (``tunnel``, ``bank_shot``), CMA-ES, the
``--methods`` option and the scenes' gradient check against central differences.

Phase one (the miss): plain Adam on a lifted-event loss. Phase two, from the first iterate in
the wanted contact region ("good": the designated face is hit, the shot banks): a fresh Adam
whose iterates are *guarded*: one that leaves the region or does not lower the loss is rejected
(back to the last accepted iterate and its gradient, half the step), an accepted one grows the
step by ``growth`` up to the initial rate. The loss changes discontinuously where the contact
set changes (a second contact, a neighbouring face), and a plain Adam step across such a
boundary would never come back. A step after a rejection goes along the steepest descent (the
negative gradient, normalised, of length ``lr``) instead of Adam's direction: Adam scales
each coordinate by its own history, so near a kink of an ill-conditioned loss (the tunnel's
barrier at a face's edge) its direction can leave the region or raise the loss at every length,
and the halved steps then shrink to nothing; the gradient itself lowers the loss for a step
short enough.
"""

from __future__ import annotations

import contextlib

from scenes import interrupts


class GuardedAdam:
    """Adam on one tensor ``v`` (requires grad) with the guarded second phase.

    Per iteration: ``zero_grad()``, a rollout, ``take = judge(loss, good)``, then (unless the
    loop stops) ``step(loss, good, take)``.

    Args:
        v: the optimised tensor.
        lr: Adam's step, and the second phase's largest.
        betas: Adam's moment decay rates.
        growth: factor of the step after an accepted second-phase iterate.
    """

    def __init__(self, v, lr: float, betas, growth: float):
        import torch

        self._torch = torch
        self.v, self.initial_lr, self.betas, self.growth = v, lr, betas, growth
        self.lr = lr
        self.opt = torch.optim.Adam([v], lr=lr, betas=betas)
        self.accepted = None  # second phase: (v, loss, gradient) of the last accepted iterate

    @property
    def guarded(self) -> bool:
        """Whether the second phase has started (misses are then rejected, not optimised)."""
        return self.accepted is not None

    def zero_grad(self) -> None:
        self.opt.zero_grad()

    def judge(self, loss, good: bool) -> bool:
        """Whether the current iterate is taken (``loss`` a tensor, or None for no value). The
        first good iterate starts the second phase with a fresh Adam (the first phase's moments
        mean nothing for the new loss)."""
        if self.accepted is None and good:
            self.opt = self._torch.optim.Adam([self.v], lr=self.initial_lr, betas=self.betas)
            self.lr = self.initial_lr
        return self.accepted is None or (good and loss is not None and float(loss.detach()) < self.accepted[1])

    def step(self, loss, good: bool, take: bool) -> float:
        """Backward of a taken iterate (recorded as accepted in the second phase) or a return to
        the accepted one; then the step: Adam's after an accepted iterate, the steepest descent's
        after a rejected one. Returns the norm of the gradient stepped along."""
        torch = self._torch
        if take:
            loss.backward()
            if good:
                if self.accepted is not None:
                    self.lr = min(self.lr * self.growth, self.initial_lr)
                self.accepted = (self.v.detach().clone(), float(loss.detach()), self.v.grad.detach().clone())
        else:
            # back to the accepted iterate with half the step; along the steepest descent (of
            # length lr), or Adam's step where the gradient there is exactly zero
            self.lr *= 0.5
            gradient = self.accepted[2]
            with torch.no_grad():
                self.v.copy_(self.accepted[0])
            self.v.grad = gradient.clone()
            grad_norm = float(torch.linalg.norm(gradient))
            if grad_norm > 0.0:
                with torch.no_grad():
                    self.v.sub_((self.lr / grad_norm) * gradient)
                return grad_norm
        grad_norm = float(torch.linalg.norm(self.v.grad))
        for group in self.opt.param_groups:
            group["lr"] = self.lr
        self.opt.step()
        return grad_norm


def to_polar(velocity, heading_scale: float):
    """A planar velocity (2,) [m/s] as an optimiser's variables (speed, heading /
    ``heading_scale``): Adam then turns a shot instead of only speeding it up (a path that passes
    behind a ball has a gradient along its velocity in (vx, vy)). ``heading_scale`` [rad] is
    the heading's unit: Adam turns by up to ``lr * heading_scale`` rad per step."""
    import numpy as np

    vx, vy = (float(c) for c in velocity)
    return np.array([np.hypot(vx, vy), np.arctan2(vy, vx) / heading_scale])


def from_polar(polar, heading_scale: float):
    """The velocity (2,) (a tensor) of the variables of :func:`to_polar` (a tensor (2,))."""
    import torch

    heading = polar[1] * heading_scale
    return torch.stack([polar[0] * torch.cos(heading), polar[0] * torch.sin(heading)])


def polar_gradient(polar, grad, heading_scale: float):
    """A loss' gradient w.r.t. the variables of :func:`to_polar` from the one w.r.t. the
    velocity (2,) (the chain rule)."""
    import math

    import torch

    heading = float(polar[1]) * heading_scale
    c, s, speed = math.cos(heading), math.sin(heading), float(polar[0])
    g = grad.detach()
    return torch.stack([g[0] * c + g[1] * s, heading_scale * speed * (-g[0] * s + g[1] * c)])


def reported_iterate(accepted_flags: list[bool], reached, guarded: bool) -> int:
    """Index of the iterate a run reports: the last one, or the last accepted one when the run
    ended on a rejected second-phase step without reaching the target."""
    last = len(accepted_flags) - 1
    if reached is None and guarded and not accepted_flags[-1]:
        last = max(i for i, a in enumerate(accepted_flags) if a)
    return last


ITERS_HELP = "optimiser steps per method; the start and each step's result are rolled out: N + 1 rollouts"
"""The one meaning of ``--iters`` in every optimisation scene (the paper scenes' too): ``N``
optimiser steps, ``N + 1`` evaluated iterates; CMA-ES gets the same rollout budget."""


def run_cma(x0, sigma: float, budget: int, evaluate) -> None:
    """CMA-ES (the ``cma`` package, seed 1) from ``x0`` with initial step ``sigma``: asks for
    candidates and calls ``evaluate(x) -> (value, reached)`` on each (one rollout, recorded by the
    caller) until ``budget`` evaluations are spent or one has ``reached`` the target."""
    import cma
    import numpy as np

    es = cma.CMAEvolutionStrategy(np.asarray(x0, dtype=np.float64), sigma,
                                  {"seed": 1, "verbose": -9, "maxfevals": budget})
    spent, reached = 0, False
    while not es.stop() and not reached and spent < budget:
        xs = es.ask()
        values = []
        for x in xs:
            if spent >= budget or reached:
                values.append(np.inf)  # unevaluated: CMA-ES needs a value for every candidate
                continue
            value, reached = evaluate(np.asarray(x, dtype=np.float64).copy())
            spent += 1
            values.append(value)
        es.tell(xs, values)


def parse_methods(text: str, methods) -> list[str]:
    """The comma-separated ``--methods`` option as a list, each one of ``methods``."""
    chosen = [m.strip() for m in text.split(",") if m.strip()]
    if not chosen or any(m not in methods for m in chosen):
        raise ValueError(f"--methods must be a comma-separated subset of {','.join(methods)}, got {text!r}")
    return chosen


def central_difference_check(analytic, value, x, step: float) -> dict:
    """A gradient ``analytic`` (n,) against central differences of ``value`` (a float of an
    (n,) numpy array) at ``x`` with ``step``: both, and their relative error."""
    import numpy as np

    analytic = np.asarray(analytic, dtype=np.float64)
    numeric = np.zeros(len(analytic))
    for k in range(len(analytic)):
        values = []
        for sign in (1.0, -1.0):
            shifted = np.asarray(x, dtype=np.float64).copy()
            shifted[k] += sign * step
            values.append(float(value(shifted)))
        numeric[k] = (values[0] - values[1]) / (2.0 * step)
    return {"analytic": analytic.tolist(), "numeric": numeric.tolist(),
            "relative_error": float(np.linalg.norm(analytic - numeric) / max(np.linalg.norm(numeric), 1e-300))}


@contextlib.contextmanager
def progress(description: str, total: int):
    """A progress bar of an optimisation (tqdm on stderr, shown when stderr is a terminal): yields
    the ``callback(iteration, history)`` the scenes' optimisers call after each rollout; the bar
    shows the iterations done and the last loss."""
    import sys

    from tqdm import tqdm

    bar = tqdm(total=total, desc=description, unit="it", file=sys.stderr, disable=None, leave=False)

    def callback(iteration: int, history) -> None:
        interrupts.raise_pending()
        bar.update(max(iteration + 1 - bar.n, 0))
        losses = history.get("loss") if isinstance(history, dict) else None
        if losses:
            bar.set_postfix_str(f"loss {losses[-1]:.3g}", refresh=False)

    try:
        yield callback
    finally:
        bar.close()


def draw_loss_curves(ax, curves: dict, ylabel: str) -> None:
    """The loss per rollout of each method on ``ax`` (``curves``: name -> values; log scale); a
    one-rollout run (an exactly zero gradient at the start) is drawn flat and says so."""
    import numpy as np

    longest = max((len(c) for c in curves.values()), default=1)
    for method, curve in curves.items():
        values = np.maximum(np.asarray(curve, dtype=np.float64), 1e-12)
        if len(values) == 1:  # an exactly zero gradient at the start: the run stops at once
            ax.semilogy([0, max(longest - 1, 1)], [values[0], values[0]], linestyle="--",
                        label=f"{method} (gradient 0: stops, drawn flat)")
            continue
        ax.semilogy(np.arange(len(values)), values, label=f"{method} ({len(values)} rollouts)")
    ax.set_xlabel("iteration (rollout)")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)


def plot_loss_curves(curves: dict, path: str, title: str, ylabel: str) -> None:
    """:func:`draw_loss_curves` in a figure of its own, written atomically to ``path``."""
    import matplotlib

    from sim.logging import save_figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    draw_loss_curves(ax, curves, ylabel)
    ax.set_title(title)
    try:
        save_figure(fig, path)
    finally:
        plt.close(fig)
