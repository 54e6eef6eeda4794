"""Refine a BOP scene folder into an output folder: what ``autoalign refine`` does, without its
argument parsing and printing. One object (``model``) or every instance (``models``,
:mod:`autoalign.jobs.refine_scene_folder`); the outputs (``scene_gt.json``, ``refine.json``,
``overlay.png``, sometimes ``scene_camera.json``) are written all or none.

The command line, the batch runner (:mod:`autoalign.batch`, whose scene lists carry each scene's
options as text, parsed by the command's own parser: :func:`~autoalign.jobs.refine_arguments.scene_job`)
and Python users call
:func:`refine_folder`; its options and outcome are in :mod:`autoalign.jobs.job`.

Standard library only at import (the command's start-up stays fast); the rest loads inside.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from autoalign.jobs.job import (
    EXIT_FLAGGED,
    EXIT_OK,
    OUTPUT_FILES,
    FolderJob,
    FolderOutcome,
    NoProgress,
    RunLog,
    Stages,
    write_json_outputs,
)

if TYPE_CHECKING:
    from autoalign.jobs.report import RefineReport


def refine_folder(job: FolderJob, log: RunLog | None = None, progress: Stages | None = None,
                  t_start: float | None = None) -> FolderOutcome:
    """Refine ``job.scene`` and write its outputs into ``job.out`` (created if missing, removed
    again if the run fails). ``log`` collects the warnings (those before the report go into
    ``refine.json``); ``t_start``: when the run began (``time.perf_counter``), for its timings.

    Raises :class:`AutoalignError` (one line naming the file or option and the fix) for a mistake
    in the inputs; nothing is written then."""
    from autoalign.io.out_folder import (
        check_outputs_spare_inputs,
        prepare_out_dir,
        remove_empty_dirs,
    )
    from autoalign.runtime.interrupts import preload

    t_start = time.perf_counter() if t_start is None else t_start
    log = log if log is not None else RunLog()
    progress = progress if progress is not None else NoProgress()
    preload("numpy", "cv2")  # extension modules, with Ctrl-C deferred (trimesh: only for a mesh not in the cache)
    click = None
    if job.click is not None:
        from autoalign.engine.seeding import Click

        click = Click.parse(job.click)
    job.check()
    job = _photos_as_found(job, log)
    out = Path(job.out)
    inputs = [Path(x) for x in (job.model, job.init, job.instances) if x is not None]
    check_outputs_spare_inputs(out, Path(job.scene), inputs, OUTPUT_FILES)
    created = prepare_out_dir(out)
    try:
        if job.models is not None:
            from autoalign.jobs.refine_scene_folder import refine_scene_folder

            return refine_scene_folder(job, log, progress, t_start)
        return _refine_object(job, click, log, progress)
    except BaseException:
        remove_empty_dirs(created)
        raise


def _photos_as_found(job: FolderJob, log: RunLog) -> FolderJob:
    """``--photos auto`` with a view that lacks its photo: ``job`` with the photos off, and one warning
    in ``log`` saying so (:func:`~autoalign.io.evidence.photos_if_complete`); ``--photos on`` stops at
    the missing photo instead. The command, a batch's scenes and Python callers alike."""
    if job.photos != "auto" or job.masks == "none":  # without masks the photos are the evidence
        return job
    from dataclasses import replace

    from autoalign.io.evidence import photos_if_complete

    complete = photos_if_complete(job.scene, None if job.models is not None else job.instance, log.warning)
    return job if complete else replace(job, photos="off")


def _refine_object(job: FolderJob, click: Any, log: RunLog, progress: Stages) -> FolderOutcome:
    """:func:`refine_folder` with one object (``job.model``)."""
    from autoalign.engine.refine import refine
    from autoalign.geometry.mesh import load_mesh
    from autoalign.io.evidence import read_evidence
    from autoalign.jobs.table_plane import resting_plane
    from autoalign.quality.overlay import render_overlay
    from autoalign.rasterizers.pyramid import MeshPyramid

    scene = read_evidence(job.scene, job.instance, job.modalities)
    mesh = load_mesh(job.model, units=job.units)
    pyramid = MeshPyramid(mesh)
    seed, seed_record = _seed(job, scene, click)
    options = replace(job.refine_options(), resting=resting_plane(job.resting, job.scene, [scene]))
    progress.start("loading the renderer" if seed_record.kind == "init" else "seeding")
    try:
        result = refine(scene, pyramid, seed, options, progress=progress)
        progress("overlay", 0, 1)
        t0 = time.perf_counter()
        overlay = render_overlay(scene, pyramid.fine(options.detail), result.T_init, result.T_wm, result.iou_before,
                                 result.iou_after)
        progress("overlay", 1, 1)
    finally:
        progress.close()
    t_overlay = time.perf_counter() - t0
    report = _object_report(job, scene, mesh, result, seed_record, options, log)
    report.timings["overlay"] = t_overlay
    from autoalign.io.bop import scene_gt_dict
    from autoalign.quality.overlay import encode_png

    all_cams, all_ids = _all_cameras(scene)
    scene_gt = scene_gt_dict(result.T_wm, all_cams, all_ids, job.obj_id)
    paths = write_json_outputs(Path(job.out), {"scene_gt.json": scene_gt, "refine.json": report.to_json()},
                               {"overlay.png": encode_png(overlay)})
    notes = report.notes()
    if report.verdict.status != "ok":
        notes.append(f"verdict {report.verdict.status}: {'; '.join(report.verdict.reasons)}; look at overlay.png "
                     "before using this pose")
    status = EXIT_OK if report.verdict.status == "ok" else EXIT_FLAGGED
    return FolderOutcome(status, report, paths, notes)


def _seed(job: FolderJob, scene: Any, click: Any) -> tuple[Any, Any]:
    """The starting pose of ``job`` (a 4x4, a :class:`~autoalign.engine.seeding.Click` in the
    scene's pixels, or ``None``) and its record for the report."""
    import numpy as np

    from autoalign.io.bop import read_init_pose
    from autoalign.jobs.report import Seed

    if job.init is not None:
        seed = read_init_pose(job.init, scene, job.obj_id, job.instance)
        return seed, Seed("init", str(Path(job.init).absolute()), None, seed)
    if click is not None:
        from autoalign.engine.seeding import check_click
        from autoalign.geometry.camera import uv_to_opencv

        u, v = uv_to_opencv(np.array([click.u, click.v]))  # as typed: OpenCV pixels of the image files
        record = Seed("click", None, {"image_id": click.image_id, "u": float(u), "v": float(v)})
        click = click.scaled(scene.image_scale)
        check_click(scene, click)  # fail now, before the slow start-up of the renderer
        return click, record
    return None, Seed()


def _object_report(job: FolderJob, scene: Any, mesh: Any, result: Any, seed: Any, options: Any,
                   log: RunLog) -> RefineReport:
    """The report of one object's refinement (:class:`~autoalign.jobs.report.RefineReport`)."""
    from autoalign.jobs.report import RefineReport, RunnerUp
    from autoalign.quality.verdict import PoseEvidence, judge

    ids = [int(i) for i in result.image_ids or scene.image_ids]
    from autoalign.geometry.se3 import pose_change

    seed_move = None if seed.pose is None else pose_change(seed.pose, result.T_wm, mesh.centre)
    verdict = judge(replace(PoseEvidence.of(result, tuple(scene.empty), seed_move=seed_move,
                                            seed_radius=job.seed_radius_mm_deg), image_ids=ids))
    if seed_move is not None:
        seed.moved = seed_move
        seed.radius = job.seed_radius_mm_deg
    return RefineReport(
        scene_dir=Path(job.scene).absolute(), model=Path(job.model).absolute(), obj_id=job.obj_id,
        instance=job.instance, result=result, verdict=verdict, seed=seed, image_ids=ids,
        T_cm_first=scene.cameras[0].T_cw @ result.T_wm, runner_up=RunnerUp.of(result, mesh.centre),
        skipped=[int(i) for i in scene.skipped], empty=[int(i) for i in scene.empty],
        image_scale=scene.image_scale, options=options, timings=dict(result.timings), warnings=list(log.warnings))


def _all_cameras(scene: Any) -> tuple[list[Any], list[int]]:
    """Cameras and ids of every image in scene_camera.json (also those skipped for lack of a mask)."""
    from autoalign.geometry.camera import Camera
    from autoalign.io.bop import read_cameras

    if scene.path is None:
        return list(scene.cameras), list(scene.image_ids)
    W, H = scene.cameras[0].width, scene.cameras[0].height
    cams = read_cameras(Path(scene.path))
    return [Camera.from_opencv(K, R, t, W, H) for K, R, t in cams.values()], list(cams)

