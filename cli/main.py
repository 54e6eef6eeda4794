"""The ``autoalign`` command line: ``autoalign refine`` (and ``autoalign simulate`` when available);
the other subcommands register from their own modules. ``refine`` parses its arguments, calls
:func:`autoalign.jobs.refine_folder.refine_folder` (or :func:`autoalign.batch.refine_many`) and prints.

Start-up is kept fast: only the standard library and autoalign modules that need nothing more
(:mod:`autoalign.cli.common`, :mod:`autoalign.jobs.job`, :mod:`autoalign.errors`, ...) load
here; numpy, OpenCV, trimesh and the rendering backend (mitsuba/drjit) load inside the command,
after the arguments are parsed. Nothing on this path imports torch or jax.

Exit status: 0 success; 2 a usage or input mistake (one line ``autoalign: error: ...`` on stderr,
no output files); 3 outputs written but a pose is in doubt (its verdict, or an instance's, is
check or failed); 130 interrupted; anything else is a bug (Python prints a traceback).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from autoalign import __version__
from autoalign.cli.common import (
    EXIT_FLAGGED,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    LOG,
    PROG,
    WARNINGS,
    HelpFormatter,
    Parser,
    ProgressBar,
    UsageError,
    error,
    warn,
)
from autoalign.errors import AutoalignError
from autoalign.io.out_folder import write_outputs  # noqa: F401 - where the tests and scripts found it
from autoalign.jobs.job import (
    OUTPUT_FILES,  # noqa: F401 - the tests read it here
    FolderOutcome,
)
from autoalign.jobs.refine_arguments import add_refine_arguments, job_of, shared_argv
from autoalign.jobs.refine_folder import refine_folder
from autoalign.runtime.interrupts import STOP_SIGNALS, Interrupts, is_command_process

# ------------------------------------------------------------------------------------------
# Argument parsing
# ------------------------------------------------------------------------------------------

_MAIN_DESCRIPTION = """\
Label the 6-DoF pose of a known object from calibrated multi-view masks: the object mesh is
moved until its silhouettes match the masks in every view (BOP format, millimetres, OpenCV
pinhole cameras: cam_K and pixel coordinates put the centre of the top-left pixel at 0,0)."""

_REFINE_DESCRIPTION = """\
Find the pose of the object whose silhouettes best match the masks of one instance in a BOP
scene folder, starting from a coarse pose (--init), a click on the object (--click) or, with
neither, from the visual hull of the masks and a search over orientations."""

_REFINE_EPILOG = """\
input scene (SCENE_DIR):
  scene_camera.json   per image id: cam_K (9 numbers, pixels), cam_R_w2c (9, row-major) and
                      cam_t_w2c (3, mm): x_cam = R_w2c x_world + t_w2c
  mask_visib/{im_id:06d}_{instance:06d}.png
                      the object's mask in each image (white = object); all the same size.
                      Images without a mask file are skipped, and empty masks are treated as
                      missing (both listed in refine.json). Any non-zero pixel is the object
                      (0/255, 0/1 and colour masks all work; one kind per scene).

outputs (written into OUT_DIR, replacing files of the same name; if the run fails none is written):
  scene_gt.json  BOP ground truth: for every image of scene_camera.json a list with one entry
                 {"obj_id": K, "cam_R_m2c": 9 numbers (row-major), "cam_t_m2c": 3 numbers (mm)}
  refine.json    the world-from-model pose ("pose": T_wm 4x4, R 9, t 3 mm; world = the frame of
                 scene_camera.json), the seed, per-view IoU before/after and robust weights
                 (mean 1; low = the view's mask disagrees with the others) with their image ids,
                 iterations, renders, timings (s), every hypothesis tried (stage, loss, mean IoU,
                 poses), "ambiguous" and "runner_up" (pose, loss, rotation_deg and translation_mm
                 from the winner), "turn_gap" (how much better the pose fits than its turns about
                 weakly observed axes; near 0: nearly symmetric), with depth "turn_rise" and
                 "turn_rise_axis" (how much the whole fit rises turned 10-20 deg about that model
                 axis; under 0.1: nearly symmetric), the verdict (ok, check or failed) and its reasons, the
                 uncertainty (sigma along/about the model axes, weakly observed directions,
                 covariance), the options, the version, skipped image ids, empty masks,
                 the pixel convention of cam_K and warnings
  overlay.png    up to 12 views (always the worst-fitting one), zoomed on the object: the target
                 mask in grey, the silhouette outline before (red) and after (green) refinement,
                 with image id and IoU before -> after

several objects (--models MODELS_DIR):
  every instance is refined; instance N is mask_visib/{im_id:06d}_{N:06d}.png, and its object comes
  from --instances {"instances": {"N": obj_id, ...}} or else the scene's scene_gt.json (entry N of
  every image). In each view the pixels that other instances' masks claim (and its own does not)
  are ignored for it: it may be hidden there. --init gives entry N of a coarse scene_gt.json.
  Outputs: scene_gt.json with every instance in every image (in instance order), refine.json with
  a record per instance (pose, per-view IoU and weights, verdict ok/check/failed and its reasons),
  overlay.png with every instance in its own colour over the photos (rgb/) and its verdict.

examples:
  autoalign refine scenes/000002 --models models/ --out labels/000002 --init coarse/scene_gt.json
  autoalign refine scenes/000001 --model models/obj_000001.ply --out labels/000001 --init coarse/scene_gt.json
  autoalign refine scenes/000001 --model models/obj_000001.ply --out labels/000001 --click 0:412,233
  autoalign refine scenes/000001 --model models/obj_000001.ply --out labels/000001 --json --quiet

exit status: 0 success, 2 a mistake in the command or the input files (one line on stderr),
3 outputs written but the verdict on a pose is check or failed (reasons on stderr), 130 interrupted."""


def add_refine_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign refine`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "refine", help="refine the pose of an object from multi-view masks (writes scene_gt.json, refine.json, overlay.png)",
        description=_REFINE_DESCRIPTION, epilog=_REFINE_EPILOG, formatter_class=HelpFormatter)
    add_refine_arguments(p)
    p.set_defaults(func=run_refine)
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``autoalign`` parser with its subcommands (``simulate`` only if its module imports)."""
    parser = Parser(prog=PROG, description=_MAIN_DESCRIPTION, formatter_class=HelpFormatter,
                     epilog="Run 'autoalign COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands", parser_class=Parser)
    add_refine_parser(sub)
    from autoalign.cli.check import add_check_parser
    from autoalign.cli.export import add_export_parser
    from autoalign.cli.label import add_label_parser
    from autoalign.cli.recon import add_recon_parser

    add_recon_parser(sub)
    add_check_parser(sub)
    add_export_parser(sub)
    add_label_parser(sub)
    try:
        # by its full name, which sys.modules answers first (a test puts a stand-in there)
        simulate = importlib.import_module("autoalign.experiments.studies.simulate")
    except ImportError:
        simulate = None
    if simulate is not None and hasattr(simulate, "add_simulate_parser"):
        simulate.add_simulate_parser(sub)
    return parser


# ------------------------------------------------------------------------------------------
# Entry point
# ------------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 usage/input error, 130 interrupted)."""
    import threading

    # Only the main thread may handle signals; a process that ignores Ctrl-C (a batch worker, whose
    # parent stops it; nohup) keeps ignoring it.
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return _main(argv)
    previous = Interrupts.install()  # Ctrl-C and SIGTERM both unwind the run (workers stopped), see interrupts.py
    if Interrupts.seen and is_command_process():  # pressed while the command's modules loaded
        Interrupts.restore(previous)
        print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    Interrupts.reset()
    try:
        status = _main(argv)
    except KeyboardInterrupt:  # pressed while the parser's modules loaded, before the command's own handling
        print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
        return Interrupts.exit_status()
    finally:
        Interrupts.restore(previous)
    if status == EXIT_INTERRUPTED:  # stopped by a signal: 143 when it was SIGTERM
        return Interrupts.exit_status()
    if Interrupts.seen:  # Ctrl-C after Interrupts.outputs_written()
        print(f"\n{PROG}: {Interrupts.name()} came after the outputs were written; they are complete", file=sys.stderr,
              flush=True)
    return status


def _main(argv: list[str] | None) -> int:
    WARNINGS.clear()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        error(str(exc))
        return EXIT_USAGE
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else 0
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        error("no command given; use e.g. 'autoalign refine SCENE_DIR --model MESH --out OUT_DIR' "
               "(see 'autoalign --help')")
        return EXIT_USAGE
    with LOG.python_warnings():
        try:
            return int(func(args) or 0)
        except BaseException as exc:
            if not (Interrupts.seen or isinstance(exc, KeyboardInterrupt)):
                if isinstance(exc, (AutoalignError, UsageError)):
                    error(str(exc))
                    return EXIT_USAGE
                raise
            # also an error raised because a library turned the interrupt into another exception
            print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
            return EXIT_INTERRUPTED


# ------------------------------------------------------------------------------------------
# autoalign refine
# ------------------------------------------------------------------------------------------

def run_refine_batch(args: argparse.Namespace) -> int:
    """``autoalign refine --batch LIST``: every listed scene, resumable (:mod:`autoalign.batch`)."""
    if args.scene is not None:
        raise UsageError("give either SCENE_DIR or --batch LIST, not both")
    if args.init is not None or args.click is not None:
        raise UsageError("--init and --click are one scene's: put them after that scene's folder in the --batch list")
    from autoalign.batch import (
        BATCH_RECORDS,
        read_records,
        read_scene_list,
        refine_many,
        refine_tasks,
    )

    shared = shared_argv(args)
    scenes = read_scene_list(args.batch)
    records = Path(args.out) / BATCH_RECORDS
    listed = {t["id"] for t in refine_tasks([s for s, _ in scenes], shared, args.out)}
    try:
        summary = refine_many([s for s, _ in scenes], shared, args.out, args.workers, args.scheduler, not args.quiet,
                              extra={str(s): e for s, e in scenes})
    except KeyboardInterrupt:
        done = len(listed & {r["id"] for r in read_records(records)})
        if done < len(listed):
            print(f"\n{PROG}: interrupted; {done} of {len(listed)} scene(s) done (records in {records}); run the "
                  f"same command again to finish the other {len(listed) - done}", file=sys.stderr, flush=True)
            return EXIT_INTERRUPTED
        # every scene was done: main() says that the Ctrl-C came after the outputs were written
    else:
        if not args.quiet:
            print(f"{summary.done} scene(s) refined, {summary.skipped} already done, {summary.failed} failed, "
                  f"{summary.seconds:.1f} s; records in {records}", flush=True)
        if summary.failed:
            warn(f"{summary.failed} scene(s) failed: see {Path(args.out) / 'errors.jsonl'}; fix them and run the "
                 "same command again (finished scenes are skipped)")
            return EXIT_USAGE
    flagged = [r for r in read_records(records) if r["id"] in listed and r.get("status") == EXIT_FLAGGED]
    if flagged:
        warn(f"{len(flagged)} scene(s) have doubtful labels (exit 3): " + ", ".join(Path(r["scene"]).name for r in flagged[:10]))
        return EXIT_FLAGGED
    return 0


def run_refine(args: argparse.Namespace) -> int:
    """``autoalign refine``: see ``autoalign refine --help``."""
    if args.batch is not None:
        return run_refine_batch(args)
    if args.scene is None:
        raise UsageError("give a SCENE_DIR, or --batch LIST for many scenes")
    if args.workers != 1 or args.scheduler is not None:
        raise UsageError("--workers and --scheduler go with --batch LIST")
    t_start = time.perf_counter()
    photos = args.photos
    if photos == "auto" and args.masks != "none":  # a view without its photo: go on with the masks, and say so
        from autoalign.io.evidence import photos_if_complete

        photos = "auto" if photos_if_complete(args.scene, None if args.models else args.instance, warn) else "off"
    outcome = refine_folder(job_of(args, photos), LOG, ProgressBar(enabled=not args.quiet), t_start)
    elapsed = time.perf_counter() - t_start
    if args.models is not None:
        from autoalign.cli.refine_scene import print_scene_outcome

        print_scene_outcome(outcome, Path(args.out), elapsed, as_json=args.json, quiet=args.quiet)
    else:
        _print_object_outcome(outcome, Path(args.out), elapsed, as_json=args.json, quiet=args.quiet)
    for note in outcome.notes:
        warn(note)
    return outcome.status


def _print_object_outcome(outcome: FolderOutcome, out: Path, elapsed: float, as_json: bool, quiet: bool) -> None:
    """Print what one object's refinement found: one JSON object (``--json``) or a few lines."""
    import numpy as np

    from autoalign.jobs.report import RefineReport

    report = outcome.report
    assert isinstance(report, RefineReport)
    if as_json:
        print(json.dumps(report.summary(elapsed, out, outcome.paths), allow_nan=False), flush=True)
        return
    if quiet:
        return
    r, ids, T_cm = report.result, report.image_ids, report.T_cm_first
    iou_b, iou_a = np.asarray(r.iou_before, float), np.asarray(r.iou_after, float)
    rows = "\n".join("    [" + ", ".join(f"{x:+.6f}" for x in row) + "]" for row in T_cm[:3, :3])
    u = r.uncertainty
    trusted = report.verdict.status == "ok"  # a sigma is the precision of a pose only where the pose is trusted
    sigma = "" if u is None else (
        (f"sigma (model x, y, z): {', '.join(f'{x:.3f}' for x in u.sigma_mm)} mm, "
         f"{', '.join(f'{x:.3f}' for x in u.sigma_deg)} deg"
         + (f"; along / across the view: {u.sigma_ray_mm:.3f} / {u.sigma_across_mm:.3f} mm" if u.sigma_ray_mm is not None
            else "")
         + (f"; weakly observed: {'; '.join(u.weak)}" if u.weak else "")) if trusted else
        f"no sigma shown: the pose is '{report.verdict.status}', so a sigma would not be its precision (refine.json "
        "has the covariance)") + "\n"
    print(f"pose of obj {report.obj_id} in the camera of image {ids[0]} (model to camera):\n"
          f"  cam_R_m2c =\n{rows}\n"
          f"  cam_t_m2c = [{', '.join(f'{x:.2f}' for x in T_cm[:3, 3])}] mm\n"
          f"IoU over {len(ids)} views: mean {iou_b.mean():.3f} -> {iou_a.mean():.3f}, "
          f"min {iou_b.min():.3f} -> {iou_a.min():.3f} (image {ids[int(np.argmin(iou_a))]})\n"
          + sigma + f"verdict: {report.verdict.status}"
          + ("" if trusted else " (its reasons are listed on stderr)") + "\n"
          f"time {elapsed:.1f} s ({r.iterations} iterations, {r.renders} renders)\n"
          f"wrote {', '.join(outcome.paths)} to {out}", flush=True)


def entry() -> None:
    """The ``autoalign`` command: exit with :func:`main`'s status. After Ctrl-C the process ends
    without Python's finalization: drjit's worker threads, still busy, crashed it (SIGSEGV, an abort
    on the GIL) in about one interrupted run in ten, and a late SIGINT could still raise there."""
    status = main()
    for s in STOP_SIGNALS:  # the status is decided: Ctrl-C or SIGTERM from here on changes nothing
        signal.signal(s, signal.SIG_IGN)
    if status in (128 + s for s in STOP_SIGNALS):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    entry()
