"""The check of a scene's labels: its inputs read and validated before any photo
(:func:`prepare_check`), then one image at a time (:func:`check_prepared`), and the scene's report.

Conventions as :mod:`autoalign.quality.check`: BOP files, mm, OpenCV / BOP ``cam_K``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.io.bop import (
    MAX_IMAGE_PIXELS,
    Label,
    depth_scales,
    mask_path,
    photo_path,
    read_cameras,
    read_depth,
    read_labels,
    read_masks,
)
from autoalign.io.models import FEATURELESS, ColouredMesh, ModelSet
from autoalign.io.photos import ScaledPhoto, read_photo_scaled, scaled_K
from autoalign.quality.check import check_image, summarize
from autoalign.quality.check_report import CheckReport, ViewInstanceCheck
from autoalign.quality.stats import pooled_mean_ci


def select_images(image_ids: Sequence[int], n: int | None) -> list[int]:
    """``n`` image ids spread evenly over ``image_ids`` (sorted; first and last included), or all."""
    ids = sorted(image_ids)
    if n is None or n >= len(ids):
        return ids
    if n <= 1:
        return ids[:max(n, 0)]
    picks = np.unique(np.rint(np.linspace(0, len(ids) - 1, n)).astype(int))
    return [ids[i] for i in picks]


@dataclass
class CheckInputs:
    """Everything a check reads before its first image, validated (:func:`prepare_check`): the labels
    (BOP ``scene_gt.json``, mm), the scene's cameras (file ``cam_K``, px), the images to check, their
    photos' paths and the meshes (mm) of the objects labelled there."""

    scene_dir: Path
    labels_path: Path
    models_dir: Path
    labels: dict[int, list[Label]]
    cameras: dict[int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
    image_ids: list[int]
    photos: dict[int, Path]
    meshes: dict[int, ColouredMesh]
    warnings: list[str] = field(default_factory=list)
    materials: dict[int, str] = field(default_factory=dict)


def prepare_check(scene_dir: str | Path, labels_path: str | Path, models_dir: str | Path,
                  images: int | None = None, image_ids: Sequence[int] | None = None,
                  labels: Mapping[int, list[Label]] | None = None) -> CheckInputs:
    """Read and validate the inputs of a check (no photo is read, nothing is rendered).

    ``images``: check only that many images, spread evenly over the labelled ones (default all);
    ``image_ids``: or exactly these labelled images (then ``images`` is ignored); ``labels``: the
    labels file as :func:`autoalign.io.bop.read_labels` read it, if already read. Raises
    :class:`AutoalignError` (naming the file and the fix) for missing or malformed inputs.
    """
    scene_dir, labels_path, models_dir = Path(scene_dir), Path(labels_path), Path(models_dir)
    if not scene_dir.is_dir():
        raise AutoalignError(f"{scene_dir}: not a folder; give a BOP scene folder with scene_camera.json and rgb/")
    labels = dict(labels) if labels is not None else read_labels(labels_path)
    cameras = read_cameras(scene_dir)
    missing = [i for i in labels if i not in cameras]
    if missing:
        raise AutoalignError(f"{labels_path}: image {missing[0]} has no camera in {scene_dir / 'scene_camera.json'} "
                             f"({len(missing)} image(s) like this); label only images of the scene or add their cameras")
    labelled = [i for i, labs in labels.items() if labs]
    if not labelled:
        raise AutoalignError(f"{labels_path}: no image has a label; give a scene_gt.json with at least one pose")
    if image_ids is not None:
        unknown = [i for i in image_ids if i not in labelled]
        if unknown:
            raise AutoalignError(f"{labels_path}: image {unknown[0]} has no label; choose labelled images")
        chosen = sorted(set(int(i) for i in image_ids))
    else:
        chosen = select_images(labelled, images)
    photos = {im: photo_path(scene_dir, im) for im in chosen}
    models = ModelSet.read(models_dir, with_info=False)  # the check needs no models_info.json
    meshes = models.coloured_meshes([lab.obj_id for i in chosen for lab in labels[i]], labels_path)
    warnings = [f"{m.path}: no vertex colours; rendered grey, so few matches are expected"
                for obj, m in meshes.items() if not m.has_colours and models.materials.get(obj) not in FEATURELESS]
    return CheckInputs(scene_dir, labels_path, models_dir, labels, cameras, chosen, photos, meshes, warnings,
                       models.materials)


def check_prepared(inputs: CheckInputs, seed: int = 0, progress: Any = None,
                   max_pixels: int | None = MAX_IMAGE_PIXELS) -> CheckReport:
    """Check the labels of :func:`prepare_check`'s ``inputs`` on their photos, one image at a time
    (only one photo, its masks and its rendering are held at once).

    Photos and masks of more than ``max_pixels`` are read downscaled by a whole factor, ``cam_K``
    with them (:func:`read_photo_scaled`; ``None``: full size). ``progress``: optional
    ``callable(done, total)`` called before the first image and after each.
    """
    views: list[ViewInstanceCheck] = []
    scales: dict[int, float] = {}
    chosen = inputs.image_ids
    featureless = {o for o, m in inputs.materials.items() if m in FEATURELESS}
    depth_scale = depth_scales(inputs.scene_dir) if (inputs.scene_dir / "depth").is_dir() else None
    if progress is not None:
        progress(0, len(chosen))
    for n_done, im in enumerate(chosen, 1):
        photo = read_photo_scaled(inputs.photos[im], max_pixels)
        paths = {(im, lab.instance): mask_path(inputs.scene_dir, im, lab.instance) for lab in inputs.labels[im]}
        read = read_masks({k: p for k, p in paths.items() if p.is_file()}, max_pixels)
        if read.size is not None and read.size != photo.size:
            p = next(p for p in paths.values() if p.is_file())
            raise AutoalignError(f"{p}: mask is {read.size[1]}x{read.size[0]} but the photo is {photo.size[1]}x"
                                 f"{photo.size[0]}; masks must have the photo's size")
        masks = {inst: m for (_, inst), m in read.masks.items()}  # empty masks: none, as in autoalign.io.bop
        K = scaled_K(inputs.cameras[im][0], photo.factor)
        depth = None if depth_scale is None else _depth_as_checked(inputs.scene_dir, im, depth_scale.get(im, 1.0),
                                                                   photo)
        _, checks = check_image(im, photo.bgr, K, inputs.labels[im], inputs.meshes, masks, seed,
                                featureless=featureless, depth_mm=depth)
        views.extend(checks)
        scales[im] = 1.0 / photo.factor
        del photo, read, masks  # before the next image's are read
        if progress is not None:
            progress(n_done, len(chosen))
    instances = summarize(views, seed, inputs.materials)
    ok = {(s.instance, s.obj_id) for s in instances if s.mean_px is not None}
    groups = [v.distances_px for v in views if v.n_matches and (v.instance, v.obj_id) in ok]
    n = int(sum(len(g) for g in groups))
    mean, ci = pooled_mean_ci(groups, np.random.default_rng([seed, 2_000_003]))
    edge, edge_ci = pooled_mean_ci([v.edge_distances for v in views if v.edge_px is not None],
                                   np.random.default_rng([seed, 4_000_037]))
    return CheckReport(inputs.scene_dir, inputs.labels_path, inputs.models_dir, chosen, views, instances, mean, ci, n,
                       seed, list(inputs.warnings), edge, edge_ci, scales, max_pixels)


def _depth_as_checked(scene_dir: Path, image_id: int, scale: float, photo: ScaledPhoto) -> NDArray[np.float64] | None:
    """The depth of ``image_id`` (mm, 0 = none) at the photo's size as checked (every ``factor``-th
    pixel of a downscaled one: depth is not averaged across an object's edge), or ``None``."""
    H, W = photo.size
    depth = read_depth(scene_dir, image_id, scale, (W, H))
    if depth is None or photo.factor == 1:
        return depth
    h, w = photo.bgr.shape[:2]
    f = photo.factor
    return np.ascontiguousarray(depth[f // 2::f, f // 2::f][:h, :w])


def check_scene(scene_dir: str | Path, labels_path: str | Path, models_dir: str | Path,
                images: int | None = None, seed: int = 0, image_ids: Sequence[int] | None = None,
                progress: Any = None, max_pixels: int | None = MAX_IMAGE_PIXELS) -> CheckReport:
    """Check the labels of ``labels_path`` (BOP scene_gt.json, mm) on the photos of ``scene_dir``:
    :func:`prepare_check` then :func:`check_prepared` (see them for the arguments)."""
    return check_prepared(prepare_check(scene_dir, labels_path, models_dir, images, image_ids), seed, progress,
                          max_pixels)
