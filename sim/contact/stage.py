"""What an integrator calls once per substep after the forces: the collision stage.

:class:`CollisionStage` is the interface: ``stage(state_in, state_pred, h)`` returns the State
after contact (None: the prediction stands), and the stage says what the integrator's other
stages must know of it (:attr:`CollisionStage.surface_separation`,
:attr:`CollisionStage.last_body_particles`). :class:`sim.contact.response.ImpulseCollisionHandler`
is the stage; :class:`StageObserver` wraps one to watch its calls (the scenes gather contacts,
the rollout counts contact substeps) and passes those attributes through, so the integrator
never has to find the stage behind its wrappers.
"""

from __future__ import annotations

import numpy as np


class CollisionStage:
    """The collision stage of a substep (see the module docstring)."""

    surface_separation: float | None = None
    """The separation [m] every contact keeps when the stage acts on collidable surfaces (the
    integrator's particle-plane stage then stops particles that far from the planes too, where
    the stage's vertex-plane rows hold them); None when it acts on none (the plane stage keeps
    the model's thickness)."""

    @property
    def last_body_particles(self) -> np.ndarray:
        """(K,) the particles that shared a contact with a rigid body's vertex in the last call."""
        return np.zeros(0, dtype=np.int64)

    def __call__(self, state_in, state_pred, h: float):
        raise NotImplementedError

    def set_exact_gravity(self, exact: bool) -> None:
        """Whether the integrator's stored velocities are the substep's end ones (the exact
        ballistic update, ``exact_gravity=True``) rather than semi-implicit Euler's; the
        integrator says so before each call (the contacts' plane law depends on it)."""


class StageObserver(CollisionStage):
    """A collision stage that watches another one (``handler``): calls it, and passes its
    :attr:`surface_separation`, :attr:`last_body_particles` and statistics through."""

    def __init__(self, handler) -> None:
        self.handler = handler

    @property
    def surface_separation(self) -> float | None:
        return getattr(self.handler, "surface_separation", None)

    @property
    def last_body_particles(self) -> np.ndarray:
        return getattr(self.handler, "last_body_particles", np.zeros(0, dtype=np.int64))

    def __call__(self, state_in, state_pred, h: float):
        return self.handler(state_in, state_pred, h)

    def set_exact_gravity(self, exact: bool) -> None:
        if isinstance(self.handler, CollisionStage):
            self.handler.set_exact_gravity(exact)

    def save_stats(self):
        """The watched stage's statistics (for :meth:`restore_stats` after calls an integrator
        discards: a trial pass, a rejected substep)."""
        return self.handler.save_stats()

    def restore_stats(self, stats) -> None:
        """Puts back the statistics of :meth:`save_stats`."""
        self.handler.restore_stats(stats)
