"""Registry of the scenes runnable with ``python -m scenes NAME``.

A scene is a module that defines:

* ``NAME: str`` and ``DESCRIPTION: str`` (one line, shown by ``--list``);
* ``add_arguments(parser)``: adds its own options to an ``argparse`` parser that already has the
  common ``--out`` and ``--precision`` (``--steps`` if ``SUPPORTS_STEPS``; ``--seed`` if
  ``USES_SEED``, the help text of a scene that draws something at random);
* optionally ``PRECISIONS`` (default ``("float64",)``; the CLI offers exactly these)
  and ``SUPPORTS_STEPS`` (default ``False``);
* optionally ``check_arguments(args) -> str | None``: a usage error (exit code 2) for options
  that do not fit together, before anything runs;
* ``run(args, log) -> dict``: runs, logs to ``log`` (an open :class:`sim.logging.RerunLogger`) and
  returns the JSON-serialisable summary that the CLI prints as its last line.

Modules are imported lazily, so ``--list`` stays fast and a scene that fails to import does not
break the others. Add a scene by adding one line to :data:`SCENES`.
"""

from __future__ import annotations

import argparse
import importlib
import math
from collections.abc import Mapping
from types import ModuleType
from typing import Any

import numpy as np

SCENES: dict[str, str] = {
    "paper_quadratic": "scenes.paper_quadratic",
    "paper_cubic": "scenes.paper_cubic",
    "cloth_drop": "scenes.cloth_drop",
    "rigid_toss": "scenes.rigid_toss",
    "cloth_rigid": "scenes.cloth_rigid",
    "grazing": "scenes.grazing",
    "tunnel": "scenes.tunnel",
    "bank_shot": "scenes.bank_shot",
    "cloth_toss": "scenes.cloth_toss",
    "billiards": "scenes.billiards",
}
"""Scene name -> module path."""


def scene_names() -> list[str]:
    """Sorted names of the registered scenes."""
    return sorted(SCENES)


def load_scene(name: str) -> ModuleType:
    """Imports a registered scene module.

    Args:
        name: Scene name.

    Returns:
        The module.

    Raises:
        KeyError: ``name`` is not registered (the message lists the scenes).
    """
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; available scenes: {', '.join(scene_names())}")
    return importlib.import_module(SCENES[name])


def describe(name: str) -> str:
    """One-line description of a scene (imports it)."""
    return getattr(load_scene(name), "DESCRIPTION", "")


def int_at_least(minimum: int, what: str = "an integer"):
    """``argparse`` type factory: an integer >= ``minimum`` (``what`` names it in messages)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be {what} (>= {minimum}), got {value}")
        return value

    return parse


positive_int = int_at_least(1, "a positive integer")
"""``argparse`` type: an integer >= 1."""
non_negative_int = int_at_least(0, "a non-negative integer")
"""``argparse`` type: an integer >= 0."""


def float_in(low: float, high: float):
    """``argparse`` type factory: a float in ``[low, high]`` (NaN refused)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must lie in [{low:g}, {high:g}], got {text!r}")
        return value

    return parse


def positive_float(text: str) -> float:
    """``argparse`` type: a finite float > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (value > 0.0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """``argparse`` type: a finite float >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text!r}") from None
    if not (value >= 0.0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a non-negative finite number, got {text!r}")
    return value


def add_optimisation_arguments(
    parser: argparse.ArgumentParser,
    *,
    default_iters: int,
    default_lr: float,
    default_max_derivative: float,
) -> None:
    """Options shared by the optimisation scenes: ``--iters``, ``--lr``, ``--max-derivative``.

    Args:
        parser: Parser to extend.
        default_iters: Default number of optimiser steps.
        default_lr: Default learning rate.
        default_max_derivative: Default ``M`` of the robust division.
    """
    parser.add_argument("--iters", type=positive_int, default=default_iters,
                        help=f"optimiser steps (>= 1; default {default_iters})")
    parser.add_argument("--lr", type=positive_float, default=default_lr,
                        help=f"Adam learning rate (default {default_lr:g})")
    add_max_derivative_argument(parser, default_max_derivative)


def add_max_derivative_argument(parser: argparse.ArgumentParser, default: float, note: str = "") -> None:
    """``--max-derivative``: ``M``, the robust division's bound on the roots' derivatives (> 0);
    ``note`` is appended to the help."""
    parser.add_argument("--max-derivative", type=positive_float, default=default, dest="max_derivative",
                        help=f"M of the robust division (default {default:g}){note}")


def jsonable(value: Any) -> Any:
    """Recursively converts numpy scalars/arrays and non-finite floats (-> ``None``) for strict JSON.

    Args:
        value: Any nest of mappings, sequences, numpy arrays and numbers.

    Returns:
        The converted value.
    """
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    return value
