"""Images downscaled by a whole factor as exact block means, so that the pixel grid stays exact.

Output pixel ``(i, j)`` is the mean of the file's pixels ``[j f, (j+1) f) x [i f, (i+1) f)``, as
:meth:`autoalign.geometry.camera.Camera.scaled` assumes (``K' = diag(1/f, 1/f, 1) K``, internal
convention). An image whose size is not a multiple of ``f`` is padded to whole blocks first.
"""

from __future__ import annotations

from enum import Enum

import cv2
from numpy.typing import NDArray


class Pad(Enum):
    """How the last, partial blocks are filled: with zeros (masks: no object beyond the image) or
    with the edge pixels (photos: no dark border)."""

    ZEROS = cv2.BORDER_CONSTANT
    EDGE = cv2.BORDER_REPLICATE


def block_mean(image: NDArray, factor: int, pad: Pad) -> NDArray:
    """``image`` (H, W[, C]) downscaled ``factor`` times by exact block means (same dtype; ``cv2.INTER_AREA``
    at a whole factor), to ``(ceil(H / factor), ceil(W / factor))``; ``factor`` 1 returns ``image``."""
    if factor == 1:
        return image
    H, W = image.shape[:2]
    h, w = -(-H // factor), -(-W // factor)
    if (h * factor, w * factor) != (H, W):  # padded only when needed: a large photo is copied once less
        image = cv2.copyMakeBorder(image, 0, h * factor - H, 0, w * factor - W, pad.value, value=0)
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
