"""Scene CLI.

Usage::

    python -m scenes --list
    python -m scenes NAME --out PATH.rrd [--precision P] [--seed S where the scene draws at random]
                          [scene options: --steps N for simulations; --iters N --lr LR
                           --max-derivative M for the optimisation scenes]
    python -m scenes NAME --help

``tunnelsim`` is the same command. ``--out`` takes a regular file or a new path (a folder, device
or FIFO is refused; a symbolic link is followed: the file it points to is replaced). Only a
successful run replaces ``PATH.rrd``, atomically. Bad input caught while a simulation scene is
built leaves nothing behind; a run that fails or is interrupted after that (Ctrl-C, SIGTERM, an
error) keeps the frames recorded so far in ``PATH.partial.rrd``, a complete, readable recording
whose ``/status`` says where it stopped, and leaves ``PATH.rrd`` as it was. It shows a tqdm
progress bar on stderr when stderr is a terminal, and ends by printing exactly one line of JSON
(the scene's summary plus ``wall_time_s`` and ``out``) to stdout. Everything else a run prints
(Warp's start-up banner, kernel compilation notes) is diverted to stderr, so stdout is
machine-readable.

Exit codes: 0 success; 2 usage error (unknown scene, bad option values, an ``--out`` that is not a
regular file or a new path in an existing folder); 1 the scene failed (traceback on stderr); 130
interrupted (SIGINT); 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path

from scenes import interrupts
from scenes.registry import describe, jsonable, load_scene, positive_int, scene_names

PROG = "tunnelsim" if Path(sys.argv[0]).name == "tunnelsim" else "python -m scenes"


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("tunnelsim")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def _top_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Run a tunnelsim scene headless and write a rerun .rrd recording.",
        epilog=f"scenes: {', '.join(scene_names())}. Use '{PROG} NAME --help' for a scene's options.",
    )
    parser.add_argument("--list", action="store_true", help="list the scenes and exit")
    parser.add_argument("--version", action="version", version=f"tunnelsim {version()}")
    return parser


def _scene_parser(name: str, module) -> argparse.ArgumentParser:
    """Common options (design.md "Scene CLI") plus the scene's own."""
    parser = argparse.ArgumentParser(prog=f"{PROG} {name}", description=getattr(module, "DESCRIPTION", None))
    parser.add_argument("--out", required=True, type=Path,
                        help="output rerun recording (.rrd): a regular file or a new path; a failed or "
                             "interrupted run writes NAME.partial.rrd instead")
    if getattr(module, "USES_SEED", False):  # only where something is random
        parser.add_argument("--seed", type=int, default=0, help=module.USES_SEED + " (default 0)")
    # only what the scene can honour is offered: every scene steps in float64 today (the float32
    # root solver and CCD are measured by `python -m benchmarks`, not offered as a scene setting)
    precisions = tuple(getattr(module, "PRECISIONS", ("float64",)))
    parser.add_argument("--precision", choices=precisions, default=precisions[0],
                        help=f"floating-point precision (this scene: {', '.join(precisions)}; default {precisions[0]})")
    supports_steps = getattr(module, "SUPPORTS_STEPS", False)
    if supports_steps:
        from scenes.sim_common import DEFAULT_STEPS
    parser.add_argument("--steps", type=positive_int, default=None,
                        help=f"simulation steps (>= 1; default {DEFAULT_STEPS})" if supports_steps else argparse.SUPPRESS)
    module.add_arguments(parser)
    return parser


def _check_scene_options(parser: argparse.ArgumentParser, name: str, module, args: argparse.Namespace) -> None:
    """Rejects options the scene cannot honour, with a clear message (exit code 2)."""
    if args.steps is not None and not getattr(module, "SUPPORTS_STEPS", False):
        hint = " (an optimisation scene: use --iters)" if hasattr(args, "iters") else ""
        parser.error(f"--steps does not apply to scene {name!r}{hint}")
    if hasattr(args, "ccd_precision"):
        from scenes.sim_common import check_ccd_arguments

        check_ccd_arguments(parser, args)
    if hasattr(args, "integrator"):
        from scenes.sim_common import integrator_options

        try:
            integrator_options(args)
        except ValueError as exc:
            parser.error(str(exc))
    if hasattr(args, "methods") and hasattr(module, "METHODS"):
        from scenes.optim import parse_methods

        try:
            parse_methods(args.methods, module.METHODS)
        except ValueError as exc:
            parser.error(str(exc))
    check = getattr(module, "check_arguments", None)
    problem = check(args) if check is not None else None
    if problem:
        parser.error(problem)


@contextlib.contextmanager
def _stdout_to_stderr() -> Iterator[None]:
    """Diverts file descriptor 1 (and ``sys.stdout``) to stderr for the duration of the block."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _what_was_written(log, out: Path) -> str:
    """Names the file that really holds the frames of a failed run (the logger's ``written``)."""
    untouched = f"{out} is untouched" if out.exists() else f"no {out} written"
    if log is not None and log.written == log.path:  # interrupted after the recording was finished
        return f"the recording is complete in {out}"
    if log is not None and log.written is not None:
        return f"the frames recorded so far are in {log.written} (its /status says where it stopped); {untouched}"
    return f"no recording kept; {untouched}"


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point.

    Args:
        argv: Arguments without the program name (default ``sys.argv[1:]``).

    Returns:
        Process exit code.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    if not argv or argv[0].startswith("-"):
        args, rest = top.parse_known_args(argv)
        if args.list and not rest:
            for name in scene_names():
                try:
                    desc = describe(name)
                except Exception as exc:  # a broken scene must not hide the others
                    desc = f"(failed to import: {exc})"
                print(f"{name}\t{desc}")
            return 0
        top.error(f"give a scene name first, or --list. Available scenes: {', '.join(scene_names())}")

    name, rest = argv[0], argv[1:]
    if name not in scene_names():
        top.error(f"unknown scene {name!r}. Available scenes: {', '.join(scene_names())}")
    module = load_scene(name)
    parser = _scene_parser(name, module)
    args = parser.parse_args(rest)
    _check_scene_options(parser, name, module, args)
    out: Path = args.out

    from sim.logging import RerunLogger

    try:
        log = RerunLogger(out, recording_name=name, seed=getattr(args, "seed", 0), name="--out",
                          # simulation scenes switch it on once their input is validated
                          keep_partial=not getattr(module, "SUPPORTS_STEPS", False))
    except (ValueError, FileNotFoundError) as exc:
        parser.error(str(exc))
    start = time.perf_counter()
    try:
        with interrupts.handled(), _stdout_to_stderr():
            with log:
                summary = module.run(args, log)
                summary = {**summary, "wall_time_s": round(time.perf_counter() - start, 3), "out": str(out)}
                text = json.dumps(jsonable(summary), allow_nan=False)
                log.log_text("/summary", text)
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, interrupts.Terminated)
        print(f"{'terminated' if terminated else 'interrupted'}; {_what_was_written(log, out)}", file=sys.stderr)
        return 143 if terminated else 130
    except Exception as exc:
        from scenes.sim_common import SimulationDiverged

        if isinstance(exc, SimulationDiverged):  # a setting to change, not a bug: no traceback
            print(f"error: {exc}", file=sys.stderr)
        else:
            traceback.print_exc()
        print(f"{PROG} {name}: failed; {_what_was_written(log, out)}", file=sys.stderr)
        return 1
    print(text, flush=True)
    return 0


def console() -> None:
    """The ``tunnelsim`` console command."""
    sys.exit(main())


if __name__ == "__main__":
    sys.exit(main())
