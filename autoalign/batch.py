"""Many refinements at once, resumable: in this process, across processes, or on a Dask cluster
(``autoalign refine --batch LIST.txt``; the simulation study runs on the same engine).

* :func:`run_tasks` runs the tasks (JSON-able dicts with a unique, stable ``id``) whose ids are
  not yet in ``OUT/<records>``: one after the other (``workers=1``), on a ``ProcessPoolExecutor``
  (``workers > 1``) or on a Dask cluster (``scheduler``: its address or a ``Client``), appending
  each finished record as one JSON line (flushed and fsynced), so that an interrupted run resumes
  where it stopped. Failed tasks go to ``OUT/errors.jsonl`` and run again next time. One
  progress bar (tqdm).
* :func:`refine_many` runs ``autoalign refine`` on many scene folders with the same options,
  each into ``OUT/<scene folder name>``, one record per scene in ``OUT/batch.jsonl`` (its exit
  status: 0 ok, 3 written but flagged); a scene with a mistake in its inputs (status 2) goes to
  ``OUT/errors.jsonl`` with its one-line error and runs again next time.

Why Dask (``dask.distributed``) rather than Ray: it is pure Python and pip-installable with no
compiled core, a ``LocalCluster`` starts in a second inside a test, and a cluster is just
``dask scheduler`` plus ``dask worker ADDRESS`` on any machines. The work only needs "run this
function on that dict somewhere and give me the result", which ``Client.submit`` /
``as_completed`` is.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from autoalign.atomic_files import write_bytes_atomic
from autoalign.errors import AutoalignError

Task = dict[str, Any]
TaskFn = Callable[[Task], dict[str, Any]]


def safe_task(task: Task, fn: TaskFn) -> dict[str, Any]:
    """Run ``fn(task)``; an exception becomes ``{"id", "error", "traceback"}`` instead of killing the run."""
    try:
        return fn(task)
    except Exception as exc:  # noqa: BLE001 - reported per task, run again on resume
        return {"id": task["id"], "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


def init_worker(threads: int) -> None:
    """Give each worker process its share of the cores (drjit defaults to all of them)."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    try:
        from autoalign.backend import drjit

        drjit().set_thread_count(max(1, threads))
    except Exception:  # pragma: no cover - reported by the first task instead
        pass


def read_records(path: str | Path) -> list[dict[str, Any]]:
    """Complete JSON lines of a records file (a half-written last line is ignored)."""
    path = Path(path)
    out = []
    if not path.is_file():
        return out
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict) and "id" in rec:
                out.append(rec)
    return out


def repair_jsonl(path: str | Path) -> int:
    """Drop incomplete or invalid lines (a kill during a write) by rewriting the file atomically.

    Returns the number of lines dropped. A file that is already clean is not touched.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    raw = path.read_bytes()
    good, bad = [], 0
    for line in raw.split(b"\n"):
        if not line.strip():
            continue
        try:
            json.loads(line)
            good.append(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            bad += 1
    if bad == 0 and (not raw or raw.endswith(b"\n")):
        return 0
    write_bytes_atomic(path, b"".join(x + b"\n" for x in good))
    return bad


class RecordWriter:
    """Appends one JSON line per finished task and fsyncs it (crash-safe resume)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f = open(self.path, "a")

    def write(self, rec: dict[str, Any]) -> None:
        self._f.write(json.dumps(rec, separators=(",", ":")) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.close()


@dataclass
class RunSummary:
    """Counts of one :func:`run_tasks` call: tasks in all, already done before it (skipped), done
    by it, failed, and its wall time (s)."""

    total: int
    skipped: int
    done: int
    failed: int
    seconds: float


def run_tasks(tasks: Sequence[Task], task_fn: TaskFn, out_dir: str | Path, records: str = "trials.jsonl",
              workers: int = 1, scheduler: Any = None, progress: bool = True, desc: str = "tasks",
              unit: str = "task") -> RunSummary:
    """Run every task whose id is not yet in ``out_dir/records`` (see module doc).

    Args:
        tasks: JSON-able dicts, each with a unique ``id``.
        task_fn: run per task; it must be importable by worker processes when ``workers > 1``.
        workers: processes (1 = in this process); ignored with ``scheduler``.
        scheduler: a Dask scheduler address (``tcp://host:8786``) or a ``dask.distributed.Client``.
    """
    from tqdm import tqdm

    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    records_path = out / records
    repair_jsonl(records_path)
    done_ids = {r["id"] for r in read_records(records_path)}
    pending = [t for t in tasks if t["id"] not in done_ids]
    summary = RunSummary(len(tasks), len(tasks) - len(pending), 0, 0, 0.0)
    if not pending:
        summary.seconds = time.perf_counter() - t_start
        return summary
    writer = RecordWriter(records_path)
    err_writer = RecordWriter(out / "errors.jsonl")
    bar = tqdm(total=len(pending), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)

    def handle(rec: dict[str, Any]) -> None:
        if "error" in rec:
            err_writer.write(rec)
            summary.failed += 1
            bar.write(f"{unit} {rec['id']} failed: {rec['error']}")
        else:
            writer.write(rec)
            summary.done += 1
        bar.update(1)

    try:
        if scheduler is not None:
            _run_dask(pending, scheduler, handle, task_fn, desc)
        elif workers <= 1:
            for t in pending:
                handle(safe_task(t, task_fn))
        else:
            threads = max(1, (os.cpu_count() or 1) // workers)
            ex = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                                     initializer=init_worker, initargs=(threads,))
            try:
                futs = [ex.submit(safe_task, t, task_fn) for t in pending]
                for fut in as_completed(futs):
                    handle(fut.result())
            except BaseException:
                ex.shutdown(wait=False, cancel_futures=True)
                raise
            ex.shutdown(wait=True)
    finally:
        bar.close()
        writer.close()
        err_writer.close()
        summary.seconds = time.perf_counter() - t_start
    return summary


def _run_dask(pending: list[Task], scheduler: Any, handle: Callable[[dict[str, Any]], None], task_fn: TaskFn,
              desc: str) -> None:
    try:
        from dask.distributed import Client
        from dask.distributed import as_completed as dask_completed
    except ImportError:
        raise AutoalignError("--scheduler needs dask.distributed; install it with "
                             "`pip install 'dask[distributed]'` (or autoalign[distributed])") from None
    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler, timeout="20s") if own else scheduler
    except (OSError, TimeoutError) as exc:
        raise AutoalignError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc}); "
                             "start one with `dask scheduler` and pass its tcp://HOST:PORT") from None
    try:
        futs = [client.submit(safe_task, t, task_fn, pure=False, key=f"{desc}-{i}-{abs(hash(t['id']))}")
                for i, t in enumerate(pending)]
        try:
            for fut in dask_completed(futs):
                handle(fut.result())
        except BaseException:
            client.cancel(futs)
            raise
    finally:
        if own:
            client.close()


# ----------------------------------------------------------------------------------------------
# autoalign refine --batch
# ----------------------------------------------------------------------------------------------

BATCH_RECORDS = "batch.jsonl"


def read_scene_list(path: str | Path) -> list[tuple[Path, list[str]]]:
    """The scene folders of a batch list, each with its own extra ``refine`` options: one scene per
    line, its folder first (relative to the list's folder unless absolute), then its options as on
    a command line (e.g. ``--init coarse.json``); blank lines and ``#`` comments skipped. Each
    folder must exist and their names must differ (each scene's outputs go to ``OUT/<name>``)."""
    import shlex

    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise AutoalignError(f"{path}: cannot read the batch list ({exc}); give a text file with one scene folder "
                             "per line") from None
    scenes = []
    for n, line in enumerate(lines, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            first, *extra = shlex.split(line)
        except ValueError as exc:
            raise AutoalignError(f"{path}: line {n}: {exc}; quote paths with spaces") from None
        p = Path(first) if Path(first).is_absolute() else path.parent / first
        if not p.is_dir():
            raise AutoalignError(f"{path}: line {n}: {first} is not a folder; list existing scene folders, "
                                 "one per line")
        scenes.append((p, extra))
    if not scenes:
        raise AutoalignError(f"{path}: no scene folders listed; write one scene folder per line")
    names = [p.name for p, _ in scenes]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise AutoalignError(f"{path}: scene folders named alike ({', '.join(twice)}) would share an output folder; "
                             "rename them or run them in separate batches")
    return scenes


def refine_task(task: Task) -> dict[str, Any]:
    """One scene of a batch: ``autoalign refine SCENE ARGS --out OUT --quiet`` in this process."""
    import contextlib
    import io

    from autoalign.cli.main import main

    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err):
        status = main(["refine", task["scene"], *task["args"], "--out", task["out"], "--quiet"])
    messages = err.getvalue().strip().splitlines()
    if status == 2:  # a mistake in this scene's inputs: not done, so that it runs again once fixed
        return {"id": task["id"], "error": messages[-1] if messages else "exit status 2"}
    return {"id": task["id"], "scene": task["scene"], "out": task["out"], "status": int(status),
            "seconds": time.perf_counter() - t0, "messages": messages[-5:]}


def refine_many(scenes: Sequence[str | Path], args: Sequence[str], out_dir: str | Path, workers: int = 1,
                scheduler: Any = None, progress: bool = True, extra: dict[str, list[str]] | None = None) -> RunSummary:
    """``autoalign refine`` with the options ``args`` (e.g. ``["--models", "models/"]``) on every
    scene folder, each into ``out_dir/<its name>`` (``extra[str(scene)]``: that scene's own
    options); resumable (``out_dir/batch.jsonl``)."""
    extra = extra or {}
    tasks = [{"id": str(Path(s).absolute()), "scene": str(Path(s)), "args": [*args, *extra.get(str(s), [])],
              "out": str(Path(out_dir) / Path(s).name)} for s in scenes]
    return run_tasks(tasks, refine_task, out_dir, BATCH_RECORDS, workers, scheduler, progress, "refine", "scene")
