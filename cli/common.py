"""What every subcommand of ``autoalign`` shares: the parser class whose mistakes are one line
(:class:`UsageError`), argument types, warnings (:func:`warn`, kept for the run's report),
the progress bar and the exit statuses. The subcommand modules import this one, and
:mod:`autoalign.cli.main` imports them, never the other way round.

Standard library and :mod:`autoalign.errors` only at import, so that ``autoalign --help`` stays fast.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from autoalign.jobs.job import EXIT_FLAGGED, RunLog, one_line  # noqa: F401 - EXIT_FLAGGED for the subcommands
from autoalign.jobs.refine_arguments import nonnegative_int
from autoalign.runtime.interrupts import Interrupts

PROG = "autoalign"
EXIT_OK = 0
EXIT_USAGE = 2
"""A mistake in the command or its input files (one line on stderr, no output files)."""
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """A command-line syntax mistake (unknown option, missing argument, bad value)."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors become :class:`UsageError` (one line) instead of usage + exit."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see '{self.prog} --help')")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=30, width=min(100, max(60, _terminal_width())))


def _terminal_width() -> int:
    try:
        return os.get_terminal_size().columns
    except OSError:
        return 100


def index_list(text: str) -> list[int]:
    """An argparse type: comma-separated whole numbers of 0 or more (``0,3``), at least one."""
    parts = [p.strip() for p in text.split(",")]
    if not any(parts):
        raise argparse.ArgumentTypeError(f"{text!r}: give whole numbers separated by commas, such as 0,3")
    return [nonnegative_int(p) for p in parts]


def error(message: str) -> None:
    """Print ``autoalign: error: MESSAGE`` (one line) on stderr."""
    print(f"{PROG}: error: {one_line(message)}", file=sys.stderr, flush=True)


def _print_warning(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr, flush=True)


LOG = RunLog(show=_print_warning)
"""The warnings of the current run (also written to refine.json); ``main`` clears it."""
WARNINGS = LOG.warnings


def warn(message: str) -> None:
    """Print ``autoalign: warning: MESSAGE`` (one line) on stderr and keep it in :data:`LOG`."""
    LOG.warning(message)


class ProgressBar:
    """``progress(stage, done, total)`` callback drawing one tqdm bar on stderr."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: Any = None
        self.stage: str | None = None
        self.last = -1

    def start(self, desc: str) -> None:
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=None, desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True,
                            unit="it", bar_format="{desc}: {elapsed}")
            self.stage = desc

    def __call__(self, stage: str, done: int, total: int) -> None:
        Interrupts.check()
        if not self.enabled:
            return
        if self.bar is None:
            self.start(stage)
        if stage != self.stage or done < self.last or self.bar.total != total:
            self.bar.bar_format = None
            self.bar.set_description(stage, refresh=False)
            self.bar.reset(total=total)
            self.stage, self.last = stage, 0
        self.bar.update(max(0, done - self.bar.n))
        self.last = done

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
