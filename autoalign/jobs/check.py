"""``autoalign.check``: a scene's labels checked without ground truth, as ``autoalign check`` does
it, without its argument parsing and printing.

Two checks: against the photos (SIFT feature distance and edge distance,
:mod:`autoalign.quality.scene_check`), or, with ``split_half``, the labels' precision from two
labels of every instance made from interleaved halves of the views, both seeded with the labels
being checked (:mod:`autoalign.quality.split_half`). Each half is refined exactly as ``autoalign
refine SCENE --models MODELS --init LABELS`` refines a scene
(:func:`~autoalign.jobs.refine_scene_folder.read_scene_inputs`, :func:`~autoalign.scene.refine.refine_scene`),
on the views of that half only.

Standard library only at import (the command's start-up stays fast); the rest loads inside.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from autoalign.errors import AutoalignError
from autoalign.jobs.job import FolderJob, RunLog

if TYPE_CHECKING:
    from autoalign.jobs.refine_scene_folder import SceneInputs
    from autoalign.quality.check_report import CheckReport
    from autoalign.quality.split_half import SplitHalfReport

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``."""


def check(scene_dir: str | os.PathLike[str], labels: str | os.PathLike[str], models_dir: str | os.PathLike[str],
          split_half: bool = False, images: int | None = None, photos: str = "auto", depth: str = "auto",
          progress: Progress | None = None, *, instances: Iterable[int] | None = None) -> CheckReport | SplitHalfReport:
    """Check the labels ``labels`` (BOP ``scene_gt.json``, mm) of the scene ``scene_dir`` with the
    models of ``models_dir``, without ground truth.

    Without ``split_half``: against the photos (``rgb/``), on ``images`` images spread over the
    scene (default all): :func:`autoalign.quality.scene_check.check_scene`, a
    :class:`~autoalign.quality.check_report.CheckReport`. With ``split_half``: both halves of the
    views refined from the labels and compared (:func:`split_half_check`, ``photos`` and ``depth``
    as evidence as ``autoalign refine`` takes them; ``instances``: only these of the labels'
    instances, by mask number, as ``autoalign refine --instances`` refines only some), a
    :class:`~autoalign.quality.split_half.SplitHalfReport`.

    Raises :class:`AutoalignError` (one line naming the file and the fix) for a mistake in the inputs.
    """
    if split_half:
        if images is not None:
            raise AutoalignError("images: the split-half check refines every view of the scene; leave images out")
        return split_half_check(scene_dir, labels, models_dir, photos, depth, progress, instances=instances)
    if instances is not None:
        raise AutoalignError("instances: only the split-half check takes them; the photo check checks every label")
    from autoalign.quality.scene_check import check_scene

    report: CheckReport = check_scene(scene_dir, labels, models_dir, images=images,
                                      progress=None if progress is None else
                                      lambda done, total: progress("checking images", done, total))
    return report


@dataclass
class SplitHalfInputs:
    """Everything the split-half check reads before refining, validated (:func:`prepare_split_half`):
    the job of one half (``autoalign refine SCENE --models MODELS --init LABELS``), what it read
    (instances from the labels, their scenes, models, seeds) and the two halves' image ids."""

    job: FolderJob
    inputs: SceneInputs
    halves: tuple[list[int], list[int]]
    log: RunLog


def prepare_split_half(scene_dir: str | os.PathLike[str], labels: str | os.PathLike[str],
                       models_dir: str | os.PathLike[str], photos: str = "auto", depth: str = "auto",
                       log: RunLog | None = None, *, instances: Iterable[int] | None = None) -> SplitHalfInputs:
    """Read and validate the split-half check's inputs: the instances are those the labels list
    (entry k of an image is mask ``..._{k:06d}.png``), each seeded with its label; each half must
    hold :data:`~autoalign.quality.split_half.MIN_HALF_VIEWS` views of every instance.

    ``instances`` (mask numbers): check only these of the labels' instances; the masks of the
    others are left as unmodelled instances, as ``autoalign refine --instances`` leaves them. A
    real scene needs it when the labels list objects that are not one pose over all its views
    (LM-O's objects moved between sub-sequences): refined as one they would disagree with
    themselves, not measure the labels' precision."""
    from autoalign.io.instances import instances_of_scene_gt
    from autoalign.jobs.refine_scene_folder import read_scene_inputs
    from autoalign.quality.split_half import MIN_HALF_VIEWS, interleaved_halves

    labels, scene_dir = Path(labels), Path(scene_dir)
    if not scene_dir.is_dir():
        raise AutoalignError(f"{scene_dir}: not a folder; give a BOP scene folder with scene_camera.json and "
                             "mask_visib/")
    job = FolderJob(str(scene_dir), "", models=str(models_dir), init=str(labels), photos=photos, depth=depth)
    job.check()
    listed = instances_of_scene_gt(labels, 'give the labels to check, a BOP scene_gt.json ({"0": [{"obj_id", '
                                           '"cam_R_m2c", "cam_t_m2c"}, ...], ...})')
    if instances is not None:
        wanted = sorted({int(k) for k in instances})
        if not wanted:
            raise AutoalignError("instances: none given; name the mask numbers to check, or leave instances out to "
                                 "check every label")
        by_index = {i.index: i for i in listed}
        absent = [k for k in wanted if k not in by_index]
        if absent:
            raise AutoalignError(f"{labels}: lists no instance {', '.join(map(str, absent))} (it lists "
                                 f"{', '.join(str(i.index) for i in listed)}); give instances that the labels list")
        listed = [by_index[k] for k in wanted]
    log = log if log is not None else RunLog()
    inputs = read_scene_inputs(job, log, listed)
    found = inputs.found
    unseeded = [i.index for i in found.instances if i.index not in inputs.seeds]
    if unseeded:
        raise AutoalignError(f"{labels}: no pose of instance(s) {', '.join(map(str, unseeded))} in an image of "
                             f"{scene_dir / 'scene_camera.json'}; the split-half check starts both halves from "
                             "the labels, so label every instance in at least one image of the scene")
    halves = interleaved_halves(found.image_ids)
    sets = [set(h) for h in halves]
    for inst, sc in zip(found.instances, found.scenes):
        counts = [sum(im in s for im in sc.image_ids) for s in sets]
        if min(counts) < MIN_HALF_VIEWS:
            raise AutoalignError(
                f"{scene_dir / 'mask_visib'}: instance {inst.index} (obj {inst.obj_id}) has masks in {len(sc)} views, "
                f"{counts[0]} and {counts[1]} in the two halves; --split-half needs at least {MIN_HALF_VIEWS} in "
                f"each ({2 * MIN_HALF_VIEWS} views in all): add views of it, or check it without --split-half")
    return SplitHalfInputs(job, inputs, halves, log)


def run_split_half(prepared: SplitHalfInputs, progress: Progress | None = None) -> SplitHalfReport:
    """Refine both halves of :func:`prepare_split_half`'s scene from the labels and compare them."""
    from autoalign.quality.split_half import (
        HalfLabel,
        SplitHalfReport,
        compare_halves,
    )
    from autoalign.scene.refine import refine_scene

    job, inputs = prepared.job, prepared.inputs
    found, models = inputs.found, inputs.models
    options = job.refine_options()
    halves: list[list[HalfLabel]] = []
    seconds = []
    for name, ids in zip("AB", prepared.halves):
        def step(stage: str, done: int, total: int, name: str = name) -> None:
            if progress is not None:
                progress(f"half {name}: {stage}", done, total)

        t0 = time.perf_counter()
        refined = refine_scene(found.views(ids), models, inputs.seeds, options, solve_scale=inputs.guess is not None,
                               progress=step, seed_radius=job.seed_radius_mm_deg)
        seconds.append(time.perf_counter() - t0)
        halves.append([HalfLabel.of(sc.image_ids, r.result.T_wm, r.verdict.status, r.verdict.reasons,
                                    r.result.uncertainty)
                       for r, sc in zip(refined.results, refined.found.scenes)])
    compared = []
    for k, (inst, sc) in enumerate(zip(found.instances, found.scenes)):
        mesh = models.mesh(inst.obj_id)
        compared.append(compare_halves(inst.index, inst.obj_id, mesh.centre, mesh.diameter, halves[0][k], halves[1][k],
                                       sc.cameras, sc.image_ids, models.symmetries(inst.obj_id)))
    return SplitHalfReport(Path(job.scene), Path(str(job.init)), Path(str(job.models)), prepared.halves, compared,
                           (seconds[0], seconds[1]), list(prepared.log.warnings))


def split_half_check(scene_dir: str | os.PathLike[str], labels: str | os.PathLike[str],
                     models_dir: str | os.PathLike[str], photos: str = "auto", depth: str = "auto",
                     progress: Progress | None = None, log: RunLog | None = None, *,
                     instances: Iterable[int] | None = None) -> SplitHalfReport:
    """:func:`prepare_split_half` then :func:`run_split_half` (see them)."""
    return run_split_half(prepare_split_half(scene_dir, labels, models_dir, photos, depth, log, instances=instances),
                          progress)
