"""Same numbers before and after a change, on the studies: the refine study, ``real_scenes`` and
``uncertainty_calibration`` run by two checkouts of the code, study by study in turn, and their
rows compared instance by instance.

Per study: the largest difference of each instance's error against the truth (mm, degrees; a
pose that moved by d changes its error by at most d, so equal errors bound nothing away but
unequal ones show a move), of its largest sigma where the study reports one, whether every
verdict and every reason is the same, and the whole study's wall time. ``bench_scene``'s poses
are compared pose by pose in :mod:`autoalign.experiments.benchmarks.same_numbers`.

``python -m autoalign.experiments.benchmarks.same_numbers_studies --before /tmp/before_repo [--after .] [--keep DIR]``
(``--before``: a copy of the older code, e.g. ``git archive REV | tar -x -C /tmp/before_repo``).
Results: ``experiments/results/same_numbers_studies.md``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from autoalign.experiments import RESULTS
from autoalign.experiments.benchmarks.same_numbers import largest_difference
from autoalign.experiments.result_files import write_results


@dataclass(frozen=True)
class Study:
    """One study's command (module and arguments, without ``--out``), the file its rows are in
    (under ``--out``), and the fields that name an instance."""

    name: str
    module: str
    args: tuple[str, ...]
    rows_file: str
    key: tuple[str, ...]


STUDIES = (
    Study("refine study", "refine_study", ("--scenes", "10", "--search-scenes", "5", "--seeds", "init,none,corrupt"),
          "results.json", ("scene", "seed")),
    Study("real_scenes", "real_scenes", ("--seeds", "init,none"), "real_scenes.json", ("scene", "seed", "obj_id")),
    Study("uncertainty_calibration", "uncertainty_calibration", ("--scenes", "10"), "uncertainty_calibration.json",
          ("scene", "obj")),
)


def run_study(checkout: Path, study: Study, out: Path) -> tuple[float, dict[tuple, dict[str, Any]]]:
    """The wall time (s) of the study run by ``checkout``'s code, and its rows by instance."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", f"autoalign.experiments.studies.{study.module}", *study.args,
                        "--out", str(out)], cwd=checkout, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{checkout}: {study.module} failed ({p.returncode}): {p.stderr[-1500:]}")
    data = json.loads((out / study.rows_file).read_text())
    rows = data["rows"] if isinstance(data, dict) else data
    return wall, {tuple(r[k] for k in study.key): r for r in rows}


def _largest(a: dict[tuple, dict[str, Any]], b: dict[tuple, dict[str, Any]], field: str) -> float | None:
    """The largest absolute difference of ``field`` over the instances (None where no row has it)."""
    pairs = [(x.get(field), b[k].get(field)) for k, x in a.items()]
    pairs = [(x, y) for x, y in pairs if x is not None and y is not None]
    return max((largest_difference(x, y) for x, y in pairs), default=None)


def compare_rows(before: dict[tuple, dict[str, Any]], after: dict[tuple, dict[str, Any]]) -> dict[str, Any]:
    """The differences between two runs' rows (the same instances in both)."""
    if set(before) != set(after):
        raise RuntimeError(f"the runs have different instances: {sorted(set(before) ^ set(after))[:5]}")
    differ = [k for k in before if before[k].get("verdict") != after[k].get("verdict")]
    reworded = [k for k in before if before[k].get("reasons") != after[k].get("reasons")]
    sigma = next((f for f in ("largest_sigma_mm", "sigma_mm") if any(f in r for r in before.values())), None)
    return {"instances": len(before), "err_mm": _largest(before, after, "err_mm"),
            "err_deg": _largest(before, after, "err_deg"),
            "sigma_mm": _largest(before, after, sigma) if sigma else None,
            "has_verdicts": any("verdict" in r for r in before.values()),
            "verdicts_differ": [list(k) for k in differ], "reasons_differ": [list(k) for k in reworded]}


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.2g}"


def table(rows: list[dict[str, Any]], before: Path, after: Path) -> list[str]:
    """The results as markdown lines."""
    out = ["# Same numbers before and after: the studies", "",
           f"`{before}` against `{after}`, study by study in turn on one machine: the largest difference of "
           "any instance's error against the truth and of its largest sigma, verdicts and reasons compared as "
           "text (`-`: the study has none), and the whole study's wall time.", "",
           "| study | instances | max d err mm | max d err deg | max d sigma mm | verdicts | reasons | "
           "wall before s | wall after s | ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        verdicts = "-" if not r["has_verdicts"] else ("same" if not r["verdicts_differ"] else
                                                       f"{len(r['verdicts_differ'])} differ")
        reasons = "-" if not r["has_verdicts"] else ("same" if not r["reasons_differ"] else
                                                      f"{len(r['reasons_differ'])} differ")
        out.append(f"| {r['study']} | {r['instances']} | {_num(r['err_mm'])} | {_num(r['err_deg'])} | "
                   f"{_num(r['sigma_mm'])} | {verdicts} | {reasons} | {r['wall_before_s']:.0f} | "
                   f"{r['wall_after_s']:.0f} | {r['wall_after_s'] / r['wall_before_s']:.2f} |")
    for r in rows:
        for what in ("verdicts_differ", "reasons_differ"):
            if r[what]:
                out.append(f"\n{r['study']}, {what.replace('_', ' ')}: {r[what]}")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="a checkout of the older code")
    ap.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[2], help="default: this checkout")
    ap.add_argument("--studies", default=",".join(s.module for s in STUDIES), help="comma-separated modules")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--keep", type=Path, default=None, help="keep each run's results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    chosen = [s for s in STUDIES if s.module in args.studies.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        runs = (args.keep or Path(tmp)).resolve()
        for s in chosen:
            (wall_b, got_b), (wall_a, got_a) = (run_study(c.resolve(), s, runs / f"{tag}_{s.module}")
                                               for tag, c in (("before", args.before), ("after", args.after)))
            rows.append({"study": s.name, **compare_rows(got_b, got_a), "wall_before_s": wall_b, "wall_after_s": wall_a})
            print(f"{s.name}: err {rows[-1]['err_mm']} mm, {wall_b:.0f} s -> {wall_a:.0f} s", flush=True)
    write_results("same_numbers_studies", {"before": str(args.before), "after": str(args.after), "rows": rows},
                  table(rows, args.before, args.after), args.out)


if __name__ == "__main__":
    main()
