"""The check's figures: the photos with the most kept matches, the matches, outlines and boxes drawn
(:func:`match_figure`), and what both figures of ``autoalign check`` share: marks with a dark rim,
which stay visible on any texture (a red outline vanished on a red object), and a legend.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import photo_path
from autoalign.io.photos import read_photo_scaled
from autoalign.quality.check_report import CheckReport, ViewInstanceCheck

Colour = tuple[int, int, int]
"""BGR."""
RIM = (0, 0, 0)
"""Under every mark, one pixel wider: a dark rim that parts it from the photo whatever its colours."""
LEGEND_BACKGROUND = (40, 40, 40)
LEGEND_TEXT = (235, 235, 235)
LEGEND_FONT_SCALE = 0.45
LEGEND_LINE_PX = 18


def _colour(instance: int) -> Colour:
    """A distinct BGR colour per instance."""
    hue = (instance * 47) % 180
    hsv = np.uint8([[[hue, 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def paint_rimmed(img: NDArray[np.uint8], layers: Sequence[tuple[NDArray[np.bool_], Colour]]) -> None:
    """Paint each boolean pixel layer of ``layers`` in its colour (later ones on top) over ``img``,
    after a one-pixel dark rim around all of them."""
    if not layers:
        return
    union = np.logical_or.reduce([m for m, _ in layers])
    img[cv2.dilate(union.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)] = RIM
    for m, colour in layers:
        img[m] = colour


def rimmed_text(img: NDArray[np.uint8], text: str, origin: tuple[int, int], colour: Colour,
                scale: float = 0.4) -> None:
    """``text`` at ``origin`` in ``colour``, over a dark rim."""
    cv2.putText(img, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, RIM, 3, cv2.LINE_AA)
    cv2.putText(img, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def _wrapped(text: str, width_px: int) -> list[str]:
    """``text`` broken into lines of at most ``width_px`` at the legend's font (a long word stays whole)."""
    lines: list[str] = []
    for word in text.split():
        line = f"{lines[-1]} {word}" if lines else word
        fits = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, LEGEND_FONT_SCALE, 1)[0][0] <= width_px
        if lines and fits:
            lines[-1] = line
        else:
            lines.append(word)
    return lines


def legend_strip(width: int, entries: Sequence[tuple[Colour | None, str]]) -> NDArray[np.uint8]:
    """A dark band ``width`` px wide explaining a figure: each entry's text after a swatch of its
    colour (``None``: no swatch), wrapped to the width; to be stacked under the figure."""
    rows: list[tuple[Colour | None, str]] = []
    for colour, text in entries:
        parts = _wrapped(text, width - 32)
        rows += [(colour if k == 0 else None, part) for k, part in enumerate(parts)]
    strip = np.full((LEGEND_LINE_PX * len(rows) + 8, width, 3), LEGEND_BACKGROUND, np.uint8)
    for k, (colour, text) in enumerate(rows):
        base = 4 + LEGEND_LINE_PX * (k + 1) - 5
        if colour is not None:
            cv2.rectangle(strip, (6, base - 11), (18, base + 1), colour, -1)
        cv2.putText(strip, text, (26, base), cv2.FONT_HERSHEY_SIMPLEX, LEGEND_FONT_SCALE, LEGEND_TEXT, 1, cv2.LINE_AA)
    return strip


def with_legend(figure: NDArray[np.uint8], entries: Sequence[tuple[Colour | None, str]]) -> NDArray[np.uint8]:
    """``figure`` with :func:`legend_strip` under it."""
    return np.vstack([figure, legend_strip(figure.shape[1], entries)])


def _draw_view(img: NDArray[np.uint8], v: ViewInstanceCheck, colour: Colour) -> None:
    """One instance's box, matches (a line from the rendering's keypoint, a dot, to the photo's) and
    numbers in ``colour``, each over a dark rim (its outline is painted before, :func:`paint_rimmed`)."""
    for under, width, radius in ((RIM, 3, 3), (colour, 1, 2)):
        if v.bbox is not None:
            u0, v0, u1, v1 = v.bbox
            cv2.rectangle(img, (u0, v0), (u1 - 1, v1 - 1), under, width)
        for ur, vr, up, vp in v.matches:
            a = (int(round(ur * 16)), int(round(vr * 16)))
            b = (int(round(up * 16)), int(round(vp * 16)))
            cv2.line(img, a, b, under, width, cv2.LINE_AA, shift=4)
            cv2.circle(img, a, radius * 16, under, -1, cv2.LINE_AA, shift=4)
    if v.bbox is not None:
        text = f"{v.obj_id}: " + (f"{v.mean_px:.1f}px ({v.n_matches})" if v.mean_px is not None else "no match")
        text += f", edge {v.edge_px:.1f}px" if v.edge_px is not None else ""
        rimmed_text(img, text, (v.bbox[0] + 2, max(v.bbox[1] - 3, 10)), colour)


def _match_tile(report: CheckReport, im: int) -> NDArray[np.uint8]:
    """Image ``im`` as checked, darkened, with every instance's outline, box, matches and numbers."""
    img = read_photo_scaled(photo_path(report.scene_dir, im), report.max_pixels).bgr  # as checked
    img = (img.astype(np.float32) * 0.6).astype(np.uint8)
    views = [c for c in report.views if c.image_id == im]
    layers = []
    for v in views:
        m = np.zeros(img.shape[:2], bool)
        m[v.outline_rc[:, 0], v.outline_rc[:, 1]] = True
        layers.append((m, _colour(v.instance)))
    paint_rimmed(img, layers)
    for v in views:
        _draw_view(img, v, _colour(v.instance))
    rimmed_text(img, f"image {im}", (6, 18), (255, 255, 255), 0.55)
    return img


def match_legend(report: CheckReport) -> list[tuple[Colour | None, str]]:
    """The entries of :func:`match_figure`'s legend: one colour per instance, then what the marks are."""
    objects = {v.instance: v.obj_id for v in report.views}
    return [(_colour(k), f"instance {k} (obj {obj})") for k, obj in sorted(objects.items())] + [
        (None, "outline: the label's visible silhouette; box: the region searched around it; dot: a feature of the "
               "label's rendering, its line ends at the matching feature in the photo"),
        (None, "text: obj id: mean match distance px (kept matches), edge: mean distance of the outline from the "
               "photo's edges px")]


def match_figure(report: CheckReport, max_views: int = 4) -> NDArray[np.uint8]:
    """A BGR image of up to ``max_views`` checked photos (those with the most kept matches, in image
    order; read as they were checked, downscaled if large) with the kept matches: a line from the
    rendering keypoint (dot) to the photo keypoint,
    the label's visible outline, the dilated bounding box, and ``obj id: mean px (n), edge px`` per
    instance, in one colour per instance, every mark over a dark rim; two photos per row, and a
    legend under them (:func:`match_legend`)."""
    counts = {im: 0 for im in report.image_ids}
    for v in report.views:
        counts[v.image_id] = counts.get(v.image_id, 0) + v.n_matches
    ids = sorted(sorted(counts, key=lambda im: (-counts[im], im))[:max_views])
    tiles = [_match_tile(report, im) for im in ids]
    if not tiles:
        return np.zeros((32, 32, 3), np.uint8)
    H = max(t.shape[0] for t in tiles)
    W = max(t.shape[1] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, H - t.shape[0], 0, W - t.shape[1], cv2.BORDER_CONSTANT) for t in tiles]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0])) if len(tiles) > 1 else None
    rows = [np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles), 2)]
    return with_legend(np.vstack(rows), match_legend(report))
