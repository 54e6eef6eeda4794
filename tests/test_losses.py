"""Loss values and their twist gradients, checked by finite differences on the soft masks."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.losses import LOSSES, cauchy_weights, robust_view_weights, targets_in_crops
from autoalign.rasterizers.soft_silhouette import Silhouettes


def _fake_silhouettes(rng: np.random.Generator, n_views: int = 3, w: int = 12, h: int = 9) -> tuple[Silhouettes, list]:
    crops = np.array([[2 + i, 1, w, h] for i in range(n_views)], dtype=np.int64)
    offsets = np.arange(n_views + 1, dtype=np.int64) * w * h
    P = int(offsets[-1])
    hard = rng.random(P) < 0.5
    soft = hard.astype(np.float64)
    band = np.sort(rng.choice(P, size=P // 3, replace=False))
    soft[band] = rng.uniform(0.05, 0.95, size=len(band))
    view_of_band = np.searchsorted(offsets, band, side="right") - 1
    jac = rng.normal(size=(len(band), 6))
    sil = Silhouettes(crops, offsets, soft, hard, band, jac, view_of_band, np.zeros(n_views, np.int64))
    targets = [(rng.random((20, 30)) < 0.4).astype(np.float32) for _ in range(n_views)]
    return sil, targets


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_gradient_matches_finite_differences(name: str) -> None:
    rng = np.random.default_rng(1)
    sil, targets = _fake_silhouettes(rng)
    t_crop = targets_in_crops(targets, sil)
    totals = np.array([t.sum() for t in targets], dtype=np.float64)
    terms = LOSSES[name](sil, t_crop, totals)
    eps = 1e-6
    for k in range(6):
        up, dn = (Silhouettes(**{**sil.__dict__, "soft": sil.soft.copy()}) for _ in range(2))
        up.soft[sil.band] += eps * sil.jac[:, k]
        dn.soft[sil.band] -= eps * sil.jac[:, k]
        fd = (LOSSES[name](up, t_crop, totals).loss - LOSSES[name](dn, t_crop, totals).loss) / (2 * eps)
        np.testing.assert_allclose(terms.grad[:, k], fd, rtol=1e-5, atol=1e-9)
    for H in terms.gn:  # Gauss-Newton matrices are symmetric positive semi-definite
        np.testing.assert_allclose(H, H.T, atol=1e-12)
        assert np.linalg.eigvalsh(H).min() > -1e-9


def test_soft_iou_equals_hard_iou_for_binary_masks() -> None:
    rng = np.random.default_rng(2)
    sil, targets = _fake_silhouettes(rng)
    sil.soft = sil.hard.astype(np.float64)
    t_crop = targets_in_crops(targets, sil)
    totals = np.array([t.sum() for t in targets], dtype=np.float64)
    terms = LOSSES["iou"](sil, t_crop, totals)
    for i, t in enumerate(targets):
        full = sil.image(i, "hard", (t.shape[1], t.shape[0])) > 0.5
        tt = t > 0.5
        assert terms.iou[i] == pytest.approx((full & tt).sum() / (full | tt).sum())
        assert terms.loss[i] == pytest.approx(0.5 * (1 - terms.iou[i]) ** 2)


def test_l2_counts_target_pixels_outside_the_crop() -> None:
    rng = np.random.default_rng(3)
    sil, targets = _fake_silhouettes(rng, n_views=1)
    sil.soft[:] = 0.0
    t_crop = targets_in_crops(targets, sil)
    totals = np.array([t.sum() for t in targets], dtype=np.float64)
    # nothing rendered: the loss is half the target area over the target area, wherever the target is
    assert LOSSES["l2"](sil, t_crop, totals).loss[0] == pytest.approx(0.5)


def test_cauchy_weights_suppress_outlier_views() -> None:
    r = np.array([0.01] * 9 + [0.5])
    w = cauchy_weights(r)
    assert w[:9].min() > 0.79 and w[9] < 0.01
    assert np.all(cauchy_weights(np.zeros(5)) == 1.0)


def test_wrong_masks_do_not_change_how_the_rest_are_weighed() -> None:
    """Views whose mask is implausible get no weight, and do not raise the Cauchy scale either:
    partly failed masks (IoU 0.5) weigh the same against well-fitting ones (IoU 0.9) with no
    wrong mask beside them or with a third of the views wrong."""
    good, partial = [0.9] * 10, [0.5] * 5
    for wrong in (0, 3, 8):
        w = robust_view_weights(np.array(good + partial + [0.02] * wrong))
        assert np.all(w[15:] == 0.0)
        assert w[10] / w[0] == pytest.approx(1.25 / 7.25)  # (1 + (0.1 / 0.2)^2) / (1 + (0.5 / 0.2)^2)
    # the scale's own default: every view's median
    r = np.array([0.1] * 10 + [0.5] * 5 + [0.98] * 8)
    assert cauchy_weights(r)[0] > cauchy_weights(r, inliers=r < 0.9)[0] * 0.99
    assert cauchy_weights(r)[10] > 2.0 * cauchy_weights(r, inliers=r < 0.9)[10]


def test_per_view_sums_are_those_of_each_view_s_pixels_alone():
    """The per-view sums the losses are built of (band and crop pixels laid out view by view, some
    views with none) equal sums over each view's pixels taken one view at a time."""
    from autoalign.losses.silhouette import _per_view_outer, _per_view_sum, _per_view_vec

    rng = np.random.default_rng(3)
    sizes = [0, 40, 1, 0, 300, 7, 0]  # empty views first, between and last
    view = np.repeat(np.arange(len(sizes)), sizes)
    coeff, jac = rng.uniform(0.1, 2.0, len(view)), rng.normal(size=(len(view), 6))
    sums, vecs, outers = (_per_view_sum(coeff, view, len(sizes)), _per_view_vec(coeff, jac, view, len(sizes)),
                          _per_view_outer(coeff, jac, view, len(sizes)))
    for v in range(len(sizes)):
        c, J = coeff[view == v], jac[view == v]
        assert sums[v] == pytest.approx(sum(c.tolist()), rel=1e-12, abs=0)
        np.testing.assert_allclose(vecs[v], sum((ci * Ji for ci, Ji in zip(c, J)), np.zeros(6)), rtol=1e-12)
        np.testing.assert_allclose(outers[v], sum((ci * np.outer(Ji, Ji) for ci, Ji in zip(c, J)), np.zeros((6, 6))),
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(outers[v], outers[v].T)
