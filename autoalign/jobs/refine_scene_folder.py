"""Refine every instance of a BOP scene folder into an output folder (``autoalign refine --models``;
:func:`~autoalign.jobs.refine_folder.refine_folder` calls this for a job with ``models``).

Reads the instances (:mod:`autoalign.io.instances`), solves the scene's scale when asked or when
the cameras have none, refines each instance (:mod:`autoalign.scene.refine`), and writes
``scene_gt.json`` (every instance in every image), ``refine.json``
(:class:`~autoalign.jobs.report.SceneReport`), ``overlay.png`` (every instance in its own colour,
labelled with its verdict) and, with corrected cameras or a solved scale, ``scene_camera.json``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from autoalign.engine.refine import RefineOptions
from autoalign.errors import AutoalignError
from autoalign.io.instances import (
    Instance,
    InstanceScenes,
    read_init_poses,
    read_instance_scenes,
    read_instances,
)
from autoalign.io.models import ModelSet
from autoalign.jobs.job import (
    EXIT_FLAGGED,
    EXIT_OK,
    FolderJob,
    FolderOutcome,
    RunLog,
    Stages,
    one_line,
    write_json_outputs,
)
from autoalign.jobs.table_plane import resting_plane
from autoalign.jobs.report import (
    InstanceReport,
    ScaleReport,
    SceneReport,
    cameras_record,
)
from autoalign.rasterizers.pyramid import MeshDetail
from autoalign.scene.refine import SceneRefinement, refine_scene
from autoalign.scene.scale import (
    ScaleGuess,
    cameras_up_to_scale,
    rescaled,
    scale_by_overlap,
    scale_from_masks,
)

SCALE_SIGMA_WARN = 0.01
"""A solved scene scale with a relative sigma above this is reported as uncertain."""


@dataclass
class SceneInputs:
    """What a scene job reads before refining: the instances' scenes (rescaled to mm when the
    scale is solved), the models, the seeds by instance index (4x4 world from model, mm), the
    first guess of the scale (``None``: not solved)."""

    found: InstanceScenes
    models: ModelSet
    seeds: dict[int, np.ndarray]
    guess: ScaleGuess | None


def refine_scene_folder(job: FolderJob, log: RunLog, progress: Stages, t_start: float) -> FolderOutcome:
    """Every instance of ``job.scene`` refined, its outputs written into ``job.out`` (see module doc)."""
    from autoalign.quality.overlay import encode_png

    inputs = read_scene_inputs(job, log)
    options = replace(job.refine_options(), resting=resting_plane(job.resting, job.scene, inputs.found.scenes))
    progress.start("loading the renderer")
    try:
        refined = refine_scene(inputs.found, inputs.models, inputs.seeds, options, job.refine_cameras,
                               inputs.guess is not None, progress, job.seed_radius_mm_deg)
        progress("overlay", 0, 1)
        t0 = time.perf_counter()
        overlay = scene_overlay(refined, inputs.models, Path(job.scene), options.detail)
        progress("overlay", 1, 1)
    finally:
        progress.close()
    t_overlay = time.perf_counter() - t0
    report = scene_report(job, inputs, refined, options, list(log.warnings))
    report.timings.update(total=time.perf_counter() - t_start, overlay=t_overlay)
    _warn_cameras_and_scale(refined, report, log)
    from autoalign.io.bop import scene_gt_of

    found = refined.found
    documents: dict[str, Any] = {"scene_gt.json": scene_gt_of([(r.instance.obj_id, r.result.T_wm)
                                                                for r in refined.results],
                                                               found.cameras, found.image_ids)}
    if report.cameras_written:
        documents["scene_camera.json"] = corrected_cameras(Path(job.scene), found)
    documents["refine.json"] = report.to_json()
    paths = write_json_outputs(Path(job.out), documents, {"overlay.png": encode_png(overlay)},
                               order=("scene_gt.json", "overlay.png", "scene_camera.json"))
    flagged = report.flagged
    notes = []
    if flagged:
        notes.append(f"{len(flagged)} of {len(report.instances)} instance(s) flagged: "
                     + "; ".join(f"obj {i.obj_id} (instance {i.index}) {i.verdict.status}: "
                                 + one_line(", ".join(i.verdict.reasons)) for i in flagged)
                     + "; look at them in overlay.png")
    return FolderOutcome(EXIT_FLAGGED if flagged else EXIT_OK, report, paths, notes)


def read_scene_inputs(job: FolderJob, log: RunLog, instances: list[Instance] | None = None) -> SceneInputs:
    """The instances (``instances``, else ``job``'s), models and seeds of ``job``; with a scale to
    solve, the scene rescaled by a first guess from the masks' areas, then by the factor at which the
    seeds overlap their masks best; else, with ``job.depth`` ``auto``, every instance's scene with
    the folder's measured depth."""
    scene_dir = Path(job.scene)
    if instances is None:
        instances = read_instances(scene_dir, Path(job.instances) if job.instances else None)
    if job.masks == "none":
        from autoalign.io.evidence import read_instance_scenes_without_masks

        found = read_instance_scenes_without_masks(scene_dir, instances)
    else:
        found = read_instance_scenes(scene_dir, instances)
        if job.uses_photos:
            from autoalign.io.evidence import instance_scenes_with_photos

            found = instance_scenes_with_photos(found)
    models = ModelSet.read(job.models, job.units)
    for inst in found.instances:
        models.mesh(inst.obj_id)  # every model present and readable before the slow part
    seeds = read_init_poses(job.init, found) if job.init is not None else {}
    if job.masks == "none":
        missing = [i.index for i in found.instances if i.index not in seeds]
        if missing:
            raise AutoalignError(f"{job.init}: no pose for instance(s) {', '.join(map(str, missing))}; without masks "
                                 "every instance needs a coarse pose to start from")
        if job.solve_scale or cameras_up_to_scale(scene_dir):
            raise AutoalignError("--masks none needs metric cameras: the scale is solved from the masks; "
                                 "give the masks or a metric scene_camera.json")
        from autoalign.scene.photos import others_left_out

        found = others_left_out(found, models, seeds)  # each instance's colour models leave the others out
    guess = None
    if job.depth == "auto" and not (job.solve_scale or cameras_up_to_scale(scene_dir)):
        found = found.with_depth()  # metric depth and cameras of an unknown unit would disagree
    if job.solve_scale or cameras_up_to_scale(scene_dir):
        if not job.solve_scale:
            log.warning(f"{scene_dir / 'recon.json'} says the cameras have no metric scale: solving it from the "
                     "objects' size (as --solve-scale)")
        guess = scale_from_masks(found, models)
        found = rescaled(found, guess.factor)
        if seeds:
            factor, _ = scale_by_overlap(found, models, Path(job.init))
            found = rescaled(found, factor)
            guess = replace(guess, factor=guess.factor * factor)
        seeds = read_init_poses(job.init, found) if job.init is not None else {}  # their positions in mm
    missing = [i.index for i in found.instances if i.index not in seeds]
    if job.init is not None and missing:
        log.warning(f"{job.init} gives no pose for instance(s) {', '.join(map(str, missing))}; they are searched "
                 "from their masks instead")
    return SceneInputs(found, models, seeds, guess)


def scene_report(job: FolderJob, inputs: SceneInputs, refined: SceneRefinement, options: RefineOptions,
                 warnings: list[str]) -> SceneReport:
    """The report of a scene's refinement (its ``timings`` to be filled in)."""
    found, models = refined.found, inputs.models
    from autoalign.geometry.se3 import pose_change

    instances = [InstanceReport(r.instance.index, r.instance.obj_id, pos, models.path(r.instance.obj_id).absolute(),
                                r.result, r.verdict, r.instance.index in inputs.seeds,
                                [int(i) for i in found.scenes[pos].empty], models.symmetric(r.instance.obj_id),
                                r.seconds,
                                None if r.instance.index not in inputs.seeds or inputs.guess is not None else
                                pose_change(inputs.seeds[r.instance.index], r.result.T_wm,
                                            models.mesh(r.instance.obj_id).centre),
                                job.seed_radius_mm_deg if r.instance.index in inputs.seeds else None,
                                models.continuous_axes(r.instance.obj_id))
                 for pos, r in enumerate(refined.results)]
    scale = None
    if inputs.guess is not None:
        scale = ScaleReport(refined.scale_settled, inputs.guess.factor * refined.scale, refined.scale_sigma,
                            inputs.guess.factor, inputs.guess.spread)
    attempt = refined.with_cameras
    return SceneReport(
        scene_dir=Path(job.scene).absolute(), models=Path(job.models).absolute(),
        image_scale=found.scenes[0].image_scale if found.scenes else 1.0,
        instances_from=str(Path(job.instances).absolute()) if job.instances else "scene_gt.json of the scene",
        unmodelled=found.unmodelled, instances=instances, options=options, timings={}, warnings=warnings,
        joint=refined.joint, scale=scale, cameras_written=attempt is not None or scale is not None,
        cameras=None if attempt is None else cameras_record(attempt, refined.cameras_accepted),
        image_ids=[int(i) for i in found.image_ids])


def _warn_cameras_and_scale(refined: SceneRefinement, report: SceneReport, log: RunLog) -> None:
    """Warn of camera corrections that were dropped and of an uncertain scale (after the report:
    ``refine.json`` records both in its ``cameras`` and ``scale`` entries)."""
    from autoalign.scene.cameras import MIN_MISFIT_GAIN

    attempt = refined.with_cameras
    if attempt is not None and not refined.cameras_accepted:
        log.warning("--refine-cameras: the camera corrections explained too little of the misfit (median per-view "
                 f"1 - IoU {np.median(list(attempt.view_misfit_before.values())):.3f} -> "
                 f"{np.median(list(attempt.view_misfit_after.values())):.3f}, less than {MIN_MISFIT_GAIN:.0%} "
                 "lower), so the masks, not the cameras, are what is off; the given cameras are kept")
    if report.scale is not None and report.scale.sigma_relative > SCALE_SIGMA_WARN:
        log.warning(f"the scene's scale is uncertain: {report.scale.mm_per_unit:.4g} mm per unit, sigma "
                 f"{report.scale.sigma_relative:.1%}; more views of the objects from different distances, or "
                 "depth (recon --depth), pin it down")


def corrected_cameras(scene_dir: Path, found: InstanceScenes) -> dict[str, Any]:
    """``scene_camera.json`` with the cameras used at the end (corrected, or rescaled to mm); the
    images without any instance keep their given pose."""
    from autoalign.io.bop import read_cameras

    final = found.camera_by_id
    corrected = {}
    for im, (K, R, t) in read_cameras(scene_dir).items():
        T_cw = final[im].T_cw if im in final else np.vstack([np.column_stack([R, t]), [0, 0, 0, 1]])
        corrected[str(im)] = {"cam_K": K.ravel(), "cam_R_w2c": T_cw[:3, :3].ravel(), "cam_t_w2c": T_cw[:3, 3]}
    return corrected


def scene_overlay(refined: SceneRefinement, models: ModelSet, scene_dir: Path, detail: MeshDetail) -> np.ndarray:
    """The overlay of every instance in up to 9 views spread over the scene, each drawn at its
    pyramid's full-resolution ``detail``."""
    from autoalign.quality.overlay import instance_label, render_instances_overlay

    found = refined.found
    n = len(found.image_ids)
    views = sorted(set(np.linspace(0, n - 1, min(9, n)).round().astype(int).tolist()))
    cams = [found.cameras[i] for i in views]
    drawn = {found.image_ids[i] for i in views}
    layers = []
    for r, scene in zip(refined.results, found.scenes):
        rast = models.pyramid(r.instance.obj_id).fine(detail)
        masks = {v.image_id: np.asarray(v.mask) > 0.5 for v in scene.views if v.image_id in drawn}
        layers.append((instance_label(r.instance.obj_id, r.verdict.status), masks,
                       np.stack(rast.hard_masks(r.result.T_wm, cams))))
    return render_instances_overlay(found.cameras, found.image_ids, scene_dir, layers, views)
