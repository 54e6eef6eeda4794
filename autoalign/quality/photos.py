"""Photos as the check reads them: downscaled by a whole factor when large, with their ``cam_K``.

A photo of more than :data:`autoalign.io.bop.MAX_IMAGE_PIXELS` is read at ``1 / factor`` of its
size (:func:`autoalign.io.bop.downscale_factor`, the factor ``autoalign refine`` reads its masks at),
as exact block means (:func:`autoalign.io.block_mean.block_mean`, last blocks padded with the edge
pixels), so that its ``cam_K`` scales exactly (:func:`scaled_K`). Pixels: OpenCV / BOP ``cam_K``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import K_from_opencv, K_to_opencv
from autoalign.io.block_mean import Pad, block_mean
from autoalign.io.bop import MAX_IMAGE_PIXELS, downscale_factor, read_photo


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
