"""What every benchmark of ``python -m benchmarks`` shares: the machine's name, markdown tables,
and writing ``benchmarks/results/<name>.md`` / ``.json`` atomically (a temporary file renamed into
place, so an interrupted run never leaves half a table behind).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import tempfile
from collections.abc import Sequence
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")


def machine() -> str:
    """One line naming the machine the numbers come from (CPU model, cores, memory, Python)."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    memory = ""
    try:
        with open("/proc/meminfo") as fh:
            kib = int(fh.readline().split()[1])
        memory = f", {kib / 2**20:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{memory}, Python {platform.python_version()}, Warp CPU kernels (one thread)"


def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: floats to ``digits`` significant digits, None as an em dash."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if value == 0.0:
            return "0"
        if 1e-3 <= abs(value) < 1e5:
            return f"{value:.{digits}g}"
        return f"{value:.{max(digits - 1, 1)}e}"
    return str(value)


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    """A markdown table (lines) of ``rows`` under ``header``; cells through :func:`fmt`."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(fmt(c) for c in row) + " |")
    return lines


def atomic_write(path: str, text: str) -> None:
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)  # mkstemp makes it private; results are for everyone to read
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        try:
            return _jsonable(value.item())
        except (TypeError, ValueError):
            pass
    return value


def write(prefix: str, title: str, lines: Sequence[str], data: dict[str, Any] | None = None,
          echo: bool = True) -> None:
    """Writes ``<prefix>.md`` (``# title``, the machine, then ``lines``) and, with ``data``,
    ``<prefix>.json``; prints the markdown when ``echo``."""
    text = "\n".join([f"# {title}", "", f"Machine: {machine()}.", "", *lines, ""])
    atomic_write(prefix + ".md", text)
    if data is not None:
        atomic_write(prefix + ".json", json.dumps(_jsonable(data), indent=1) + "\n")
    if echo:
        print(text, flush=True)


def save_figure(fig, path: str) -> None:
    """Saves a matplotlib figure atomically (PNG): :func:`sim.logging.save_figure`."""
    from sim.logging import save_figure as save

    save(fig, path)


def add_size_arguments(parser: argparse.ArgumentParser, scenes: Sequence[str], out_name: str,
                       quick_help: str, full_help: str) -> None:
    """The options every per-scene benchmark shares: ``--quick`` / ``--full`` (one of them),
    ``--scenes``, ``--steps`` and ``--out`` (default ``results/<out_name>``)."""
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help=quick_help)
    size.add_argument("--full", action="store_true", help=full_help)
    parser.add_argument("--scenes", default=",".join(scenes), help="comma-separated scenes (default all)")
    parser.add_argument("--steps", type=int, default=None, help="override the steps per run")
    parser.add_argument("--out", default=os.path.join(RESULTS, out_name), help="output prefix")


def chosen(parser: argparse.ArgumentParser, args: argparse.Namespace, configs: dict[str, dict],
           scenes: Sequence[str]) -> tuple[dict, list[str]]:
    """(a copy of the configuration ``--quick`` / ``--full`` / neither picks, with ``--steps``
    applied; the ``--scenes`` asked for); a usage error for a bad value."""
    config = dict(configs["quick" if args.quick else "full" if args.full else "default"])
    if args.steps is not None:
        if args.steps < 1:
            parser.error("--steps must be >= 1")
        config["steps"] = args.steps
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    bad = [s for s in names if s not in scenes]
    if bad or not names:
        parser.error(f"--scenes: unknown {bad}; choose from {', '.join(scenes)}")
    return config, names
