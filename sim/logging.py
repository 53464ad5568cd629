"""Small reusable rerun helper shared by every scene.

Conventions (see ``docs/design.md``, section "rerun conventions"):

* one :class:`rerun.RecordingStream` per run, ``save(path)`` is called *before* anything is logged;
* deterministic output: ``log_time`` and ``log_tick`` are disabled and the recording id is derived
  from the application id, the recording name and the seed (``uuid5``), so two runs with the same
  arguments log the same data on the same timelines;
* timelines: ``frame`` (sequence) and, where meaningful, ``sim_time`` (duration, seconds);
  optimisation scenes add their own sequence timeline (e.g. ``iteration``);
* a default blueprint made of time-series views (see :func:`time_series_blueprint`);
* atomic files: the stream writes to a hidden temporary file next to the requested path, which is
  renamed onto the target only when the ``with`` block exits without an exception. On error the
  temporary file is removed, so no half-written ``.rrd`` is ever left behind. With
  ``keep_partial=True`` (used by :class:`sim.recorder.SimRecorder` and the scene CLI) an exception
  instead flushes the stream and renames it to ``NAME.partial.rrd`` beside the target: a
  complete, readable recording of everything logged before the error, whose ``/status`` says
  where it stopped. The target ``NAME.rrd`` is only ever replaced by a finished run, so an
  earlier good recording survives a failed one. A hard kill (SIGKILL, power loss) leaves the
  target untouched and a stale temporary file, which the next logger writing beside it removes;
* the target must be a regular file or a new path: a folder, device or FIFO is refused, and a
  symbolic link is followed (the file it points to is replaced).

Example:
    >>> with RerunLogger("out.rrd", recording_name="demo") as log:  # doctest: +SKIP
    ...     log.send_blueprint(time_series_blueprint({"loss": ["/metrics/loss"]}))
    ...     log.log_scalars("/metrics/loss", np.array([1.0, 0.5]), sequence={"frame": [0, 1]})
"""

from __future__ import annotations

import contextlib
import glob
import os
import signal
import threading
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

__all__ = ["RerunLogger", "time_series_blueprint", "grid_of_time_series", "output_path", "partial_path"]


def output_path(path: str | os.PathLike[str], name: str = "path") -> Path:
    """The file a recording for ``path`` replaces: ``path`` itself, or the file a symbolic link
    points to. Raises FileNotFoundError when its folder does not exist and ValueError when it is
    not a regular file (a folder, device or FIFO); both messages name ``name``."""
    target = Path(path)
    if target.is_symlink():
        target = Path(os.path.realpath(target))
    if not target.parent.is_dir():
        raise FileNotFoundError(f"{name}: folder {str(target.parent)!r} does not exist")
    if target.exists() and not target.is_file():
        kind = "a folder" if target.is_dir() else "not a regular file (a device, FIFO or socket)"
        raise ValueError(f"{name}: {str(target)!r} is {kind}; give a regular file or a new path")
    return target


def partial_path(path: str | os.PathLike[str]) -> Path:
    """Where a failed or interrupted run keeps its frames: ``NAME.partial.rrd`` for ``NAME.rrd``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.partial{path.suffix}" if path.suffix else f"{path.name}.partial")


def _remove_stale_temporaries(path: Path) -> None:
    """Removes the temporary files ``.NAME.PID.tmp`` that killed runs (PID no longer alive) left
    beside ``path``."""
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        pid = tmp.name[len(path.name) + 2:-len(".tmp")]
        if not tmp.name.startswith(f".{path.name}.") or not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except (PermissionError, OverflowError):
            pass  # alive (another user's) or not a process id: not ours to remove


@contextlib.contextmanager
def _interrupts_held():
    """SIGINT and SIGTERM held back while a recording is finished, so that a second Ctrl-C or a
    TERM cannot stop the flush half way and leave a half-written file or a temporary one: their
    handlers are swapped for one that notes the signal, and when the block ends the original
    handlers take the noted signals (a default action is raised again). Python runs signal
    handlers in the main thread only; elsewhere nothing is held, nor where a handler was
    installed outside Python."""
    held = (signal.SIGINT, signal.SIGTERM)
    # a handler installed outside Python (getsignal: None) could not be put back: hold nothing
    if threading.current_thread() is not threading.main_thread() or any(signal.getsignal(s) is None for s in held):
        yield
        return
    noted: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: noted.append(signum)) for s in held}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(noted):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(s)


class RerunLogger:
    """Owns one rerun recording written atomically to ``path``.

    Use it as a context manager. Inside the block, data goes to ``<dir>/.<name>.<pid>.tmp``; on a
    clean exit the temporary file is renamed to ``path``; on an exception it is deleted (or, with
    ``keep_partial``, renamed to :func:`partial_path` of ``path``) and the exception propagates.
    After the block, :attr:`written` is the file that holds the recording (None: nothing kept).

    Args:
        path: Destination ``.rrd`` file: a regular file or a new path in an existing folder (a
            symbolic link is followed).
        application_id: Rerun application id.
        recording_name: Human-readable recording name (also part of the deterministic recording id).
        seed: Seed of the run (part of the deterministic recording id).
        name: How error messages name ``path`` (e.g. the CLI's ``--out``).
        keep_partial: On an exception inside the block, keep what was logged so far as
            ``NAME.partial.rrd`` (flushed, complete and readable, with ``/status`` saying where it
            stopped) instead of deleting it. If flushing itself fails the temporary file is
            deleted either way.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        application_id: str = "tunnelsim",
        recording_name: str = "tunnelsim",
        seed: int = 0,
        keep_partial: bool = False,
        name: str = "path",
    ) -> None:
        self.path = output_path(path, name)
        self.partial_path = output_path(partial_path(self.path), f"{name} (its partial recording)")
        self.tmp_path = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        self.written: Path | None = None
        self._status_logged = False
        self.application_id = application_id
        self.recording_name = recording_name
        self.seed = int(seed)
        self.keep_partial = bool(keep_partial)
        self.rec: rr.RecordingStream | None = None

    # ------------------------------------------------------------------ context management
    def __enter__(self) -> RerunLogger:
        recording_id = uuid.uuid5(
            uuid.NAMESPACE_URL, f"tunnelsim/{self.application_id}/{self.recording_name}/{self.seed}"
        )
        rec = rr.RecordingStream(
            self.application_id, recording_id=recording_id, send_properties=False
        )
        _remove_stale_temporaries(self.path)
        self.written = None
        self._status_logged = False
        rec.save(str(self.tmp_path))  # the sink must be set before anything is logged
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.send_recording_name(self.recording_name)
        self.rec = rec
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        with _interrupts_held():  # an interrupt now arrives once the file is in place
            rec = self.rec
            flushed = False
            try:
                if rec is not None:
                    if exc_type is not None and self.keep_partial and not self._status_logged:
                        self.log_text("/status", f"interrupted: {exc_type.__name__}: {exc}")
                    rec.flush()
                    rec.disconnect()
                flushed = True
            finally:
                self.rec = None
                if not flushed:
                    target = None  # an unfinished file replaces nothing
                else:
                    target = self.path if exc_type is None else self.partial_path if self.keep_partial else None
                if target is not None and self.tmp_path.exists():
                    os.replace(self.tmp_path, target)
                    self.written = target
                else:
                    self.tmp_path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ logging
    @property
    def stream(self) -> rr.RecordingStream:
        """The underlying recording stream (only valid inside the ``with`` block)."""
        if self.rec is None:
            raise RuntimeError("RerunLogger is not open; use it as a context manager")
        return self.rec

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        """Sends the default blueprint (layout) of the recording.

        Args:
            blueprint: The blueprint, e.g. from :func:`time_series_blueprint`.
        """
        self.stream.send_blueprint(blueprint, make_active=True, make_default=True)

    def log_scalars(
        self,
        entity: str,
        values: np.ndarray | Sequence[float],
        *,
        sequence: Mapping[str, np.ndarray | Sequence[int]] | None = None,
        sim_time: np.ndarray | Sequence[float] | None = None,
    ) -> None:
        """Logs a whole time series of ``rr.Scalars`` in one columnar call.

        Args:
            entity: Entity path, e.g. ``/metrics/loss``.
            values: Shape ``(T,)`` for one series or ``(T, K)`` for ``K`` series on one entity.
                Non-finite values are logged as they are (the viewer shows gaps).
            sequence: Sequence timelines, name -> ``T`` integers. Defaults to
                ``{"frame": arange(T)}``.
            sim_time: Optional ``T`` simulated times in seconds (timeline ``sim_time``).
        """
        vals = np.asarray(values, dtype=np.float64)
        if vals.ndim not in (1, 2):
            raise ValueError(f"values must be 1-D or 2-D, got shape {vals.shape}")
        n = vals.shape[0]
        if sequence is None:
            sequence = {"frame": np.arange(n)}
        indexes = []
        for name, seq in sequence.items():
            seq = np.asarray(seq, dtype=np.int64)
            if seq.shape != (n,):
                raise ValueError(f"timeline {name!r} has shape {seq.shape}, expected ({n},)")
            indexes.append(rr.TimeColumn(name, sequence=seq))
        if sim_time is not None:
            st = np.asarray(sim_time, dtype=np.float64)
            if st.shape != (n,):
                raise ValueError(f"sim_time has shape {st.shape}, expected ({n},)")
            indexes.append(rr.TimeColumn("sim_time", duration=st))
        self.stream.send_columns(entity, indexes=indexes, columns=rr.Scalars.columns(scalars=vals))

    def log_scalar(
        self, entity: str, value: float, *, frame: int, sim_time: float | None = None
    ) -> None:
        """Logs one scalar sample at ``frame`` (and ``sim_time`` if given), row-wise.

        Args:
            entity: Entity path.
            value: The scalar.
            frame: Value on the ``frame`` sequence timeline.
            sim_time: Optional simulated time in seconds.
        """
        rec = self.stream
        rec.set_time("frame", sequence=int(frame))
        if sim_time is not None:
            rec.set_time("sim_time", duration=float(sim_time))
        rec.log(entity, rr.Scalars(float(value)))

    def series_names(self, entity: str, names: Sequence[str]) -> None:
        """Names the series of a multi-valued scalar entity (static ``rr.SeriesLines``).

        Args:
            entity: Entity path.
            names: One name per series.
        """
        self.stream.log(entity, rr.SeriesLines(names=list(names)), static=True)

    def log_text(self, entity: str, text: str, *, media_type: str = "text/plain") -> None:
        """Logs a static text document (e.g. a run summary).

        Args:
            entity: Entity path.
            text: Document body.
            media_type: ``text/plain`` or ``text/markdown``.
        """
        self.stream.log(entity, rr.TextDocument(text, media_type=media_type), static=True)
        if entity == "/status":
            self._status_logged = True


def grid_of_time_series(name: str, views: Mapping[str, Sequence[str]]) -> rrb.Grid:
    """A grid container with one time-series view per entry.

    Args:
        name: Container name (tab title).
        views: View name -> entity paths (or entity path expressions) shown in it.

    Returns:
        The grid container.
    """
    return rrb.Grid(
        *[
            rrb.TimeSeriesView(
                name=view_name, origin="/", contents=[f"+ {p}" for p in paths]
            )
            for view_name, paths in views.items()
        ],
        name=name,
    )


def time_series_blueprint(
    views: Mapping[str, Sequence[str]] | Mapping[str, Mapping[str, Sequence[str]]],
) -> rrb.Blueprint:
    """Default blueprint made of time-series views.

    Args:
        views: Either view name -> entity paths (one grid), or tab name -> (view name -> entity
            paths) for one grid per tab.

    Returns:
        The blueprint.
    """
    values = list(views.values())
    if values and isinstance(values[0], Mapping):
        tabs = [grid_of_time_series(tab, v) for tab, v in views.items()]  # type: ignore[arg-type]
        layout: rrb.Container = rrb.Tabs(*tabs)
    else:
        layout = grid_of_time_series("time series", views)  # type: ignore[arg-type]
    return rrb.Blueprint(layout, collapse_panels=True)


def save_figure(fig, path: str) -> None:
    """Saves a matplotlib figure as a PNG at ``path`` atomically: a temporary file next to it,
    renamed into place (an interrupted save leaves the old file, or none)."""
    import tempfile

    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".png")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.chmod(tmp, 0o644)  # mkstemp makes it private; a figure is for everyone to read
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
