"""The options of ``autoalign refine``, defined once: the command line parses them, and so does a
batch for each listed scene's line (:func:`scene_job`), into the one typed job (:class:`FolderJob`).

Standard library only at import (the command's start-up stays fast).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any

from autoalign.errors import AutoalignError
from autoalign.jobs.job import DEPTH_MODES, LOSSES, MASK_MODES, MESH_UNITS, OPTIMIZERS, PHOTO_MODES, FolderJob

BATCH_ONLY = ("batch", "workers", "scheduler", "out", "quiet", "json")
"""Options of the whole run, never of one scene's line in a batch list."""
SCENE_OWN = ("init", "click")
"""Options of one scene only: given once for a whole batch they would seed every scene alike."""


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
    group.add_argument("--units", choices=MESH_UNITS, default=None,
                       help="units of the mesh files; default mm, and a mesh under 2 units across is then refused "
                            "as probably metres (pass --units m to scale it by 1000, --units mm to keep it)")


def add_refine_arguments(p: argparse.ArgumentParser) -> None:
    """Every option of ``autoalign refine`` on ``p``."""
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
                     help="which instance's masks to use, mask_visib/{im_id:06d}_{N:06d}.png; in the --init file, "
                          "the entry at position N if it has obj_id K (a whole scene_gt.json), else the N-th "
                          "entry with obj_id K (default: 0)")
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
    _add_algorithm_arguments(p)
    _add_batch_and_output_arguments(p)


def _add_algorithm_arguments(p: argparse.ArgumentParser) -> None:
    """``refine``'s loss, solver, cameras, scale, depth and robustness options."""
    alg = p.add_argument_group("algorithm")
    alg.add_argument("--loss", choices=LOSSES, default="l2",
                     help="silhouette loss per view: l2 = squared pixel differences (default, fastest to "
                          "converge), bce = binary cross-entropy, iou = 1 - soft IoU, dice = 1 - soft Dice; the "
                          "objects of --models refined together take l2 only")
    alg.add_argument("--optimizer", choices=OPTIMIZERS, default="lm",
                     help="lm = Levenberg-Marquardt (default), gn = Gauss-Newton, adam = first-order Adam (not for "
                          "the objects of --models refined together)")
    alg.add_argument("--refine-cameras", action="store_true",
                     help="with --models: also correct every camera's pose (a silhouette bundle adjustment: "
                          "the objects seen together pin each camera down, a prior keeps corrections small); "
                          "writes the corrected scene_camera.json")
    alg.add_argument("--solve-scale", action="store_true",
                     help="with --models: scene_camera.json's translations are in an unknown unit (structure "
                          "from motion without depth); solve the scene's scale from the objects' known size with "
                          "the poses and write the metric scene_camera.json. On by itself when the scene's "
                          "recon.json says it has no metric scale")
    alg.add_argument("--depth", choices=DEPTH_MODES, default="auto",
                     help="auto (default): when the scene has depth/ (times scene_camera.json's depth_scale = mm) and "
                          "metric cameras, the measured depth joins the masks as evidence (a sensor noise model, "
                          "nearer measurements taken as occluders); off: masks only")
    alg.add_argument("--seed-radius", metavar="MM,DEG",
                     help="how far (mm at the model's centre, degrees) the --init pose may be off: a result "
                          "farther from it is returned only when it fits at least twice as well as the best pose "
                          "within it, and is flagged for a check either way (default 25,30)")
    alg.add_argument("--resting", nargs="?", const="table", metavar="NX,NY,NZ,D",
                     help="the objects stand on the table: each result is polished again with its lowest point held "
                          "to the table plane (what masks fix worst, along the viewing rays; glass most of all), "
                          "unless its masks then fit clearly worse (it stands on something else). The plane: "
                          "recon.json's table (z = 0), else fitted to the measured depth, or given as "
                          "NX x + NY y + NZ z + D = 0 (world frame, mm, normal towards the objects). Without it, "
                          "an object whose depth is seen through (glass) is held to the plane its depth shows when "
                          "its other evidence puts it there; 'off': not even then")
    alg.add_argument("--masks", choices=MASK_MODES, default="auto",
                     help="auto (default): the instance masks of mask_visib/; none: withhold every mask, the photos "
                          "(rgb/) place the objects from --init")
    alg.add_argument("--photos", choices=PHOTO_MODES, default="auto",
                     help="auto (default): when the scene has rgb/, the photos join the masks as evidence (colour "
                          "models of each object and its surroundings around its outline: a mask that misses parts "
                          "is completed, a pose the photo contradicts is flagged); on: the same, and a missing photo "
                          "is an error; off: never")
    alg.add_argument("--no-robust", action="store_true",
                     help="weigh all views equally; by default views whose mask disagrees with the others "
                          "(occlusion, bad segmentation) are down-weighted (Cauchy weights on 1 - IoU)")


def _add_batch_and_output_arguments(p: argparse.ArgumentParser) -> None:
    """``refine``'s options for many scenes and for what it prints."""
    many = p.add_argument_group("many scenes")
    many.add_argument("--batch", metavar="LIST",
                      help="instead of SCENE_DIR: a text file with one scene folder per line (# comments), "
                           "optionally followed by that scene's own options (e.g. --init FILE); every path in it "
                           "is relative to the file; each scene is refined with the other options into "
                           "OUT_DIR/<folder name>; OUT_DIR/batch.jsonl records the finished ones, so a run started "
                           "again with the same options skips them (with others it is refused)")
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


def job_of(args: argparse.Namespace, photos: str | None = None) -> FolderJob:
    """The job the parsed options ``args`` ask for (``photos``: the photo mode decided for the scene,
    default the option's)."""
    return FolderJob(scene=args.scene, out=args.out, model=args.model, models=args.models, units=args.units,
                     obj_id=args.obj_id, instance=args.instance, instances=args.instances, init=args.init,
                     click=args.click, loss=args.loss, optimizer=args.optimizer, refine_cameras=args.refine_cameras,
                     solve_scale=args.solve_scale, robust=not args.no_robust, depth=args.depth, masks=args.masks,
                     photos=args.photos if photos is None else photos, seed_radius=args.seed_radius,
                     resting=args.resting)


class _LineParser(argparse.ArgumentParser):
    """The refine options' parser for a batch's scene line: a mistake is one :class:`AutoalignError`."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise AutoalignError(f"{message} (see 'autoalign refine --help')")


def _scene_parser() -> _LineParser:
    p = _LineParser(prog="autoalign refine", add_help=False)
    add_refine_arguments(p)
    return p


def scene_job(scene: str, argv: Sequence[str], out: str) -> FolderJob:
    """The job of ``autoalign refine SCENE ARGV --out OUT``: one scene of a batch, ``argv`` its options
    (the batch's shared ones, then its own line's, e.g. ``["--models", "models/", "--init", "coarse.json"]``),
    parsed by the command's own parser; an option of the whole run (``--workers`` ...) is refused."""
    words = list(argv)
    refused = [name for name in BATCH_ONLY if name not in ("quiet", "json")]
    for word in words:
        name = word.split("=", 1)[0].lstrip("-").replace("-", "_")
        if word.startswith("--") and name in refused:
            raise AutoalignError(f"{word.split('=', 1)[0]}: an option of the whole batch, not of one scene's line "
                                 "(see 'autoalign refine --help')")
    parser = _scene_parser()
    args = parser.parse_args([str(scene), *words, "--out", str(out)])
    # spelt short (--work 2 is --workers 2 to argparse): found by its value; --out is this function's own
    given = [name for name in refused if name != "out" and getattr(args, name) != parser.get_default(name)]
    if given:
        what = "an option" if len(given) == 1 else "options"
        raise AutoalignError(f"{', '.join('--' + n for n in given)}: {what} of the whole batch, not of one scene's "
                             "line (see 'autoalign refine --help')")
    return job_of(args)


def shared_argv(args: argparse.Namespace) -> list[str]:
    """The options of ``args`` (a batch's command line) that every scene shares, as the argv
    :func:`scene_job` reads: each option of the command's parser that is set away from its default,
    except those of the whole run (:data:`BATCH_ONLY`) and of one scene (:data:`SCENE_OWN`)."""
    out: list[str] = []
    for action in _scene_parser()._actions:
        if not action.option_strings or action.dest in (*BATCH_ONLY, *SCENE_OWN):
            continue
        value = getattr(args, action.dest, action.default)
        if value is None or value == action.default:
            continue
        if isinstance(action, argparse._StoreTrueAction):
            out.append(action.option_strings[0])
        else:
            out += [action.option_strings[0], str(value)]
    return out
