"""The band of pixels near an outline, and the hard mask of the crops around it.

Only pixels within ``band_r`` of an outline segment can have a soft value strictly between 0 and
1, so the cost follows the silhouette's length, not pixels x faces. Off the band no outline
passes, so each connected off-band region is wholly inside or wholly outside the silhouette:
three rays decide it.

Pixels are addressed by a flat index: the crops of all views (N, 4: ``x0, y0, w, h``) laid one
after the other, each row-major, view ``i`` starting at ``offsets[i]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import pixel_centres, uv_from_opencv
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.outline import Outline
from autoalign.rasterizers.ray_casting import RayCaster

@dataclass
class Band:
    """The band pixels and the off-band regions of all crops.

    Attributes:
        pixels: (B,) flat indices of the band pixels, grouped by view, increasing.
        segment: (B,) the nearest outline segment of each (index into the :class:`Outline`).
        region: (P,) the off-band region of every flat pixel (-1 in the band).
        samples: (R, 3) three flat pixels of each off-band region.
        view: (B,) the view of each band pixel.
        px, py: (B,) the band pixels' centres in their (scaled) images, pixels (internal
            convention): the values :func:`flat_pixel_centres` gives.
    """

    pixels: NDArray[np.int64]
    segment: NDArray[np.int64]
    region: NDArray[np.int64]
    samples: NDArray[np.int64]
    view: NDArray[np.int64]
    px: NDArray[np.float64]
    py: NDArray[np.float64]


def flat_pixel_centres(crops: NDArray[np.int64], offsets: NDArray[np.int64],
                  flat: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The view and the continuous centre (N, 2; internal convention) of flat pixels."""
    view = np.searchsorted(offsets, flat, side="right") - 1
    local = flat - offsets[view]
    w = crops[view, 2]
    return view, pixel_centres(crops[view, 0] + local % w, crops[view, 1] + local // w)


def find_band(outline: Outline, crops: NDArray[np.int64], offsets: NDArray[np.int64], band_r: float) -> Band:
    """Band pixels (within ``band_r`` px of the outline) with their nearest segment, and off-band regions.

    All crops are stacked into one atlas image, separated by gaps wider than the band, so that
    one distance transform (with labels) and one connected-components pass serve every view.
    The labels propose, for every pixel, the segments nearest to it and to its 4 neighbours;
    the exact point-to-segment distance picks the nearest of them. Taking the minimum over
    several nearby candidates keeps the distance continuous as the outline moves.
    """
    atlas = _Atlas(crops, offsets, gap=int(np.ceil(band_r)) + 2)
    seg = _Segments(outline)
    if len(outline):
        cells, owners = _outline_cells(outline, seg, crops, atlas)
        src = np.ones(atlas.shape, dtype=np.uint8)
        src.ravel()[cells] = 0
        dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        lab_flat = labels.ravel()
        cell_labels = lab_flat[cells]
        # DIST_LABEL_PIXEL: one label per zero pixel (outline cell); every pixel carries its nearest's
        lut = np.full(int(cell_labels.max()) + 1, -1, dtype=np.int64)
        lut[cell_labels] = owners
        in_band = (dist <= band_r) & atlas.valid
    else:
        in_band = np.zeros(atlas.shape, dtype=bool)
    region, samples = _off_band_regions(atlas, in_band)
    at = np.flatnonzero(in_band)  # atlas index of each band pixel
    if len(at) == 0:
        empty = np.zeros(0, np.int64)
        return Band(empty, empty, region, samples, empty, np.zeros(0), np.zeros(0))
    W = atlas.shape[1]
    rr = at // W
    cc = at - rr * W
    band = atlas.flat_index(rr, cc)
    view = atlas.view_of_row[rr]
    px, py = uv_from_opencv(atlas.x0_of_row[rr] + cc), uv_from_opencv(atlas.y0_of_row[rr] + rr)  # centres
    # A band pixel's nearest outline segment is chosen among those nearest to it and to its 4
    # neighbours (in this order: itself, above, below, left, right; clamped at the atlas border).
    # A neighbour across a gap belongs to another view and is never taken.
    neighbours = (at, at - W * (rr > 0), at + W * (rr < atlas.shape[0] - 1), at - (cc > 0), at + (cc < W - 1))
    cand = [lut[lab_flat[i]] for i in neighbours]
    # Distances only where a candidate differs from the best so far (mostly all five agree).
    best = cand[0].copy()
    d_best = seg.dist2(px, py, best)
    d_best[seg.view[best] != view] = np.inf
    for alt in cand[1:]:
        i = np.flatnonzero((alt != best) & (seg.view[alt] == view))
        d = seg.dist2(px[i], py[i], alt[i])
        m = d < d_best[i]
        best[i[m]] = alt[i[m]]
        d_best[i[m]] = d[m]
    return Band(band, best, region, samples, view, px, py)


def _outline_cells(outline: Outline, seg: _Segments, crops: NDArray[np.int64],
                   atlas: _Atlas) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The atlas cells (flat atlas indices, increasing, unique) holding outline segment midpoints,
    and the segment that owns each.

    Several segments (of different edges) can fall in one cell: the cell keeps the one whose
    visible edge interval passes nearest to the cell centre (of equally near ones, the last).
    """
    sv = outline.view
    cx = np.clip(np.floor(outline.mid[:, 0] - crops[sv, 0]).astype(np.int64), 0, crops[sv, 2] - 1)
    cy = np.clip(np.floor(outline.mid[:, 1] - crops[sv, 1]).astype(np.int64), 0, crops[sv, 3] - 1)
    ay = atlas.row0[sv] + cy
    d_cell = seg.dist2(uv_from_opencv(crops[sv, 0] + cx), uv_from_opencv(crops[sv, 1] + cy), np.arange(len(sv)))
    cell = ay * atlas.shape[1] + cx
    order = np.argsort(cell, kind="stable")  # by cell, and within a cell by segment
    by_cell = cell[order]
    first = np.flatnonzero(np.concatenate([[True], by_cell[1:] != by_cell[:-1]]))  # each cell's first segment
    d = d_cell[order]
    nearest = np.repeat(np.minimum.reduceat(d, first), np.diff(np.append(first, len(d))))
    # each cell's nearest segment; of equally near ones the last (the cell's segments keep their order)
    last_nearest = np.maximum.reduceat(np.where(d == nearest, np.arange(len(d)), -1), first)
    return by_cell[first], order[last_nearest]


def _off_band_regions(atlas: _Atlas, in_band: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The off-band region of every flat pixel (P,; -1 in the band) and three flat pixels of
    each region (R, 3): its first and last pixel in row-major order, and its first in
    column-major order (of the atlas)."""
    off_band = atlas.valid & ~in_band
    _, lab, stats, _ = cv2.connectedComponentsWithStats(off_band.view(np.uint8), connectivity=4)
    # The atlas's crop pixels, in row-major order, are the flat pixels in order: band pixels
    # carry component 0, so region -1.
    region = lab[atlas.valid].astype(np.int64) - 1
    # A region's first pixel in row-major order lies in the top row of its bounding box, its
    # last in the bottom row, its first in column-major order in the left column: scanning
    # those rows and columns (not the whole atlas) finds them.
    left, top, width, height = (stats[1:, i].astype(np.int64) for i in range(4))
    right, bottom = left + width - 1, top + height - 1
    samples = np.stack([atlas.flat_index(*_first_match(lab, top, left, width, 0, 1)),
                        atlas.flat_index(*_first_match(lab, bottom, right, width, 0, -1)),
                        atlas.flat_index(*_first_match(lab, top, left, height, 1, 0))], 1)
    return region, samples


def _first_match(lab: NDArray[np.int32], r0: NDArray[np.int64], c0: NDArray[np.int64], n: NDArray[np.int64],
                 dr: int, dc: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For each component ``k + 1`` of ``lab``, the (row, column) of its first pixel along the
    ``n[k]`` pixels from ``(r0[k], c0[k])`` in steps of ``(dr, dc)`` (there must be one)."""
    k = np.repeat(np.arange(len(n)), n)
    step = np.arange(len(k)) - np.repeat(np.cumsum(n) - n, n)
    r, c = r0[k] + dr * step, c0[k] + dc * step
    hit = np.flatnonzero(lab[r, c] == k + 1)  # increasing: grouped by component
    first = hit[np.flatnonzero(np.append(True, k[hit[1:]] != k[hit[:-1]]))]
    return r[first], c[first]


def hard_mask(caster: RayCaster, T_wm: NDArray[np.float64], cams: CameraBatch, crops: NDArray[np.int64],
              offsets: NDArray[np.int64], band: Band) -> NDArray[np.bool_]:
    """The hard mask of all crop pixels from rays at band pixels and three per off-band region.

    A region whose rays disagree (an outline the segment test missed) is ray-cast pixel by pixel.
    """
    def hits(flat: NDArray[np.int64]) -> NDArray[np.bool_]:
        return caster.pixel_hits(T_wm, cams, *flat_pixel_centres(crops, offsets, flat))

    n_band = len(band.pixels)
    sample_view, sample_uv = flat_pixel_centres(crops, offsets, band.samples.ravel())
    h = caster.pixel_hits(T_wm, cams, np.concatenate([band.view, sample_view]),
                          np.concatenate([np.column_stack([band.px, band.py]), sample_uv]))
    if band.samples.size:
        sv = h[n_band:].reshape(band.samples.shape)
        hard = sv[band.region, 0]  # each off-band pixel its region's value (band pixels: set below)
        mixed = np.flatnonzero(~np.all(sv == sv[:, :1], axis=1))
        if len(mixed):
            redo = np.flatnonzero(np.isin(band.region, mixed))
            hard[redo] = hits(redo)
    else:
        hard = np.zeros(int(offsets[-1]), dtype=bool)
    hard[band.pixels] = h[:n_band]
    return hard


def point_segment_dist2(p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared distance from points ``p`` to segments ``[a, b]`` (broadcast over leading axes)."""
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    qx, qy = p[..., 0] - a[..., 0], p[..., 1] - a[..., 1]
    t = np.clip((qx * dx + qy * dy) / np.maximum(dx * dx + dy * dy, 1e-18), 0.0, 1.0)
    ex, ey = t * dx - qx, t * dy - qy
    return ex * ex + ey * ey


class _Segments:
    """The outline segments' constants of the point-to-segment distance (pixels): the start
    ``a``, the direction ``b - a`` and its squared length (at least 1e-18), computed once per
    segment and gathered per pixel. :meth:`dist2` does the operations of
    :func:`point_segment_dist2` in the same order, so the distances are the same to the bit."""

    def __init__(self, outline: Outline) -> None:
        self.view = outline.view
        self.ax, self.ay = outline.a[:, 0].copy(), outline.a[:, 1].copy()
        self.dx, self.dy = outline.b[:, 0] - outline.a[:, 0], outline.b[:, 1] - outline.a[:, 1]
        self.den = np.maximum(self.dx * self.dx + self.dy * self.dy, 1e-18)

    def dist2(self, px: NDArray[np.float64], py: NDArray[np.float64], s: NDArray[np.int64]) -> NDArray[np.float64]:
        """Squared distance (px^2) from the points ``(px, py)`` (n,) to the segments ``s`` (n,)."""
        dx, dy = self.dx[s], self.dy[s]
        qx, qy = px - self.ax[s], py - self.ay[s]
        t = qx * dx
        t += qy * dy
        t /= self.den[s]
        np.clip(t, 0.0, 1.0, out=t)
        ex, ey = t * dx, t * dy
        ex -= qx
        ey -= qy
        ex *= ex
        ey *= ey
        ex += ey
        return ex


class _Atlas:
    """All crops stacked top to bottom in one image, ``gap`` rows apart, left-aligned.

    ``valid`` marks crop pixels, ``row0[i]`` is the first atlas row of view ``i``, ``view_of_row``
    the view of each row (-1 in gaps), and ``x0_of_row``/``y0_of_row`` what to add to an atlas
    column/row to get the image column/row of its view (pixels). Read in row-major order, the
    crop pixels of the atlas are the flat pixels in order: :meth:`flat_index` maps one to the other.
    """

    def __init__(self, crops: NDArray[np.int64], offsets: NDArray[np.int64], gap: int) -> None:
        n = len(crops)
        heights = crops[:, 3] + gap
        self.row0 = np.concatenate([[0], np.cumsum(heights)[:-1]]).astype(np.int64)
        H = int(heights.sum()) if n else 1
        W = int(crops[:, 2].max()) + gap if n else 1
        self.shape = (max(H, 1), max(W, 1))
        # Each atlas row's view: the crop it lies in, or the crop its gap follows (no views: index
        # -1, the appended empty crop).
        view = np.full(self.shape[0], -1, dtype=np.int64)
        view[:int(heights.sum())] = np.repeat(np.arange(n), heights)
        crop = np.vstack([crops, np.zeros((1, 4), dtype=np.int64)])[view]
        row0 = np.append(self.row0[:n], 0)[view]
        local = np.arange(self.shape[0]) - row0  # row within the crop
        in_crop = local < crop[:, 3]
        width = np.where(in_crop, crop[:, 2], 0)
        self.view_of_row = np.where(in_crop, view, -1)
        self.valid = np.arange(self.shape[1]) < width[:, None]
        self.x0_of_row = crop[:, 0]
        self.y0_of_row = crop[:, 1] - row0
        self._flat_row0 = np.append(offsets[:n], 0)[view] + local * width  # flat index of column 0

    def flat_index(self, r: NDArray[np.int64], c: NDArray[np.int64]) -> NDArray[np.int64]:
        """The flat pixel index of the atlas crop pixels ``(r, c)`` (rows, columns)."""
        return self._flat_row0[r] + c
