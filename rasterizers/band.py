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

from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.outline import Outline
from autoalign.rasterizers.ray_casting import RayCaster

# A band pixel's nearest outline segment is chosen among those nearest to it and to its 4 neighbours.
_CANDIDATE_OFFSETS = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))


@dataclass
class Band:
    """The band pixels and the off-band regions of all crops.

    Attributes:
        pixels: (B,) flat indices of the band pixels, grouped by view, increasing.
        segment: (B,) the nearest outline segment of each (index into the :class:`Outline`).
        region: (P,) the off-band region of every flat pixel (-1 in the band).
        samples: (R, 3) three flat pixels of each off-band region.
    """

    pixels: NDArray[np.int64]
    segment: NDArray[np.int64]
    region: NDArray[np.int64]
    samples: NDArray[np.int64]


def pixel_centres(crops: NDArray[np.int64], offsets: NDArray[np.int64],
                  flat: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The view and the continuous centre (N, 2; internal convention, +0.5) of flat pixels."""
    view = np.searchsorted(offsets, flat, side="right") - 1
    local = flat - offsets[view]
    w = crops[view, 2]
    return view, np.column_stack([crops[view, 0] + local % w + 0.5, crops[view, 1] + local // w + 0.5])


def find_band(outline: Outline, crops: NDArray[np.int64], offsets: NDArray[np.int64], band_r: float) -> Band:
    """Band pixels (within ``band_r`` px of the outline) with their nearest segment, and off-band regions.

    All crops are stacked into one atlas image, separated by gaps wider than the band, so that
    one distance transform (with labels) and one connected-components pass serve every view.
    The labels propose, for every pixel, the segments nearest to it and to its 4 neighbours;
    the exact point-to-segment distance picks the nearest of them. Taking the minimum over
    several nearby candidates keeps the distance continuous as the outline moves.
    """
    P = int(offsets[-1])
    region = np.full(P, -1, dtype=np.int64)
    atlas = _Atlas(crops, offsets, gap=int(np.ceil(band_r)) + 2)
    src = np.ones(atlas.shape, dtype=np.uint8)
    if len(outline):
        sv = outline.view
        cx = np.clip(np.floor(outline.mid[:, 0] - crops[sv, 0]).astype(np.int64), 0, crops[sv, 2] - 1)
        cy = np.clip(np.floor(outline.mid[:, 1] - crops[sv, 1]).astype(np.int64), 0, crops[sv, 3] - 1)
        ay = atlas.row0[sv] + cy
        src[ay, cx] = 0
        # Several segments (of different edges) can fall in one cell: the cell keeps the one
        # whose visible edge interval passes nearest to the cell centre.
        centre = np.stack([crops[sv, 0] + cx + 0.5, crops[sv, 1] + cy + 0.5], 1)
        d_cell = point_segment_dist2(centre, outline.a, outline.b)
        cell = ay * atlas.shape[1] + cx
        order = np.lexsort((-d_cell, cell))  # within a cell, nearest last: the last write wins
        owner = np.full(atlas.shape, -1, dtype=np.int64)
        owner[ay[order], cx[order]] = order
        dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        lut = np.full(int(labels.max()) + 1, -1, dtype=np.int64)
        lut[labels[ay, cx]] = owner[ay, cx]
        in_band = (dist <= band_r) & atlas.valid
    else:
        in_band = np.zeros(atlas.shape, dtype=bool)
    off_band = atlas.valid & ~in_band
    n_lab, lab = cv2.connectedComponents(off_band.astype(np.uint8), connectivity=4)
    off = np.flatnonzero(off_band.ravel())  # atlas pixels, row-major
    flat_off = atlas.flat.ravel()[off]
    lab_off = lab.ravel()[off].astype(np.int64) - 1
    region[flat_off] = lab_off
    # three sample pixels per region without sorting: its first and last pixel in row-major
    # order, and its first in column-major order (later writes win in a fancy assignment)
    samples = np.zeros((n_lab - 1, 3), dtype=np.int64)
    samples[lab_off[::-1], 0] = flat_off[::-1]
    samples[lab_off, 1] = flat_off
    lab_t = lab.T.ravel()  # column-major copies
    in_t = np.flatnonzero(lab_t)
    samples[lab_t[in_t[::-1]].astype(np.int64) - 1, 2] = atlas.flat.T.ravel()[in_t[::-1]]
    rr, cc = np.nonzero(in_band)
    if len(rr) == 0:
        return Band(np.zeros(0, np.int64), np.zeros(0, np.int64), region, samples)
    band = atlas.flat[rr, cc]
    view = atlas.view_of_row[rr]
    nearest = np.pad(lut[labels], 1, mode="edge")
    cand = np.stack([nearest[rr + 1 + dy, cc + 1 + dx] for dy, dx in _CANDIDATE_OFFSETS], 1)
    p = np.stack([crops[view, 0] + cc + 0.5, crops[view, 1] + rr - atlas.row0[view] + 0.5], 1)
    # Distances only where a candidate differs from the best so far (mostly all five agree);
    # a neighbour across a gap belongs to another view and is never taken.
    best = cand[:, 0].copy()
    d_best = point_segment_dist2(p, outline.a[best], outline.b[best])
    d_best[outline.view[best] != view] = np.inf
    for k in range(1, cand.shape[1]):
        alt = cand[:, k]
        i = np.flatnonzero((alt != best) & (outline.view[alt] == view))
        d = point_segment_dist2(p[i], outline.a[alt[i]], outline.b[alt[i]])
        m = d < d_best[i]
        best[i[m]] = alt[i[m]]
        d_best[i[m]] = d[m]
    return Band(band, best, region, samples)


def hard_mask(caster: RayCaster, T_wm: NDArray[np.float64], cams: CameraBatch, crops: NDArray[np.int64],
              offsets: NDArray[np.int64], band: Band) -> NDArray[np.bool_]:
    """The hard mask of all crop pixels from rays at band pixels and three per off-band region.

    A region whose rays disagree (an outline the segment test missed) is ray-cast pixel by pixel.
    """
    def hits(flat: NDArray[np.int64]) -> NDArray[np.bool_]:
        return caster.pixel_hits(T_wm, cams, *pixel_centres(crops, offsets, flat))

    hard = np.zeros(int(offsets[-1]), dtype=bool)
    h = hits(np.concatenate([band.pixels, band.samples.ravel()]))
    hard[band.pixels] = h[:len(band.pixels)]
    if band.samples.size:
        sv = h[len(band.pixels):].reshape(band.samples.shape)
        value = sv[:, 0]
        off = np.flatnonzero(band.region >= 0)
        hard[off] = value[band.region[off]]
        mixed = np.flatnonzero(~np.all(sv == sv[:, :1], axis=1))
        if len(mixed):
            redo = off[np.isin(band.region[off], mixed)]
            hard[redo] = hits(redo)
    return hard


def point_segment_dist2(p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared distance from points ``p`` to segments ``[a, b]`` (broadcast over leading axes)."""
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    qx, qy = p[..., 0] - a[..., 0], p[..., 1] - a[..., 1]
    t = np.clip((qx * dx + qy * dy) / np.maximum(dx * dx + dy * dy, 1e-18), 0.0, 1.0)
    ex, ey = t * dx - qx, t * dy - qy
    return ex * ex + ey * ey


class _Atlas:
    """All crops stacked top to bottom in one image, ``gap`` rows apart, left-aligned.

    ``flat[y, x]`` is the flat pixel index of atlas pixel (y, x) (-1 in gaps), ``valid`` marks crop
    pixels, ``row0[i]`` is the first atlas row of view ``i`` and ``view_of_row`` the view of each row.
    """

    def __init__(self, crops: NDArray[np.int64], offsets: NDArray[np.int64], gap: int) -> None:
        heights = crops[:, 3] + gap
        self.row0 = np.concatenate([[0], np.cumsum(heights)[:-1]]).astype(np.int64)
        H = int(heights.sum()) if len(crops) else 1
        W = int(crops[:, 2].max()) + gap if len(crops) else 1
        self.shape = (max(H, 1), max(W, 1))
        self.flat = np.full(self.shape, -1, dtype=np.int64)
        self.view_of_row = np.full(self.shape[0], -1, dtype=np.int64)
        for i, (x0, y0, w, h) in enumerate(crops):
            r0 = self.row0[i]
            self.flat[r0:r0 + h, :w] = offsets[i] + np.arange(w * h).reshape(h, w)
            self.view_of_row[r0:r0 + h] = i
        self.valid = self.flat >= 0
