"""Refine every instance of a multi-object scene, each with a verdict.

Each instance is refined against its own masks, its views' pixels that other instances' masks
claim being ignored (:mod:`autoalign.instances`): where another object hides it, or another mask
strayed onto it, its silhouette costs nothing. Measured on a synthetic five-object scene with
mutual occlusion (40 views, masks from open3d ray casting, starts 10 mm / 15 degrees off), this
took the errors from 0.26-6.9 mm to 0.02-0.08 mm (README, "Several objects").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.camera_refine import CameraRefinement, refine_cameras
from autoalign.engine import RefineOptions, RefineResult, refine
from autoalign.instances import Instance, InstanceScenes
from autoalign.models import ModelSet
from autoalign.verdict import Verdict, judge

if TYPE_CHECKING:
    from autoalign.camera import Camera

Progress = Callable[[str, int, int], None]


@dataclass
class InstanceResult:
    """One instance's refined pose (``result.T_wm``, world from model, mm), its verdict and time (s)."""

    instance: Instance
    result: RefineResult
    verdict: Verdict
    seconds: float


def refine_instances(found: InstanceScenes, models: ModelSet, seeds: dict[int, NDArray[np.float64]],
                     options: RefineOptions | None = None, progress: Progress | None = None) -> list[InstanceResult]:
    """Refine every instance of ``found`` from its seed (``seeds[index]``: 4x4 world-from-model, mm;
    an instance without one is searched from the visual hull of its masks)."""
    out = []
    n = len(found.instances)
    for k, (inst, scene) in enumerate(zip(found.instances, found.scenes)):
        t0 = time.perf_counter()
        label = f"obj {inst.obj_id} (instance {inst.index}, {k + 1}/{n})"

        def step(stage: str, done: int, total: int, label: str = label) -> None:
            if progress is not None:
                progress(f"{label}: {stage}", done, total)

        result = refine(scene, models.mesh(inst.obj_id), seeds.get(inst.index), options, progress=step)
        verdict = judge(result.iou_after, result.weights, result.image_ids, scene.empty, result.ambiguous,
                        models.symmetric(inst.obj_id), result.uncertainty, models.continuous_axes(inst.obj_id))
        out.append(InstanceResult(inst, result, verdict, time.perf_counter() - t0))
    return out


def with_cameras(found: InstanceScenes, cameras: dict[int, "Camera"]) -> InstanceScenes:
    """``found`` seen through ``cameras`` (by image id), e.g. corrected ones."""
    return replace(found, scenes=[replace(sc, cameras=[cameras[im] for im in sc.image_ids]) for sc in found.scenes],
                   cameras=[cameras.get(im, c) for im, c in zip(found.image_ids, found.cameras)])


def refine_instances_and_cameras(found: InstanceScenes, models: ModelSet, seeds: dict[int, NDArray[np.float64]],
                                 options: RefineOptions | None = None, progress: Progress | None = None
                                 ) -> tuple[list[InstanceResult], CameraRefinement, InstanceScenes]:
    """Each instance alone, then every pose and a correction of every camera together
    (:func:`~autoalign.camera_refine.refine_cameras`), then each instance again through the
    corrected cameras from its joint pose (its per-view fit, uncertainty and verdict then describe
    the corrected scene). When the corrections explain too little of the misfit to be trusted
    (``CameraRefinement.accepted``), the instances' own results and the given cameras are kept.
    Returns the results, the camera refinement and the scenes they were refined in."""
    alone = refine_instances(found, models, seeds, options, progress)
    if progress is not None:
        progress("refining cameras with the objects", 0, 1)
    joint = refine_cameras(found, [models.mesh(r.instance.obj_id) for r in alone], [r.result.T_wm for r in alone])
    if progress is not None:
        progress("refining cameras with the objects", 1, 1)
    if not joint.accepted:
        return alone, joint, found
    corrected = with_cameras(found, joint.cameras)
    seeds_after = {r.instance.index: T for r, T in zip(alone, joint.poses)}
    return refine_instances(corrected, models, seeds_after, options, progress), joint, corrected
