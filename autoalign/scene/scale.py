"""The scene scale of cameras known only up to scale (structure from motion without depth:
``autoalign recon`` on RGB), from the known size of the objects in their masks.

A reconstruction from photos alone fixes the cameras up to a similarity: their translations are
in an arbitrary unit. :func:`scale_from_masks` gives a first guess of the millimetres per unit
from the masks' areas; :func:`scaled_cameras` applies it; the joint stage then solves the scale
exactly as a 7th parameter with the poses (:func:`autoalign.scene.joint.refine_jointly`,
``with_scale``), which is what the ProgressLabeller paper had a person do by dragging the object.

The first guess uses Cauchy's formula: a convex body's projected area, averaged over all
directions, is a quarter of its surface area ``S``. An object of hull area ``S`` (mm^2) at depth
``z`` (mm) covers about ``f^2 S / (4 z^2)`` pixels, so a mask of ``A`` pixels puts it at
``z = f sqrt(S / 4A)``; its depth in reconstruction units comes from the point nearest to the
rays through its masks' centroids. The median over views and instances of ``z_mm / z_unit`` is the
guess. It assumes the views' directions spread evenly around the object: on eight one-object
scenes of the scene benchmark it was within 3% for six, 11% for one and 39% off for a thin bar
seen from above more than edge-on. Once an orientation is known (a seed's, or the one the first
round found: rotations need no scale), the model drawn in it gives the scale within 1.7% on the
same eight, and the joint stage solves it exactly (it converges from 30-40% off when the
orientations are right).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import CENTROID_OUTLIER
from autoalign.engine.seeding import closest_point_to_rays
from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_json_file
from autoalign.io.instances import InstanceScenes
from autoalign.io.models import ModelSet
from autoalign.rasterizers.pyramid import MeshDetail


@dataclass(frozen=True)
class ScaleGuess:
    """``factor``: by how much to multiply the cameras' translations to have them in mm;
    ``spread``: the relative spread of the per-view estimates (half their 16-84 percentile range;
    for several instances, that of the weighted combination); ``views``: how many views gave one."""

    factor: float
    spread: float
    views: int


def scale_from_masks(found: InstanceScenes, models: ModelSet,
                     rotations: dict[int, NDArray[np.float64]] | None = None,
                     use: list[bool] | None = None) -> ScaleGuess:
    """The factor that puts ``found``'s camera translations in mm, from every instance's masks and
    its model's size. Each instance sits at the point nearest the rays through its masks'
    centroids. Without its world-from-model rotation (``rotations[index]``, 3x3) its expected
    area is Cauchy's (see module doc); with one, the model is rendered there in that orientation,
    and a view's estimate is ``sqrt(rendered area / mask area)``: the orientation is known in every
    view, because rotations do not depend on the scale. The rendered area leaves out the pixels that
    another instance's mask claims (:attr:`~autoalign.io.bop.Scene.ignore`), where this object may be
    hidden: counted, every occluded view grew the estimate (1.10-1.14 at the true scale and
    orientations on 3- and 4-object scenes of ``bench_scene``; 1.007-1.033 without them).

    Each instance's estimate is the median of its views'; they are combined in log scale weighted
    by ``views / spread^2``, the precision of that median. Masks that miss parts or are hidden make
    the estimate too large, masks that leak or cover another object too small, and both spread
    the views' estimates: on the real LM-O scene ``lmo_im0115_0389`` the cat's SAM masks gave
    0.99 of the true scale with a spread of 11%, the driller's, egg box's and glue's 1.18-1.84
    with spreads of 37-48%; pooling all views gave 1.45, the weighting about 1.1. ``use`` (per
    instance, default all): the instances that count, e.g. those whose pose fits its masks."""
    per_instance = []
    for k, (inst, scene) in enumerate(zip(found.instances, found.scenes)):
        if use is not None and not use[k]:
            continue
        ratios: list[float] = []
        mesh = models.mesh(inst.obj_id)
        seen = [(v, m) for v in scene.views if (m := v.mask > 0.5).any()]  # each mask thresholded once
        views = [(v.camera, m) for v, m in seen]
        if len(views) < 2:
            continue
        centroids = [np.argwhere(m).mean(0) for _, m in views]  # (row, column)
        rays = np.array([cam.pixel_rays(c[1], c[0])[0] for (cam, _), c in zip(views, centroids)])
        X = closest_point_to_rays(np.array([cam.centre for cam, _ in views]), rays, outlier=CENTROID_OUTLIER)
        areas = np.array([m.sum() for _, m in views], dtype=np.float64)
        R = None if rotations is None else rotations.get(inst.index)
        if R is None:
            hull_area = float(mesh.trimesh.convex_hull.area)  # mm^2
            for (cam, _), area in zip(views, areas):
                z = float(cam.R_w2c[2] @ X + cam.t_w2c[2])
                if z > 0:
                    f = float(np.sqrt(abs(np.linalg.det(cam.K[:2, :2]))))
                    ratios.append(f * np.sqrt(hull_area / (4.0 * area)) / z)
        else:
            T = make_pose(R, X - R @ mesh.centre)
            drawn = models.pyramid(inst.obj_id).with_faces(AREA_DETAIL).hard_masks(T, [cam for cam, _ in views])
            drawn = [d if v.ignore is None else d & ~v.ignore for d, (v, _) in zip(drawn, seen)]  # where not hidden
            ratios += [float(np.sqrt(d.sum() / a)) for d, a in zip(drawn, areas) if d.any()]
        if ratios:
            per_instance.append(_robust(np.asarray(ratios)))
    if not per_instance:
        raise AutoalignError("the scene scale cannot be guessed: no instance has a non-empty mask in two views "
                             "with its centre in front of the cameras; check the masks and scene_camera.json")
    w = np.array([g.views / max(g.spread, MIN_SPREAD) ** 2 for g in per_instance])
    log_scale = float(np.sum(w * np.log([g.factor for g in per_instance])) / w.sum())
    spread = float(np.sqrt(1.0 / np.sum(w / np.array([g.views for g in per_instance]))))
    return ScaleGuess(float(np.exp(log_scale)), spread, sum(g.views for g in per_instance))


def scale_by_overlap(found: InstanceScenes, models: ModelSet, init_path: str | os.PathLike[str],
                     factors: NDArray[np.float64] | None = None, resolution: float = 0.25) -> tuple[float, float]:
    """The factor (of ``factors``, default 0.6-1.6 in steps of 2%) that makes the coarse poses of
    ``init_path`` overlap their masks best, and that best mean IoU. The init gives each pose in one
    camera's frame, in mm whatever the scale; every other camera sees it where the scale puts
    that camera, so at a wrong scale the far views miss the object. This is the paper's human
    dragging the object until it fits, done as a search over one number: the joint stage needs a
    start within about 10% on real masks (the alone stage lost every object of a real LM-O scene
    started 10% off), which the masks' areas do not give when the masks miss parts."""
    from autoalign.io.instances import read_init_poses
    from autoalign.losses.overlap import mask_iou

    factors = np.exp(np.arange(np.log(0.6), np.log(1.6), np.log(1.02))) if factors is None else factors
    rasts = {inst.index: models.pyramid(inst.obj_id).at(resolution) for inst in found.instances}
    small = [[cv2.resize(m, None, fx=resolution, fy=resolution, interpolation=cv2.INTER_AREA) > 0.5 for m in sc.masks]
             for sc in found.scenes]
    scores = []
    for f in factors:
        grown = rescaled(found, float(f))
        seeds = read_init_poses(init_path, grown)
        ious = []
        for k, (inst, sc) in enumerate(zip(grown.instances, grown.scenes)):
            if inst.index in seeds:
                drawn = rasts[inst.index].hard_masks(seeds[inst.index], [c.scaled(resolution) for c in sc.cameras])
                ious += [mask_iou(d, m) for d, m in zip(drawn, small[k])]
        scores.append(float(np.mean(ious)) if ious else 0.0)
    best = int(np.argmax(scores))
    return float(factors[best]), scores[best]


MIN_SPREAD = 0.02
"""An instance's spread counts as at least this in the weighting: a few clean views must not
outweigh every other instance."""


def _robust(ratios: NDArray[np.float64]) -> ScaleGuess:
    """The median of per-view estimates and their spread (half the 16-84 percentile range, relative)."""
    med = float(np.median(ratios))
    lo, hi = np.percentile(ratios, [16, 84])
    return ScaleGuess(med, float((hi - lo) / 2.0 / med), len(ratios))


AREA_DETAIL = MeshDetail().coarse
"""The model is drawn with at most this many triangles for the scale's estimate (its area only)."""


def scaled_cameras(cameras: dict[int, Camera], factor: float,
                   about: NDArray[np.float64] | None = None) -> dict[int, Camera]:
    """``cameras`` with every centre moved ``factor`` times as far from ``about`` (world; default
    the origin), orientations and intrinsics kept: the same views of a scene ``factor`` times as large."""
    p = np.zeros(3) if about is None else np.asarray(about, dtype=np.float64)
    return {im: replace(c, t_w2c=-c.R_w2c @ (p + factor * (c.centre - p))) for im, c in cameras.items()}


def cameras_up_to_scale(scene_dir: str | os.PathLike[str]) -> bool:
    """Whether ``scene_dir/recon.json`` (written by ``autoalign recon``) says its cameras have no
    metric scale (a reconstruction from RGB alone); ``False`` without one."""
    path = Path(scene_dir) / "recon.json"
    if not path.is_file():
        return False
    fix = "write it again with autoalign recon, or remove it if the cameras are in mm"
    data = read_json_file(path, fix)
    if not isinstance(data, dict):
        raise AutoalignError(f"{path}: not the report of autoalign recon; {fix}")
    return data.get("metric") is False


def rescaled(found: InstanceScenes, factor: float) -> InstanceScenes:
    """``found`` with every camera's translation times ``factor`` (:func:`scaled_cameras` about the origin)."""
    return found.through(scaled_cameras(found.camera_by_id, factor))


def grown_pose(T_wm: NDArray[np.float64], centre_m: NDArray[np.float64], factor: float) -> NDArray[np.float64]:
    """``T_wm`` (world from model, mm) moved with a scene grown ``factor`` times about the world
    origin: its centre ``centre_m`` (model frame) goes ``factor`` times as far from the origin."""
    out = np.array(T_wm, dtype=np.float64)
    out[:3, 3] += (factor - 1.0) * (out[:3, :3] @ centre_m + out[:3, 3])
    return out
