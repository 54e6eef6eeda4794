"""SIFT keypoints of a photo and of a rendering, and their matches (OpenCV: brute force, Lowe's ratio test).

Keypoint positions are OpenCV / BOP pixel coordinates (the centre of pixel (row i, col j) at (j, i)),
in the pixels of the image given, whatever resolution SIFT sees it at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import uv_from_opencv, uv_to_opencv

RATIO_TEST = 0.8
"""Lowe's ratio: a match is kept when its descriptor distance is below this times the second best's."""
MAX_MATCH_PX = 10.0
"""A kept match's keypoints are closer than this in the image (px)."""
UPSAMPLE = 2
"""Both images are enlarged this many times (bilinear) before SIFT: LM-O-sized objects (50-150 px
across at 640x480) give three to four times more matches than at native size (measured on LM-O
scene 2); keypoint positions are mapped back to the original pixels."""
MAX_SIFT_PIXELS = 640 * 480 * UPSAMPLE ** 2
"""SIFT sees at most this many pixels (an LM-O photo enlarged ``UPSAMPLE`` times): a photo larger than
640 x 480 is searched only in its region around the labels
(:data:`autoalign.quality.check_report.CONTEXT_PX`), enlarged ``UPSAMPLE`` times while that fits and
reduced to fit otherwise (SIFT's own pyramid of a 12-megapixel photo enlarged twice took 11 GB and 24 s)."""


@dataclass
class Features:
    """SIFT keypoint positions (n, 2) (u, v OpenCV px) and descriptors (n, 128) float32."""

    uv: NDArray[np.float64]
    descriptors: NDArray[np.float32]

    def subset(self, keep: NDArray[np.bool_]) -> "Features":
        return Features(self.uv[keep], self.descriptors[keep])

    def moved(self, du: float, dv: float) -> "Features":
        """The same keypoints with (du, dv) px added to their positions (a crop's to the photo's)."""
        return Features(self.uv + [du, dv], self.descriptors)


def sift_features(gray: NDArray[np.uint8], upsample: float = UPSAMPLE) -> Features:
    """SIFT keypoints (``cv2.SIFT_create`` defaults) of a grey image resized ``upsample`` times
    (bilinear when enlarged, area-averaged when reduced; pixel centres aligned); positions in the
    original image's OpenCV pixels."""
    s = float(upsample)
    big = gray if s == 1 else cv2.resize(gray, None, fx=s, fy=s,
                                         interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
    kps, desc = cv2.SIFT_create().detectAndCompute(big, None)
    del big
    if desc is None or not kps:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    uv = np.array([k.pt for k in kps], dtype=np.float64)
    return Features(uv_to_opencv(uv_from_opencv(uv) / s), desc.astype(np.float32))


def sift_scale(width: int, height: int) -> float:
    """How many times an image region ``width x height`` is resized for SIFT: ``UPSAMPLE`` while the
    result has at most ``MAX_SIFT_PIXELS``, else the factor (below ``UPSAMPLE``) that brings it there."""
    if width * height * UPSAMPLE ** 2 <= MAX_SIFT_PIXELS:
        return float(UPSAMPLE)
    return math.sqrt(MAX_SIFT_PIXELS / (width * height))


def photo_sift(photo_bgr: NDArray[np.uint8]) -> Features:
    """:func:`sift_features` of a BGR photo (grey levels)."""
    return sift_features(cv2.cvtColor(photo_bgr, cv2.COLOR_BGR2GRAY))


def match_features(render: Features, photo: Features, ratio: float = RATIO_TEST,
                   max_px: float = MAX_MATCH_PX) -> NDArray[np.float64]:
    """Matches (n, 4) ``(u_r, v_r, u_p, v_p)``: each rendering keypoint's nearest photo descriptor
    (``cv2.BFMatcher``, L2) that passes Lowe's ratio test and lies closer than ``max_px`` (px)."""
    if len(render.uv) == 0 or len(photo.uv) < 2:
        return np.zeros((0, 4))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(render.descriptors, photo.descriptors, k=2)
    rows = []
    for pair in pairs:
        if len(pair) < 2:
            continue
        m, second = pair
        if m.distance < ratio * second.distance:
            rows.append((*render.uv[m.queryIdx], *photo.uv[m.trainIdx]))
    if not rows:
        return np.zeros((0, 4))
    out = np.asarray(rows, dtype=np.float64)
    d = np.hypot(out[:, 2] - out[:, 0], out[:, 3] - out[:, 1])
    return out[d < max_px]


def in_box(uv: NDArray[np.float64], box: tuple[int, int, int, int]) -> NDArray[np.bool_]:
    """Whether each (u, v) (OpenCV px) lies in the pixels of ``box`` (u0, v0, u1, v1), end exclusive."""
    lo, hi = uv_to_opencv(np.array(box[:2])), uv_to_opencv(np.array(box[2:]))  # the box's edges
    return (uv[:, 0] >= lo[0]) & (uv[:, 0] < hi[0]) & (uv[:, 1] >= lo[1]) & (uv[:, 1] < hi[1])


def at_pixels(uv: NDArray[np.float64], image: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``image`` at the pixel nearest each (u, v) (OpenCV: pixel centres at integers)."""
    H, W = image.shape
    j = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, W - 1)
    i = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, H - 1)
    return image[i, j]
