"""The band of pixels near an outline (``rasterizers/band.py``) against brute force: every pixel of
every crop measured to every outline segment of its view."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.geometry.camera import pixel_centres
from autoalign.rasterizers.band import find_band, point_segment_dist2
from autoalign.rasterizers.outline import Outline

BAND_R = 2.5


def _outline(rng: np.random.Generator, crops: np.ndarray, edge_px: float = 3.0, step_px: float = 0.75) -> Outline:
    """Closed wobbly polygons, one or two a view, as the outline finder gives them (pixels, internal
    convention; grouped by view): each polygon edge (about ``edge_px`` long) cut into segments of about
    ``step_px``, each segment with its midpoint and its whole edge as the interval distances go to."""
    views, edges, mids, a, b = [], [], [], [], []
    for v, (x0, y0, w, h) in enumerate(crops):
        for _ in range(1 + v % 2):
            c = np.array([x0 + w * rng.uniform(0.35, 0.65), y0 + h * rng.uniform(0.35, 0.65)])
            r0 = min(w, h) * rng.uniform(0.15, 0.3)
            n = int(2 * np.pi * r0 / edge_px) + 3
            phi = np.linspace(0.0, 2 * np.pi, n + 1) + rng.uniform(0, 1)
            r = r0 * (1.0 + 0.15 * np.sin(3 * phi + rng.uniform(0, 6)))
            p = c + np.column_stack([r * np.cos(phi), r * np.sin(phi)])
            for e in range(n):
                k = max(1, int(np.ceil(np.linalg.norm(p[e + 1] - p[e]) / step_px)))
                t = (np.arange(k) + 0.5) / k
                views.append(np.full(k, v))
                edges.append(np.full(k, len(edges)))
                mids.append(p[e] + t[:, None] * (p[e + 1] - p[e]))
                a.append(np.repeat(p[e][None], k, 0))
                b.append(np.repeat(p[e + 1][None], k, 0))
    S = sum(len(x) for x in views)
    return Outline(np.concatenate(views), np.concatenate(edges), np.concatenate(mids), np.zeros(S), np.ones(S),
                   np.concatenate(a), np.concatenate(b))


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_band_pixels_and_their_nearest_segments_match_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    crops = np.array([[10, 20, 60, 50], [0, 0, 41, 73], [100, 5, 35, 35], [3, 9, 80, 64]])
    offsets = np.concatenate([[0], np.cumsum(crops[:, 2] * crops[:, 3])])
    outline = _outline(rng, crops)
    band = find_band(outline, crops, offsets, BAND_R)
    near_d, in_view = [], []
    for v, (x0, y0, w, h) in enumerate(crops):
        yy, xx = np.mgrid[y0:y0 + h, x0:x0 + w]
        uv = pixel_centres(xx.ravel(), yy.ravel())
        mine = np.flatnonzero(outline.view == v)
        d2 = point_segment_dist2(uv[:, None, :], outline.a[mine][None], outline.b[mine][None])  # (P, S)
        near_d.append(np.sqrt(d2.min(axis=1)))
        in_view.append(np.full(len(uv), v))
    near_d, in_view = np.concatenate(near_d), np.concatenate(in_view)
    in_band = np.zeros(int(offsets[-1]), dtype=bool)
    in_band[band.pixels] = True
    # the band: every pixel within the radius of the outline, none far beyond it (the distance
    # transform that finds it measures to segment midpoints' cells with a chamfer metric)
    assert in_band[near_d <= BAND_R - 1.0].all()
    assert near_d[in_band].max() <= BAND_R + 1.0
    assert np.array_equal(band.view, in_view[band.pixels])
    # each band pixel's segment is its view's, and as near as the nearest edge for all but a few pixels
    # near the polygon's corners (the candidates are the segments nearest to the pixel and its 4 neighbours;
    # where the nearest point is a corner, both its edges are)
    assert np.array_equal(outline.view[band.segment], band.view)
    got = np.sqrt(point_segment_dist2(np.column_stack([band.px, band.py]), outline.a[band.segment],
                                      outline.b[band.segment]))
    exact = np.isclose(got, near_d[band.pixels], rtol=0, atol=1e-9)
    assert exact.mean() > 0.98, exact.mean()
    assert (got - near_d[band.pixels]).max() < 0.5
    # off the band every region is whole: no region holds a band pixel, and each reaches its three samples
    assert (band.region[band.pixels] == -1).all()
    off = np.flatnonzero(~in_band)
    assert (band.region[off] >= 0).all()
    assert np.array_equal(band.region[band.samples], np.repeat(np.arange(len(band.samples))[:, None], 3, 1))
