"""Silhouette losses between rendered soft masks and target masks, per view (see package doc)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.rasterizers.soft_silhouette import Silhouettes

_EPS = 1e-9


@dataclass
class ViewTerms:
    """Per-view loss terms. ``loss``: (N,); ``grad``: (N, 6); ``gn``: (N, 6, 6); ``iou``: (N,) soft IoU
    (``None``: a term that measures no overlap, such as the depth term)."""

    loss: NDArray[np.float64]
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]
    iou: NDArray[np.float64] | None = None


def targets_in_crops(targets: list[NDArray[np.float32]], sil: Silhouettes) -> NDArray[np.float64]:
    """Target values at the flat crop pixels of ``sil`` (targets are full (H, W) images in [0, 1])."""
    parts = [t[y0:y0 + h, x0:x0 + w].ravel() for t, (x0, y0, w, h) in zip(targets, sil.crops)]
    return np.concatenate(parts).astype(np.float64) if parts else np.zeros(0)


def _view_bounds(view: NDArray[np.int64], n: int) -> NDArray[np.int64]:
    """Where each view's run starts in ``view`` and where the last one ends, (n + 1,): the flat crop
    pixels and the band are laid out view by view, so ``view`` is sorted."""
    return np.searchsorted(view, np.arange(n + 1))


def _per_view_sum(values: NDArray[np.float64], view: NDArray[np.int64], n: int) -> NDArray[np.float64]:
    """``sum_p values_p`` per view, (n,) (``view`` sorted; a view with no pixels sums to 0)."""
    bounds = _view_bounds(view, n)
    out = np.zeros(n)
    filled = bounds[1:] > bounds[:-1]
    if filled.any():  # reduceat sums from each start to the next one given: the empty views are left out
        out[filled] = np.add.reduceat(np.asarray(values, dtype=np.float64), bounds[:-1][filled])
    return out


def _per_view_vec(coeff: NDArray[np.float64], jac: NDArray[np.float64], view: NDArray[np.int64],
                  n: int) -> NDArray[np.float64]:
    """``sum_p coeff_p jac_p`` per view, (n, 6) (``view`` sorted)."""
    bounds = _view_bounds(view, n)
    out = np.zeros((n, 6))
    for v in np.flatnonzero(bounds[1:] > bounds[:-1]):
        s, e = bounds[v], bounds[v + 1]
        out[v] = coeff[s:e] @ jac[s:e]
    return out


def _per_view_outer(coeff: NDArray[np.float64], jac: NDArray[np.float64], view: NDArray[np.int64],
                    n: int) -> NDArray[np.float64]:
    """``sum_p coeff_p jac_p jac_p^T`` per view, (n, 6, 6) (``view`` sorted), exactly symmetric."""
    bounds = _view_bounds(view, n)
    H = np.zeros((n, 6, 6))
    weighted = jac * coeff[:, None]
    for v in np.flatnonzero(bounds[1:] > bounds[:-1]):
        s, e = bounds[v], bounds[v + 1]
        M = weighted[s:e].T @ jac[s:e]
        H[v] = np.triu(M) + np.triu(M, 1).T
    return H


def _overlap_sums(sil: Silhouettes, t_crop: NDArray[np.float64], t_total: NDArray[np.float64]):
    n = sil.n_views
    vp = sil.view_of_pixel()
    inter = _per_view_sum(sil.soft * t_crop, vp, n)
    area_s = _per_view_sum(sil.soft, vp, n)
    union = area_s + t_total - inter
    return inter, area_s, union


def _soft_iou(inter, union) -> NDArray[np.float64]:
    return np.where(union > _EPS, inter / np.maximum(union, _EPS), 1.0)


def _scalar_terms(r: NDArray[np.float64], dr_ds: NDArray[np.float64], sil: Silhouettes,
                  iou_v: NDArray[np.float64]) -> ViewTerms:
    """Terms of a one-residual-per-view loss ``rho_i = r_i`` with ``d r_i / d s_p = dr_ds[p]`` (band)."""
    n = sil.n_views
    J = _per_view_vec(dr_ds, sil.jac, sil.view_of_band, n)  # (n, 6)
    return ViewTerms(0.5 * r * r, J * r[:, None], J[:, :, None] * J[:, None, :], iou_v)


def iou(sil: Silhouettes, t_crop: NDArray[np.float64], t_total: NDArray[np.float64]) -> ViewTerms:
    """Soft IoU loss, ``rho_i = 1 - IoU_i`` with ``IoU = sum(s t) / sum(s + t - s t)``."""
    inter, _, union = _overlap_sums(sil, t_crop, t_total)
    v = _soft_iou(inter, union)
    b, vb = sil.band, sil.view_of_band
    tb, I, U = t_crop[b], inter[vb], np.maximum(union[vb], _EPS)
    d_iou = (tb * U - I * (1.0 - tb)) / (U * U)
    return _scalar_terms(1.0 - v, -d_iou, sil, v)


def dice(sil: Silhouettes, t_crop: NDArray[np.float64], t_total: NDArray[np.float64]) -> ViewTerms:
    """Soft Dice loss, ``rho_i = 1 - 2 sum(s t) / (sum(s) + sum(t))``."""
    inter, area_s, union = _overlap_sums(sil, t_crop, t_total)
    den = np.maximum(area_s + t_total, _EPS)
    d = 2.0 * inter / den
    b, vb = sil.band, sil.view_of_band
    d_dice = (2.0 * t_crop[b] * den[vb] - 2.0 * inter[vb]) / (den[vb] ** 2)
    return _scalar_terms(1.0 - d, -d_dice, sil, _soft_iou(inter, union))


def l2(sil: Silhouettes, t_crop: NDArray[np.float64], t_total: NDArray[np.float64]) -> ViewTerms:
    """Per-pixel squared error normalised by the target area: ``rho = (s - t) / sqrt(area_t)``."""
    n = sil.n_views
    vp = sil.view_of_pixel()
    inter, _, union = _overlap_sums(sil, t_crop, t_total)
    norm = np.maximum(t_total, 1.0)
    outside = t_total - _per_view_sum(t_crop, vp, n)  # target pixels outside the crop: s = 0 there
    e = sil.soft - t_crop
    loss = 0.5 * (_per_view_sum(e * e, vp, n) + np.maximum(outside, 0.0)) / norm
    b, vb = sil.band, sil.view_of_band
    grad = _per_view_vec(e[b] / norm[vb], sil.jac, vb, n)
    gn = _per_view_outer(1.0 / norm[vb], sil.jac, vb, n)
    return ViewTerms(loss, grad, gn, _soft_iou(inter, union))


def bce(sil: Silhouettes, t_crop: NDArray[np.float64], t_total: NDArray[np.float64],
        eps: float = 1e-3) -> ViewTerms:
    """Binary cross-entropy per pixel (``s`` clipped to ``[eps, 1 - eps]``), normalised by the target area.

    The Gauss-Newton matrix is the Fisher information ``sum_p jac_p jac_p^T / (s_p (1 - s_p))``.
    """
    n = sil.n_views
    vp = sil.view_of_pixel()
    inter, _, union = _overlap_sums(sil, t_crop, t_total)
    norm = np.maximum(t_total, 1.0)
    s = np.clip(sil.soft, eps, 1.0 - eps)
    outside = np.maximum(t_total - _per_view_sum(t_crop, vp, n), 0.0)
    ce = -(t_crop * np.log(s) + (1.0 - t_crop) * np.log(1.0 - s))
    loss = (_per_view_sum(ce, vp, n) - outside * np.log(eps)) / norm
    b, vb = sil.band, sil.view_of_band
    sb = s[b]
    dce = (sb - t_crop[b]) / (sb * (1.0 - sb))
    grad = _per_view_vec(dce / norm[vb], sil.jac, vb, n)
    gn = _per_view_outer(1.0 / (sb * (1.0 - sb) * norm[vb]), sil.jac, vb, n)
    return ViewTerms(loss, grad, gn, _soft_iou(inter, union))


_SQUARE = np.ones((3, 3), np.uint8)
_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def outline_shift_rate(target: NDArray) -> NDArray[np.float32]:
    """How a target mask's pixels change per pixel of outward shift of its outline (thresholded at
    0.5): 1/2 on the two-pixel ring across the outline, 0 elsewhere, from the mean of the square
    and the cross 3x3 dilations and erosions (which move a slanted outline by 1 to 1.41 and 0.71 to
    1 px: their mean by 1 to 1.12). Kept within a pixel of the outline, where the silhouette's soft
    edge (and its derivative) lies: a blurred outline's gradient has the exact length but, spread
    wider, under-predicted the pose's response to a real 1 px shift by 30%; this ring by 5-20%
    (``tests/test_uncertainty.py``)."""
    t = (np.asarray(target) > 0.5).astype(np.uint8)
    if t.size == 0:  # a view whose crop is empty (the object beyond the image's edge): no outline to shift
        return np.zeros(t.shape, np.float32)
    grown = cv2.dilate(t, _SQUARE).astype(np.float32) + cv2.dilate(t, _CROSS)
    shrunk = cv2.erode(t, _SQUARE).astype(np.float32) + cv2.erode(t, _CROSS)
    return (grown - shrunk) / 4.0


def boundary_bias_grads(sil: Silhouettes, targets: list[NDArray], t_total: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 6) per view, the change of :func:`l2`'s gradient per pixel of outward shift of the
    target's outline (``-sum_p dt_p jac_p / area``, band pixels), for the covariance's prior on a
    shift every mask shares (:mod:`autoalign.engine.uncertainty`)."""
    rates = [outline_shift_rate(t[y0:y0 + h, x0:x0 + w]) for t, (x0, y0, w, h) in zip(targets, sil.crops)]
    flat = np.concatenate([r.ravel() for r in rates]).astype(np.float64) if rates else np.zeros(0)
    b, vb = sil.band, sil.view_of_band
    return -_per_view_vec(flat[b] / np.maximum(t_total, 1.0)[vb], sil.jac, vb, sil.n_views)


LossFn = Callable[[Silhouettes, NDArray[np.float64], NDArray[np.float64]], ViewTerms]
LOSSES: dict[str, LossFn] = {"iou": iou, "dice": dice, "l2": l2, "bce": bce}
