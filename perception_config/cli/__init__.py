"""The `perception-config` command: one subcommand per job, heavy imports deferred to the job."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import warnings

from ..util.allocator import keep_freed_memory
from ..util.stop_signals import StopRequested
from . import (
    bag,
    bench,
    blocks,
    calibrate,
    cell_sim,
    episodes,
    estimate,
    evaluate,
    fit_score,
    launch,
    replay_check,
    show,
    study,
    synth,
    train,
)
from .train import agent_params

__all__ = ["agent_params", "build_parser", "main"]

# The commands in the order of `perception-config --help`; each module adds its parser (and
# imports what its job needs only when it runs).
COMMANDS = (synth, bag, show, blocks, bench, calibrate, train, evaluate, study, launch, estimate, episodes,
            replay_check, cell_sim, fit_score)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="perception-config", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def _show_data_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Warnings about the user's data (a repaired annotation) as one line naming the file; other
    warnings keep Python's format (they are for developers)."""
    if issubclass(category, UserWarning) and category.__module__.startswith("perception_config"):
        print(f"warning: {message}", file=sys.stderr if file is None else file)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    warnings.showwarning = _show_data_warning
    keep_freed_memory()  # the operators' arrays reuse freed memory (util/allocator.py)
    try:
        return int(args.func(args) or 0)
    except (FileNotFoundError, FileExistsError, ValueError, KeyError) as exc:
        # Bad input: one clear line naming what was wrong, no traceback.
        print(f"perception-config {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        # A job stopped by a signal (StopRequested names it, e.g. train; otherwise 130): exit 128 +
        # the signal number, the shell's convention (130 SIGINT, 143 SIGTERM, 129 SIGHUP). One more
        # Ctrl-C while the StopRequested was on its way here raises over it: it still names the stop.
        _ignore_further_signals()
        cause: BaseException | None = exc
        while cause is not None and not isinstance(cause, StopRequested):
            cause = cause.__context__
        exc = cause if cause is not None else exc
        code = exc.exit_code if isinstance(exc, StopRequested) else 130
        _say_quietly(f"perception-config {args.command}: {str(exc) or 'interrupted'}")
        return code


def _ignore_further_signals() -> None:
    """The work is saved and the process is leaving: a further stop signal (one more Ctrl-C)
    must not turn the exit code into death by SIGINT. Ignored ones stay ignored through the
    interpreter's shutdown (handlers set in Python are reset to the default there)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)


def _say_quietly(text: str) -> None:
    """A last line on stderr; after SIGHUP the terminal may be gone: then stdout and stderr go
    to /dev/null, so flushing them at exit cannot turn the exit code into 120."""
    try:
        print(text, file=sys.stderr, flush=True)
        sys.stdout.flush()
    except OSError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.dup2(devnull, sys.stderr.fileno())
