"""Two sets of labels of the same photos compared without ground truth (``autoalign check --against``).

Which of two labels of an object (ours and a dataset's, say) sits where the photos show it? Both
are checked by :func:`autoalign.quality.scene_check.check_scene` on the same images, and for every
instance the views where both have an outline to judge are paired: the share of them where the
first label's outline is closer to the photo's edges (:mod:`autoalign.quality.edge_distance`), and the
mean of the paired differences (reference minus labels, px; positive: the labels are closer) with
a 95% bootstrap interval over the views. Pairing matters: texture edges near an object make every
outline look closer than it is, by the same amount for both labels of one view.

:func:`comparison_figure` draws, per instance, a few of those views cropped around the object with
the outline of its mask (cyan), of the labels (green) and of the reference (red) over the photo,
for a person to judge by eye. Outlines are the rendered visible silhouettes' outline pixels
(:func:`autoalign.quality.edge_distance.outline_pixels`), the same pixels the edge distance measures.
Pixels: OpenCV / BOP convention, as in :mod:`autoalign.quality.check`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import mask_path, photo_path, read_masks
from autoalign.io.photos import read_photo_scaled
from autoalign.quality.check_report import CheckReport, ViewInstanceCheck
from autoalign.quality.edge_distance import outline_pixels
from autoalign.quality.figures import paint_rimmed, rimmed_text, with_legend
from autoalign.quality.stats import bootstrap_mean_ci

FIGURE_VIEWS = 5
"""Views per instance in :func:`comparison_figure`, spread evenly over the paired views."""
TILE_PX = 240
"""Side of one cropped view in the figure (px)."""
COLOURS = {"mask": (255, 255, 0), "labels": (0, 220, 0), "reference": (0, 0, 255)}
"""BGR outline colours: cyan, green, red."""


@dataclass(frozen=True)
class InstanceComparison:
    """Labels against a reference for one instance (same image ids, same instance number).

    ``views``: images where both outlines were judged; ``labels_edge_px`` /
    ``reference_edge_px``: their mean edge distance over those views (px); ``closer_share``: the
    share of those views where the labels' outline is the closer one; ``gain_px``: the mean of
    (reference minus labels) over the views, ``gain_ci95`` its 95% bootstrap interval (None below
    two views). ``image_ids``: the paired views, in image order.
    """

    instance: int
    obj_id: int
    views: int
    labels_edge_px: float
    reference_edge_px: float
    closer_share: float
    gain_px: float
    gain_ci95: tuple[float, float] | None
    image_ids: tuple[int, ...]

    @property
    def verdict(self) -> str:
        """``labels closer``, ``reference closer`` (the interval excludes 0) or ``no clear difference``."""
        if self.gain_ci95 is not None and self.gain_ci95[0] > 0:
            return "labels closer"
        if self.gain_ci95 is not None and self.gain_ci95[1] < 0:
            return "reference closer"
        return "no clear difference"

    def record(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {"instance": self.instance, "obj_id": self.obj_id, "views": self.views,
                "labels_edge_px": self.labels_edge_px, "reference_edge_px": self.reference_edge_px,
                "closer_share": self.closer_share, "gain_px": self.gain_px,
                "gain_ci95": list(self.gain_ci95) if self.gain_ci95 is not None else None,
                "verdict": self.verdict, "image_ids": list(self.image_ids)}


def compare_views(labels: Sequence[ViewInstanceCheck], reference: Sequence[ViewInstanceCheck],
                  seed: int = 0) -> list[InstanceComparison]:
    """Per (instance, obj_id) judged in both, the paired comparison of the edge distances (see the
    module docstring), sorted by instance. An instance whose obj_id differs between the two sets is
    not compared."""
    ref = {(v.image_id, v.instance, v.obj_id): v.edge_px for v in reference if v.edge_px is not None}
    pairs: dict[tuple[int, int], list[tuple[int, float, float]]] = {}
    for v in labels:
        r = ref.get((v.image_id, v.instance, v.obj_id))
        if v.edge_px is not None and r is not None:
            pairs.setdefault((v.instance, v.obj_id), []).append((v.image_id, v.edge_px, r))
    out = []
    for (inst, obj), p in sorted(pairs.items()):
        p.sort()
        a, b = np.array([x[1] for x in p]), np.array([x[2] for x in p])
        out.append(InstanceComparison(inst, obj, len(p), float(a.mean()), float(b.mean()), float(np.mean(a < b)),
                                      float((b - a).mean()),
                                      bootstrap_mean_ci(b - a, np.random.default_rng([seed, 5_000_011, inst, obj])),
                                      tuple(x[0] for x in p)))
    return out


def compare_reports(labels: CheckReport, reference: CheckReport, seed: int = 0) -> list[InstanceComparison]:
    """:func:`compare_views` of two checks of the same scene."""
    return compare_views(labels.views, reference.views, seed)


def comparison_figure(labels: CheckReport, reference: CheckReport, comparisons: Sequence[InstanceComparison],
                      views: int = FIGURE_VIEWS, tile: int = TILE_PX) -> NDArray[np.uint8]:
    """A BGR image: one row per compared instance, ``views`` of its paired views (spread evenly),
    each cropped around the two labels' outlines and scaled to ``tile`` px, with the outline pixels
    of the mask (cyan, where ``mask_visib`` has one), the labels (green) and the reference (red), each
    over a dark rim, and a legend under them (:data:`COMPARE_LEGEND`)."""
    outline = {(v.image_id, v.instance): v.outline_rc for v in labels.views}
    outline_ref = {(v.image_id, v.instance): v.outline_rc for v in reference.views}
    rows = []
    for c in comparisons:
        picks = np.unique(np.rint(np.linspace(0, c.views - 1, min(views, c.views))).astype(int))
        tiles = []
        for im in (c.image_ids[k] for k in picks):
            # photo and mask as they were checked (downscaled if large), where the outlines are
            photo = read_photo_scaled(photo_path(labels.scene_dir, im), labels.max_pixels).bgr
            lines = {"labels": outline[(im, c.instance)], "reference": outline_ref[(im, c.instance)]}
            p = mask_path(labels.scene_dir, im, c.instance)
            key = (im, c.instance)
            mask = read_masks({key: p}, labels.max_pixels).masks.get(key) if p.is_file() else None
            lines["mask"] = outline_pixels(mask.astype(np.int32), 1) if mask is not None else np.zeros((0, 2), int)
            tiles.append(_tile(photo, lines, f"obj {c.obj_id} inst {c.instance}, image {im}", tile))
        tiles += [np.zeros((tile, tile, 3), np.uint8)] * (views - len(tiles))
        rows.append(np.hstack(tiles))
    return with_legend(np.vstack(rows) if rows else np.zeros((tile, tile * views, 3), np.uint8), COMPARE_LEGEND)


def _tile(photo: NDArray[np.uint8], lines: dict[str, NDArray[np.int64]], text: str, tile: int) -> NDArray[np.uint8]:
    """``photo`` cropped to a square around the labels' and the reference's outline pixels
    (``(row, col)``), scaled to ``tile`` px, with each outline's pixels drawn in its colour."""
    both = np.concatenate([lines["labels"], lines["reference"]])
    lo, hi = both.min(axis=0), both.max(axis=0)
    half = int(max(hi - lo) * 0.6) + 8
    r0, c0 = (lo + hi) // 2 - half
    padded = cv2.copyMakeBorder(photo, half, half, half, half, cv2.BORDER_CONSTANT)
    s = tile / (2 * half)
    img = cv2.resize(padded[r0 + half:r0 + 3 * half, c0 + half:c0 + 3 * half], (tile, tile),
                     interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
    k = max(int(np.ceil(s)), 1)
    layers = []
    for name in ("mask", "reference", "labels"):
        # pixel (r, c) covers [c, c+1) x [r, r+1) of the crop before scaling: fill that square
        m = np.zeros((tile, tile), bool)
        for r, c in ((lines[name] - [r0, c0]) * s).astype(int):
            if 0 <= r < tile and 0 <= c < tile:
                m[r:r + k, c:c + k] = True
        layers.append((m, COLOURS[name]))
    paint_rimmed(img, layers)  # a red outline stays visible on a red object
    rimmed_text(img, text, (4, 14), (255, 255, 255))
    return img


COMPARE_LEGEND = [(COLOURS["mask"], "the outline of the instance's mask (mask_visib), where the scene has one"),
                  (COLOURS["labels"], "the outline of the labels checked (--labels)"),
                  (COLOURS["reference"], "the outline of the reference labels (--against)")]
"""What :func:`comparison_figure`'s colours show."""
