"""``autoalign check``: a ground-truth-free quality check of 6-DoF pose labels (feature and edge distance).

Start-up imports only the standard library and :mod:`autoalign.errors`; numpy, OpenCV and
trimesh load inside :func:`run_check` (nothing here imports torch or jax). Its helpers come from
:mod:`autoalign.cli.common` (:mod:`autoalign.cli.main` registers this module, never the other way round).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError

REPORT_FILES = ("check.json", "check.png", "compare.png")

_CHECK_DESCRIPTION = """\
Check 6-DoF pose labels against the photos without any ground truth (the "feature distance" of
ProgressLabeller): every labelled object is rendered with its vertex colours at its label's pose,
SIFT keypoints of the rendering and of the photo inside the object's box are matched (Lowe's
ratio test 0.8) and the matches closer than 10 px are kept; their mean distance is small (1-4 px)
when the label puts the object where the photo shows it. Untextured objects give too few matches
to judge and are flagged so. The edge distance needs no texture: the mean distance (px, each
pixel counted at most 10) from the label's rendered outline to the nearest edge of the photo
(Canny); compare it between labels of the same photos, since texture edges near the object make
every outline look closer than it is. With visible masks in mask_visib/, the IoU of the label's rendered
visible silhouette with them is reported too.

--split-half measures the labels' precision instead (the photo check above is skipped): every
instance is labelled twice, as 'autoalign refine SCENE_DIR --models MODELS_DIR --init LABELS' would,
once from the views at even positions of the scene's image ids and once from those at odd
positions, both starting from the labels being checked, and the two labels are compared."""

_CHECK_EPILOG = """\
inputs:
  SCENE_DIR/scene_camera.json  per image id: cam_K (9 numbers, px; OpenCV/BOP convention: the
                               centre of the top-left pixel is at 0,0); cam_R_w2c, cam_t_w2c unused
  SCENE_DIR/rgb/{im_id:06d}.png or .jpg
                               the photos
  SCENE_DIR/mask_visib/{im_id:06d}_{k:06d}.png
                               optional: visible mask of entry k of the image's labels (for IoU)
  --labels SCENE_GT_JSON       BOP scene_gt.json: image id -> list of {"obj_id", "cam_R_m2c": 9
                               numbers (row-major), "cam_t_m2c": 3 numbers (mm)}, the model-to-camera
                               pose x_cam = R_m2c x_model + t_m2c; entry k is instance k
  --models MODELS_DIR          obj_{obj_id:06d}.ply in mm, with vertex colours (a mesh without
                               colours is rendered grey and will give too few matches);
                               materials.json beside them may declare an object transparent or
                               reflective: its feature distance is then not measured

output:
  a table per instance: obj id, instance, views, median IoU, mean feature distance (px) with its
  95% confidence interval (bootstrap over views), kept matches, or "too few matches" (< 10 over all
  views), or "not measurable (transparent)" or "(reflective)" (materials.json: the photo's features
  on such an object are its surroundings', refracted or mirrored; with the scene's depth/, glass
  whose depth is seen through at its labels is recognised: "(transparent, from the depth)"), and
  the mean edge distance (px) with its interval. With --out: check.json (every image
  and instance: IoU, matches, mean distance and its interval, mean offset photo - rendering in px,
  edge distance, bounding box; the per-instance summaries; the parameters) and check.png (up to 4
  photos with the labels' outlines and the kept matches: dot = rendering keypoint, line to the
  photo keypoint).
  With --against REFERENCE: the reference is checked on the same images, and per instance the
  views where both outlines are judged are paired: the mean edge distance of each, the share of
  views where the labels' outline is the closer one, and the mean difference (reference - labels,
  px; > 0: the labels fit the photos' edges better) with its 95% bootstrap interval over the views.
  check.json gets "against" (the reference's report and the comparison) and compare.png shows a
  row per instance: 5 views cropped around the object, mask outline cyan, labels green,
  reference red.
  With --split-half (instead of all the above): a table per instance: each half's views and
  verdict, how far apart the halves are (mm at the model's centre, degrees; along and across the
  viewing ray of the median view), the largest |z| (the difference along/about a model axis over
  sqrt(sigma_A^2 + sigma_B^2)), how many of the 6 axes are within 3 sigma, the chi-square
  d^T (S_A + S_B)^-1 d (6 on average when the sigmas are right) and whether both reached the same
  solution (neither failed, less than 10% of the diameter and 10 degrees apart); then per instance
  the difference, z and both halves' sigmas per axis. check.json holds only a "split_half" block
  with all of it (twist in the model's axes about its centre: mm and radians). The instances are
  those the labels list; each needs its masks (mask_visib/) in at least 3 views of each half, and
  the halves read rgb/ and depth/ as evidence as 'autoalign refine' does (--photos, --depth).
  Photos over 3.2 megapixels are checked at 1/2, 1/3, ... of their size (the smallest whole factor
  that brings them under it, masks and cam_K with them, as refine reads masks): check.json's
  "image_scale" says so, and its px (distances, boxes, the 10 px limits) are those pixels.

examples:
  autoalign check scenes/000002 --labels labels/000002/scene_gt.json --models models/
  autoalign check scenes/000002 --labels scenes/000002/scene_gt.json --models models/ --images 10 --out report/
  autoalign check scenes/000002 --labels labels/000002/scene_gt.json --against scenes/000002/scene_gt.json \\
      --models models/ --out report/
  autoalign check scenes/000002 --labels labels/000002/scene_gt.json --models models/ --split-half --out report/
  autoalign check scenes/000002 --labels labels/000002/scene_gt.json --models models/ --split-half --instances 0,3

exit status: 0 the check ran (whatever the numbers), 2 a mistake in the command or the input files."""


def add_check_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign check`` on an argparse subparsers object."""
    from autoalign.cli.common import HelpFormatter, index_list
    from autoalign.jobs.refine_arguments import positive_int
    from autoalign.jobs.job import DEPTH_MODES, PHOTO_MODES

    p = subparsers.add_parser(
        "check", help="check pose labels against the photos without ground truth (SIFT feature distance, edge "
                      "distance, IoU)",
        description=_CHECK_DESCRIPTION, epilog=_CHECK_EPILOG, formatter_class=HelpFormatter)
    p.add_argument("scene", metavar="SCENE_DIR",
                   help="BOP scene folder with scene_camera.json and rgb/ (mask_visib/ optional; see 'inputs')")
    req = p.add_argument_group("required")
    req.add_argument("--labels", metavar="SCENE_GT_JSON", required=True,
                     help="the labels to check, a BOP scene_gt.json (model-to-camera poses, mm); entry k of an "
                          "image is instance k, whose mask is mask_visib/{im_id:06d}_{k:06d}.png")
    req.add_argument("--models", metavar="MODELS_DIR", required=True,
                     help="BOP models folder with obj_XXXXXX.ply (mm, vertex colours) for every obj_id of the labels")
    opt = p.add_argument_group("check and report")
    opt.add_argument("--against", metavar="REFERENCE_SCENE_GT_JSON", default=None,
                     help="other labels of the same scene (a dataset's own, say) to compare with, image by image and "
                          "instance by instance (entry k is instance k in both); see 'output'")
    opt.add_argument("--images", metavar="N", type=positive_int, default=None,
                     help="check only N labelled images, spread evenly over the scene (default: all; about "
                          "0.5 s an image at 640x480, 1 s at 4000x3000, which is read at half size)")
    opt.add_argument("--out", metavar="REPORT_DIR", default=None,
                     help="write check.json and check.png into this folder (created if missing; files of the same "
                          "name are replaced)")
    opt.add_argument("--json", action="store_true",
                     help="print one JSON object on stdout (the contents of check.json, plus the output paths) and "
                          "nothing else there")
    opt.add_argument("--quiet", action="store_true",
                     help="no progress bar on stderr (the table or --json, warnings and errors still appear)")
    half = p.add_argument_group("precision without ground truth")
    half.add_argument("--split-half", action="store_true",
                      help="label every instance again from the views at even positions and from those at odd "
                           "positions, both from --labels, and report how far apart the two labels are, in mm, "
                           "degrees and units of their sigmas (see 'output'); the photo check is skipped, and "
                           "--images and --against do not apply")
    half.add_argument("--instances", metavar="K,K,...", type=index_list, default=None,
                      help="with --split-half, check only these instances (mask numbers: entry k of an image's "
                           "labels is mask k); the other masks stay as unmodelled objects, as 'autoalign refine "
                           "--instances' leaves them. For labels of objects that are not one pose over all the "
                           "views (moved between takes), which halves would only find disagreeing with themselves")
    half.add_argument("--photos", choices=PHOTO_MODES, default=None,
                      help="with --split-half, the photos as evidence as in 'autoalign refine' (auto: when the scene "
                           "has rgb/; on; off: masks only)")
    half.add_argument("--depth", choices=DEPTH_MODES, default=None,
                      help="with --split-half, the measured depth as evidence as in 'autoalign refine' (auto: when the "
                           "scene has depth/ and metric cameras; off)")
    p.set_defaults(func=run_check)
    return p


def _ci(ci: tuple[float, float] | None) -> str:
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]" if ci is not None else ""


def format_table(report: Any) -> str:
    """The per-instance table of a :class:`autoalign.quality.check_report.CheckReport`, and a total line."""
    head = (f"{'obj':>4} {'inst':>4} {'views':>5} {'median IoU':>10}  {'feature distance px (95% CI)':<30} "
            f"{'matches':>7}  {'edge distance px (95% CI)':<26}")
    lines = [head, "-" * len(head)]
    for s in report.instances:
        iou = f"{s.median_iou:.2f}" if s.median_iou is not None else "-"
        why = f"{s.material}, from the depth" if s.recognised else s.material
        dist = (f"not measurable ({why})" if not s.features_measurable else "too few matches"
                if s.too_few_matches else f"{s.mean_px:.2f} {_ci(s.ci95)}")
        edge = f"{s.edge_px:.2f} {_ci(s.edge_ci95)}" if s.edge_px is not None else "-"
        lines.append(f"{s.obj_id:>4} {s.instance:>4} {s.views:>5} {iou:>10}  {dist:<30} {s.n_matches:>7}  {edge:<26}")
    ids = ", ".join(str(i) for i in report.image_ids)
    if report.mean_px is not None:
        lines.append(f"all instances with enough matches: {report.mean_px:.2f} px {_ci(report.ci95)} "
                     f"over {report.n_matches} matches")
    else:
        lines.append("no instance has enough matches to judge (untextured objects, or labels far off)")
    if report.edge_px is not None:
        lines.append(f"edge distance, all judged views: {report.edge_px:.2f} px {_ci(report.edge_ci95)}")
    lines.append(f"images ({len(report.image_ids)}): {ids}")
    if report.image_scale != 1.0:
        scale = f"{report.image_scale:g}" if report.image_scale is not None else "per image, see check.json"
        lines.append(f"photos over {report.max_pixels / 1e6:g} megapixels were checked downscaled (image_scale "
                     f"{scale}): every px above is a pixel of the photo as checked; divide by image_scale for the "
                     "files' pixels")
    return "\n".join(lines)


def format_comparison(comparisons: list[Any]) -> str:
    """The per-instance table of :func:`autoalign.quality.label_compare.compare_reports`."""
    head = (f"{'obj':>4} {'inst':>4} {'views':>5}  {'edge px labels':>14} {'edge px reference':>17}  "
            f"{'labels closer in':>16}  {'reference - labels px (95% CI)':<31} verdict")
    lines = ["labels against the reference (edge distance, paired views):", head, "-" * len(head)]
    for c in comparisons:
        gain = f"{c.gain_px:+.2f} {_ci(c.gain_ci95)}"
        lines.append(f"{c.obj_id:>4} {c.instance:>4} {c.views:>5}  {c.labels_edge_px:>14.2f} "
                     f"{c.reference_edge_px:>17.2f}  {c.closer_share:>15.0%}  {gain:<31} {c.verdict}")
    if not comparisons:
        lines.append("no instance has an outline judged in both label sets")
    return "\n".join(lines)


def run_check(args: argparse.Namespace) -> int:
    """``autoalign check``: see ``autoalign check --help``. Returns 0 once the check ran."""
    from autoalign.runtime.interrupts import preload

    preload("numpy", "cv2", "trimesh")  # extension modules, with Ctrl-C deferred
    from autoalign.cli.common import ProgressBar, warn
    from autoalign.io.out_folder import prepare_out_dir, remove_empty_dirs

    _keep_freed_memory()

    scene, labels, models = Path(args.scene), Path(args.labels), Path(args.models)
    against = Path(args.against) if getattr(args, "against", None) is not None else None
    out = Path(args.out) if getattr(args, "out", None) is not None else None
    if out is not None:
        taken = {labels.resolve()} | ({against.resolve()} if against is not None else set())
        for name in REPORT_FILES:
            if (out / name).resolve() in taken:
                raise AutoalignError(f"--out {out}: writing {name} there would replace the input file {out / name}; "
                                     "choose another folder with --out")
    as_json = bool(getattr(args, "json", False))
    if getattr(args, "split_half", False):
        return run_split_half(args, scene, labels, models, out, as_json)
    for option in ("photos", "depth", "instances"):
        if getattr(args, option, None) is not None:
            raise AutoalignError(f"--{option}: only with --split-half, whose halves are refined with that evidence "
                                 "and for those instances; add --split-half or drop it")
    from autoalign.quality import scene_check

    # every input file is read and validated before any photo is checked (a bad --against file
    # was found only after the labels' whole check) and before --out is created
    inputs = scene_check.prepare_check(scene, labels, models, images=getattr(args, "images", None))
    ref_inputs = _prepare_reference(scene, against, models, inputs) if against is not None else None
    created = prepare_out_dir(out) if out is not None else []
    try:
        from autoalign.quality.figures import match_figure
        from autoalign.quality.overlay import encode_png

        bar = ProgressBar(enabled=not getattr(args, "quiet", False))
        try:
            report = scene_check.check_prepared(inputs, progress=lambda done, total: bar("checking images", done, total))
            reference = None
            if ref_inputs is not None:
                reference = scene_check.check_prepared(
                    ref_inputs, progress=lambda done, total: bar("checking the reference", done, total))
        finally:
            bar.close()
        for w in report.warnings:
            warn(w)
        record = report.record()
        comparison = None
        if reference is not None:
            from autoalign.quality import label_compare

            comparison = label_compare.compare_reports(report, reference)
            record["against"] = {"labels": str(against), "report": reference.record(),
                                 "comparison": [c.record() for c in comparison]}
        paths: dict[str, str] = {}
        if out is not None:
            files = {out / "check.json": (json.dumps(record, indent=1) + "\n").encode(),
                     out / "check.png": encode_png(match_figure(report))}
            if comparison is not None:
                files[out / "compare.png"] = encode_png(label_compare.comparison_figure(report, reference, comparison))
            paths = _write(files, out)
    except BaseException:
        remove_empty_dirs(created)
        raise
    return _emit(record, paths, as_json, [format_table(report)]
                 + ([format_comparison(comparison)] if comparison is not None else []))


def run_split_half(args: argparse.Namespace, scene: Path, labels: Path, models: Path, out: Path | None,
                   as_json: bool) -> int:
    """``autoalign check --split-half``: every input read and validated before anything is refined
    or created, then both halves refined; the table, or --json, and check.json with --out."""
    from autoalign.cli.common import LOG, ProgressBar
    from autoalign.io.out_folder import prepare_out_dir, remove_empty_dirs
    from autoalign.jobs.check import prepare_split_half, run_split_half

    for option in ("against", "images"):
        if getattr(args, option, None) is not None:
            raise AutoalignError(f"--{option}: not with --split-half, which refines every view of the scene from "
                                 "--labels; drop one of them")
    photos = getattr(args, "photos", None) or "auto"
    if photos == "auto":  # a view without its photo: the halves go on with the masks, as 'refine' does
        from autoalign.io.evidence import photos_if_complete

        photos = "auto" if photos_if_complete(scene, None, LOG.warning) else "off"
    prepared = prepare_split_half(scene, labels, models, photos=photos,
                                  depth=getattr(args, "depth", None) or "auto", log=LOG,
                                  instances=getattr(args, "instances", None))
    created = prepare_out_dir(out) if out is not None else []
    try:
        bar = ProgressBar(enabled=not getattr(args, "quiet", False))
        try:
            report = run_split_half(prepared, progress=bar)
        finally:
            bar.close()
        record = {"split_half": report.record()}
        paths: dict[str, str] = {}
        if out is not None:
            paths = _write({out / "check.json": (json.dumps(record, indent=1) + "\n").encode()}, out)
    except BaseException:
        remove_empty_dirs(created)
        raise
    return _emit(record, paths, as_json, [format_split_half(report)])


def format_split_half(report: Any) -> str:
    """The tables of a :class:`autoalign.quality.split_half.SplitHalfReport`: a line per instance, then
    its difference, z and both halves' sigmas per model axis."""
    import numpy as np

    from autoalign.quality.split_half import AXES, WITHIN_SIGMAS

    a, b = report.halves
    head = (f"{'obj':>4} {'inst':>4} {'views A/B':>9}  {'verdict A/B':<15} {'apart mm':>8} {'deg':>6} "
            f"{'along ray mm':>12} {'across mm':>9} {'max |z|':>7} {f'in {WITHIN_SIGMAS:g} sigma':>10} "
            f"{'chi2 (6)':>8}  same solution")
    lines = [f"split half: A = {len(a)} images at even positions, B = {len(b)} at odd positions, both from the labels",
             head, "-" * len(head)]
    for s in report.instances:
        zmax = f"{np.max(np.abs(s.z)):.2f}" if s.z is not None else "-"
        within = f"{int(np.sum(s.within))}/6" if s.within is not None else "-"
        chi2 = f"{s.mahalanobis_sq:.2f}" if s.mahalanobis_sq is not None else "-"
        verdicts = f"{s.a.status} / {s.b.status}"
        lines.append(f"{s.obj_id:>4} {s.index:>4} {f'{len(s.a.image_ids)}/{len(s.b.image_ids)}':>9}  {verdicts:<15} "
                     f"{s.translation_mm:>8.2f} {s.rotation_deg:>6.2f} {s.along_ray_mm:>+12.2f} "
                     f"{s.across_ray_mm:>9.2f} {zmax:>7} {within:>10} {chi2:>8}  {'yes' if s.same_basin else 'no: ' + s.basin_reason}")
    if report.fraction_within is not None:
        lines.append(f"axes within {WITHIN_SIGMAS:g} sigma, all instances: {report.fraction_within:.0%}")
    lines.append("")
    lines.append("per model axis (B - A in mm / deg; z = difference / sqrt(sigma_A^2 + sigma_B^2)):")
    lines.append(f"{'obj':>4} {'inst':>4} {'':<9}" + "".join(f"{ax:>8}" for ax in AXES))
    for s in report.instances:
        diff = np.concatenate([s.twist[:3], np.degrees(s.twist[3:])])
        rows = [("B - A", diff), ("z", s.z)]
        for name, h in (("sigma A", s.a), ("sigma B", s.b)):
            rows.append((name, None if h.sigma_mm is None else np.concatenate([h.sigma_mm, h.sigma_deg])))
        for name, values in rows:
            cells = "".join(f"{x:>+8.2f}" if name in ("B - A", "z") else f"{x:>8.2f}" for x in values) \
                if values is not None else f"{'-':>8}" * 6
            lines.append(f"{s.obj_id:>4} {s.index:>4} {name:<9}{cells}")
    return "\n".join(lines)


def _keep_freed_memory(trim_mb: int = 256) -> None:
    """Let glibc's malloc keep up to ``trim_mb`` MB of freed memory for reuse instead of handing it
    back at once: SIFT allocates and frees its image pyramids (about 100 MB) twice per photo, and
    taking those pages back from the system cost more than SIFT's own work (24 photos of 12 MP:
    2.2 million page faults and 7.8 s of system time in a 20 s run; 0.16 million and 1.2 s in 15 s
    with this, the same peak memory). Does nothing without glibc."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-1, trim_mb << 20)  # M_TRIM_THRESHOLD
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD: blocks up to 32 MB from the heap (glibc's own upper bound)
    except (OSError, AttributeError):
        pass


def _prepare_reference(scene: Path, against: Path, models: Path, inputs: Any) -> Any:
    """The validated inputs of the reference's check (:func:`autoalign.quality.scene_check.prepare_check`):
    the images of ``inputs`` that the reference labels too."""
    from autoalign.io.bop import read_labels
    from autoalign.quality import scene_check

    ref_labels = read_labels(against)
    common = [i for i in inputs.image_ids if ref_labels.get(i)]
    if not common:
        raise AutoalignError(f"--against {against}: it labels none of the checked images of {inputs.labels_path}; "
                             "compare labels of the same scene")
    return scene_check.prepare_check(scene, against, models, image_ids=common, labels=ref_labels)


def _emit(record: dict[str, Any], paths: dict[str, str], as_json: bool, tables: list[str]) -> int:
    """Print the report: ``record`` with the output paths as one JSON object, or the ``tables`` and
    the files written; the check's exit status (0: it ran)."""
    if as_json:
        print(json.dumps({**record, "outputs": paths}))
    else:
        print("\n".join(tables))
        for p in paths.values():
            print(f"wrote {p}")
    return 0


def _write(files: dict[Path, bytes], out: Path) -> dict[str, str]:
    """Write the report files atomically (all or none); a failure names ``--out``. Returns their
    paths by file name."""
    from autoalign.io.atomic_files import write_files_atomic
    from autoalign.runtime.interrupts import Interrupts

    Interrupts.check()
    try:
        write_files_atomic(files)
    except OSError as exc:
        raise AutoalignError(f"--out {out}: cannot write the report ({exc.strerror or exc}); "
                             "free some space or choose another --out") from None
    return {p.name: str(p) for p in files}
