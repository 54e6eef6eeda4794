"""Photos as the check and the region term read them: downscaled by a whole factor when large, with their ``cam_K``.

A photo of more than :data:`autoalign.io.bop.MAX_IMAGE_PIXELS` is read at ``1 / factor`` of its
size (:func:`autoalign.io.bop.downscale_factor`, the factor ``autoalign refine`` reads its masks at),
as exact block means (:func:`autoalign.io.block_mean.block_mean`, last blocks padded with the edge
pixels), so that its ``cam_K`` scales exactly (:func:`scaled_K`). Pixels: OpenCV / BOP ``cam_K``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera, K_from_opencv, K_to_opencv
from autoalign.io.block_mean import Pad, block_mean
from autoalign.io.bop import (
    MAX_IMAGE_PIXELS,
    Scene,
    check_scene_dir,
    downscale_factor,
    find_photo,
    read_cameras,
    read_photo,
)


@dataclass
class ScaledPhoto:
    """A photo as checked: ``bgr`` (h, w, 3) uint8 at ``1 / factor`` of the file's ``size`` (H, W)."""

    bgr: NDArray[np.uint8]
    factor: int
    size: tuple[int, int]


def read_photo_scaled(path: Path, max_pixels: int | None = MAX_IMAGE_PIXELS) -> ScaledPhoto:
    """A photo (BGR) downscaled by :func:`autoalign.io.bop.downscale_factor` when it has more than
    ``max_pixels`` pixels: output pixel (i, j) is the mean of the file's pixels
    ``[j f, (j+1) f) x [i f, (i+1) f)``, the last blocks padded with the edge pixels, as
    :meth:`autoalign.geometry.camera.Camera.scaled` assumes (:func:`autoalign.io.bop.read_masks`
    does the same to the masks, padding with zeros)."""
    img = read_photo(path)
    H, W = img.shape[:2]
    f = downscale_factor(W, H, max_pixels)
    return ScaledPhoto(block_mean(img, f, Pad.EDGE), f, (H, W))


def scaled_K(K: NDArray[np.float64], factor: int) -> NDArray[np.float64]:
    """OpenCV / BOP ``cam_K`` of the image read at ``1 / factor`` (:func:`read_photo_scaled`): scaled in
    autoalign's internal convention (pixel edges on integers, see :mod:`autoalign.geometry.camera`), so a file
    ``cx`` becomes ``(cx + 0.5) / factor - 0.5``."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if factor == 1:
        return K
    return K_to_opencv(np.diag([1.0 / factor, 1.0 / factor, 1.0]) @ K_from_opencv(K))


def read_scene_photos(scene: Scene, read: dict[int, NDArray[np.uint8]] | None = None) -> list[NDArray[np.uint8]]:
    """The photo (BGR uint8) of every view of ``scene`` at the masks' resolution: the file read at
    ``1 / factor`` (:func:`read_photo_scaled`) with the factor the masks were read at. ``read``
    (image id -> photo) keeps what was read for the next instance of the same folder."""
    if scene.path is None:
        raise AutoalignError("the scene was not read from a folder: give its photos as Scene.photos")
    read = {} if read is None else read
    factor = int(round(1.0 / scene.image_scale))
    for im, cam in zip(scene.image_ids, scene.cameras):
        if im in read:
            continue
        path = find_photo(scene.path, im)
        if path is None:
            raise AutoalignError(f"{scene.path / 'rgb' / f'{im:06d}'}.png (or .jpg): not found; the photos are evidence "
                                 f"here (--photos): put image {im}'s photo in {scene.path / 'rgb'}, or pass --photos off")
        photo = read_photo_scaled(path, None if factor == 1 else MAX_IMAGE_PIXELS)
        if photo.bgr.shape[:2] != (cam.height, cam.width):
            raise AutoalignError(f"{path}: the photo is {photo.size[1]}x{photo.size[0]} but its masks are "
                                 f"{round(cam.width / scene.image_scale)}x{round(cam.height / scene.image_scale)}; "
                                 "give photos and masks of one size")
        read[im] = photo.bgr
    return [read[im] for im in scene.image_ids]


def with_photos(scene: Scene, read: dict[int, NDArray[np.uint8]] | None = None) -> Scene:
    """``scene`` with its photos as evidence (:attr:`~autoalign.io.bop.Scene.photos`, :func:`read_scene_photos`)."""
    return replace(scene, photos=read_scene_photos(scene, read))


def read_scene_without_masks(scene_dir: str | Path, max_pixels: int | None = MAX_IMAGE_PIXELS) -> Scene:
    """The views of a BOP scene folder that have a camera and a photo, with empty masks and the
    photos as evidence (``--masks none``): the photo alone places the object."""
    scene_dir = check_scene_dir(scene_dir)
    cams = read_cameras(scene_dir)
    photos = {im: p for im in cams if (p := find_photo(scene_dir, im)) is not None}
    if not photos:
        raise AutoalignError(f"{scene_dir / 'rgb'}: no photos named {{im_id:06d}}.png for the images of "
                             "scene_camera.json; without masks the photos are the evidence")
    ids = list(photos)
    H, W = read_photo(photos[ids[0]]).shape[:2]
    f = downscale_factor(W, H, max_pixels)
    cameras = [Camera.from_opencv(*cams[im], W, H).scaled(1.0 / f) for im in ids]
    masks = [np.zeros((c.height, c.width), np.float32) for c in cameras]
    scene = Scene(cameras, masks, ids, scene_dir, image_scale=1.0 / f)
    return with_photos(scene)
