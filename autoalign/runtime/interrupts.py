"""Ctrl-C that cannot be lost, for the ``autoalign`` command (standard library only).

SIGINT raises ``KeyboardInterrupt`` as usual *and* is remembered: libraries may swallow the
exception (trimesh wraps failed optional imports with ``except BaseException``), and a run
interrupted there went on and wrote its outputs with exit status 0. :meth:`Interrupts.check`
raises again wherever the run may stop safely (progress updates, before writing).

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


class Interrupts:
    """Whether Ctrl-C was pressed during this run, and the handlers that record it."""

    seen = False

    @classmethod
    def remember(cls, signum: int, frame: Any) -> None:
        """SIGINT handler while modules load: only remember it."""
        cls.seen = True

    @classmethod
    def handler(cls, signum: int, frame: Any) -> None:
        """SIGINT handler while the command runs: remember it and raise ``KeyboardInterrupt``."""
        cls.seen = True
        raise KeyboardInterrupt

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
        if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) == cls.handler:
            signal.signal(signal.SIGINT, cls.remember)

    @classmethod
    @contextmanager
    def deferred(cls) -> Iterator[None]:
        """Within the command, Ctrl-C during the block is remembered and raised after it (:func:`held_signals`).

        C++ extension modules run Python code while they initialise (drjit imports its submodules
        from its module init); an exception raised there ends in ``std::terminate``: the process
        aborted or crashed in about one run in ten interrupted during drjit's import. Outside the
        command (another SIGINT handler installed), and in any thread but the main one (only it
        receives signals; ``autoalign label`` refines on a worker thread), this does nothing.
        """
        if signal.getsignal(signal.SIGINT) != cls.handler:
            yield
            return
        with held_signals(signal.SIGINT):
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
