"""A picture of how well a pose fits: target masks with the silhouette outline before and after.

``render_overlay(scene, rasterizer, T_before, T_after, ious_before, ious_after)`` draws a grid (BGR; :func:`encode_png`
makes it a PNG) of up to 12 views (evenly chosen over the scene, always including the worst-fitting
view after refinement). Each tile is cropped and zoomed around the object and shows

* the target mask in grey (darker grey: inside the image but not in the mask, near-black:
  outside the image),
* the ray-cast silhouette outline at ``T_before`` in red and at ``T_after`` in green,
* the image id and the IoU before -> after refinement (the worst view after is marked ``worst``).

All poses are world-from-model 4x4 matrices in millimetres (BOP world frame of the scene).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import uv_from_opencv, uv_to_opencv
from autoalign.io.bop import Scene, photo_path, read_photo
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

MAX_TILES = 12
TILE_W, TILE_H = 320, 240
GAP = 4
LEGEND_H = 28

# BGR colours
_OUTSIDE = (12, 12, 12)
_BACKGROUND = (48, 48, 48)
_TARGET = (150, 150, 150)
_BEFORE = (40, 40, 235)
_AFTER = (40, 210, 40)
_TEXT = (255, 255, 255)
_WORST = (0, 200, 255)
_SHIFT = 4  # sub-pixel bits for cv2 drawing


def choose_views(ious_after: ArrayLike, max_views: int = MAX_TILES) -> list[int]:
    """Indices of up to ``max_views`` views spread evenly over the scene, always with the worst one.

    The worst view (lowest IoU after) replaces the evenly chosen view nearest to it if it is not
    already among them. Returned sorted.
    """
    iou = np.asarray(ious_after, dtype=np.float64).ravel()
    n = len(iou)
    if n == 0:
        return []
    k = min(max_views, n)
    idx = sorted(set(np.linspace(0, n - 1, k).round().astype(int).tolist()))
    worst = int(np.nanargmin(iou)) if np.any(np.isfinite(iou)) else 0
    if worst not in idx:
        nearest = min(range(len(idx)), key=lambda j: abs(idx[j] - worst))
        idx[nearest] = worst
        idx.sort()
    return idx


def _crop_box(masks: list[NDArray[np.bool_]], width: int, height: int,
              aspect: float = TILE_W / TILE_H) -> tuple[float, float, float, float]:
    """Continuous crop ``(x0, y0, w, h)`` around the union of ``masks``, with margin, at ``aspect``."""
    union = np.zeros((height, width), dtype=bool)
    for m in masks:
        union |= m
    box = _mask_box(union)
    if box is None:
        x0, y0, x1, y1 = 0.0, 0.0, float(width), float(height)
    else:
        rows, cols = box
        x0, x1 = float(cols.start), float(cols.stop)
        y0, y1 = float(rows.start), float(rows.stop)
    w, h = x1 - x0, y1 - y0
    margin = max(8.0, 0.15 * max(w, h))
    w, h = w + 2 * margin, h + 2 * margin
    w, h = max(w, h * aspect, 32.0), max(h, w / aspect, 32.0 / aspect)
    w = max(w, h * aspect)
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    return cx - w / 2.0, cy - h / 2.0, w, h


def _mask_box(mask: NDArray[np.bool_]) -> tuple[slice, slice] | None:
    """The rows and columns of the smallest box holding every pixel of ``mask``; ``None`` if it is empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def _contour_polys(mask: NDArray[np.bool_], x0: float, y0: float, s: float) -> list[NDArray[np.int32]]:
    """Outline polygons of ``mask`` in tile coordinates (fixed point with ``_SHIFT`` bits)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in contours:
        p = uv_from_opencv(c.reshape(-1, 2))  # the contour's pixel centres, continuous coordinates
        p = uv_to_opencv((p - [x0, y0]) * s)  # to tile pixel indices
        out.append(np.round(p * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2))
    return out


def _put_label(img: NDArray[np.uint8], text: str, org: tuple[int, int], colour: tuple[int, int, int],
               scale: float = 0.5) -> None:
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = org
    cv2.rectangle(img, (x - 3, y - th - 4), (x + tw + 3, y + base + 1), (0, 0, 0), -1)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def tile_map(x0: int, y0: int, s: float) -> NDArray[np.float64]:
    """The 2x3 affine map (``cv2.warpAffine``) from image pixel indices to the indices of a tile
    showing the image from pixel ``(x0, y0)`` on at ``s`` tile pixels per image pixel: pixel centres
    map onto pixel centres."""
    shift = uv_to_opencv((uv_from_opencv(np.zeros(2)) - [x0, y0]) * s)
    return np.array([[s, 0.0, shift[0]], [0.0, s, shift[1]]])


def _tile(target: NDArray[np.bool_], before: NDArray[np.bool_], after: NDArray[np.bool_], label: str,
          worst: bool) -> NDArray[np.uint8]:
    H, W = target.shape
    x0, y0, w, h = _crop_box([target, before, after], W, H)
    s = TILE_W / w
    A = tile_map(x0, y0, s)
    interp = cv2.INTER_NEAREST if s >= 1.0 else cv2.INTER_LINEAR  # zoomed in: show the mask's pixels
    inside = cv2.warpAffine(np.ones((H, W), np.float32), A, (TILE_W, TILE_H), flags=interp,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    tgt = cv2.warpAffine(target.astype(np.float32), A, (TILE_W, TILE_H), flags=interp,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    img = np.empty((TILE_H, TILE_W, 3), np.float32)
    for c in range(3):
        img[..., c] = _OUTSIDE[c] + inside * (_BACKGROUND[c] - _OUTSIDE[c]) + tgt * (_TARGET[c] - _BACKGROUND[c])
    img = np.clip(img, 0, 255).astype(np.uint8)
    thick = 2 if s >= 1.5 else 1
    for m, colour in ((before, _BEFORE), (after, _AFTER)):
        polys = _contour_polys(m, x0, y0, s)
        if polys:
            cv2.polylines(img, polys, True, colour, thick, cv2.LINE_AA, _SHIFT)
    _put_label(img, label, (6, 18), _WORST if worst else _TEXT)
    if s != 1.0:
        _put_label(img, f"x{s:.2g}", (TILE_W - 44, TILE_H - 8), (200, 200, 200), 0.4)
    return img


def render_overlay(scene: Scene, rasterizer: SoftSilhouetteRasterizer, T_before: ArrayLike, T_after: ArrayLike,
                   ious_before: ArrayLike, ious_after: ArrayLike, max_views: int = MAX_TILES) -> NDArray[np.uint8]:
    """The overlay grid as a BGR uint8 image (see the module docstring); nothing is written.

    Args:
        scene: the views and target masks.
        rasterizer: draws the object model (mm): the one its IoUs were measured with
            (:meth:`MeshPyramid.fine <autoalign.rasterizers.pyramid.MeshPyramid.fine>`).
        T_before / T_after: world-from-model poses (4x4, mm) drawn in red / green.
        ious_before / ious_after: per-view IoU at ``T_before`` / ``T_after``
            (:func:`~autoalign.losses.overlap.view_ious`; ``ious_after`` chooses the worst view).
        max_views: at most this many tiles.
    """
    before_ious = np.asarray(ious_before, dtype=np.float64).ravel()
    ious = np.asarray(ious_after, dtype=np.float64).ravel()
    if len(ious) != len(scene) or len(before_ious) != len(scene):
        raise ValueError(f"{len(before_ious)} and {len(ious)} IoUs before and after for {len(scene)} views")
    idx = choose_views(ious, max_views)
    worst = int(np.nanargmin(ious)) if np.any(np.isfinite(ious)) else -1
    cams = [scene.cameras[i] for i in idx]
    before = rasterizer.hard_masks(np.asarray(T_before, dtype=np.float64), cams)
    after = rasterizer.hard_masks(np.asarray(T_after, dtype=np.float64), cams)
    tiles = []
    for j, i in enumerate(idx):
        target = np.asarray(scene.masks[i]) > 0.5
        label = f"im {scene.image_ids[i]}  IoU {before_ious[i]:.3f} -> {ious[i]:.3f}" + ("  worst" if i == worst else "")
        tiles.append(_tile(target, before[j], after[j], label, i == worst))
    cols = min(4, len(tiles))
    rows = -(-len(tiles) // cols)
    W = max(cols, 2) * TILE_W + (max(cols, 2) + 1) * GAP  # at least two tiles wide, for the legend
    H = LEGEND_H + rows * TILE_H + (rows + 1) * GAP
    grid = np.full((H, W, 3), 24, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        y, x = LEGEND_H + GAP + r * (TILE_H + GAP), GAP + c * (TILE_W + GAP)
        grid[y:y + TILE_H, x:x + TILE_W] = t
    _legend(grid, ious)
    return grid


def _legend(grid: NDArray[np.uint8], ious: NDArray[np.float64]) -> None:
    x, y = GAP + 4, 19
    for colour, text, swatch in ((_TARGET, "target mask", "fill"), (_BEFORE, "before", "line"),
                                 (_AFTER, "after", "line")):
        if swatch == "fill":
            cv2.rectangle(grid, (x, y - 10), (x + 16, y + 2), colour, -1)
        else:
            cv2.line(grid, (x, y - 4), (x + 16, y - 4), colour, 2, cv2.LINE_AA)
        cv2.putText(grid, text, (x + 22, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _TEXT, 1, cv2.LINE_AA)
        x += 22 + cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0] + 18
    text = f"IoU after: mean {np.nanmean(ious):.3f}, min {np.nanmin(ious):.3f}"
    cv2.putText(grid, text, (x + 10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _TEXT, 1, cv2.LINE_AA)


def encode_png(img: NDArray[np.uint8]) -> bytes:
    """PNG bytes of a BGR image."""
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 BGR image
        raise RuntimeError("cv2.imencode failed to encode the overlay")
    return buf.tobytes()


# ------------------------------------------------------------------------------------------
# Several instances
# ------------------------------------------------------------------------------------------

INSTANCE_COLOURS = ((60, 180, 255), (255, 120, 60), (80, 220, 80), (220, 80, 220), (60, 230, 230),
                    (255, 200, 80), (120, 120, 255), (200, 255, 120), (160, 80, 255), (80, 160, 160))
"""BGR colour of instance ``k`` (cycled)."""
_STATUS_MARK = {"ok": "ok", "check": "CHECK", "failed": "FAILED"}
MULTI_TILE_W, MULTI_TILE_H = 480, 360


def photo_at(scene_dir: str | os.PathLike[str] | None, image_id: int, width: int, height: int) -> NDArray[np.uint8] | None:
    """The scene's photo of ``image_id`` (:func:`autoalign.io.bop.photo_path`) at ``width x height``
    (BGR), or ``None`` if there is none to read."""
    if scene_dir is None:
        return None
    try:
        img = read_photo(photo_path(Path(scene_dir), image_id))
    except AutoalignError:
        return None
    return img if img.shape[:2] == (height, width) else cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def render_instances_overlay(cameras: list, image_ids: list[int], scene_dir: str | os.PathLike[str] | None,
                             instances: list[tuple[str, dict[int, NDArray[np.bool_]], NDArray[np.bool_] | None]],
                             views: list[int]) -> NDArray[np.uint8]:
    """A grid of whole views with every instance in its own colour (BGR uint8); nothing is written.

    Args:
        cameras / image_ids: the views (at the masks' scale).
        scene_dir: where the photos are (``rgb/``), drawn dimmed underneath; dark grey without.
        instances: per instance ``(label, masks, silhouettes)``: its label (object id and verdict),
            its target masks by image id (tinted), and its ray-cast silhouettes after refinement,
            (V, H, W) for the views ``views`` (outlined); colours follow :data:`INSTANCE_COLOURS`.
        views: positions in ``cameras`` of the views to draw (at most 12 read well).
    """
    tiles = []
    for j, i in enumerate(views):
        cam, im = cameras[i], image_ids[i]
        photo = photo_at(scene_dir, im, cam.width, cam.height)
        base = (photo.astype(np.float32) * 0.55 if photo is not None
                else np.full((cam.height, cam.width, 3), 40.0, np.float32))
        for k, (_, masks, _) in enumerate(instances):
            m = masks.get(im)
            if m is not None and (box := _mask_box(m)) is not None:
                sub, on = base[box], m[box]  # the mask's box: a few thousand pixels of the whole image
                sub[on] = 0.55 * sub[on] + 0.45 * np.array(INSTANCE_COLOURS[k % len(INSTANCE_COLOURS)], np.float32)
        x0, y0, w, h = _crop_box([m for _, ms, _ in instances if (m := ms.get(im)) is not None]
                                 + [sil[j] for _, _, sil in instances if sil is not None], cam.width, cam.height,
                                 MULTI_TILE_W / MULTI_TILE_H)
        s = MULTI_TILE_W / w
        A = tile_map(x0, y0, s)
        tile = cv2.warpAffine(np.clip(base, 0, 255).astype(np.uint8), A, (MULTI_TILE_W, MULTI_TILE_H),
                              flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=_OUTSIDE)
        for k, (label, _, sil) in enumerate(instances):
            if sil is None or not sil[j].any():
                continue
            colour = INSTANCE_COLOURS[k % len(INSTANCE_COLOURS)]
            cv2.polylines(tile, _contour_polys(sil[j], x0, y0, s), True, colour, 2, cv2.LINE_AA, _SHIFT)
            rows, cols = _mask_box(sil[j])
            ys, xs = np.nonzero(sil[j][rows, cols])
            ys, xs = ys + rows.start, xs + cols.start
            _put_label(tile, label, (int((xs.mean() - x0) * s) - 20, max(int((ys.min() - y0) * s) - 4, 30)), colour, 0.4)
        _put_label(tile, f"im {im}", (6, 18), _TEXT)
        tiles.append(tile)
    cols = min(3, max(len(tiles), 1))
    rows = max(-(-len(tiles) // cols), 1)
    grid = np.full((LEGEND_H + rows * MULTI_TILE_H + (rows + 1) * GAP, cols * MULTI_TILE_W + (cols + 1) * GAP, 3),
                   24, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        y, x = LEGEND_H + GAP + r * (MULTI_TILE_H + GAP), GAP + c * (MULTI_TILE_W + GAP)
        grid[y:y + MULTI_TILE_H, x:x + MULTI_TILE_W] = t
    cv2.putText(grid, "tint: the instance's mask; outline: its silhouette after refinement; label: obj id and verdict",
                (GAP + 4, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _TEXT, 1, cv2.LINE_AA)
    return grid


def instance_label(obj_id: int, status: str) -> str:
    """The overlay label of an instance: its object id and verdict (``obj 5 CHECK``)."""
    return f"obj {obj_id} {_STATUS_MARK.get(status, status)}"
