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

from autoalign.io.bop import Scene
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
    :data:`MIN_OUTLINE_PX` such pixels. Exact Euclidean distances between pixel centres, the
    outline half a pixel beyond its last pixel: a mask equal to the silhouette gives 0, one grown
    by a pixel 1."""
    vis = np.asarray(visible, dtype=bool)
    v8 = vis.astype(np.uint8)
    d_out = cv2.distanceTransform(1 - v8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_in = cv2.distanceTransform(v8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    signed = np.where(vis, 1.0 - d_in, d_out)  # at the mask's last pixel: where its outline lies
    m = np.asarray(mask, dtype=np.uint8)
    edge = (m - cv2.erode(m, np.ones((3, 3), np.uint8))) > 0
    if others is not None:
        edge &= cv2.dilate(np.asarray(others, dtype=np.uint8), _NEAR) == 0
    b = OCCLUSION_PX
    edge[:b], edge[-b:], edge[:, :b], edge[:, -b:] = False, False, False, False
    return float(np.median(signed[edge])) if edge.sum() >= MIN_OUTLINE_PX else float("nan")


def shared_outline_offset(silhouettes: Sequence[NDArray[np.bool_]], scene: Scene) -> float:
    """The median over ``scene``'s views of :func:`outline_offset` of its masks from the hard
    ``silhouettes`` (one per view, full resolution), the pixels the scene ignores (other masks'
    claims) counting as other objects; views whose mask has an IoU below :data:`ON_OBJECT_IOU`
    with the silhouette left out. NaN where no view has an offset."""
    offsets = []
    for k, (sil, target) in enumerate(zip(silhouettes, scene.masks)):
        mask = np.asarray(target) > 0.5
        others = None if scene.ignore is None else scene.ignore[k]
        if mask_iou(sil, mask, scene.compared(k)) >= ON_OBJECT_IOU:
            offsets.append(outline_offset(mask, sil, others))
    found = np.asarray(offsets, dtype=np.float64)
    found = found[np.isfinite(found)]
    return float(np.median(found)) if len(found) else float("nan")
