"""The multi-view silhouette objective at one resolution level: render, compare, weight."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import transform_points
from autoalign.io.bop import Scene
from autoalign.losses import LOSSES, ViewTerms, robust_view_weights, targets_in_crops
from autoalign.losses.depth import MAX_SAMPLES, DepthNoise, DepthTerms, depth_terms
from autoalign.rasterizers.pyramid import MeshDetail, MeshPyramid
from autoalign.rasterizers.soft_silhouette import Silhouettes

if TYPE_CHECKING:
    from autoalign.engine.seed_region import PriorTerm, SeedRegion

DEPTH_SAMPLES_MIN = 250
"""Below full resolution the depth term samples fewer pixels (in proportion), but at least these."""


@dataclass(frozen=True)
class Level:
    """One stage of the coarse-to-fine schedule.

    Attributes:
        scale: image resolution relative to the input (0.25 = a quarter of the width).
        sigma: edge softness in pixels of that resolution.
        max_iters: iteration budget of the stage.
        max_views: use at most this many views, spread through the scene (``None``: all).
        ftol: Levenberg-Marquardt stops before a step predicted to decrease the objective by
            less than this fraction of it (``None``: ``optim.FTOL / scale``, the loss's own noise
            growing as the resolution drops; see :func:`~autoalign.engine.solver.levenberg_marquardt`).
    """

    scale: float
    sigma: float
    max_iters: int
    max_views: int | None = None
    ftol: float | None = None


@dataclass(frozen=True)
class LevelViews:
    """The views of one resolution level: cameras, area-resampled targets in [0, 1], per-view
    target sums, and the pixels not compared (``None``: all are), all at that resolution; and the
    same views' full-resolution cameras, masks and measured depth (``None``: no depth term)."""

    cameras: list[Camera]
    targets: list[NDArray[np.float32]]
    totals: NDArray[np.float64]
    ignore: list[NDArray[np.bool_]] | None
    full_cameras: list[Camera]
    full_masks: list[NDArray[np.float32]]
    depths: list[NDArray[np.float32]] | None = None


@dataclass
class ViewTermsRecord:
    """Each evidence term per view at one pose: the mask term's loss (area-normalised L2), the depth
    term's (mean robust loss in noise units; ``None`` without depth), the view's robust weight, and
    the depth's share of the view's loss (0-1; ``None`` without depth)."""

    mask_loss: NDArray[np.float64]
    depth_loss: NDArray[np.float64] | None
    weights: NDArray[np.float64]

    @property
    def depth_share(self) -> NDArray[np.float64] | None:
        if self.depth_loss is None:
            return None
        total = self.mask_loss + self.depth_loss
        return np.where(total > 0, self.depth_loss / np.maximum(total, 1e-300), 0.0)


@dataclass
class Evaluation:
    """Objective value and derivatives at one pose. ``value = sum_i w_i loss_i``; ``grad``/``gn``
    alike. ``terms`` are the views' whole terms (mask plus depth), ``depth`` the depth's own part
    (``None`` without depth); ``prior`` a term on the pose alone (:class:`~autoalign.engine.seed_region.SeedRegion`)."""

    value: float
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]
    terms: ViewTerms
    weights: NDArray[np.float64]
    silhouettes: Silhouettes
    depth: DepthTerms | None = None
    prior: PriorTerm | None = None  # the seed region's penalty, included in value, grad and gn

    def record(self) -> ViewTermsRecord:
        """Each term per view (:class:`ViewTermsRecord`)."""
        depth = None if self.depth is None else self.depth.loss
        return ViewTermsRecord(self.terms.loss - (0.0 if depth is None else depth), depth, self.weights)


class SilhouetteObjective:
    """Weighted multi-view silhouette loss of one scene, with resampled targets per scale.

    Args:
        pyramid: the object's mesh and its simplified versions (:class:`~autoalign.rasterizers.pyramid.MeshPyramid`).
        scene: cameras and target masks.
        loss: one of :data:`autoalign.losses.LOSSES`.
        robust: re-weight views with Cauchy weights on ``1 - IoU`` (see :func:`~autoalign.losses.robust_view_weights`).
        detail: the mesh's detail at each level's resolution (:class:`~autoalign.rasterizers.pyramid.MeshDetail`).
        depth: the depth sensor's noise: with it, and the scene's measured depth
            (:attr:`~autoalign.io.bop.Scene.depths`), each view's term adds the depth term
            (:mod:`autoalign.losses.depth`) to the mask term; ``None``: masks only.
    """

    def __init__(self, pyramid: MeshPyramid, scene: Scene, loss: str = "l2", robust: bool = True,
                 detail: MeshDetail = MeshDetail(), depth: DepthNoise | None = None) -> None:
        if loss not in LOSSES:
            raise ValueError(f"unknown loss {loss!r}; choose one of {sorted(LOSSES)}")
        self.pyramid = pyramid
        self.detail = detail
        self.depth = depth
        self.centre_m = pyramid.mesh.centre  # the point twists turn about, model frame (mm)
        self.scene = scene
        self.loss_name = loss
        self.loss_fn = LOSSES[loss]
        self.robust = robust
        self._levels: dict[tuple[float, int | None], LevelViews] = {}
        self.renders = 0
        self.region: SeedRegion | None = None  # while set, poses are held within it (engine.refine)

    def at_scale(self, scale: float, max_views: int | None = None) -> LevelViews:
        """The views at ``scale`` (cached), at most ``max_views`` of them spread through the scene
        (see :meth:`Scene.spread`); a resampled pixel is ignored when most of it was."""
        key = (scale, max_views)
        if key not in self._levels:
            scene = self.scene if max_views is None else self.scene.subset(self.scene.spread(max_views))
            cams = [c.scaled(scale) for c in scene.cameras]

            def resampled(m: NDArray, c: Camera) -> NDArray[np.float32]:
                if scale == 1.0:
                    return np.asarray(m, dtype=np.float32)  # no copy: targets are only read
                return cv2.resize(np.asarray(m, dtype=np.float32), (c.width, c.height), interpolation=cv2.INTER_AREA)

            tg = [resampled(m, c) for m, c in zip(scene.masks, cams)]
            ignore = None if scene.ignore is None else [resampled(g, c) > 0.5 for g, c in zip(scene.ignore, cams)]
            depths = scene.depths if self.depth is not None else None
            self._levels[key] = LevelViews(cams, tg, np.array([float(t.sum()) for t in tg]), ignore, scene.cameras,
                                           scene.masks, depths)
        return self._levels[key]

    def subset(self, idx: list[int] | NDArray[np.int64]) -> "SilhouetteObjective":
        """The same objective on the views at positions ``idx`` (no seed region), with the
        resampled targets of every view at each scale already computed taken from this one."""
        idx = [int(i) for i in idx]
        sub = SilhouetteObjective(self.pyramid, self.scene.subset(idx), self.loss_name, self.robust, self.detail,
                                  self.depth)
        for (scale, max_views), lv in self._levels.items():
            if max_views is None:
                sub._levels[(scale, None)] = LevelViews(
                    [lv.cameras[i] for i in idx], [lv.targets[i] for i in idx], lv.totals[idx],
                    None if lv.ignore is None else [lv.ignore[i] for i in idx], [lv.full_cameras[i] for i in idx],
                    [lv.full_masks[i] for i in idx], None if lv.depths is None else [lv.depths[i] for i in idx])
        return sub

    def use_cameras(self, cameras: list[Camera]) -> None:
        """Render through ``cameras`` (one per view of the scene, e.g. corrected ones) from now on."""
        self.scene = replace(self.scene, cameras=list(cameras))
        self._levels.clear()

    def evaluate(self, T_wm: NDArray[np.float64], level: Level, weights: NDArray[np.float64] | None = None,
                 with_derivatives: bool = True) -> Evaluation:
        """Render at ``level`` and compare. Without ``weights`` they are computed here (robust or 1)."""
        views = self.at_scale(level.scale, level.max_views)
        rasterizer = self.pyramid.at(level.scale, self.detail)
        sil = rasterizer.render(T_wm, views.cameras, level.sigma, with_jacobian=with_derivatives)
        self.renders += 1
        depth = None
        if views.depths is not None:
            depth = depth_terms(rasterizer.caster, rasterizer.mesh, T_wm, views.full_cameras, views.depths,
                                transform_points(T_wm, self.centre_m[None])[0], self.depth,
                                max(DEPTH_SAMPLES_MIN, int(MAX_SAMPLES * level.scale)), views.full_masks)
        ignore = self._ignored(views, depth, level.scale)
        if ignore is not None:
            sil = sil.without(targets_in_crops(ignore, sil) > 0.5)
        terms = self.loss_fn(sil, targets_in_crops(views.targets, sil), views.totals)
        if depth is not None:
            terms = ViewTerms(terms.loss + depth.loss, terms.grad + depth.grad, terms.gn + depth.gn, terms.iou)
        prior = None if self.region is None else self.region.term(T_wm)
        return replace(self.combine(terms, sil, weights, prior), depth=depth)

    @staticmethod
    def _ignored(views: LevelViews, depth: DepthTerms | None, scale: float) -> list[NDArray[np.bool_]] | None:
        """The pixels not compared with the masks: those the scene ignores, and those the measured
        depth shows hidden by an unmodelled occluder (the visible mask is empty there, and the
        silhouette must not be pulled out of them)."""
        if depth is None or not depth.hidden.any():
            return views.ignore
        hidden = [depth.hidden_mask(k, (c.height, c.width), scale) for k, c in enumerate(views.cameras)]
        return hidden if views.ignore is None else [a | b for a, b in zip(views.ignore, hidden)]

    def combine(self, terms: ViewTerms, sil: Silhouettes, weights: NDArray[np.float64] | None = None,
                prior: PriorTerm | None = None) -> Evaluation:
        """Weighted sums of per-view terms, plus ``prior``; without ``weights`` they are computed from the fit."""
        if weights is None:
            weights = self.view_weights(terms)
        value = float(weights @ terms.loss)
        grad = np.einsum("i,ij->j", weights, terms.grad)
        gn = np.einsum("i,ijk->jk", weights, terms.gn)
        if prior is not None:
            value, grad, gn = value + prior.value, grad + prior.grad, gn + prior.gn
        return Evaluation(value, grad, gn, terms, weights, sil, prior=prior)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        """The same render with weights re-computed from its own fit (IRLS step; no new render)."""
        return replace(self.combine(ev.terms, ev.silhouettes, prior=ev.prior), depth=ev.depth) if self.robust else ev

    def view_weights(self, terms: ViewTerms) -> NDArray[np.float64]:
        """Per-view weights for the current fit (:func:`~autoalign.losses.robust_view_weights`; 1 if not robust)."""
        return robust_view_weights(terms.iou) if self.robust else np.ones(len(terms.iou))
