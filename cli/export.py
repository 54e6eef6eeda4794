"""``autoalign export``: a BOP scene folder with labels for every frame, from poses (e.g. refine's).

Start-up imports only the standard library and :mod:`autoalign.errors`; the rest loads inside
:func:`run_export`. Its helpers come from
:mod:`autoalign.cli.common` (:mod:`autoalign.cli.main` registers this module, never the other way round).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError
from autoalign.runtime.interrupts import Interrupts, preload

_DESCRIPTION = """\
Export BOP labels for every frame of a scene: for each image and each labelled object in view,
its pose (scene_gt.json), its full and visible masks (mask/, mask_visib/), its boxes and pixel
counts (scene_gt_info.json, as the bop_toolkit defines them) and, with --coco, COCO instance
annotations (RLE). Visibility comes from all labelled objects (the nearest surface wins) and,
where SCENE_DIR/depth/ has a depth image, from the measured depth (15 mm tolerance, as the
bop_toolkit). An object out of view in an image gets no entry there, and mask file k is always
entry k of that image's list. The scene's photos, depth and cameras are copied along, so OUT_DIR
is a complete BOP scene folder."""

_EPILOG = """\
inputs:
  SCENE_DIR/scene_camera.json  per image id: cam_K (9 numbers, px; OpenCV/BOP convention: the
                               centre of the top-left pixel is at 0,0), cam_R_w2c, cam_t_w2c (mm),
                               depth_scale (depth png value times it = mm; default 1)
  SCENE_DIR/rgb/{im_id:06d}.png or .jpg, SCENE_DIR/depth/{im_id:06d}.png (optional)
  --labels SCENE_GT_JSON       BOP scene_gt.json: image id -> list of {"obj_id", "cam_R_m2c": 9
                               numbers (row-major), "cam_t_m2c": 3 numbers (mm)}, e.g. the one
                               'autoalign refine' wrote (every object in every image)
  --models MODELS_DIR          obj_{obj_id:06d}.ply (mm) for every obj_id of the labels
  --cameras SCENE_CAMERA_JSON  the cameras to export (default: the scene_camera.json beside
                               --labels if there is one, i.e. the cameras 'autoalign refine'
                               corrected or scaled, else SCENE_DIR's)

outputs (OUT_DIR, written all or none; an earlier export there is replaced as a whole, and a
non-empty OUT_DIR without export.json is refused):
  scene_gt.json, scene_gt_info.json, mask/ and mask_visib/{im_id:06d}_{k:06d}.png (0/255),
  scene_camera.json (the labelled images' cameras), rgb/ and depth/ (copies), export.json (counts,
  parameters, version) and, with --coco, scene_gt_coco.json (COCO image id = BOP image id,
  category id = obj_id).

examples:
  autoalign export scenes/000001 --labels labels/000001/scene_gt.json --models models/ --out bop/000001
  autoalign export scenes/000001 --labels labels/000001/scene_gt.json --models models/ --out bop/000001 --coco

exit status: 0 exported, 2 a mistake in the command or the input files (nothing written)."""


def add_export_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign export`` on an argparse subparsers object."""
    from autoalign.cli.common import HelpFormatter
    from autoalign.jobs.refine_arguments import add_units_argument

    p = subparsers.add_parser("export", help="write BOP labels (poses, masks, boxes; COCO) for every frame of a scene",
                              description=_DESCRIPTION, epilog=_EPILOG, formatter_class=HelpFormatter)
    p.add_argument("scene", metavar="SCENE_DIR", help="BOP scene folder with scene_camera.json and rgb/")
    req = p.add_argument_group("required")
    req.add_argument("--labels", metavar="SCENE_GT_JSON", required=True, help="the poses, a BOP scene_gt.json")
    req.add_argument("--models", metavar="MODELS_DIR", required=True, help="BOP models folder (obj_XXXXXX.ply, mm)")
    req.add_argument("--out", metavar="OUT_DIR", required=True,
                     help="the BOP scene folder to write (created if missing; not SCENE_DIR); an earlier export "
                          "there is replaced as a whole, any other non-empty folder refused")
    opt = p.add_argument_group("options")
    opt.add_argument("--cameras", metavar="SCENE_CAMERA_JSON", default=None,
                     help="cameras to export (default: scene_camera.json beside --labels if present, else SCENE_DIR's)")
    opt.add_argument("--coco", action="store_true", help="also write scene_gt_coco.json (COCO RLE of mask_visib)")
    add_units_argument(opt)
    opt.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run_export)
    return p


def run_export(args: argparse.Namespace) -> int:
    """``autoalign export``: see ``autoalign export --help``."""

    preload("numpy", "cv2", "trimesh")  # extension modules, with Ctrl-C deferred
    from autoalign.cli.common import ProgressBar
    from autoalign.io.export import cameras_to_export, export_dataset
    from autoalign.io.models import ModelSet
    from autoalign.io.out_folder import check_replaceable, replace_folder

    t0 = time.perf_counter()
    scene, labels_path, out = Path(args.scene), Path(args.labels), Path(args.out)
    if not (scene / "scene_camera.json").is_file():
        raise AutoalignError(f"{scene}: no scene_camera.json; pass a BOP scene folder as SCENE_DIR")
    if out.resolve() == scene.resolve():
        raise AutoalignError(f"--out {out}: is the scene folder itself; choose another folder with --out")
    cameras = cameras_to_export(scene, labels_path, Path(args.cameras) if args.cameras else None)
    _check_inputs_outside(out, {"SCENE_DIR": scene, "--labels": labels_path, "--cameras": cameras,
                                "--models": Path(args.models)})
    check_replaceable(out, "export.json")  # before the rendering, not after it
    models = ModelSet.read(args.models, args.units)
    bar = ProgressBar(enabled=not args.quiet)
    try:
        dataset = export_dataset(scene, labels_path, models, cameras, args.coco, progress=bar)
    finally:
        bar.close()
    files = dataset.files
    replace_folder(out, files, marker="export.json")
    Interrupts.outputs_written()
    if not args.quiet:
        print(f"{dataset.images} image(s), {dataset.entries} entries ({dataset.dropped} out of view left out), "
              f"{time.perf_counter() - t0:.1f} s; wrote {len(files)} files to {out}", file=sys.stdout, flush=True)
    return 0


def _check_inputs_outside(out: Path, inputs: dict[str, Path]) -> None:
    """Refuse an ``--out`` that holds an input: the export replaces the whole folder."""
    root = out.resolve()
    for option, path in inputs.items():
        if path.resolve() == root or root in path.resolve().parents:
            raise AutoalignError(f"--out {out}: holds the input {path} ({option}), and an export replaces the whole "
                                 "folder; choose another folder with --out")
