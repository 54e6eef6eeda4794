"""``autoalign refine SCENE --models DIR``: every instance of a multi-object scene, with verdicts.

Reads the instances (:mod:`autoalign.io.instances`), refines each (:mod:`autoalign.scene.refine`),
and writes ``scene_gt.json`` (every instance in every image), ``refine.json`` (per instance: pose,
per-view IoU and weights, verdict and reasons, timings) and ``overlay.png`` (every instance in its
own colour, labelled with its verdict) atomically. A ``check`` or ``failed`` verdict is printed
and exits 3, so that no script takes a doubtful label for a good one.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from autoalign import __version__
from autoalign.cli.main import (
    EXIT_FLAGGED,
    WARNINGS,
    ProgressBar,
    jsonable,
    one_line,
    pose_record,
    uncertainty_record,
    warn,
    write_outputs,
)
from autoalign.runtime.interrupts import Interrupts

SCALE_SIGMA_WARN = 0.01
"""A solved scene scale with a relative sigma above this is reported as uncertain."""


def refine_scene_into(args: argparse.Namespace, out: Path, t_start: float) -> int:
    """Run the multi-object refinement of ``args`` and write its outputs into ``out``."""
    import numpy as np

    from autoalign.engine.refine import RefineOptions
    from autoalign.geometry.camera import PIXEL_CONVENTION
    from autoalign.io.instances import (
        read_init_poses,
        read_instance_scenes,
        read_instances,
    )
    from autoalign.io.models import ModelSet

    scene_dir = Path(args.scene)
    instances = read_instances(scene_dir, Path(args.instances) if args.instances else None)
    found = read_instance_scenes(scene_dir, instances)
    models = ModelSet.read(args.models, args.units)
    for inst in found.instances:
        models.mesh(inst.obj_id)  # every model present and readable before the slow part
    from autoalign.scene.scale import (
        cameras_up_to_scale,
        rescaled,
        scale_by_overlap,
        scale_from_masks,
    )

    solve_scale = args.solve_scale or cameras_up_to_scale(scene_dir)
    seeds = read_init_poses(args.init, found) if args.init is not None else {}
    guess = None
    if solve_scale:  # a first guess from the masks' areas, then the one at which the seeds overlap their masks best
        if not args.solve_scale:
            warn(f"{scene_dir / 'recon.json'} says the cameras have no metric scale: solving it from the objects' "
                 "size (as --solve-scale)")
        guess = scale_from_masks(found, models)
        found = rescaled(found, guess.factor)
        if seeds:
            factor, _ = scale_by_overlap(found, models, Path(args.init))
            found = rescaled(found, factor)
            guess = replace(guess, factor=guess.factor * factor)
        seeds = read_init_poses(args.init, found) if args.init is not None else {}  # their positions in mm
    missing = [i.index for i in found.instances if i.index not in seeds]
    if args.init is not None and missing:
        warn(f"{args.init} gives no pose for instance(s) {', '.join(map(str, missing))}; they are searched "
             "from their masks instead")

    from autoalign.quality.overlay import encode_png
    from autoalign.scene.refine import refine_scene

    options = RefineOptions(loss=args.loss, optimizer=args.optimizer, robust=not args.no_robust)
    progress = ProgressBar(enabled=not args.quiet)
    progress.start("loading the renderer")
    try:
        refined = refine_scene(found, models, seeds, options, args.refine_cameras, solve_scale, progress)
        results, found, joint = refined.results, refined.found, refined.joint
        progress("overlay", 0, 1)
        t0 = time.perf_counter()
        overlay = _overlay(found, models, results, scene_dir)
        progress("overlay", 1, 1)
    finally:
        progress.close()
    t_overlay = time.perf_counter() - t0

    from autoalign.geometry.se3 import rotation_angle_deg
    from autoalign.io.bop import scene_gt_of

    scene_gt = scene_gt_of([(r.instance.obj_id, r.result.T_wm) for r in results], found.cameras, found.image_ids)
    records = []
    for pos, r in enumerate(results):
        res = r.result
        records.append({
            "instance": r.instance.index, "obj_id": r.instance.obj_id, "scene_gt_position": pos,
            "model": str(models.path(r.instance.obj_id).absolute()),
            "verdict": r.verdict.status, "reasons": r.verdict.reasons, "set_aside_ids": r.verdict.set_aside,
            "pose": pose_record(res.T_wm), "pose_before": pose_record(res.T_init),
            "uncertainty": uncertainty_record(res.uncertainty),
            "seed": "init" if r.instance.index in seeds else "hull",
            "image_ids": [int(i) for i in res.image_ids], "iou_before": res.iou_before, "iou_after": res.iou_after,
            "weights": res.weights, "median_iou_after": float(np.median(res.iou_after)),
            "empty_masks": [int(i) for i in found.scenes[pos].empty],
            "ambiguous": bool(res.ambiguous), "symmetric": models.symmetric(r.instance.obj_id), "turn_gap": res.turn_gap,
            "iterations": res.iterations, "renders": res.renders, "timings": {**res.timings, "instance": r.seconds},
        })
    flagged = [r for r in results if r.verdict.status != "ok"]
    report = {
        "autoalign_version": __version__,
        "scene_dir": str(scene_dir.absolute()), "models": str(Path(args.models).absolute()),
        "units": "mm; poses are world-from-model, world = the frame of scene_camera.json",
        "pixel_convention": PIXEL_CONVENTION,
        "image_scale": found.scenes[0].image_scale if found.scenes else 1.0,
        "instances_from": str(Path(args.instances).absolute()) if args.instances else "scene_gt.json of the scene",
        "unmodelled_instances": found.unmodelled,
        "instances": records,
        "options": options,
        "timings": {"total": time.perf_counter() - t_start, "overlay": t_overlay},
        "outputs": {"scene_gt": "scene_gt.json", "refine": "refine.json", "overlay": "overlay.png"},
        "warnings": list(WARNINGS),
    }
    files = {"scene_gt.json": json.dumps(jsonable(scene_gt), indent=1).encode(),
             "overlay.png": encode_png(overlay)}
    from autoalign.scene.cameras import MIN_MISFIT_GAIN

    if joint is not None:
        report["joint"] = {"iterations": joint.iterations, "loss_before": joint.loss_before,
                           "loss_after": joint.loss_after,
                           "median_view_misfit_before": float(np.median(list(joint.view_misfit_before.values()))),
                           "median_view_misfit_after": float(np.median(list(joint.view_misfit_after.values())))}
    attempt = refined.with_cameras
    if attempt is not None and not refined.cameras_accepted:
        warn("--refine-cameras: the camera corrections explained too little of the misfit (median per-view "
             f"1 - IoU {np.median(list(attempt.view_misfit_before.values())):.3f} -> "
             f"{np.median(list(attempt.view_misfit_after.values())):.3f}, less than {MIN_MISFIT_GAIN:.0%} lower), "
             "so the masks, not the cameras, are what is off; the given cameras are kept")
    if guess is not None:
        mm_per_unit = guess.factor * refined.scale
        report["scale"] = {"solved": True, "settled": refined.scale_settled, "mm_per_unit": mm_per_unit,
                           "sigma_relative": refined.scale_sigma,
                           "guess_mm_per_unit": guess.factor, "guess_spread": guess.spread,
                           "file": "scene_camera.json"}
        if refined.scale_sigma > SCALE_SIGMA_WARN:
            warn(f"the scene's scale is uncertain: {mm_per_unit:.4g} mm per unit, sigma {refined.scale_sigma:.1%}; "
                 "more views of the objects from different distances, or depth (recon --depth), pin it down")
    if attempt is not None or guess is not None:
        from autoalign.io.bop import read_cameras

        final = found.camera_by_id
        corrected = {}
        for im, (K, R, t) in read_cameras(scene_dir).items():
            T_cw = final[im].T_cw if im in final else np.vstack([np.column_stack([R, t]), [0, 0, 0, 1]])
            corrected[str(im)] = {"cam_K": K.ravel(), "cam_R_w2c": T_cw[:3, :3].ravel(), "cam_t_w2c": T_cw[:3, 3]}
        files["scene_camera.json"] = json.dumps(jsonable(corrected), indent=1).encode()
        report["outputs"]["scene_camera"] = "scene_camera.json"
    if attempt is not None:
        report["cameras"] = {
            "refined": refined.cameras_accepted, "file": "scene_camera.json", "iterations": attempt.iterations,
            "loss_before": attempt.loss_before, "loss_after": attempt.loss_after,
            "median_view_misfit_before": float(np.median(list(attempt.view_misfit_before.values()))),
            "median_view_misfit_after": float(np.median(list(attempt.view_misfit_after.values()))),
            "per_view": {str(im): {"translation_mm": float(np.linalg.norm(E[:3, 3])),
                                   "rotation_deg": rotation_angle_deg(E[:3, :3], np.eye(3)),
                                   "T_correction": E,  # corrected T_cw = T_cw @ E, kept or not
                                   "misfit_before": attempt.view_misfit_before.get(im),
                                   "misfit_after": attempt.view_misfit_after.get(im)}
                         for im, E in attempt.corrections.items()}}
    files["refine.json"] = json.dumps(jsonable(report), indent=1, allow_nan=False).encode()
    write_outputs(out, files)
    Interrupts.outputs_written()
    elapsed = time.perf_counter() - t_start
    if args.json:
        print(json.dumps(jsonable({"instances": [{k: rec[k] for k in ("instance", "obj_id", "verdict", "reasons",
                                                                      "median_iou_after", "pose")}
                                                 for rec in records],
                                   "time_s": elapsed, "out_dir": str(out.absolute()),
                                   "warnings": list(WARNINGS)}), allow_nan=False), flush=True)
    elif not args.quiet:
        rows = [f"  obj {rec['obj_id']:>3} (instance {rec['instance']}): {rec['verdict']:<6} median IoU "
                f"{rec['median_iou_after']:.3f} over {len(rec['image_ids'])} views, sigma up to "
                f"{max(rec['uncertainty']['sigma_mm']):.2g} mm / {max(rec['uncertainty']['sigma_deg']):.2g} deg"
                + (f"; {'; '.join(rec['reasons'])}" if rec["reasons"] else "") for rec in records]
        print(f"{len(records)} instance(s) in {len(found.image_ids)} images, {elapsed:.1f} s:\n" + "\n".join(rows)
              + f"\nwrote {', '.join(files)} to {out}", flush=True)
    if flagged:
        warn(f"{len(flagged)} of {len(results)} instance(s) flagged: "
             + "; ".join(f"obj {r.instance.obj_id} (instance {r.instance.index}) {r.verdict.status}: "
                         + one_line(", ".join(r.verdict.reasons)) for r in flagged)
             + "; look at them in overlay.png")
        return EXIT_FLAGGED
    return 0


def _overlay(found: Any, models: Any, results: list, scene_dir: Path) -> Any:
    """The overlay of every instance in up to 9 views spread over the scene."""
    import numpy as np

    from autoalign.quality.overlay import instance_label, render_instances_overlay
    from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

    n = len(found.image_ids)
    views = sorted(set(np.linspace(0, n - 1, min(9, n)).round().astype(int).tolist()))
    cams = [found.cameras[i] for i in views]
    layers = []
    for r, scene in zip(results, found.scenes):
        rast = SoftSilhouetteRasterizer(models.mesh(r.instance.obj_id))
        masks = {im: np.asarray(m) > 0.5 for im, m in zip(scene.image_ids, scene.masks)}
        layers.append((instance_label(r.instance.obj_id, r.verdict.status), masks,
                       np.stack(rast.hard_masks(r.result.T_wm, cams))))
    return render_instances_overlay(found.cameras, found.image_ids, scene_dir, layers, views)
