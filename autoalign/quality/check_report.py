"""The check's records: one instance in one image, one instance over the images, and the scene's
report with the parameters it ran with (the contents of ``check.json``).

Pixels: OpenCV / BOP convention (the centre of pixel (row i, col j) at (j, i)), in the pixels of the
photos as checked (``image_scale`` times the files').
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import MAX_IMAGE_PIXELS
from autoalign.io.models import FEATURELESS
from autoalign.quality.edge_distance import (
    BLUR_SIGMA_PX,
    CANNY_HIGH,
    CANNY_LOW,
    MAX_EDGE_PX,
    MIN_OUTLINE_PX,
    ORIENTATION_BINS,
)
from autoalign.quality.sift import MAX_MATCH_PX, MAX_SIFT_PIXELS, RATIO_TEST, UPSAMPLE
from autoalign.quality.stats import N_BOOTSTRAP

BBOX_MARGIN_PX = 10
"""The rendered object's bounding box is dilated by this many pixels on every side."""
SILHOUETTE_MARGIN_PX = 3
"""Rendering keypoints must lie within this many pixels of the instance's own visible silhouette
(not on another instance that occludes it, nor on the black background far from it)."""
CONTEXT_PX = 32
"""The region searched in a photo larger than 640 x 480: the labels' rendered pixels' box dilated by
this many pixels (more than ``BBOX_MARGIN_PX`` plus ``MAX_EDGE_PX`` and SIFT's border, so that the
features and edges near the outlines are those of the whole photo)."""
MIN_MATCHES = 10
"""An instance with fewer kept matches than this over all its views is flagged ``too_few_matches``."""


@dataclass
class ViewInstanceCheck:
    """The check of one instance in one image.

    ``iou``: IoU of the rendered visible silhouette with ``mask_visib`` (None without a mask file).
    ``n_matches``: kept matches; ``mean_px``: their mean keypoint distance (px, None without
    matches); ``ci95``: its 95% bootstrap interval over the matches (None below 2 matches);
    ``offset_px``: mean (du, dv) photo keypoint minus rendering keypoint (px; a systematic offset
    hints at a translation error). ``bbox``: (u0, v0, u1, v1) pixel box (exclusive end) of the
    rendered visible silhouette dilated by ``BBOX_MARGIN_PX``, None when nothing is visible.
    ``matches``: (n, 4) float (u_render, v_render, u_photo, v_photo) of the kept matches (OpenCV px).
    ``edge_px``: mean outline-to-edge distance (px, :mod:`autoalign.quality.edge_distance`; None below
    ``MIN_OUTLINE_PX`` outline pixels); ``edge_distances``: per outline pixel; ``outline_rc``: the
    outline pixels (row, col). ``through_share``: with the scene's depth, the share of the label's
    visible pixels (inside its mask) whose depth is seen through (NaN: too few; None: no depth).
    """

    image_id: int
    instance: int
    obj_id: int
    iou: float | None
    n_matches: int
    mean_px: float | None
    ci95: tuple[float, float] | None = None
    offset_px: tuple[float, float] | None = None
    visible_px: int = 0
    bbox: tuple[int, int, int, int] | None = None
    n_render_keypoints: int = 0
    n_photo_keypoints: int = 0
    matches: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)), repr=False, compare=False)
    edge_px: float | None = None
    through_share: float | None = None
    edge_distances: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False, compare=False)
    outline_rc: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64), repr=False,
                                          compare=False)

    @property
    def distances_px(self) -> NDArray[np.float64]:
        """Image distance (px) of each kept match."""
        return np.hypot(self.matches[:, 2] - self.matches[:, 0], self.matches[:, 3] - self.matches[:, 1])

    def record(self) -> dict[str, Any]:
        """A JSON-ready dict (without the match list)."""
        return {"image_id": self.image_id, "instance": self.instance, "obj_id": self.obj_id,
                "iou": _num(self.iou), "n_matches": self.n_matches, "mean_px": _num(self.mean_px),
                "ci95": _pair(self.ci95), "offset_px": _pair(self.offset_px), "visible_px": self.visible_px,
                "bbox": list(self.bbox) if self.bbox is not None else None,
                "n_render_keypoints": self.n_render_keypoints, "n_photo_keypoints": self.n_photo_keypoints,
                "edge_px": _num(self.edge_px), "outline_px": int(len(self.edge_distances))}


@dataclass
class InstanceSummary:
    """One instance over all checked images.

    ``mean_px``: mean distance (px) of all its kept matches, pooled over the views; None when
    ``too_few_matches`` (fewer than ``MIN_MATCHES`` kept matches: an untextured object, or a bad
    label). ``ci95``: 95% bootstrap interval of ``mean_px`` over the views (over the matches when
    only one view has any). ``views``: images where the instance is labelled; ``views_with_matches``:
    those with at least one kept match. ``median_iou``: over the views with a mask (None if none).
    ``offset_px``: mean (du, dv) photo minus rendering over the kept matches (px).
    ``edge_px``: mean outline-to-edge distance (px) pooled over the views' outline pixels, with its
    95% bootstrap interval over the views ``edge_ci95``; None when no view has an outline to judge.
    ``material``: as ``materials.json`` declares it, or ``transparent`` where ``recognised`` from the
    depth (``through_share``: the median over the views of the share of its depth seen through; None
    without depth); a transparent or reflective object's feature distance is not measured
    (:attr:`features_measurable`): its photo features are its surroundings'.
    """

    instance: int
    obj_id: int
    mean_px: float | None
    ci95: tuple[float, float] | None
    n_matches: int
    views: int
    median_iou: float | None
    too_few_matches: bool
    views_with_matches: int = 0
    offset_px: tuple[float, float] | None = None
    edge_px: float | None = None
    edge_ci95: tuple[float, float] | None = None
    views_with_outline: int = 0
    material: str = "opaque"
    through_share: float | None = None
    recognised: bool = False

    @property
    def features_measurable(self) -> bool:
        """Whether the photo's features are the object's own (not refracted or mirrored surroundings)."""
        return self.material not in FEATURELESS

    def record(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {"instance": self.instance, "obj_id": self.obj_id, "mean_px": _num(self.mean_px),
                "ci95": _pair(self.ci95), "n_matches": self.n_matches, "views": self.views,
                "views_with_matches": self.views_with_matches, "median_iou": _num(self.median_iou),
                "too_few_matches": self.too_few_matches, "material": self.material,
                "material_recognised": self.recognised, "through_share": _num(self.through_share),
                "features_measurable": self.features_measurable, "offset_px": _pair(self.offset_px),
                "edge_px": _num(self.edge_px), "edge_ci95": _pair(self.edge_ci95),
                "views_with_outline": self.views_with_outline}


@dataclass
class CheckReport:
    """The check of a scene: every (image, instance), the per-instance summaries, and the pooled
    mean feature distance (px) over the instances with enough matches, with its 95% bootstrap
    interval over the (image, instance) views; ``edge_px`` / ``edge_ci95`` the same for the
    outline-to-edge distance over every judged view."""

    scene_dir: Path
    labels_path: Path
    models_dir: Path
    image_ids: list[int]
    views: list[ViewInstanceCheck]
    instances: list[InstanceSummary]
    mean_px: float | None
    ci95: tuple[float, float] | None
    n_matches: int
    seed: int = 0
    warnings: list[str] = field(default_factory=list)
    edge_px: float | None = None
    edge_ci95: tuple[float, float] | None = None
    image_scales: dict[int, float] = field(default_factory=dict)
    max_pixels: int | None = MAX_IMAGE_PIXELS

    @property
    def image_scale(self) -> float | None:
        """The photos as checked over the files' resolution when all images share it (else None):
        1 unless they have more than ``max_pixels`` pixels (then 1/2, 1/3, ...)."""
        scales = set(self.image_scales.values()) or {1.0}
        return scales.pop() if len(scales) == 1 else None

    def record(self) -> dict[str, Any]:
        """The JSON-ready contents of ``check.json``."""
        return {
            "scene": str(self.scene_dir), "labels": str(self.labels_path), "models": str(self.models_dir),
            "image_ids": list(self.image_ids),
            "image_scale": self.image_scale,
            "pixels": "every px value, pixel coordinate and px parameter is in pixels of the photos as checked: "
                      "image_scale times the files' resolution (photos over max_image_pixels are read downscaled "
                      "by a whole factor, area-averaged, masks and cam_K with them, as autoalign refine reads "
                      "masks); divide by image_scale for the files' pixels",
            "mean_px": _num(self.mean_px), "ci95": _pair(self.ci95), "n_matches": self.n_matches,
            "edge_px": _num(self.edge_px), "edge_ci95": _pair(self.edge_ci95),
            "instances": [s.record() for s in self.instances],
            "views": [{**v.record(), "image_scale": self.image_scales.get(v.image_id, 1.0)} for v in self.views],
            "parameters": {"ratio_test": RATIO_TEST, "max_match_px": MAX_MATCH_PX, "bbox_margin_px": BBOX_MARGIN_PX,
                           "silhouette_margin_px": SILHOUETTE_MARGIN_PX, "upsample": UPSAMPLE, "min_matches": MIN_MATCHES,
                           "n_bootstrap": N_BOOTSTRAP, "seed": self.seed,
                           "canny_low": CANNY_LOW, "canny_high": CANNY_HIGH, "blur_sigma_px": BLUR_SIGMA_PX,
                           "orientation_bins": ORIENTATION_BINS, "max_edge_px": MAX_EDGE_PX,
                           "min_outline_px": MIN_OUTLINE_PX, "max_image_pixels": self.max_pixels,
                           "max_sift_pixels": MAX_SIFT_PIXELS, "context_px": CONTEXT_PX},
            "pixel_convention": "OpenCV/BOP: cam_K and keypoint positions put the centre of pixel (row i, col j) at (j, i)",
            "warnings": list(self.warnings),
        }


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _pair(p: tuple[float, float] | None) -> list[float | None] | None:
    return None if p is None else [_num(p[0]), _num(p[1])]
