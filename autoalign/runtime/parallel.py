"""Independent pieces of work (the instances of a scene) run side by side on the cores drjit was given.

drjit renders on a pool of threads, one per core unless it is told otherwise (``AUTOALIGN_THREADS``,
or a batch worker's share of the cores: :mod:`autoalign.batch`). A refinement's renders are small
(a band of a few thousand pixels per view) and Python works between them, so a pool of two keeps the
second core busy with little but waiting. Instances refined side by side, each rendering on its
share of the pool, keep both busy with work (``docs/results.md``, "Speed of a whole command").
The results are those of the instances refined one after the other: each piece of work must
depend on nothing the others change.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from typing import TypeVar

from autoalign.runtime.backend import device, drjit

_here = threading.local()

Item = TypeVar("Item")
Result = TypeVar("Result")


def side_by_side(work: Callable[[Item], Result], items: Sequence[Item]) -> list[Result]:
    """``[work(item) for item in items]``, run on as many threads at once as drjit's pool has (at most
    one per item), drjit's pool shared out among them while they run. Called from one of those
    threads, it runs the items one after the other. Once an item fails, no more are started; when the
    items under way have ended, the error of the first in their order that failed is raised. Ctrl-C
    waits for the items under way too (each stops at its next progress report)."""
    dr = drjit()
    cores = int(dr.thread_count())
    # on the GPU one after the other: drjit's CUDA backend refuses a variable made on one thread and
    # used on another, and one GPU runs the kernels either way
    workers = min(len(items), cores) if device() == "cpu" else 1
    if workers <= 1 or getattr(_here, "inside", False):
        return [work(item) for item in items]

    def one(item: Item) -> Result:
        _here.inside = True  # the pool is shared out once, by the outermost call
        return work(item)

    dr.set_thread_count(max(1, cores // workers))
    pool = ThreadPoolExecutor(workers, thread_name_prefix="autoalign")
    try:
        futures = [pool.submit(one, item) for item in items]
        wait(futures, return_when=FIRST_EXCEPTION)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # after an error (or Ctrl-C): start nothing more
        dr.set_thread_count(cores)
    return [f.result() for f in futures]  # the first item's error in their order, if any failed
