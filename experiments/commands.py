"""The ``autoalign`` command run in a child process, as a user runs it, for studies and benchmarks
(process start included in the wall time)."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import dataclass

from autoalign.jobs.job import EXIT_FLAGGED


def autoalign_command(*args: str) -> list[str]:
    """The command line of ``autoalign ARGS`` with this interpreter."""
    return [sys.executable, "-m", "autoalign.cli.main", *args]


@dataclass(frozen=True)
class CommandRun:
    """A finished ``autoalign`` child process: its command line, wall time (s), exit status and stderr."""

    command: list[str]
    wall_s: float
    returncode: int
    stderr: str

    @property
    def ok(self) -> bool:
        """Whether it wrote its outputs (exit 0, or :data:`EXIT_FLAGGED`: written, a verdict flags a pose)."""
        return self.returncode in (0, EXIT_FLAGGED)

    def check(self) -> CommandRun:
        """Itself when :attr:`ok`; else a RuntimeError with the command and the end of its stderr."""
        if not self.ok:
            raise RuntimeError(f"{' '.join(self.command)} failed ({self.returncode}): {self.stderr[-2000:]}")
        return self


def run_autoalign(*args: str) -> CommandRun:
    """Run ``autoalign ARGS`` in a child process (output captured) and time it."""
    cmd = autoalign_command(*args)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    return CommandRun(cmd, time.perf_counter() - t0, proc.returncode, proc.stderr)
