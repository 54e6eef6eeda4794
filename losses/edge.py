"""The edge term: the photo's edges as evidence for where the outline lies.

Without masks (``--masks none``) the photo's colour regions (:mod:`autoalign.losses.region`) place an
object only as far as its colours differ from its surroundings', which for clear glass is hardly at
all. Its outline still shows in the photo as a thin edge (refraction, a rim's highlight): the
evidence a person reads in ProgressLabeller's overlays. This term pulls the soft outline onto the
photo's edges, in every view at once: a texture edge lies under the outline in one view by chance,
the object's own edge in all of them.

Per view, the edge strength ``E`` in [0, 1]: the photo at the level's resolution
(:data:`EDGE_BLUR_PX` blur), the gradient magnitude of its most-changing channel, blurred the same
(a thin line, as glass shows its outline, has its gradient on its two flanks and none on it;
blurred, they make one ridge on the line), over its :data:`EDGE_PERCENTILE` percentile, clipped at
1. The view's loss is ``weight / 2`` times the mean of ``1 - E`` along the soft outline, each band
pixel weighed by ``(4 s (1 - s))^2`` with ``s`` the soft silhouette (1 on the outline, 0 off it):
it falls as the outline moves onto edges, whatever the outline's length (a sum would favour a
shorter outline, an object pushed away), and pixels entering or leaving the band change it
continuously. Its residual is the square root, one per view.
"""

from __future__ import annotations

import weakref

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.losses.silhouette import ViewTerms, _per_view_sum, _per_view_vec
from autoalign.losses.term import Fragments, TermValues

EDGE_BLUR_PX = 1.0
"""Gaussian blur (px of the level's image) before the gradient: the renderer's and a camera's noise
otherwise make edges everywhere (the same as :data:`~autoalign.quality.edge_distance.BLUR_SIGMA_PX`)."""
EDGE_PERCENTILE = 99.0
"""The gradient magnitude at this percentile of a view counts as a full edge (1): a few highlights
must not set the scale."""


def edge_strength(photo: NDArray[np.uint8], width: int, height: int) -> NDArray[np.float32]:
    """The edge strength (H, W) in [0, 1] of ``photo`` (BGR uint8) resampled to ``width`` x ``height``
    (area-averaged when smaller, as the masks are): module doc."""
    img = photo if photo.shape[1] == width and photo.shape[0] == height else cv2.resize(
        photo, (width, height), interpolation=cv2.INTER_AREA)
    blurred = cv2.GaussianBlur(img, (0, 0), EDGE_BLUR_PX).astype(np.float32)
    gx, gy = cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1)
    g = np.sqrt(gx * gx + gy * gy)
    g = g.max(axis=2) if g.ndim == 3 else g
    g = cv2.GaussianBlur(g, (0, 0), EDGE_BLUR_PX)  # a thin line's two flanks merge into one ridge on it
    top = float(np.percentile(g, EDGE_PERCENTILE))
    return np.minimum(g / max(top, 1e-6), 1.0).astype(np.float32)


_STRENGTHS: dict[tuple[int, int, int], NDArray[np.float32]] = {}
"""Edge strengths by (the photo's ``id``, width, height), each dropped when its photo is: every
instance of a scene, every photo round and the joint stage read the same photos."""


def shared_edge_strength(photo: NDArray[np.uint8], width: int, height: int) -> NDArray[np.float32]:
    """:func:`edge_strength`, worked out once per photo and size while the photo lives."""
    key = (id(photo), width, height)
    strength = _STRENGTHS.get(key)
    if strength is None:
        strength = _STRENGTHS[key] = edge_strength(photo, width, height)
        weakref.finalize(photo, _STRENGTHS.pop, key, None)
    return strength


class EdgeTerm:
    """The soft outline against the photo's edges (module doc), with ``weight`` against the mask term."""

    name = "edge"

    def __init__(self, weight: float) -> None:
        self.weight = float(weight)

    def residuals(self, fragments: Fragments) -> TermValues:
        views, sil = fragments.views, fragments.silhouettes
        if views.photos is None:
            raise ValueError("the edge term needs the views' photos")
        n = sil.n_views
        b, vb = sil.band, sil.view_of_band
        miss = np.zeros(len(b))  # 1 - E at each band pixel
        for k, (cam, photo) in enumerate(zip(views.cameras, views.photos)):
            lo, hi = np.searchsorted(vb, [k, k + 1])
            if hi == lo:
                continue
            x0, y0, w, _ = sil.crops[k]
            local = b[lo:hi] - sil.offsets[k]
            miss[lo:hi] = 1.0 - shared_edge_strength(photo, cam.width, cam.height)[y0 + local // w, x0 + local % w]
        s = sil.soft[b]
        on = 4.0 * s * (1.0 - s)
        p, dp = on * on, 2.0 * on * 4.0 * (1.0 - 2.0 * s)  # the outline's weight of a pixel, and d p / d s
        D = _per_view_sum(p, vb, n)
        mean = _per_view_sum(miss * p, vb, n) / np.maximum(D, 1e-12)  # 1 - E along the outline
        rho = np.sqrt(self.weight * mean)
        # d rho / d s_p = weight ((1 - E_p) - mean) p'(s_p) / (2 rho D)
        dr = self.weight * (miss - mean[vb]) * dp / np.maximum(2.0 * rho * D, 1e-12)[vb]
        J = _per_view_vec(dr, sil.jac, vb, n)
        return TermValues(self.name, ViewTerms(0.5 * rho * rho, J * rho[:, None], J[:, :, None] * J[:, None, :]))
