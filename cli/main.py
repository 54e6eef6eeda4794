"""The ``autoalign`` command line: ``autoalign refine`` (and ``autoalign simulate`` when available).

Start-up is kept fast: only the standard library and :mod:`autoalign.errors` are imported here;
numpy, OpenCV, trimesh and the rendering backend (mitsuba/drjit) load inside the command, after
the arguments are parsed. Nothing on this path imports torch or jax.

Exit status: 0 success; 2 a usage or input mistake (one line ``autoalign: error: ...`` on stderr,
no output files); 3 outputs written but a pose is in doubt (its verdict, or an instance's, is
check or failed); 130 interrupted; anything else is a bug (Python prints a traceback).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable

from autoalign import __version__
from autoalign.errors import AutoalignError
from autoalign.io.atomic_files import write_files_atomic
from autoalign.runtime.interrupts import Interrupts, is_command_process, preload

PROG = "autoalign"
OUTPUT_FILES = ("scene_gt.json", "refine.json", "overlay.png", "scene_camera.json")
"""Every file ``refine`` may write (``scene_camera.json`` only with ``--refine-cameras`` or a solved scale)."""
LOW_WEIGHT = 0.3  # a view whose robust weight (mean 1) ends below this ...
LOW_WEIGHT_MAX_IOU = 0.95  # ... and whose IoU after stays below this is reported as disagreeing
POOR_FIT_IOU = 0.7  # a mean IoU after refinement below this is reported as a poor fit
EXIT_FLAGGED = 3
"""Exit status when every output was written but a pose's verdict is ``check`` or ``failed``."""


class UsageError(Exception):
    """A command-line syntax mistake (unknown option, missing argument, bad value)."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors become :class:`UsageError` (one line) instead of usage + exit."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see '{self.prog} --help')")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=30, width=min(100, max(60, _terminal_width())))


def _terminal_width() -> int:
    try:
        return os.get_terminal_size().columns
    except OSError:
        return 100


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
                 weakly observed axes; near 0: nearly symmetric), the verdict (ok, check or failed) and its reasons, the
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


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: a whole number of at least ``minimum``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"{text!r} must be {minimum} or more")
        return v

    return parse


positive_int = _int_at_least(1)
nonnegative_int = _int_at_least(0)


def add_units_argument(group: Any) -> None:
    """``--units mm|m`` of the mesh files, the same for every command that reads models."""
    group.add_argument("--units", choices=("mm", "m"), default=None,
                       help="units of the mesh files; default mm, and a mesh under 2 units across is then refused "
                            "as probably metres (pass --units m to scale it by 1000, --units mm to keep it)")


def add_refine_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign refine`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "refine", help="refine the pose of an object from multi-view masks (writes scene_gt.json, refine.json, overlay.png)",
        description=_REFINE_DESCRIPTION, epilog=_REFINE_EPILOG, formatter_class=HelpFormatter)
    p.add_argument("scene", metavar="SCENE_DIR", nargs="?",
                   help="BOP scene folder with scene_camera.json and mask_visib/ (see 'input scene' below); "
                        "or --batch LIST")
    req = p.add_argument_group("required")
    what = req.add_mutually_exclusive_group(required=True)
    what.add_argument("--model", metavar="MESH",
                      help="one object: its mesh in millimetres, in its BOP model frame (PLY, OBJ, STL, GLB, OFF, "
                           "...); it needs triangles, a point cloud will not do")
    what.add_argument("--models", metavar="MODELS_DIR",
                      help="every object of the scene: a BOP models folder (obj_XXXXXX.ply, models_info.json); "
                           "which object each instance mask shows comes from --instances or the scene's "
                           "scene_gt.json (see 'several objects' below)")
    req.add_argument("--out", metavar="OUT_DIR", required=True,
                     help="output folder, created if missing; scene_gt.json, refine.json and overlay.png are "
                          "written there (see 'outputs' below); it may not be the scene folder, and no output "
                          "may replace an input file")
    add_units_argument(req)
    sel = p.add_argument_group("object")
    sel.add_argument("--instances", metavar="INSTANCES_JSON",
                     help='with --models: {"instances": {"0": 5, "3": 8}} maps instance numbers (the N of '
                          "mask_visib/{im_id:06d}_{N:06d}.png) to BOP obj_ids; instances not listed are objects "
                          "without a model, whose masks still count (default: the scene's scene_gt.json)")
    sel.add_argument("--obj-id", metavar="K", type=positive_int, default=1,
                     help="BOP object id written to scene_gt.json and looked for in the --init file (default: 1)")
    sel.add_argument("--instance", metavar="N", type=nonnegative_int, default=0,
                     help="which instance's masks to use, mask_visib/{im_id:06d}_{N:06d}.png; also picks the N-th "
                          "entry with obj_id K in the --init file (default: 0)")
    seed = p.add_argument_group("starting pose (at most one; default: visual hull of the masks + orientation search)")
    ex = seed.add_mutually_exclusive_group()
    ex.add_argument("--init", metavar="SCENE_GT_JSON",
                    help="a coarse pose as a BOP scene_gt.json: image id -> list of {\"obj_id\", \"cam_R_m2c\": 9 "
                         "numbers (row-major), \"cam_t_m2c\": 3 numbers (mm)}; the entry of the lowest image id "
                         "that is a view of the scene is used; the refinement is local, so this pose should "
                         "roughly overlap the masks")
    ex.add_argument("--click", metavar="IM_ID:U,V",
                    help="one pixel on the object: image id, then pixel coordinates U (column, to the right) and "
                         "V (row, down) as in OpenCV (the top-left pixel's centre is 0,0), e.g. 3:412,233; "
                         "the position is found along "
                         "that ray and the orientation is searched")
    alg = p.add_argument_group("algorithm")
    alg.add_argument("--loss", choices=("l2", "bce", "iou", "dice"), default="l2",
                     help="silhouette loss per view: l2 = squared pixel differences (default, fastest to "
                          "converge), bce = binary cross-entropy, iou = 1 - soft IoU, dice = 1 - soft Dice")
    alg.add_argument("--optimizer", choices=("lm", "gn", "adam"), default="lm",
                     help="lm = Levenberg-Marquardt (default), gn = Gauss-Newton, adam = first-order Adam")
    alg.add_argument("--refine-cameras", action="store_true",
                     help="with --models: also correct every camera's pose (a silhouette bundle adjustment: "
                          "the objects seen together pin each camera down, a prior keeps corrections small); "
                          "writes the corrected scene_camera.json")
    alg.add_argument("--solve-scale", action="store_true",
                     help="with --models: scene_camera.json's translations are in an unknown unit (structure "
                          "from motion without depth); solve the scene's scale from the objects' known size with "
                          "the poses and write the metric scene_camera.json. On by itself when the scene's "
                          "recon.json says it has no metric scale")
    alg.add_argument("--no-robust", action="store_true",
                     help="weigh all views equally; by default views whose mask disagrees with the others "
                          "(occlusion, bad segmentation) are down-weighted (Cauchy weights on 1 - IoU)")
    many = p.add_argument_group("many scenes")
    many.add_argument("--batch", metavar="LIST",
                      help="instead of SCENE_DIR: a text file with one scene folder per line (relative to the "
                           "file, # comments), optionally followed by that scene's own options (e.g. --init "
                           "FILE); each scene is refined with the other options into OUT_DIR/<folder name>; "
                           "OUT_DIR/batch.jsonl records the finished ones, so a run started again skips them")
    many.add_argument("--workers", metavar="N", type=positive_int, default=1,
                      help="with --batch: scenes refined at once in separate processes (default 1)")
    many.add_argument("--scheduler", metavar="ADDRESS",
                      help="with --batch: run the scenes on the Dask cluster at tcp://HOST:PORT")
    out = p.add_argument_group("output")
    out.add_argument("--quiet", action="store_true",
                     help="no progress bar and no summary; only warnings and errors, on stderr")
    out.add_argument("--json", action="store_true",
                     help="print one JSON object on stdout (pose, mean IoU before/after, time, ambiguous, "
                          "warnings, output paths) and nothing else there")
    p.set_defaults(func=run_refine)
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``autoalign`` parser with its subcommands (``simulate`` only if its module imports)."""
    parser = _Parser(prog=PROG, description=_MAIN_DESCRIPTION, formatter_class=HelpFormatter,
                     epilog="Run 'autoalign COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands", parser_class=_Parser)
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
        from autoalign.experiments.studies import simulate
    except ImportError:
        simulate = None
    if simulate is not None and hasattr(simulate, "add_simulate_parser"):
        simulate.add_simulate_parser(sub)
    return parser


# ------------------------------------------------------------------------------------------
# Entry point
# ------------------------------------------------------------------------------------------

def one_line(text: str) -> str:
    return " ".join(str(text).split())


def _error(message: str) -> None:
    print(f"{PROG}: error: {one_line(message)}", file=sys.stderr, flush=True)


WARNINGS: list[str] = []  # the warnings of the current run (also written to refine.json)


def warn(message: str) -> None:
    WARNINGS.append(one_line(message))
    print(f"{PROG}: warning: {one_line(message)}", file=sys.stderr, flush=True)


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    warn(str(message))


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 usage/input error, 130 interrupted)."""
    import threading

    # Only the main thread may handle signals; a process that ignores Ctrl-C (a batch worker, whose
    # parent stops it; nohup) keeps ignoring it.
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return _main(argv)
    previous = signal.signal(signal.SIGINT, Interrupts.handler)
    if Interrupts.seen and is_command_process():  # pressed while the command's modules loaded
        signal.signal(signal.SIGINT, previous)
        print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
        return 130
    Interrupts.seen = False
    try:
        status = _main(argv)
    except KeyboardInterrupt:  # pressed while the parser's modules loaded, before the command's own handling
        print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
        return 130
    finally:
        signal.signal(signal.SIGINT, previous)
    if Interrupts.seen and status != 130:  # Ctrl-C after Interrupts.outputs_written()
        print(f"\n{PROG}: Ctrl-C came after the outputs were written; they are complete", file=sys.stderr, flush=True)
    return status


def _main(argv: list[str] | None) -> int:
    WARNINGS.clear()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        _error(str(exc))
        return 2
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else 0
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        _error("no command given; use e.g. 'autoalign refine SCENE_DIR --model MESH --out OUT_DIR' "
               "(see 'autoalign --help')")
        return 2
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"trimesh(\.|$)")
        try:
            return int(func(args) or 0)
        except BaseException as exc:
            if not (Interrupts.seen or isinstance(exc, KeyboardInterrupt)):
                if isinstance(exc, (AutoalignError, UsageError)):
                    _error(str(exc))
                    return 2
                raise
            # also an error raised because a library turned the interrupt into another exception
            print(f"\n{PROG}: interrupted", file=sys.stderr, flush=True)
            return 130


# ------------------------------------------------------------------------------------------
# autoalign refine
# ------------------------------------------------------------------------------------------

def prepare_out_dir(out: Path) -> list[Path]:
    """Create ``out`` if needed and check a file can be written there.

    Returns the folders that were created (outermost first) so that a failed run can remove them.
    Raises :class:`AutoalignError` naming ``--out`` when that is impossible.
    """
    fix = "choose a folder you can write to with --out"
    if out.exists() and not out.is_dir():
        raise AutoalignError(f"--out {out}: exists and is not a folder; {fix}")
    missing: list[Path] = []
    p = out.absolute()
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    if not p.is_dir():
        raise AutoalignError(f"--out {out}: cannot create it because {p} is a file, not a folder; {fix}")
    created = list(reversed(missing))
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".autoalign-probe-", suffix=".tmp", dir=out)
        try:
            os.write(fd, b"autoalign")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        remove_empty_dirs(created)
        raise AutoalignError(f"--out {out}: cannot create or write to the folder ({exc.strerror or exc}); {fix}") from None
    except BaseException:  # Ctrl-C half-way: leave nothing behind
        remove_empty_dirs(created)
        raise
    return created


def remove_empty_dirs(created: list[Path]) -> None:
    """Remove the folders this run created (innermost first), if they are still empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            break


def write_outputs(out: Path, files: dict[str, bytes]) -> dict[str, Path]:
    """Write every ``name -> bytes`` into ``out`` atomically (:mod:`autoalign.io.atomic_files`): all or none.

    If any write fails no temporary file is left behind and no target file is touched. Nothing is
    written after Ctrl-C (see :class:`Interrupts`).
    """
    Interrupts.check()
    try:
        write_files_atomic({out / name: data for name, data in files.items()})
    except OSError as exc:
        raise AutoalignError(f"--out {out}: cannot write the outputs ({exc.strerror or exc}); "
                             "free some space or choose another --out") from None
    return {name: out / name for name in files}


def write_folder(out: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` (names relative to ``out``, subfolders allowed) with :func:`write_outputs`;
    the folders this creates are removed again if the writing fails."""
    created = prepare_out_dir(out)
    for sub in sorted({name.rsplit("/", 1)[0] for name in files if "/" in name}):
        if not (out / sub).is_dir():
            (out / sub).mkdir(parents=True)
            created.append(out / sub)
    try:
        write_outputs(out, files)
    except BaseException:
        remove_empty_dirs(created)
        raise


class ProgressBar:
    """``progress(stage, done, total)`` callback drawing one tqdm bar on stderr."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: Any = None
        self.stage: str | None = None
        self.last = -1

    def start(self, desc: str) -> None:
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=None, desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True,
                            unit="it", bar_format="{desc}: {elapsed}")
            self.stage = desc

    def __call__(self, stage: str, done: int, total: int) -> None:
        Interrupts.check()
        if not self.enabled:
            return
        if self.bar is None:
            self.start(stage)
        if stage != self.stage or done < self.last or self.bar.total != total:
            self.bar.bar_format = None
            self.bar.set_description(stage, refresh=False)
            self.bar.reset(total=total)
            self.stage, self.last = stage, 0
        self.bar.update(max(0, done - self.bar.n))
        self.last = done

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _floats(a: Any) -> Any:
    """Nested lists of plain floats (NaN/inf as None) from an array-like."""
    import numpy as np

    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        v = float(arr)
        return v if np.isfinite(v) else None
    return [_floats(x) for x in arr]


def jsonable(obj: Any) -> Any:
    """Plain JSON types from numpy scalars/arrays, dataclasses, tuples and paths (NaN as None)."""
    import dataclasses
    import math

    import numpy as np

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _floats(obj) if obj.dtype.kind == "f" else obj.tolist()
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def uncertainty_record(u: Any) -> dict[str, Any] | None:
    """The ``uncertainty`` entry of ``refine.json`` (see :mod:`autoalign.engine.uncertainty`)."""
    if u is None:
        return None
    return {"sigma_mm": u.sigma_mm, "sigma_deg": u.sigma_deg, "axes": "along / about the model's x, y, z",
            "weakly_observed": list(u.weak), "covariance": u.covariance,
            "covariance_of": "twist (v mm, w rad) in the model's axes, about the model centre; cluster-robust "
                             "(one cluster per view) Gauss-Newton sandwich",
            "naive_sigma_mm": u.naive_sigma_mm, "naive_sigma_deg": u.naive_sigma_deg}


def pose_record(T: Any) -> dict[str, Any]:
    import numpy as np

    T = np.asarray(T, dtype=np.float64)
    return {"T_wm": _floats(T), "R": _floats(T[:3, :3].ravel()), "t": _floats(T[:3, 3])}


def _all_cameras(scene: Any) -> tuple[list[Any], list[int]]:
    """Cameras and ids of every image in scene_camera.json (also those skipped for lack of a mask)."""
    from autoalign.geometry.camera import Camera
    from autoalign.io.bop import read_cameras

    if scene.path is None:
        return list(scene.cameras), list(scene.image_ids)
    W, H = scene.cameras[0].width, scene.cameras[0].height
    cams = read_cameras(Path(scene.path))
    return [Camera.from_opencv(K, R, t, W, H) for K, R, t in cams.values()], list(cams)


BATCH_SHARED = ("models", "model", "units", "obj_id", "instance", "instances", "loss", "optimizer")
"""Options of ``refine`` passed on to every scene of a batch (with the flags below)."""
BATCH_FLAGS = ("refine_cameras", "solve_scale", "no_robust")


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

    shared: list[str] = []
    for name in BATCH_SHARED:
        value = getattr(args, name, None)
        if value is not None:
            shared += ["--" + name.replace("_", "-"), str(value)]
    shared += ["--" + f.replace("_", "-") for f in BATCH_FLAGS if getattr(args, f, False)]
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
            return 130
        # every scene was done: main() says that the Ctrl-C came after the outputs were written
    else:
        if not args.quiet:
            print(f"{summary.done} scene(s) refined, {summary.skipped} already done, {summary.failed} failed, "
                  f"{summary.seconds:.1f} s; records in {records}", flush=True)
        if summary.failed:
            warn(f"{summary.failed} scene(s) failed: see {Path(args.out) / 'errors.jsonl'}; fix them and run the "
                 "same command again (finished scenes are skipped)")
            return 2
    flagged = [r for r in read_records(records) if r["id"] in listed and r.get("status") == EXIT_FLAGGED]
    if flagged:
        warn(f"{len(flagged)} scene(s) have doubtful labels (exit 3): " + ", ".join(Path(r["scene"]).name for r in flagged[:10]))
        return EXIT_FLAGGED
    return 0


def check_outputs_spare_inputs(out: Path, scene_dir: Path, inputs: list[Path]) -> None:
    """Refuse an ``--out`` that is the scene folder, or where an output would replace an input file."""
    fix = "choose another folder with --out"
    if out.resolve() == scene_dir.resolve():
        raise AutoalignError(f"--out {out}: is the scene folder itself, whose scene_gt.json would be replaced; {fix}")
    taken = {p.resolve() for p in inputs}
    for name in OUTPUT_FILES:
        if (out / name).resolve() in taken:
            raise AutoalignError(f"--out {out}: writing {name} there would replace the input file {out / name}; {fix}")


def run_refine(args: argparse.Namespace) -> int:
    """``autoalign refine``: see ``autoalign refine --help``."""
    if args.batch is not None:
        return run_refine_batch(args)
    if args.scene is None:
        raise UsageError("give a SCENE_DIR, or --batch LIST for many scenes")
    if args.workers != 1 or args.scheduler is not None:
        raise UsageError("--workers and --scheduler go with --batch LIST")
    t_start = time.perf_counter()
    preload("numpy", "cv2", "scipy.spatial", "trimesh")  # extension modules, with Ctrl-C deferred
    click = None
    if args.click is not None:
        from autoalign.engine.seeding import Click

        click = Click.parse(args.click)
    out = Path(args.out)
    if args.models is not None and click is not None:
        raise UsageError("--click seeds one object; with --models give a coarse --init for the scene, or no seed")
    if args.instances is not None and args.models is None:
        raise UsageError("--instances needs --models (a models folder for the objects it names)")
    if args.refine_cameras and args.models is None:
        raise UsageError("--refine-cameras needs --models: several objects seen together pin a camera down")
    if args.solve_scale and args.models is None:
        raise UsageError("--solve-scale needs --models (a models folder whose meshes give the objects' size)")
    inputs = [Path(x) for x in (args.model, args.init, args.instances) if x is not None]
    check_outputs_spare_inputs(out, Path(args.scene), inputs)
    created = prepare_out_dir(out)
    try:
        if args.models is not None:
            from autoalign.cli.refine_scene import refine_scene_into

            return refine_scene_into(args, out, t_start)
        return _refine_into(args, out, click, t_start)
    except BaseException:
        remove_empty_dirs(created)
        raise


def _refine_into(args: argparse.Namespace, out: Path, click: Any, t_start: float) -> int:
    import numpy as np

    from autoalign.geometry.mesh import load_mesh
    from autoalign.io.bop import read_init_pose, read_scene, scene_gt_dict

    scene = read_scene(args.scene, args.instance)
    mesh = load_mesh(args.model, units=args.units)
    seed: Any = None
    seed_info: dict[str, Any] = {"kind": "hull", "init_file": None, "click": None, "pose": None}
    if args.init is not None:
        seed = read_init_pose(args.init, scene, args.obj_id, args.instance)
        seed_info.update(kind="init", init_file=str(Path(args.init).absolute()), pose=pose_record(seed))
    elif click is not None:
        from autoalign.engine.seeding import check_click
        from autoalign.geometry.camera import uv_to_opencv

        u, v = uv_to_opencv(np.array([click.u, click.v]))  # as typed: OpenCV pixels of the image files
        seed_info.update(kind="click", click={"image_id": click.image_id, "u": float(u), "v": float(v)})
        click = click.scaled(scene.image_scale)
        check_click(scene, click)  # fail now, before the slow start-up of the renderer
        seed = click

    from autoalign.engine.refine import RefineOptions, refine
    from autoalign.geometry.camera import PIXEL_CONVENTION
    from autoalign.geometry.se3 import rotation_angle_deg, transform_points
    from autoalign.quality.overlay import encode_png, render_overlay
    from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

    options = RefineOptions(loss=args.loss, optimizer=args.optimizer, robust=not args.no_robust)
    progress = ProgressBar(enabled=not args.quiet)
    progress.start("loading the renderer" if seed_info["kind"] == "init" else "seeding")
    try:
        result = refine(scene, mesh, seed, options, progress=progress)
        progress("overlay", 0, 1)
        t0 = time.perf_counter()
        overlay = render_overlay(scene, mesh, result.T_init, result.T_wm, result.iou_after,
                                 rasterizer=SoftSilhouetteRasterizer(mesh))
        progress("overlay", 1, 1)
    finally:
        progress.close()
    t_overlay = time.perf_counter() - t0

    # ---------------------------------------------------------------- compose outputs in memory
    ids = [int(i) for i in result.image_ids or scene.image_ids]
    iou_b, iou_a = np.asarray(result.iou_before, float), np.asarray(result.iou_after, float)
    weights = np.asarray(result.weights, float)
    low = [(i, float(w), float(a)) for i, w, a in zip(ids, weights, iou_a)
           if w < LOW_WEIGHT and a < LOW_WEIGHT_MAX_IOU]
    runner = None
    if result.runner_up is not None:
        Ru = np.asarray(result.runner_up.T_final, float)
        c = mesh.centre[None]
        runner = {"pose": pose_record(Ru), "loss": result.runner_up.loss, "mean_iou": result.runner_up.mean_iou,
                  "stage": result.runner_up.stage,
                  "rotation_deg": rotation_angle_deg(result.T_wm[:3, :3], Ru[:3, :3]),
                  "translation_mm": float(np.linalg.norm(transform_points(result.T_wm, c) - transform_points(Ru, c)))}
    all_cams, all_ids = _all_cameras(scene)
    scene_gt = scene_gt_dict(result.T_wm, all_cams, all_ids, args.obj_id)
    cam0 = scene.cameras[0]
    T_cm = cam0.T_cw @ result.T_wm
    first = {"image_id": ids[0], "cam_R_m2c": _floats(T_cm[:3, :3].ravel()), "cam_t_m2c": _floats(T_cm[:3, 3])}
    notes = []
    if result.ambiguous and runner is not None:
        notes.append(f"ambiguous: another pose ({runner['rotation_deg']:.1f} deg, {runner['translation_mm']:.1f} mm "
                     f"away) fits almost as well (loss {result.runner_up.loss:.4g} vs {result.hypotheses[0].loss:.4g}); "
                     "the object may be symmetric in these views; check overlay.png and 'runner_up' in refine.json")
    if low:
        notes.append("views with low weight (their masks disagree with the others): image ids "
                     + ", ".join(f"{i} (IoU {a:.2f})" for i, _, a in low) + "; check those masks")
    if iou_a.mean() < POOR_FIT_IOU:
        notes.append(f"poor fit: mean IoU after refinement is only {iou_a.mean():.2f}; check the model's units (mm), "
                     "the starting pose and the masks (see overlay.png)")
    if scene.empty:
        notes.append(f"{len(scene.empty)} image(s) with an empty mask were treated as missing (not as 'object "
                     "absent') and not used: ids " + ", ".join(str(i) for i in scene.empty[:20])
                     + (" ..." if len(scene.empty) > 20 else "") + "; check the segmentation there")
    if scene.skipped:
        notes.append(f"{len(scene.skipped)} image(s) without a mask were skipped: ids "
                     + ", ".join(str(i) for i in scene.skipped[:20]) + (" ..." if len(scene.skipped) > 20 else ""))
    from autoalign.quality.verdict import judge

    verdict = judge(iou_a, weights, ids, scene.empty, bool(result.ambiguous), uncertainty=result.uncertainty,
                    turn_gap=result.turn_gap)
    timings = dict(result.timings)
    timings["overlay"] = t_overlay
    report = {
        "autoalign_version": __version__,
        "scene_dir": str(Path(args.scene).absolute()),
        "model": str(Path(args.model).absolute()),
        "obj_id": args.obj_id,
        "instance": args.instance,
        "units": "mm; poses are world-from-model, world = the frame of scene_camera.json",
        "pixel_convention": PIXEL_CONVENTION,
        "pose": pose_record(result.T_wm),
        "pose_first_camera": first,
        "pose_before": pose_record(result.T_init),
        "verdict": verdict.status, "reasons": verdict.reasons,
        "uncertainty": uncertainty_record(result.uncertainty),
        "seed": seed_info,
        "image_ids": ids,
        "iou_before": iou_b,
        "iou_after": iou_a,
        "weights": weights,
        "mean_iou_before": float(iou_b.mean()), "mean_iou_after": float(iou_a.mean()),
        "min_iou_before": float(iou_b.min()), "min_iou_after": float(iou_a.min()),
        "low_weight_ids": [i for i, _, _ in low],
        "skipped": [int(i) for i in scene.skipped],
        "empty_masks": [int(i) for i in scene.empty],
        "image_scale": scene.image_scale,
        "iterations": result.iterations,
        "renders": result.renders,
        "timings": timings,
        "hypotheses": [{"rank": k, "stage": h.stage, "loss": h.loss, "mean_iou": h.mean_iou,
                        "pose_init": pose_record(h.T_init), "pose": pose_record(h.T_final)}
                       for k, h in enumerate(result.hypotheses)],
        "ambiguous": bool(result.ambiguous), "turn_gap": result.turn_gap,
        "runner_up": runner,
        "options": options,
        "history": result.history,
        "outputs": {"scene_gt": "scene_gt.json", "refine": "refine.json", "overlay": "overlay.png"},
        "warnings": list(WARNINGS) + [one_line(n) for n in notes],
    }
    files = {
        "scene_gt.json": json.dumps(jsonable(scene_gt), indent=1).encode(),
        "refine.json": json.dumps(jsonable(report), indent=1, allow_nan=False).encode(),
        "overlay.png": encode_png(overlay),
    }
    paths = write_outputs(out, files)
    Interrupts.outputs_written()
    elapsed = time.perf_counter() - t_start

    # ---------------------------------------------------------------- report
    if args.json:
        summary = {
            "pose": report["pose"], "pose_first_camera": first,
            "mean_iou_before": report["mean_iou_before"], "mean_iou_after": report["mean_iou_after"],
            "min_iou_after": report["min_iou_after"], "time_s": elapsed, "ambiguous": report["ambiguous"],
            "verdict": verdict.status, "reasons": verdict.reasons,
            "low_weight_ids": report["low_weight_ids"], "warnings": report["warnings"],
            "out_dir": str(out.absolute()),
            "outputs": {"scene_gt": str(paths["scene_gt.json"].absolute()),
                        "refine": str(paths["refine.json"].absolute()),
                        "overlay": str(paths["overlay.png"].absolute())},
        }
        print(json.dumps(jsonable(summary), allow_nan=False), flush=True)
    elif not args.quiet:
        R = T_cm[:3, :3]
        rows = "\n".join("    [" + ", ".join(f"{x:+.6f}" for x in r) + "]" for r in R)
        print(f"pose of obj {args.obj_id} in the camera of image {ids[0]} (model to camera):\n"
              f"  cam_R_m2c =\n{rows}\n"
              f"  cam_t_m2c = [{', '.join(f'{x:.2f}' for x in T_cm[:3, 3])}] mm\n"
              f"IoU over {len(ids)} views: mean {iou_b.mean():.3f} -> {iou_a.mean():.3f}, "
              f"min {iou_b.min():.3f} -> {iou_a.min():.3f} (image {ids[int(np.argmin(iou_a))]})\n"
              + (f"sigma (model x, y, z): {', '.join(f'{x:.3f}' for x in result.uncertainty.sigma_mm)} mm, "
                 f"{', '.join(f'{x:.3f}' for x in result.uncertainty.sigma_deg)} deg"
                 + (f"; weakly observed: {'; '.join(result.uncertainty.weak)}" if result.uncertainty.weak else "")
                 + "\n" if result.uncertainty is not None else "") +
              f"time {elapsed:.1f} s ({result.iterations} iterations, {result.renders} renders)\n"
              f"wrote {', '.join(files)} to {out}", flush=True)
    for note in notes:
        warn(note)
    if verdict.status != "ok":
        warn(f"verdict {verdict.status}: {'; '.join(verdict.reasons)}; look at overlay.png before using this pose")
        return EXIT_FLAGGED
    return 0


def entry() -> None:
    """The ``autoalign`` command: exit with :func:`main`'s status. After Ctrl-C the process ends
    without Python's finalization: drjit's worker threads, still busy, crashed it (SIGSEGV, an abort
    on the GIL) in about one interrupted run in ten, and a late SIGINT could still raise there."""
    status = main()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the status is decided: Ctrl-C from here on changes nothing
    if status == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    sys.exit(status)


if __name__ == "__main__":
    entry()
