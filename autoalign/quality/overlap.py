"""Intersection over union of hard masks: one definition for every place that scores a fit.

Two empty masks agree perfectly (IoU 1): a view where neither the silhouette nor the mask has a
pixel says nothing against the pose.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def iou_from_counts(inter: ArrayLike, area_a: ArrayLike, area_b: ArrayLike) -> NDArray[np.float64]:
    """IoU from pixel counts (any matching shapes): ``inter / (area_a + area_b - inter)``."""
    inter = np.asarray(inter, dtype=np.float64)
    union = np.asarray(area_a, dtype=np.float64) + np.asarray(area_b, dtype=np.float64) - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 1.0)


def mask_iou(a: NDArray[np.bool_], b: NDArray[np.bool_], compared: NDArray[np.bool_] | None = None) -> float:
    """IoU of two boolean masks of one shape, counting only the ``compared`` pixels (all if ``None``)."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if compared is not None:
        a, b = a & compared, b & compared
    return float(iou_from_counts(np.count_nonzero(a & b), np.count_nonzero(a), np.count_nonzero(b)))
