"""Speed before and after a change: whole commands run by two checkouts of the code, alternating
run by run, so that a busy machine slows both alike; wall time (median of the repeats) and peak
memory (``/usr/bin/time``'s maximum resident set) of each, and their ratios.

The cases: ``autoalign refine --help`` (start-up); the import and initialisation a refine needs
before its first render (its modules and mitsuba's LLVM backend); the bundled example seeded and
unseeded; ``bench_scene``'s scenes of 1, 4 and 8 objects x 40 views from 10 mm / 15 deg off
(:func:`~autoalign.experiments.benchmarks.bench_scene.make_bench_scene`), with the uncertainty.
Each command runs once per checkout before the timed repeats (its first-run wall is reported too):
drjit's kernel cache and the mesh cache (:mod:`autoalign.geometry.mesh_cache`, a new folder for
this run) are then warm, as from a user's second command on. So is the code's bytecode: pip compiles
an installed package's modules, but a checkout run with ``PYTHONDONTWRITEBYTECODE`` set (as on the
development machines) would compile about 75 of them again in every command, 0.3-0.4 s each time;
the children write theirs under a prefix in the run's folder instead. The label page's click is
timed by ``bench_label_page``.

``python -m autoalign.experiments.benchmarks.bench_speed --before /tmp/before_repo [--after .] [--repeats 3]``
(``--before``: e.g. ``git archive REV | tar -x -C /tmp/before_repo``). Results: ``experiments/results/bench_speed.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from autoalign.experiments import RESULTS
from autoalign.experiments.commands import CommandRun
from autoalign.experiments.result_files import write_results

EXAMPLE = Path(__file__).resolve().parents[2] / "autoalign" / "data" / "example"
INIT_CODE = ("import autoalign.cli.main, autoalign.jobs.refine_folder, autoalign.engine.refine, autoalign.io.evidence, "
             "autoalign.jobs.report; from autoalign.runtime.backend import mitsuba; mitsuba()")


@dataclass
class Case:
    """One command: its arguments after ``python``, and what it took in each checkout."""

    name: str
    argv: list[str]
    out: Path | None = None
    first: dict[str, float] = field(default_factory=dict)
    walls: dict[str, list[float]] = field(default_factory=lambda: {"before": [], "after": []})
    peaks_mb: dict[str, list[float]] = field(default_factory=lambda: {"before": [], "after": []})


def cases(work: Path) -> list[Case]:
    """The commands timed (the bench scenes are written into ``work``)."""
    ex = EXAMPLE
    refine = ["-m", "autoalign.cli.main", "refine"]
    out = [Case("refine --help (start-up)", [*refine, "--help"]),
           Case("a refine's imports and LLVM start", ["-c", INIT_CODE]),
           Case("example seeded", [*refine, str(ex / "scene"), "--model", str(ex / "model.ply"), "--init",
                                   str(ex / "init_gt.json"), "--quiet"], work / "out"),
           Case("example unseeded", [*refine, str(ex / "scene"), "--model", str(ex / "model.ply"), "--quiet"],
                work / "out")]
    from autoalign.experiments.benchmarks.bench_scene import make_bench_scene  # open3d: bench_device runs without

    for n in (1, 4, 8):
        root = work / f"bench_{n}"
        make_bench_scene(root, n)
        out.append(Case(f"bench_scene {n} object(s) x 40 views", [*refine, str(root / "scene"), "--models",
                                                                  str(root / "models"), "--init",
                                                                  str(root / "init_gt.json"), "--quiet"],
                        work / "out"))
    return out


def run_once(checkout: Path, case: Case, env: dict[str, str]) -> tuple[float, float]:
    """Wall time (s) and peak resident memory (MB) of ``case`` run by ``checkout``'s code. The peak is
    ``/usr/bin/time``'s: a child forked by this process (which holds the bench scenes' libraries)
    would count this process's memory in its own ``ru_maxrss``."""
    argv = list(case.argv)
    if case.out is not None:
        shutil.rmtree(case.out, ignore_errors=True)
        argv += ["--out", str(case.out)]
    with tempfile.NamedTemporaryFile("r", suffix=".time") as stats:
        t0 = time.perf_counter()
        p = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", stats.name, sys.executable, *argv], cwd=checkout,
                           env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        CommandRun([sys.executable, *argv], wall, p.returncode, p.stderr).check()
        peak_kb = float(stats.read().strip().splitlines()[-1])
    return wall, peak_kb / 1024.0


def measure(before: Path, after: Path, work: Path, repeats: int) -> list[Case]:
    """Every case: once per checkout untimed, then ``repeats`` times each, the checkouts alternating."""
    env = {**{k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"},
           "AUTOALIGN_CACHE_DIR": str(work / "mesh_cache"), "PYTHONPYCACHEPREFIX": str(work / "bytecode")}
    checkouts = {"before": before, "after": after}
    todo = cases(work)
    for case in todo:
        for tag, checkout in checkouts.items():
            case.first[tag] = run_once(checkout, case, env)[0]
        for _ in range(repeats):
            for tag, checkout in checkouts.items():
                wall, peak = run_once(checkout, case, env)
                case.walls[tag].append(wall)
                case.peaks_mb[tag].append(peak)
        b, a = (statistics.median(case.walls[t]) for t in ("before", "after"))
        print(f"{case.name}: {b:.2f} s -> {a:.2f} s ({a / b:.2f})", flush=True)
    return todo


def speed_table(payload: dict, node: str) -> list[str]:
    """The results' table from their JSON ``payload`` (``rows`` as :func:`main` writes them): per command
    the first runs, the median walls and their ratio, and the median (smallest-largest) of each run's
    peak resident memory: one run's peak can stray by a few percent (a 988 MB run among 941-949 MB ones)."""
    med = statistics.median
    table = ["# Speed before and after", "",
             f"`{payload['before']}` against `{payload['after']}` on {node} ({os.cpu_count()} cores): whole commands, "
             f"median wall of {payload['repeats']} runs each after one untimed run (its wall is the first-run column), "
             "the checkouts alternating run by run; peak memory: the median (smallest-largest) over the runs of "
             "the process's largest resident set.", "",
             "| command | first run before s | first run after s | wall before s | wall after s | ratio | "
             "peak before MB | peak after MB |", "|---|---|---|---|---|---|---|---|"]
    for r in payload["rows"]:
        b, a = med(r["walls"]["before"]), med(r["walls"]["after"])
        peaks = {t: f"{med(r['peaks_mb'][t]):.0f} ({min(r['peaks_mb'][t]):.0f}-{max(r['peaks_mb'][t]):.0f})"
                 for t in ("before", "after")}
        table.append(f"| {r['case']} | {r['first']['before']:.2f} | {r['first']['after']:.2f} | {b:.2f} | {a:.2f} | "
                     f"{a / b:.2f} | {peaks['before']} | {peaks['after']} |")
    return table


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", type=Path, help="a checkout of the older code (needed unless --table-from)")
    ap.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[2], help="default: this checkout")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--table-from", type=Path, help="write the table again from this results JSON, measuring nothing")
    args = ap.parse_args(argv)
    if args.table_from is not None:
        payload = json.loads(args.table_from.read_text())
    elif args.before is None:
        ap.error("--before DIR: a checkout of the older code to compare with")
    else:
        with tempfile.TemporaryDirectory() as tmp:
            done = measure(args.before.resolve(), args.after.resolve(), Path(tmp), args.repeats)
        payload = {"before": str(args.before), "after": str(args.after), "repeats": args.repeats,
                   "node": platform.node(),
                   "rows": [{"case": c.name, "first": c.first, "walls": c.walls, "peaks_mb": c.peaks_mb} for c in done]}
    write_results("bench_speed", payload, speed_table(payload, payload.get("node", "the machine measured")), args.out)


if __name__ == "__main__":
    main()
