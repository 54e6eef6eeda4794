"""Robust per-view weights, so that a few wrong masks do not pull the pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def cauchy_weights(residual: NDArray[np.float64], c: float = 2.0, floor: float = 1e-3,
                   inliers: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
    """Cauchy (Lorentzian) IRLS weights ``1 / (1 + (r / (c * scale))^2)``, ``scale = median(r)``.

    ``residual`` is a per-view misfit such as ``1 - IoU``. Views fitting as well as the typical view
    keep a weight near 1; a view ``k`` times worse than the median gets about ``(c / k)^2``.
    ``floor`` keeps the scale positive once every view fits almost perfectly. ``inliers``: the
    views the scale is the median of (default all; all too when none is).
    """
    r = np.asarray(residual, dtype=np.float64)
    typical = r if inliers is None or not np.any(inliers) else r[np.asarray(inliers, dtype=bool)]
    scale = max(float(np.median(typical)), floor)
    return 1.0 / (1.0 + (r / (c * scale)) ** 2)


IMPLAUSIBLE_IOU = 0.2
"""A view whose IoU is below this while the pose fits most views is taken for a wrong mask."""
FITTING_IOU = 0.5
"""A view fits when its IoU is at least this ..."""
FITTING_FRACTION = 1.0 / 3.0
"""... and the pose fits the scene when at least this fraction of the views fit."""


def implausible_views(iou: NDArray[np.float64], gate: float = IMPLAUSIBLE_IOU, fitting: float = FITTING_IOU,
                      fraction: float = FITTING_FRACTION) -> NDArray[np.bool_]:
    """Views whose mask cannot be this object's: IoU below ``gate`` while the pose fits the scene
    (at least ``fraction`` of the views have IoU ``fitting`` or more). A segmenter that masked
    another object, or nothing of this one, gives such views, in real scenes up to half or more
    of them: Cauchy weights, whose scale is the median misfit, then keep a third of their pull,
    so they get none. While the pose fits too few views (a far start, a wrong hypothesis), no view
    is judged this way.
    """
    iou = np.asarray(iou, dtype=np.float64)
    if len(iou) == 0 or np.mean(iou >= fitting) < fraction:
        return np.zeros(len(iou), dtype=bool)
    return iou < gate


def robust_view_weights(iou: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-view weights for the current fit, normalised to mean 1: Cauchy weights on the misfit
    ``1 - IoU``, and none for a view whose mask is implausible (:func:`implausible_views`).

    The Cauchy scale is the median misfit of the plausible views only: wrong masks, which get no
    weight, would otherwise raise it, and the more of them a scene has the more weight the partly
    failed masks keep (on the calibration study's pen, 8 wrong masks of 38 left 11 partial ones,
    IoU 0.41-0.65, at half a good view's weight, enough to hold its roll 16 deg off)."""
    iou = np.asarray(iou, dtype=np.float64)
    wrong = implausible_views(iou)
    w = cauchy_weights(1.0 - iou, inliers=~wrong) * ~wrong
    return w * (len(w) / max(float(w.sum()), 1e-12))
