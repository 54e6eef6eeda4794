"""Many refinements at once, resumable: in this process, across processes, or on a Dask cluster
(``autoalign refine --batch LIST.txt``; the simulation study runs on the same engine).

* :func:`run_tasks` runs the tasks (JSON-able dicts with a unique, stable ``id``) whose ids are
  not yet in ``OUT/<records>``: one after the other (``workers=1``), on a ``ProcessPoolExecutor``
  (``workers > 1``) or on a Dask cluster (``scheduler``: its address or a ``Client``), appending
  each finished record as one JSON line (flushed and fsynced), so that an interrupted run resumes
  where it stopped. Failed tasks go to ``OUT/errors.jsonl`` and run again next time. One
  progress bar (tqdm).
* :func:`refine_many` refines many scene folders (:mod:`autoalign.jobs.refine_folder`) with the same options,
  each into ``OUT/<scene folder name>``, one record per scene in ``OUT/batch.jsonl`` (its exit
  status: 0 ok, 3 written but flagged); a scene with a mistake in its inputs (status 2) goes to
  ``OUT/errors.jsonl`` with its one-line error and runs again next time, and a scene interrupted
  by Ctrl-C is not recorded at all (the run stops; the same command again finishes it).

A task may carry ``settings``: what defines its result besides its id (a scene's ``refine``
options, a trial's views). They are recorded with it, and a run that finds a task recorded as done
with other settings is refused (:func:`check_resume`) rather than skipping it as done.

Ctrl-C: worker processes ignore it and are terminated by the parent, which then raises
``KeyboardInterrupt`` (the command exits 130); no worker outlives the run. SIGTERM to the parent
does the same (the command exits 143; :mod:`autoalign.runtime.interrupts`); where nothing handles
SIGTERM (a library user's program), the parent stops its workers first and then ends by SIGTERM
as it would have (:func:`_sigterm_unwinds`).

Why Dask (``dask.distributed``) rather than Ray: it is pure Python and pip-installable with no
compiled core, a ``LocalCluster`` starts in a second inside a test, and a cluster is just
``dask scheduler`` plus ``dask worker ADDRESS`` on any machines. The work only needs "run this
function on that dict somewhere and give me the result", which ``Client.submit`` /
``as_completed`` is.
"""

from __future__ import annotations

import gc
import json
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError
from autoalign.io.atomic_files import write_bytes_atomic
from autoalign.runtime.interrupts import STOP_SIGNALS, Interrupts, held_signals, is_command_process

Task = dict[str, Any]
TaskFn = Callable[[Task], dict[str, Any]]


class Terminated(BaseException):
    """SIGTERM in a worker process during a task: unwinds the task (its atomic writes remove their
    temporary files), then :func:`safe_task` ends the process."""


_in_task = False  # whether this worker process is running a task (see _on_sigterm)


def safe_task(task: Task, fn: TaskFn) -> dict[str, Any]:
    """Run ``fn(task)``; an exception becomes ``{"id", "error", "traceback"}`` instead of killing the run."""
    global _in_task
    _in_task = True
    try:
        return fn(task)
    except Exception as exc:  # noqa: BLE001 - reported per task, run again on resume
        return {"id": task["id"], "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    except Terminated:
        os._exit(128 + signal.SIGTERM)
    finally:
        _in_task = False


def _on_sigterm(signum: int, frame: Any) -> None:
    """A worker's SIGTERM handler (the parent stops its workers with it): a task in progress is
    unwound first (:class:`Terminated`); an idle worker just ends."""
    if _in_task:
        raise Terminated
    os._exit(128 + signum)


def init_worker(threads: int) -> None:
    """Set up a worker process: Ctrl-C ignored (the parent decides, and stops the workers itself:
    a worker that handled it would end its task as interrupted and take the next one), and its
    share of the cores (drjit defaults to all of them).

    The worker was started with SIGINT and SIGTERM blocked (:func:`~autoalign.runtime.interrupts.held_signals`),
    so a Ctrl-C pressed while it started is dropped here rather than raised in its start-up code. SIGTERM,
    with which the parent stops it, unwinds a task in progress before the process ends (:func:`_on_sigterm`);
    one that came while it started ends it as soon as it is unblocked here.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, set(STOP_SIGNALS))
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    try:
        from autoalign.runtime.backend import drjit

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


_ABSENT = object()


def _recorded_settings(rec: dict[str, Any], settings: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """The settings a record was made with, and whether they are all of them: a record made before
    records kept their ``settings`` has only those it names at its top level (a trial's views)."""
    if isinstance(rec.get("settings"), dict):
        return rec["settings"], True
    return {k: rec[k] for k in settings if k in rec}, False


def settings_changes(old: dict[str, Any], new: dict[str, Any], all_of_old: bool = True) -> str:
    """The settings that differ, as ``--name OLD, now NEW`` (``not given`` where one has none); ``""`` if none.
    With ``all_of_old`` false only the names ``old`` has are compared."""
    def norm(v: Any) -> Any:
        return v if v is _ABSENT else json.loads(json.dumps(v))  # tuples and lists alike

    def show(v: Any) -> str:
        return "not given" if v is _ABSENT or v is None else json.dumps(v) if isinstance(v, (dict, list)) else str(v)

    names = sorted(old.keys() | new.keys() if all_of_old else old.keys(), key=str)
    changes = [f"--{str(k).lstrip('-').replace('_', '-')} {show(old.get(k, _ABSENT))}, now {show(new.get(k, _ABSENT))}"
               for k in names if norm(old.get(k, _ABSENT)) != norm(new.get(k, _ABSENT))]
    return "; ".join(changes)


def check_resume(tasks: Sequence[Task], records_path: str | Path, unit: str = "task") -> None:
    """Refuse to resume ``records_path`` with tasks of other settings: a task recorded as done whose
    ``settings`` differ from its record's would be skipped as done, though it never ran with them
    (:class:`AutoalignError`, one line naming the file, the first such task, what differs and the fix)."""
    by_id = {r["id"]: r for r in read_records(records_path)}
    for t in tasks:
        rec = by_id.get(t["id"])
        if rec is None or not isinstance(t.get("settings"), dict):
            continue
        old, complete = _recorded_settings(rec, t["settings"])
        changes = settings_changes(old, t["settings"], complete)
        if changes:
            raise AutoalignError(f"{records_path}: {unit} {t['id']} was done with other options ({changes}); to "
                                 "resume give the same options, or write to another --out folder")


@dataclass
class RunSummary:
    """Counts of one :func:`run_tasks` call: tasks in all, already done before it (skipped), done
    by it, failed, and its wall time (s)."""

    total: int
    skipped: int
    done: int
    failed: int
    seconds: float


Handler = Callable[[dict[str, Any]], None]


def run_tasks(tasks: Sequence[Task], task_fn: TaskFn, out_dir: str | Path, records: str = "trials.jsonl",
              workers: int = 1, scheduler: Any = None, progress: bool = True, desc: str = "tasks",
              unit: str = "task") -> RunSummary:
    """Run every task whose id is not yet in ``out_dir/records`` (see module doc).

    A task is recorded only once ``task_fn`` has returned its record; a task that was running when
    the run was interrupted (``KeyboardInterrupt``, raised here or by ``task_fn``) is not, so the
    same call again runs exactly those. On an interrupt the worker processes are stopped before
    the exception goes on. A task whose worker died (killed, out of memory) goes to
    ``errors.jsonl``; on a Dask cluster the scheduler first runs it again elsewhere, and its record
    says how many workers died while holding it (``lost_workers``).

    Args:
        tasks: JSON-able dicts, each with a unique ``id``.
        task_fn: run per task; it must be importable by worker processes when ``workers > 1``.
        workers: processes (1 = in this process); ignored with ``scheduler``.
        scheduler: a Dask scheduler address (``tcp://host:8786``) or a ``dask.distributed.Client``.
    """
    from tqdm import tqdm

    t_start = time.perf_counter()
    out = Path(out_dir)
    records_path = out / records
    check_resume(tasks, records_path, unit)
    out.mkdir(parents=True, exist_ok=True)
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
    settings = {t["id"]: t["settings"] for t in pending if "settings" in t}

    def handle(rec: dict[str, Any]) -> None:
        if "error" in rec:
            err_writer.write(rec)
            summary.failed += 1
            bar.write(f"{unit} {rec['id']} failed: {rec['error']}")
        else:
            if rec.get("id") in settings and "settings" not in rec:
                rec = {**rec, "settings": settings[rec["id"]]}
            writer.write(rec)
            summary.done += 1
        bar.update(1)

    try:
        if scheduler is not None:
            _run_dask(pending, scheduler, handle, task_fn, desc)
        elif workers <= 1:
            for t in pending:
                Interrupts.check()  # a Ctrl-C that the previous task only remembered stops the run here
                handle(safe_task(t, task_fn))
        else:
            _run_processes(pending, task_fn, workers, handle)
    finally:
        bar.close()
        writer.close()
        err_writer.close()
        summary.seconds = time.perf_counter() - t_start
    return summary


def _run_processes(pending: list[Task], task_fn: TaskFn, workers: int, handle: Handler) -> None:
    """The tasks on ``workers`` spawned processes (:func:`init_worker`); stopped on any exception."""
    with _sigterm_unwinds():
        _run_pool(pending, task_fn, workers, handle)


def _run_pool(pending: list[Task], task_fn: TaskFn, workers: int, handle: Handler) -> None:
    """:func:`_run_processes` once SIGTERM unwinds: the pool, its workers stopped on any exception."""
    threads = max(1, (os.cpu_count() or 1) // workers)
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                             initializer=init_worker, initargs=(threads,))
    try:
        # The workers start here (on submit), with Ctrl-C and SIGTERM blocked until init_worker sets
        # its handlers; one that comes meanwhile is raised after the block, not inside the executor's own code.
        with held_signals(*STOP_SIGNALS):
            futs = {ex.submit(safe_task, t, task_fn): t for t in pending}
        for fut in as_completed(futs):
            if isinstance(fut.exception(), BrokenProcessPool):
                handle({"id": futs[fut]["id"], "error": "a worker process died (killed, or out of memory?) before "
                        "this task finished; it runs again next time"})
            else:
                handle(fut.result())
    except BaseException:
        with held_signals(*STOP_SIGNALS):  # a second Ctrl-C or SIGTERM must not cut the stopping short
            _stop_workers(ex)
        # Free the executor now, not at exit: the command ends an interrupted run with os._exit, which
        # runs no finalizers, and the resource tracker would then warn of its leaked semaphores.
        del ex
        gc.collect()  # its queues sit in reference cycles
        raise
    ex.shutdown(wait=True)


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """Within the block, a SIGTERM that would end this process at once (its default action: a library
    user's program; the command handles it itself) raises :class:`Terminated` instead, so that the
    worker processes are stopped; the process then ends by SIGTERM as it would have. Elsewhere (another
    thread, a handler in place) nothing changes."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def unwind(signum: int, frame: Any) -> None:
        raise Terminated

    signal.signal(signal.SIGTERM, unwind)
    try:
        yield
    except Terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.raise_signal(signal.SIGTERM)
        raise  # not reached: the default action ends the process
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _stop_workers(ex: ProcessPoolExecutor) -> None:
    """Terminate the executor's worker processes, wait for them, then shut it down (its manager
    thread sees the workers gone and ends; waiting for it frees its queues). ``shutdown`` alone lets
    each worker finish its task first, and ``ProcessPoolExecutor`` has no public list of its
    processes before Python 3.14's ``terminate_workers``."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(5)
        if p.is_alive():
            p.kill()
            p.join()
    ex.shutdown(wait=True, cancel_futures=True)


def _dask_client(scheduler: Any) -> tuple[Any, bool]:
    """A ``dask.distributed.Client`` for ``scheduler`` and whether it was made here (to close)."""
    try:
        from dask.distributed import Client
    except ImportError:
        raise AutoalignError("--scheduler needs dask.distributed; install it with "
                             "`pip install 'dask[distributed]'` (or autoalign[distributed])") from None
    if isinstance(scheduler, Client):
        return scheduler, False
    try:
        return Client(scheduler, timeout="20s"), True
    except (OSError, TimeoutError) as exc:
        raise AutoalignError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc}); "
                             "start one with `dask scheduler` and pass its tcp://HOST:PORT") from None


def _lost_workers(dask_scheduler: Any, key: str) -> int:
    """On the scheduler: how many workers died while ``key`` was assigned to them (``suspicious``)."""
    ts = dask_scheduler.tasks.get(key)
    return int(ts.suspicious) if ts is not None else 0


def _run_dask(pending: list[Task], scheduler: Any, handle: Handler, task_fn: TaskFn, desc: str) -> None:
    """The tasks on a Dask cluster. The scheduler reruns a task whose worker died (up to its
    ``distributed.scheduler.allowed-failures``); each result is released once handled, so that a
    later worker death cannot make the scheduler compute a finished task again."""
    from dask.distributed import KilledWorker
    from dask.distributed import as_completed as dask_completed

    client, own = _dask_client(scheduler)
    try:
        futs = {client.submit(safe_task, t, task_fn, pure=False, key=f"{desc}-{i}-{abs(hash(t['id']))}"): t
                for i, t in enumerate(pending)}
        try:
            for fut in dask_completed(list(futs)):
                task = futs.pop(fut)
                lost = client.run_on_scheduler(_lost_workers, key=fut.key)
                try:
                    rec = fut.result()
                except KilledWorker:
                    rec = {"id": task["id"], "error": f"{lost} Dask workers died while running it; it runs again "
                           "next time (is a scene too large for a worker's memory?)"}
                if lost:
                    rec["lost_workers"] = lost
                fut.release()
                handle(rec)
        except BaseException:
            client.cancel(list(futs))
            raise
    finally:
        if own:
            client.close()


# ----------------------------------------------------------------------------------------------
# autoalign refine --batch
# ----------------------------------------------------------------------------------------------

BATCH_RECORDS = "batch.jsonl"
PATH_OPTIONS = ("--init", "--model", "--models", "--instances")
"""``refine`` options whose value is a file or folder: in a batch list, relative to the list's folder."""


def read_scene_list(path: str | Path) -> list[tuple[Path, list[str]]]:
    """The scene folders of a batch list, each with its own extra ``refine`` options: one scene per
    line, its folder first, then its options as on a command line (e.g. ``--init coarse.json``);
    blank lines and ``#`` comments skipped. Every path in the list (the folder, and the values of
    :data:`PATH_OPTIONS`) is relative to the list's folder unless absolute, and must exist. The
    folders' names must differ (each scene's outputs go to ``OUT/<name>``)."""
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
            raise AutoalignError(f"{path}: line {n}: {first} is not a folder ({p}: paths in a batch list are relative "
                                 "to the list's folder); list existing scene folders, one per line")
        scenes.append((p, _list_paths(path, n, extra)))
    if not scenes:
        raise AutoalignError(f"{path}: no scene folders listed; write one scene folder per line")
    names = [p.name for p, _ in scenes]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise AutoalignError(f"{path}: scene folders named alike ({', '.join(twice)}) would share an output folder; "
                             "rename them or run them in separate batches")
    return scenes


def _list_paths(path: Path, n: int, options: list[str]) -> list[str]:
    """A list line's options with the values of :data:`PATH_OPTIONS` made relative to the list's
    folder (as its scene folders are), each checked to exist."""
    out = list(options)
    for k, word in enumerate(out[:-1]):
        if word not in PATH_OPTIONS:
            continue
        value = Path(out[k + 1])
        resolved = value if value.is_absolute() else path.parent / value
        if not resolved.exists():
            raise AutoalignError(f"{path}: line {n}: {word} {out[k + 1]}: not found ({resolved}: paths in a batch list "
                                 "are relative to the list's folder); fix the path")
        out[k + 1] = str(resolved)
    return out


def refine_task(task: Task) -> dict[str, Any]:
    """One scene of a batch, in this process: :func:`~autoalign.jobs.refine_folder.refine_folder` of
    ``task["scene"]`` with its options (``task["args"]``, as after ``autoalign refine SCENE``) into
    ``task["out"]``. Its record: the status (0 ok, 3 written but flagged), seconds and its last
    warnings; a mistake in the scene's inputs gives ``{"id", "error"}`` instead (not done, so that
    it runs again once fixed); Ctrl-C raises ``KeyboardInterrupt`` (not done; :func:`run_tasks` stops)."""
    from autoalign.jobs.job import RunLog, one_line
    from autoalign.jobs.refine_arguments import scene_job
    from autoalign.jobs.refine_folder import refine_folder

    log = RunLog()
    t0 = time.perf_counter()
    try:
        with _interrupts_of_a_task(), log.python_warnings():
            outcome = refine_folder(scene_job(task["scene"], task["args"], task["out"]), log)
    except AutoalignError as exc:
        return {"id": task["id"], "error": f"autoalign: error: {one_line(str(exc))}"}
    messages = [f"autoalign: warning: {m}" for m in [*log.warnings, *outcome.notes]]
    if Interrupts.seen:  # after the outputs were written: they are complete, the run stops before the next task
        messages.append(f"autoalign: {Interrupts.name()} came after the outputs were written; they are complete")
    return {"id": task["id"], "scene": task["scene"], "out": task["out"], "status": int(outcome.status),
            "seconds": time.perf_counter() - t0, "messages": messages[-5:]}


@contextmanager
def _interrupts_of_a_task() -> Iterator[None]:
    """Ctrl-C during a task run in this process's main thread, as in the ``autoalign`` command
    (:class:`~autoalign.runtime.interrupts.Interrupts`): raised as ``KeyboardInterrupt`` (also when
    a library turned it into another exception) until the task's outputs are written, only
    remembered after that; SIGTERM the same where the command handles it (a library user's
    program keeps its own). Elsewhere (a worker, which ignores Ctrl-C; another thread) nothing changes."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        yield
        return
    ours = signal.getsignal(signal.SIGTERM) in (Interrupts.handler, Interrupts.remember)
    previous = Interrupts.install(STOP_SIGNALS if ours else (signal.SIGINT,))
    try:
        if Interrupts.seen and is_command_process():  # pressed while the command's modules loaded
            raise KeyboardInterrupt
        Interrupts.seen = False
        try:
            yield
        except BaseException as exc:
            if Interrupts.seen and not isinstance(exc, KeyboardInterrupt):
                raise KeyboardInterrupt from exc
            raise
    finally:
        Interrupts.restore(previous)


def refine_many(scenes: Sequence[str | Path], args: Sequence[str], out_dir: str | Path, workers: int = 1,
                scheduler: Any = None, progress: bool = True, extra: dict[str, list[str]] | None = None) -> RunSummary:
    """``autoalign refine`` with the options ``args`` (e.g. ``["--models", "models/"]``) on every
    scene folder, each into ``out_dir/<its name>`` (``extra[str(scene)]``: that scene's own
    options); resumable (``out_dir/batch.jsonl``)."""
    return run_tasks(refine_tasks(scenes, args, out_dir, extra), refine_task, out_dir, BATCH_RECORDS, workers,
                     scheduler, progress, "refine", "scene")


def refine_tasks(scenes: Sequence[str | Path], args: Sequence[str], out_dir: str | Path,
                 extra: dict[str, list[str]] | None = None) -> list[Task]:
    """The tasks of :func:`refine_many` (one per scene, its id the scene folder's absolute path, its
    settings its options: :func:`refine_settings`)."""
    extra = extra or {}
    tasks = []
    for s in scenes:
        argv = [*args, *extra.get(str(s), [])]
        tasks.append({"id": str(Path(s).absolute()), "scene": str(Path(s)), "args": argv,
                      "out": str(Path(out_dir) / Path(s).name), "settings": refine_settings(argv)})
    return tasks


def refine_settings(argv: Sequence[str]) -> dict[str, Any]:
    """What a scene's ``refine`` options (``argv``) make of it, for :func:`check_resume`: every option
    of :class:`~autoalign.jobs.job.FolderJob` with its value (defaults included, so that ``--photos
    auto`` and no ``--photos`` are alike), files and folders as absolute paths. Options it cannot
    read (the scene then fails with their error) are kept as given."""
    from dataclasses import asdict

    from autoalign.jobs.refine_arguments import scene_job

    try:
        job = asdict(scene_job(".", argv, "."))
    except AutoalignError:
        return {"args": list(argv)}
    paths = {o.lstrip("-") for o in PATH_OPTIONS}
    return {k: str(Path(v).absolute()) if k in paths and v is not None else v
            for k, v in job.items() if k not in ("scene", "out")}
