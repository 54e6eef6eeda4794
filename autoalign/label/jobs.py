"""The one slow job of a labelling session (placing, refining or exporting) on a thread of its
own, its progress and its error where the page can read them."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace

from autoalign.errors import AutoalignError
from autoalign.label.records import JobState
from autoalign.label.state import SessionState

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``, as :func:`~autoalign.engine.refine.refine` reports it."""


class JobRunner:
    """Runs one job at a time; :attr:`job` (changed under the state's lock, each change counted as a
    revision that is not saved) is what the page shows of it."""

    def __init__(self, state: SessionState) -> None:
        self.state = state
        self.job = JobState()

    def start(self, kind: str, instance: int | None, work: Callable[[Progress], None]) -> bool:
        """Run ``work(progress)`` on a thread of its own unless a job is running (then ``False``)."""
        with self.state.lock:
            if self.job.running:
                return False
            self.job = JobState(kind, instance, True, "starting", 0, 0, None, time.perf_counter(), 0.0,
                                self.job.number + 1)
            self.state.changed(save=False)
        threading.Thread(target=self._run, args=(work,), name=f"autoalign-{kind}", daemon=True).start()
        return True

    def _progress(self, stage: str, done: int, total: int) -> None:
        with self.state.lock:
            self.job = replace(self.job, stage=stage, done=done, total=total,
                               seconds=time.perf_counter() - self.job.started)
            self.state.changed(save=False)

    def _run(self, work: Callable[[Progress], None]) -> None:
        error = None
        try:
            work(self._progress)
        except AutoalignError as exc:
            error = str(exc)
        except Exception as exc:  # a bug: the page says so instead of the job hanging forever
            error = f"internal error ({type(exc).__name__}: {exc}); please report it"
        with self.state.lock:
            self.job = replace(self.job, running=False, stage="failed" if error else "done", error=error,
                               seconds=time.perf_counter() - self.job.started)
            self.state.changed(save=False)
