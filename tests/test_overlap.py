"""The one hard-mask IoU (``autoalign.losses.overlap``) against pycocotools' own, and its edge cases."""

from __future__ import annotations

import numpy as np
from pycocotools import mask as coco_mask

from autoalign.losses.overlap import iou_from_counts, mask_iou


def test_mask_iou_matches_pycocotools():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.random((60, 80)) < rng.uniform(0.05, 0.6)
        b = rng.random((60, 80)) < rng.uniform(0.05, 0.6)
        ra, rb = (coco_mask.encode(np.asfortranarray(m.astype(np.uint8))) for m in (a, b))
        np.testing.assert_allclose(mask_iou(a, b), coco_mask.iou([ra], [rb], [0])[0, 0], rtol=1e-12)


def test_compared_pixels_and_empty_masks():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert mask_iou(a, b) == 1.0  # nothing on either side says nothing against the pose
    a[0, :2] = b[0, 1:3] = True
    assert mask_iou(a, b) == 1 / 3
    compared = np.ones((4, 4), bool)
    compared[0, 2] = False  # b's pixel there is not compared
    assert mask_iou(a, b, compared) == 0.5
    np.testing.assert_array_equal(iou_from_counts([1, 0], [2, 0], [2, 0]), [1 / 3, 1.0])
