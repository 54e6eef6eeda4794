"""``autoalign simulate``: the paper's simulated convergence study, and our methods on the same trials.

    autoalign simulate [--models procedural44 | BOP_MODELS_DIR] [--trials N] [--views 40]
                       [--method autoalign|paper|adam|autoalign-seeded|all] [--workers K] [--seed S]
                       [--scheduler ADDRESS] [--study main,views,noise,sensitivity|all] --out DIR

Writes ``DIR/trials.jsonl`` (one line per finished trial; rerunning the same command resumes),
``DIR/trials.csv``, ``DIR/results.md`` and ``DIR/plots/*.png``. Also runnable as
``python -m autoalign.experiments.studies.simulate``. The CLI registers :func:`add_simulate_parser` in
``autoalign``'s main parser; :func:`run_simulate` returns the exit code.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError

_METHOD_CHOICES = ("paper", "autoalign", "adam", "autoalign-seeded", "init", "all")


def add_simulate_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``simulate`` sub-command to an ``argparse`` sub-parsers object and return its parser."""
    p = subparsers.add_parser(
        "simulate", help="run the simulated convergence study (paper protocol) and write CSV/markdown/plots",
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(p)
    p.set_defaults(func=run_simulate)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="output folder (resumes the trials already in it)")
    p.add_argument("--models", default="procedural44",
                   help="'procedural44' (the 44 generated models) or a BOP models folder (default: procedural44)")
    p.add_argument("--model-ids", default=None, help="comma-separated model ids to use (default: all)")
    p.add_argument("--max-models", type=int, default=None, help="use only the first N models")
    p.add_argument("--trials", type=int, default=10, help="trials per model in the main condition (default 10)")
    p.add_argument("--views", type=int, default=40, help="views per trial in the main condition (default 40)")
    p.add_argument("--method", default="all",
                   help="paper, autoalign, adam, autoalign-seeded, init, or all (= the first four); "
                        "comma-separated for several (default all)")
    p.add_argument("--study", default="main",
                   help="parts to run: main, views (5/10/20/40 views), noise (eroded/dilated/shifted masks), "
                        "sensitivity (alternative readings of the paper), comma-separated, or all (default main)")
    p.add_argument("--sweep-trials", type=int, default=1, help="trials per model in the non-main parts (default 1)")
    p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1: in this process)")
    p.add_argument("--scheduler", default=None, help="run on a Dask cluster at this address (tcp://HOST:PORT)")
    p.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    p.add_argument("--sigma-mm", type=float, default=None,
                   help="initial position noise per axis in mm (default 100: 'variance of 10cm' as sigma)")
    p.add_argument("--camera-order", choices=("cycle", "random", "best"), default="cycle",
                   help="paper method: camera per iteration (default cycle)")
    p.add_argument("--rot-axis", choices=("x", "z"), default="x",
                   help="paper method: rotation axis parallel to the camera's x (figure) or z (text) axis")
    p.add_argument("--discretisation", default="geo2", help="paper method: move set geo2 (default), geo4 or geo1.4")
    p.add_argument("--max-iters", type=int, default=150, help="paper method: iteration budget (default 150)")
    p.add_argument("--width", type=int, default=640, help="image width in px (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height in px (default 480)")
    p.add_argument("--focal", type=float, default=600.0, help="focal length in px (default 600)")
    p.add_argument("--report-only", action="store_true", help="only rewrite CSV, markdown and plots from trials.jsonl")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _int_list(text: str, opt: str) -> tuple[int, ...]:
    try:
        vals = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise AutoalignError(f"{opt} {text!r}: expected comma-separated integers, e.g. {opt} 1,2,5") from None
    if not vals:
        raise AutoalignError(f"{opt} {text!r}: no ids given; e.g. {opt} 1,2,5")
    return vals


def config_from_args(args: argparse.Namespace) -> Any:
    """A validated :class:`~autoalign.experiments.studies.runner.StudyConfig` from parsed arguments."""
    from autoalign.experiments.studies.paper_method import DISCRETISATIONS, PaperOptions
    from autoalign.experiments.studies.protocol import PAPER_SIGMA_MM, ImageSetup
    from autoalign.experiments.studies.runner import (
        ALL_METHODS,
        PARTS,
        StudyConfig,
        model_ids,
        resolve_models,
    )

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise AutoalignError(f"--out {out}: is a file; pass a folder (it is created if missing)")
    for opt, val, lo in (("--trials", args.trials, 0), ("--views", args.views, 1), ("--workers", args.workers, 1),
                         ("--sweep-trials", args.sweep_trials, 0), ("--max-iters", args.max_iters, 1),
                         ("--width", args.width, 16), ("--height", args.height, 16)):
        if val < lo:
            raise AutoalignError(f"{opt} {val}: must be at least {lo}")
    if args.focal <= 0:
        raise AutoalignError(f"--focal {args.focal}: must be positive (pixels)")
    if args.sigma_mm is not None and args.sigma_mm < 0:
        raise AutoalignError(f"--sigma-mm {args.sigma_mm}: must be >= 0 (mm)")
    if args.discretisation not in DISCRETISATIONS:
        raise AutoalignError(f"--discretisation {args.discretisation}: choose one of {', '.join(DISCRETISATIONS)}")
    methods = [m.strip() for m in args.method.split(",") if m.strip()]
    bad = [m for m in methods if m not in _METHOD_CHOICES]
    if bad or not methods:
        raise AutoalignError(f"--method {args.method}: unknown {', '.join(bad) or 'empty'}; choose from "
                             f"{', '.join(_METHOD_CHOICES)} (comma-separated)")
    if "all" in methods:
        methods = list(ALL_METHODS) + [m for m in methods if m not in ALL_METHODS and m != "all"]
    parts = [x.strip() for x in args.study.split(",") if x.strip()]
    if parts == ["all"]:
        parts = list(PARTS)
    badp = [x for x in parts if x not in PARTS]
    if badp or not parts:
        raise AutoalignError(f"--study {args.study}: unknown {', '.join(badp) or 'empty'}; choose from "
                             f"{', '.join(PARTS)} or all")
    models = resolve_models(args.models)
    ids = model_ids(models)
    if args.model_ids:
        want = _int_list(args.model_ids, "--model-ids")
        missing = [i for i in want if i not in ids]
        if missing:
            raise AutoalignError(f"--model-ids: {missing} not in {args.models} (ids {ids[0]}..{ids[-1]}); "
                                 "pass ids of existing models")
        ids = want
    if args.max_models is not None:
        if args.max_models < 1:
            raise AutoalignError(f"--max-models {args.max_models}: must be at least 1")
        ids = ids[: args.max_models]
    setup = ImageSetup(width=args.width, height=args.height, focal=args.focal)
    paper = PaperOptions(rot_axis=args.rot_axis, discretisation=args.discretisation, camera_order=args.camera_order,
                         max_iters=args.max_iters)
    return StudyConfig(models=models, model_ids=tuple(ids), trials=args.trials, views=args.views,
                       methods=tuple(methods), seed=args.seed, parts=tuple(parts), sweep_trials=args.sweep_trials,
                       sigma_mm=PAPER_SIGMA_MM if args.sigma_mm is None else float(args.sigma_mm),
                       paper=paper, setup=setup)


def run_simulate(args: argparse.Namespace) -> int:
    """Run (or resume) the study and write the reports. Returns the exit code (1 if trials failed)."""
    from autoalign.experiments.studies.report import write_reports
    from autoalign.experiments.studies.runner import run_study

    out = Path(args.out)
    if args.report_only:
        if not (out / "trials.jsonl").is_file():
            raise AutoalignError(f"--out {out}: no trials.jsonl to report on; run the study first (without --report-only)")
        paths = write_reports(out)
        print(f"wrote {', '.join(str(p) for p in paths.values())}")
        return 0
    cfg = config_from_args(args)
    t0 = time.perf_counter()
    try:
        s = run_study(cfg, out, workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress)
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished trials are in {out / 'trials.jsonl'}: rerun the same command to resume",
              file=sys.stderr)
        try:
            write_reports(out)
        except Exception:  # noqa: BLE001 - the trials are safe; the report can be redone with --report-only
            pass
        return 130
    paths = write_reports(out)
    print(f"{s.done} trials run, {s.skipped} already done, {s.failed} failed ({time.perf_counter() - t0:.1f} s); "
          f"results: {paths['markdown']}, {paths['csv']}, plots in {out / 'plots'}")
    if s.failed:
        print(f"see {out / 'errors.jsonl'}; rerun to retry the failed trials", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point (``python -m autoalign.experiments.studies.simulate``)."""
    parser = argparse.ArgumentParser(prog="autoalign")
    sub = parser.add_subparsers(dest="command", required=True)
    add_simulate_parser(sub)
    args = parser.parse_args(["simulate", *(sys.argv[1:] if argv is None else argv)])
    try:
        return run_simulate(args)
    except AutoalignError as exc:
        print(f"autoalign simulate: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
