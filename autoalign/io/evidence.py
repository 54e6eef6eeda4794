"""A scene's evidence, read as asked: its masks, its photos, its measured depth.

:func:`read_evidence` is what the Python API and ``autoalign refine`` read a scene with
(``modalities``: any of :data:`MODALITIES`); the several-object forms read every instance's
(:func:`instance_scenes_with_photos`, :func:`read_instance_scenes_without_masks`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.io.bop import (
    MAX_IMAGE_PIXELS,
    Scene,
    check_scene_dir,
    find_photo,
    id_list,
    mask_files,
    read_cameras,
    read_scene,
    with_depth,
)
from autoalign.io.instances import Instance, InstanceScenes
from autoalign.io.photos import read_scene_without_masks, with_photos

MODALITIES = ("masks", "photos", "depth")
"""The evidence a scene can carry."""


def read_evidence(scene_dir: str | Path, instance: int = 0, modalities: tuple[str, ...] = ("masks",),
                  max_pixels: int | None = MAX_IMAGE_PIXELS) -> Scene:
    """Cameras and the evidence named in ``modalities`` of instance ``instance`` of a BOP scene
    folder: its masks (:func:`~autoalign.io.bop.read_scene`); its photos (``rgb/``,
    :func:`~autoalign.io.photos.with_photos`); the measured depth (``depth/``,
    :func:`~autoalign.io.bop.with_depth`; none when the folder has none). Without ``"masks"``
    every view with a photo is used with empty masks, and the photos must be named."""
    unknown = [m for m in modalities if m not in MODALITIES]
    if unknown or not modalities:
        raise AutoalignError(f"modalities {tuple(modalities)!r}: choose from {MODALITIES}")
    if "masks" in modalities:
        scene = read_scene(scene_dir, instance, max_pixels)
        scene = with_photos(scene) if "photos" in modalities else scene
    elif "photos" in modalities:
        scene = read_scene_without_masks(scene_dir, max_pixels)
    else:
        raise AutoalignError("without masks the photos are the evidence: add 'photos' to the modalities")
    return with_depth(scene) if "depth" in modalities else scene


def instance_scenes_with_photos(found: InstanceScenes) -> InstanceScenes:
    """Every instance's scene with its photos as evidence (each photo read once)."""
    read: dict[int, NDArray[np.uint8]] = {}
    return replace(found, scenes=[with_photos(sc, read) for sc in found.scenes])


def read_instance_scenes_without_masks(scene_dir: str | Path, instances: list[Instance],
                                       max_pixels: int | None = MAX_IMAGE_PIXELS) -> InstanceScenes:
    """Every instance seen in every view that has a photo, with empty masks and the photos as
    evidence (``--models ... --masks none``)."""
    base = read_scene_without_masks(scene_dir, max_pixels)
    scenes = [replace(base) for _ in instances]
    return InstanceScenes(list(instances), scenes, list(base.cameras), list(base.image_ids), [])


def views_without_photos(scene_dir: str | Path, instance: int | None = None) -> list[int]:
    """The image ids with a camera and a mask file (of ``instance``; of any with ``None``) that have
    no photo in ``rgb/``; none when the folder has no ``rgb/`` (two photos of one image are an error)."""
    scene_dir = check_scene_dir(scene_dir)
    if not (scene_dir / "rgb").is_dir():
        return []
    cams = read_cameras(scene_dir)
    views = {im for im, k in mask_files(scene_dir) if im in cams and (instance is None or k == instance)}
    return sorted(im for im in views if find_photo(scene_dir, im) is None)


def photos_if_complete(scene_dir: str | Path, instance: int | None, warn: Callable[[str], None]) -> bool:
    """``--photos auto``: whether every view has its photo; if one lacks it, ``warn`` says (one line)
    that the run goes on with the masks alone (``--photos on`` stops there instead)."""
    missing = views_without_photos(scene_dir, instance)
    if missing:
        warn(f"{Path(scene_dir) / 'rgb'}: no photo of image(s) {id_list(missing)}, so the photos are not used "
             "(--photos auto); add them, or pass --photos off to say so, or --photos on to stop without them")
    return not missing
