"""How far a mask's outline lies outside a silhouette's: per view (:func:`outline_offset`), and the
shift an instance's masks share against its fitted silhouettes (:func:`shared_outline_offset`).

The shared shift is what the covariance's outline prior stands for
(:data:`~autoalign.engine.uncertainty.BOUNDARY_BIAS_PX`, measured with :func:`outline_offset` on the
real SAM masks against the dataset's labels). Measured against a pose fitted with a second kind of
evidence (the photo's colours), it is how far the masks and that evidence disagree about where the
outline is (:func:`~autoalign.engine.uncertainty.with_outline_disagreement`).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.overlap import mask_iou

ON_OBJECT_IOU = 0.5
"""A mask whose IoU with the silhouette is below this is on another object, or misses most of
this one: its outline's offset is not a shift of this object's outline."""
OCCLUSION_PX = 2
"""Outline pixels this close to another object's pixels (or the image's border) are left out:
where an object hides this one, the two outlines meet and either mask may own the edge."""
MIN_OUTLINE_PX = 20
"""A view with fewer outline pixels than this to compare gives no offset."""
_NEAR = np.ones((2 * OCCLUSION_PX + 1, 2 * OCCLUSION_PX + 1), np.uint8)


def outline_offset(mask: NDArray[np.bool_], visible: NDArray[np.bool_],
                   others: NDArray[np.bool_] | None = None) -> float:
    """The median signed distance (px, > 0: outside) of ``mask``'s outline from the outline of the
    visible silhouette ``visible``, over ``mask``'s outline pixels away from ``others`` (the other
    objects' pixels; ``None``: none) and the image's border; NaN for fewer than
    :data:`MIN_OUTLINE_PX` such pixels or an empty silhouette. Exact Euclidean distances between
    pixel centres, the outline half a pixel beyond its last pixel: a mask equal to the silhouette
    gives 0, one grown by a pixel 1."""
    vis = np.asarray(visible, dtype=bool)
    if not vis.any():
        return float("nan")
    m = np.asarray(mask, dtype=np.uint8)
    H, W = vis.shape
    # Worked on the box of both (and OCCLUSION_PX + 1 around it) only: it holds every silhouette pixel
    # and a ring of background around them, so each distance, and each other object's pixel near the
    # outline, is the one the whole image gives.
    x, y, w, h = cv2.boundingRect(np.bitwise_or(vis.view(np.uint8), m))
    pad = OCCLUSION_PX + 1
    x0, y0, x1, y1 = max(x - pad, 0), max(y - pad, 0), min(x + w + pad, W), min(y + h + pad, H)
    v8 = vis[y0:y1, x0:x1].view(np.uint8)
    d_out = cv2.distanceTransform(1 - v8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_in = cv2.distanceTransform(v8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    signed = np.where(v8 > 0, 1.0 - d_in, d_out)  # at the mask's last pixel: where its outline lies
    m = m[y0:y1, x0:x1]
    edge = (m - cv2.erode(m, np.ones((3, 3), np.uint8))) > 0
    if others is not None:
        near = np.ascontiguousarray(np.asarray(others, dtype=np.uint8)[y0:y1, x0:x1])
        edge &= cv2.dilate(near, _NEAR) == 0
    b = OCCLUSION_PX  # the image's border rows and columns, where they fall in the box
    edge[:max(b - y0, 0)], edge[:, :max(b - x0, 0)] = False, False
    edge[max(H - b - y0, 0):], edge[:, max(W - b - x0, 0):] = False, False
    return float(np.median(signed[edge])) if edge.sum() >= MIN_OUTLINE_PX else float("nan")


def shared_outline_offset(silhouettes: Sequence[NDArray[np.bool_]], views: ComparedViews) -> float:
    """The median over ``views`` of :func:`outline_offset` of their targets from the hard
    ``silhouettes`` (one per view, full resolution), the ignored pixels (other masks' claims)
    counting as other objects; views whose target has an IoU below :data:`ON_OBJECT_IOU` with the
    silhouette left out. NaN where no view has an offset."""
    offsets = []
    for k, (sil, target) in enumerate(zip(silhouettes, views.targets)):
        mask = np.asarray(target) > 0.5
        others = None if views.ignore is None else views.ignore[k]
        if mask_iou(sil, mask, views.compared(k)) >= ON_OBJECT_IOU:
            offsets.append(outline_offset(mask, sil, others))
    found = np.asarray(offsets, dtype=np.float64)
    found = found[np.isfinite(found)]
    return float(np.median(found)) if len(found) else float("nan")
