"""The integrators: :class:`~sim.integrators.semi_implicit.SemiImplicitIntegrator` (explicit
springs, the default) and :class:`~sim.integrators.implicit.ImplicitIntegrator` (backward Euler
on the springs), and :func:`make_integrator`, which picks one by name."""

from __future__ import annotations

from sim.integrators.implicit import OPTIONS, ImplicitIntegrator, check_options
from sim.integrators.semi_implicit import SemiImplicitIntegrator
from sim.model import Model

INTEGRATORS = ("semi_implicit", "implicit")
"""Particle integrators on offer: semi-implicit Euler (explicit springs) and backward Euler
(:class:`sim.integrators.implicit.ImplicitIntegrator`)."""


def check_integrator(kind: str, options: dict | None = None) -> None:
    """Raises ``ValueError`` for an unknown integrator ``kind`` or options it does not take
    (the implicit one's :data:`sim.integrators.implicit.OPTIONS`), before anything is built."""
    options = options or {}
    if kind == "semi_implicit":
        unknown = sorted(set(options) - {"exact_gravity"})
        if unknown:
            raise ValueError(f"the semi_implicit integrator's only option is exact_gravity, got {unknown}")
        if not isinstance(options.get("exact_gravity", False), bool):
            raise ValueError(f"exact_gravity must be True or False, got {options['exact_gravity']!r}")
    elif kind == "implicit":
        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise ValueError(f"the implicit integrator's options are {', '.join(OPTIONS)}, got {unknown}")
        check_options(**options)
    else:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {kind!r}")


def make_integrator(model: Model, kind: str = "semi_implicit", requires_grad: bool | None = None,
                    **options) -> SemiImplicitIntegrator:
    """The integrator ``kind`` (one of :data:`INTEGRATORS`) for ``model``; ``options`` go to the
    implicit one (:data:`sim.integrators.implicit.OPTIONS`), or ``exact_gravity`` to the semi-implicit one."""
    check_integrator(kind, options)
    if kind == "implicit":
        return ImplicitIntegrator(model, requires_grad=requires_grad, **options)
    return SemiImplicitIntegrator(model, requires_grad=requires_grad, **options)
