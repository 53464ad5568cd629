"""Tape helpers: which ``wp.Tape`` records now, and pausing it for launches whose results are
thrown away (the decisions' trial solves); only the final, consistent launches are replayed
backwards."""

from __future__ import annotations

from core.warp_adapter import current_tape, set_current_tape


def active_tape():
    """The ``wp.Tape`` currently recording (None outside ``with tape:``)."""
    return current_tape()


class paused_tape:
    """Context manager: launches inside are not recorded on the active tape (for trial solves
    whose results are thrown away; only the final, consistent solve is replayed backwards)."""

    paused: list = []
    """The tapes paused now (innermost last): a tape exists even while none records."""

    def __enter__(self):
        self._tape = active_tape()
        if self._tape is not None:
            set_current_tape(None)
            paused_tape.paused.append(self._tape)
        return self._tape

    def __exit__(self, *exc):
        if self._tape is not None:
            paused_tape.paused.pop()
            set_current_tape(self._tape)
        return False


def any_tape() -> bool:
    """Whether a ``wp.Tape`` is recording or paused (:class:`paused_tape`): arrays made now may
    still be read by its backward (a paused trial's result can feed a later recorded launch)."""
    return active_tape() is not None or bool(paused_tape.paused)
