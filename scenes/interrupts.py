"""Ctrl-C and SIGTERM during a scene run.

Both signals raise an exception in the main thread (:class:`KeyboardInterrupt`, or its subclass
:class:`Terminated` for SIGTERM) that the CLI turns into exit code 130 or 143 with the frames so
far kept. Python drops an exception raised inside a ``__del__`` method or a C callback (it prints
"Exception ignored in ..."), and a signal that lands while a Warp array is freed would be lost that
way, leaving the run going. So the handler also notes the signal, and the scenes' loops call
:func:`raise_pending` once per step or rollout to raise it again.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["Terminated", "handled", "raise_pending"]

_HELD = (signal.SIGINT, signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C (the frames so far are kept), with exit code 143."""


_pending: list[int] = []  # the signals noted by the handler since :func:`handled` was entered


def _exception(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _handler(signum, frame) -> None:
    _pending.append(signum)
    raise _exception(signum)


def raise_pending() -> None:
    """Raise the interrupt of a signal noted while :func:`handled` is active (SIGTERM first); does
    nothing when none was. Once the exception leaves the scene, the run is over, so raising it a
    second time after it was delivered does no harm."""
    if _pending:
        raise _exception(signal.SIGTERM if signal.SIGTERM in _pending else _pending[0])


@contextlib.contextmanager
def handled() -> Iterator[None]:
    """SIGINT and SIGTERM raise (and note) an interrupt inside the block; the previous handlers
    are put back after it. The signals are held back while the handlers are swapped, so that one
    arriving then is handled by the handlers of the block it arrives in, never lost half way.
    Python runs signal handlers in the main thread only: in another thread nothing is installed;
    inside a block already active, nothing changes."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is _handler:
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
    try:
        _pending.clear()
        previous = {s: signal.signal(s, _handler) for s in _HELD}
        try:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # one held back arrives here, inside
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
            for s, handler in previous.items():
                # a handler installed outside Python (None) cannot be put back: the default then
                signal.signal(s, signal.SIG_DFL if handler is None else handler)
            _pending.clear()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # one arriving after the block: the old handlers
