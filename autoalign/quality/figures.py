"""The check's figure: the photos with the most kept matches, the matches, outlines and boxes drawn."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import photo_path
from autoalign.io.photos import read_photo_scaled
from autoalign.quality.check_report import CheckReport


def _colour(instance: int) -> tuple[int, int, int]:
    """A distinct BGR colour per instance."""
    hue = (instance * 47) % 180
    hsv = np.uint8([[[hue, 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def match_figure(report: CheckReport, max_views: int = 4) -> NDArray[np.uint8]:
    """A BGR image of up to ``max_views`` checked photos (those with the most kept matches, in image
    order; read as they were checked, downscaled if large) with the kept matches: a line from the
    rendering keypoint (dot) to the photo keypoint,
    the label's visible outline, the dilated bounding box, and ``obj id: mean px (n), edge px`` per
    instance, in one colour per instance; two photos per row."""
    counts = {im: 0 for im in report.image_ids}
    for v in report.views:
        counts[v.image_id] = counts.get(v.image_id, 0) + v.n_matches
    ids = sorted(sorted(counts, key=lambda im: (-counts[im], im))[:max_views])
    tiles = []
    for im in ids:
        img = read_photo_scaled(photo_path(report.scene_dir, im), report.max_pixels).bgr  # as checked
        img = (img.astype(np.float32) * 0.6).astype(np.uint8)
        for v in (c for c in report.views if c.image_id == im):
            col = _colour(v.instance)
            img[v.outline_rc[:, 0], v.outline_rc[:, 1]] = col
            if v.bbox is not None:
                u0, v0, u1, v1 = v.bbox
                cv2.rectangle(img, (u0, v0), (u1 - 1, v1 - 1), col, 1)
                text = f"{v.obj_id}: " + (f"{v.mean_px:.1f}px ({v.n_matches})" if v.mean_px is not None else "no match")
                text += f", edge {v.edge_px:.1f}px" if v.edge_px is not None else ""
                cv2.putText(img, text, (u0 + 2, max(v0 - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
            for ur, vr, up, vp in v.matches:
                a = (int(round(ur * 16)), int(round(vr * 16)))
                b = (int(round(up * 16)), int(round(vp * 16)))
                cv2.line(img, a, b, col, 1, cv2.LINE_AA, shift=4)
                cv2.circle(img, a, 2 * 16, col, -1, cv2.LINE_AA, shift=4)
        cv2.putText(img, f"image {im}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    if not tiles:
        return np.zeros((32, 32, 3), np.uint8)
    H = max(t.shape[0] for t in tiles)
    W = max(t.shape[1] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, H - t.shape[0], 0, W - t.shape[1], cv2.BORDER_CONSTANT) for t in tiles]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0])) if len(tiles) > 1 else None
    rows = [np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles), 2)]
    return np.vstack(rows)
