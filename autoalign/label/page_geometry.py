"""The geometry a labelling session does for the page: an object's ray-cast silhouette in every
view, its outlines (polylines to draw) and its fit with the instance's masks (hard IoU), and a
nudge of a pose along a camera's axes.

Units and frames: poses are world-from-model 4x4 in mm; pixel coordinates are OpenCV's (the
centre of the top-left pixel at 0, 0), in the views' resolution.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import make_pose, so3_exp
from autoalign.io.bop import Scene
from autoalign.io.models import ModelSet
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.overlap import view_ious
from autoalign.rasterizers.pyramid import MeshDetail

CONTOUR_EPS_PX = 0.5
"""Contours are simplified (Douglas-Peucker) to within this many pixels before they go to the page."""
Outlines = dict[int, list[list[list[float]]]]
"""image id -> the polylines of a silhouette's outer contours (OpenCV pixel coordinates)."""


def contour_polylines(mask: NDArray[np.bool_]) -> list[list[list[float]]]:
    """The outer contours of ``mask`` as polylines of OpenCV pixel coordinates (pixel centres at
    integers), simplified to within :data:`CONTOUR_EPS_PX`."""
    found, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in found:
        poly = cv2.approxPolyDP(c, CONTOUR_EPS_PX, True).reshape(-1, 2)
        out.append([[int(x), int(y)] for x, y in poly])
    return out


def nudged_pose(T_wm: NDArray[np.float64], centre_m: NDArray[np.float64], cam: Camera,
                move_mm: NDArray[np.float64], turn_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_wm`` moved by ``move_mm`` and turned by ``turn_deg`` (a rotation vector, degrees) about the
    object's centre, both given along the axes of ``cam`` (x right, y down, z forward)."""
    R_cw = cam.R_w2c.T
    c_w = T_wm[:3, :3] @ centre_m + T_wm[:3, 3]
    R = so3_exp(R_cw @ np.radians(turn_deg))
    return make_pose(R @ T_wm[:3, :3], R @ (T_wm[:3, 3] - c_w) + c_w + R_cw @ move_mm)


def outlines(silhouettes: dict[int, NDArray[np.bool_]]) -> Outlines:
    """The outlines of the non-empty silhouettes, by image id."""
    return {im: contour_polylines(m) for im, m in silhouettes.items() if m.any()}


def fit(scene: Scene, silhouettes: dict[int, NDArray[np.bool_]]) -> dict[int, float]:
    """Per-view hard IoU of the silhouettes with ``scene``'s masks
    (:func:`~autoalign.losses.overlap.view_ious`), by image id."""
    ious = view_ious([silhouettes[im] for im in scene.image_ids], ComparedViews.of(scene))
    return {im: float(v) for im, v in zip(scene.image_ids, ious)}


class SilhouetteRenderer:
    """Ray-cast silhouettes of the models in a scene's views, at the full-resolution ``detail`` of
    each model's pyramid (:meth:`~autoalign.io.models.ModelSet.pyramid`, the refinement's too). Not
    thread-safe: callers hold the session's render lock (drjit, one thread at a time)."""

    def __init__(self, models: ModelSet, image_ids: list[int], views: list[Camera], detail: MeshDetail) -> None:
        self.models, self.image_ids, self.views, self.detail = models, image_ids, views, detail

    def silhouettes(self, obj_id: int, T_wm: NDArray[np.float64]) -> dict[int, NDArray[np.bool_]]:
        """Object ``obj_id``'s silhouette at ``T_wm`` in every view, by image id."""
        rasterizer = self.models.pyramid(obj_id).fine(self.detail)
        return dict(zip(self.image_ids, rasterizer.hard_masks(T_wm, self.views)))
