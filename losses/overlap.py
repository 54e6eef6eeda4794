"""Intersection over union of hard masks: one definition for every place that scores a fit, and
one scene-level IoU (:func:`view_ious`) for every place that reports one.

Two empty masks agree perfectly (IoU 1): a view where neither the silhouette nor the mask has a
pixel says nothing against the pose.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from autoalign.losses.compared_views import ComparedViews

LOOSE_FIT_IOU = 0.75
"""Median IoU below this: the silhouette fits the masks loosely (the verdict asks for a look,
:data:`~autoalign.quality.verdict.CHECK_IOU`); masks that miss much of the object fit it about as
well turned over, so without a given pose the photos choose its side (:mod:`autoalign.engine.photo_evidence`)."""


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


def view_ious(silhouettes: Sequence[NDArray[np.bool_]], views: ComparedViews) -> NDArray[np.float64]:
    """Per-view IoU of hard silhouettes (one full-resolution mask per one of ``views``) with the
    views' targets thresholded at 0.5, the ignored pixels (other masks' claims) left out: the IoU
    that ``refine.json``, the overlay and the label page report."""
    if len(silhouettes) != len(views):
        raise ValueError(f"{len(silhouettes)} silhouettes for {len(views)} views")
    return np.array([mask_iou(s, np.asarray(t) > 0.5, views.compared(k))
                     for k, (s, t) in enumerate(zip(silhouettes, views.targets))], dtype=np.float64)
