"""Ctrl-C (and SIGTERM) that cannot be lost, for the ``autoalign`` command (standard library only).

SIGINT raises ``KeyboardInterrupt`` as usual *and* is remembered: libraries may swallow the
exception (trimesh wraps failed optional imports with ``except BaseException``), and a run
interrupted there went on and wrote its outputs with exit status 0. :meth:`Interrupts.check`
raises again wherever the run may stop safely (progress updates, before writing).

SIGTERM (what Slurm, Docker and ``timeout`` send) is handled the same way in the command: it
unwinds the run like Ctrl-C, so that worker processes are stopped before the command ends (its
default action ended the command at once and left the workers running), and the command exits
143 (128 + SIGTERM) instead of 130 (:meth:`Interrupts.exit_status`).

While the command's own modules are still being imported, a SIGINT is only remembered
(:meth:`Interrupts.remember`, installed by ``autoalign/__init__.py`` in the command's process):
raised there it would end in a traceback from the import machinery. ``main`` then exits 130
before doing anything. Only the interpreter's own start-up, before any autoalign code runs (some
tens of milliseconds), is out of reach.
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals that stop a run of the command: Ctrl-C, and SIGTERM from a job scheduler or ``kill``."""


class Interrupts:
    """Whether Ctrl-C (or SIGTERM) came during this run, which one, and the handlers that record it."""

    seen = False
    signum: int = signal.SIGINT

    @classmethod
    def remember(cls, signum: int, frame: Any) -> None:
        """Handler while modules load (and after the outputs are written): only remember it."""
        cls.seen, cls.signum = True, signum

    @classmethod
    def handler(cls, signum: int, frame: Any) -> None:
        """Handler while the command runs: remember it and raise ``KeyboardInterrupt`` (SIGTERM too,
        so that everything that cleans up after Ctrl-C, stopping worker processes included, runs).

        Interrupted inside the import machinery's own code, it only remembers: importlib releases
        its module locks in weakref callbacks, where Python prints an exception with its traceback
        and drops it. :meth:`check` raises it at the run's next safe point."""
        cls.seen, cls.signum = True, signum
        if frame is not None and frame.f_code.co_filename.startswith("<frozen importlib"):
            return
        raise KeyboardInterrupt

    @classmethod
    def reset(cls) -> None:
        """Forget an earlier run's signal (a new run of ``main`` in the same process)."""
        cls.seen, cls.signum = False, signal.SIGINT

    @classmethod
    def exit_status(cls) -> int:
        """The status of a run stopped by the signal seen: 130 after Ctrl-C, 143 after SIGTERM."""
        return 128 + int(cls.signum)

    @classmethod
    def name(cls) -> str:
        """How messages name the signal seen."""
        return "Ctrl-C" if cls.signum == signal.SIGINT else signal.Signals(cls.signum).name

    @classmethod
    def install(cls, signums: tuple[int, ...] = STOP_SIGNALS) -> dict[int, Any]:
        """Make ``signums`` raise (:meth:`handler`); returns the handlers they had, for :meth:`restore`."""
        return {s: signal.signal(s, cls.handler) for s in signums}

    @staticmethod
    def restore(previous: dict[int, Any]) -> None:
        """Put back the handlers :meth:`install` replaced."""
        for s, h in previous.items():
            signal.signal(s, h)

    @classmethod
    def check(cls) -> None:
        """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed during this run."""
        if cls.seen:
            raise KeyboardInterrupt

    @classmethod
    def outputs_written(cls) -> None:
        """The command's outputs are written and complete: from here to the command's end, Ctrl-C is
        only remembered, so that the command reports and exits with its own status (``main`` then
        says the outputs are complete) instead of calling finished work interrupted."""
        if threading.current_thread() is not threading.main_thread():
            return
        for s in STOP_SIGNALS:
            if signal.getsignal(s) == cls.handler:
                signal.signal(s, cls.remember)

    @classmethod
    @contextmanager
    def deferred(cls) -> Iterator[None]:
        """Within the command, Ctrl-C (or SIGTERM) during the block is remembered and raised after it
        (:func:`held_signals`).

        C++ extension modules run Python code while they initialise (drjit imports its submodules
        from its module init); an exception raised there ends in ``std::terminate``: the process
        aborted or crashed in about one run in ten interrupted during drjit's import. Outside the
        command (another SIGINT handler installed), and in any thread but the main one (only it
        receives signals; ``autoalign label`` refines on a worker thread), this does nothing.
        """
        ours = tuple(s for s in STOP_SIGNALS if signal.getsignal(s) == cls.handler)
        if signal.SIGINT not in ours:
            yield
            return
        with held_signals(*ours):
            yield


@contextmanager
def held_signals(*signums: int) -> Iterator[None]:
    """The signals ``signums`` that arrive during the block are delivered when it ends, to the
    handlers that were in place (a ``KeyboardInterrupt`` is raised after the block, a SIGTERM with
    the default action ends the process after it); ignored ones stay ignored.

    For work that must not be cut in two: renaming a set of output files into place, importing an
    extension module, starting worker processes. The signals are also blocked in this thread, so
    that processes started in the block begin with them blocked (a blocked signal mask is inherited
    through fork and exec: a worker can then set its own handlers before any arrives). Only the main
    thread runs Python's signal handlers; in any other thread this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = [s for s in signums if signal.getsignal(s) is not signal.SIG_IGN]
    arrived: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: arrived.append(signum)) for s in held}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, set(held))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for s, handler in previous.items():
            signal.signal(s, handler)
    for s in dict.fromkeys(arrived):
        signal.raise_signal(s)


def preload(*modules: str) -> None:
    """Import ``modules`` (extension modules the command will need) with Ctrl-C deferred."""
    with Interrupts.deferred():
        for name in modules:
            importlib.import_module(name)


def is_command_process() -> bool:
    """Whether this process was started as the ``autoalign`` command (console script or
    ``python -m autoalign.cli.main``), not as a library user's program."""
    argv = list(getattr(sys, "orig_argv", sys.argv))
    by_module = "-m" in argv[1:] and argv[argv.index("-m", 1) + 1:][:1] == ["autoalign.cli.main"]
    return by_module or os.path.basename(sys.argv[0]) == "autoalign"
