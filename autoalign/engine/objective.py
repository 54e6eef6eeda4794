"""The multi-view silhouette objective at one resolution level: render, compare, weight."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import transform_points
from autoalign.io.bop import Scene
from autoalign.losses import ViewTerms, robust_view_weights
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.depth import DepthNoise, DepthTerm
from autoalign.losses.edge import EdgeTerm
from autoalign.losses.mask_term import MaskTerm
from autoalign.losses.region_term import RegionTerm
from autoalign.losses.term import (
    Fragments,
    LevelViews,
    Measured,
    Term,
    TermValues,
    ViewTermsRecord,
    evaluate_terms,
    sum_terms,
)
from autoalign.rasterizers.pyramid import MeshDetail, MeshPyramid
from autoalign.rasterizers.soft_silhouette import Silhouettes


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
            growing as the resolution drops; see :func:`~autoalign.engine.solver.solve_pose`).
    """

    scale: float
    sigma: float
    max_iters: int
    max_views: int | None = None
    ftol: float | None = None


@dataclass
class Evaluation:
    """Objective value and derivatives at one pose. ``value = sum_i w_i loss_i`` plus the terms on
    the pose alone; ``grad``/``gn`` alike. ``terms`` are the views' whole terms (every per-view term
    summed, :func:`~autoalign.losses.term.sum_terms`), ``values`` each term's own
    (:class:`~autoalign.losses.term.TermValues`), ``silhouettes`` the render with the pixels not
    compared off."""

    value: float
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]
    terms: ViewTerms
    weights: NDArray[np.float64]
    silhouettes: Silhouettes
    values: tuple[TermValues, ...] = ()

    @property
    def measured(self) -> tuple[Measured, ...]:
        """What each term that keeps a record measured (:class:`~autoalign.losses.term.Measured`), in order."""
        return tuple(v.measured for v in self.values if v.measured is not None)

    def record(self) -> ViewTermsRecord:
        """Each per-view term's loss per view (:class:`~autoalign.losses.term.ViewTermsRecord`)."""
        return ViewTermsRecord.of(self.values, self.weights)


def view_terms(loss: str, depth: DepthNoise | None, views: ComparedViews, edges: float | None = None,
               region: RegionTerm | None = None) -> tuple[Term, ...]:
    """The evidence terms every one of ``views`` is compared with, in order: the depth term (with a
    sensor's ``depth`` noise and measured depth) before the mask term (``loss``), or in its place the
    ``region`` term (the masks fused with the photos' colours), which do not compare the pixels the
    depth shows hidden, and the edge term (with weight ``edges`` and the photos the region term leaves
    to it). The one list of per-view terms."""
    terms: list[Term] = []
    if depth is not None and views.depths is not None:
        terms.append(DepthTerm(depth))
    terms.append(MaskTerm(loss) if region is None else region)
    if edges is not None and views.photos is not None:
        terms.append(EdgeTerm(edges))
    return tuple(terms)


class SilhouetteObjective:
    """Weighted multi-view evidence of one object in one scene, with resampled targets per scale.

    Args:
        pyramid: the object's mesh and its simplified versions (:class:`~autoalign.rasterizers.pyramid.MeshPyramid`).
        scene: the views as given: cameras, masks, and the measured depth and photos if any.
        loss: one of :data:`autoalign.losses.LOSSES`, the mask term's.
        robust: re-weight views with Cauchy weights on ``1 - IoU`` (see :func:`~autoalign.losses.robust_view_weights`).
        detail: the mesh's detail at each level's resolution (:class:`~autoalign.rasterizers.pyramid.MeshDetail`).
        depth: the depth sensor's noise: with it, and the scene's measured depth
            (:attr:`~autoalign.io.bop.Scene.depths`), each view's term adds the depth term
            (:mod:`autoalign.losses.depth`) to the mask term; ``None``: masks only.
        edges: the edge term's weight: with it, and the scene's photos, each view's term adds the
            photo's edges under the outline (:mod:`autoalign.losses.edge`); ``None``: no edge term.
        region: the region term learned on the scene's views (:mod:`autoalign.losses.region_term`),
            which takes the mask term's place: the views' targets are then its
            (:meth:`~autoalign.losses.region_term.RegionTerm.targets_in`).

    The terms are :func:`view_terms`, plus those on the pose alone given to :meth:`with_pose_term`.
    ``compared`` holds the views as they are compared (:class:`~autoalign.losses.compared_views.ComparedViews`:
    the scene as given and each view's target).
    """

    def __init__(self, pyramid: MeshPyramid, scene: Scene, loss: str = "l2", robust: bool = True,
                 detail: MeshDetail = MeshDetail(), depth: DepthNoise | None = None,
                 edges: float | None = None, region: RegionTerm | None = None) -> None:
        if region is not None and region.loss != loss:
            raise ValueError(f"the region term compares with the {region.loss} loss, the objective with {loss}")
        self.pyramid = pyramid
        self.detail = detail
        self.depth = depth
        self.centre_m = pyramid.mesh.centre  # the point twists turn about, model frame (mm)
        self.compared = ComparedViews.of(scene) if region is None else region.targets_in(scene)
        self.loss_name = loss
        self.robust = robust
        self.edges = edges
        self.region = region
        self.terms: tuple[Term, ...] = view_terms(loss, depth, self.compared, edges, region)
        self._levels: dict[tuple[float, int | None], LevelViews] = {}
        self._renders = [0]  # shared with the objectives made by with_pose_term

    @property
    def renders(self) -> int:
        """Soft renders so far, by this objective and those made from it by :meth:`with_pose_term`."""
        return self._renders[0]

    def with_pose_term(self, term: Term) -> "SilhouetteObjective":
        """The same objective (its views and render count shared) with ``term`` on the pose added."""
        held = copy.copy(self)
        held.terms = self.terms + (term,)
        return held

    def without_depth(self) -> "SilhouetteObjective | None":
        """The same objective (views and render count shared) without its depth term; ``None`` when it
        has none."""
        if not any(isinstance(t, DepthTerm) for t in self.terms):
            return None
        alone = copy.copy(self)
        alone.terms = tuple(t for t in self.terms if not isinstance(t, DepthTerm))
        return alone

    def at_scale(self, scale: float, max_views: int | None = None) -> LevelViews:
        """The views at ``scale`` (cached), at most ``max_views`` of them spread through the scene
        (see :meth:`Scene.spread`); a resampled pixel is ignored when most of it was."""
        key = (scale, max_views)
        if key not in self._levels:
            views = self.compared if max_views is None else self.compared.subset(self.compared.spread(max_views))
            cams = [c.scaled(scale) for c in views.cameras]

            def resampled(m: NDArray, c: Camera) -> NDArray[np.float32]:
                if scale == 1.0:
                    return np.asarray(m, dtype=np.float32)  # no copy: targets are only read
                return cv2.resize(np.asarray(m, dtype=np.float32), (c.width, c.height), interpolation=cv2.INTER_AREA)

            def ignored(g: NDArray, c: Camera) -> NDArray[np.bool_]:
                if scale == 1.0 and g.dtype == np.bool_:
                    return g  # no copy: read only, and at full size as many bytes as the image has pixels
                return resampled(g, c) > 0.5

            tg = [resampled(m, c) for m, c in zip(views.targets, cams)]
            ignore = None if views.ignore is None else [ignored(g, c) for g, c in zip(views.ignore, cams)]
            self._levels[key] = LevelViews(cams, tg, np.array([float(t.sum()) for t in tg]), ignore, views.cameras,
                                           views.targets, views.depths, views.photos)
        return self._levels[key]

    def subset(self, idx: list[int] | NDArray[np.int64]) -> "SilhouetteObjective":
        """The same objective on the views at positions ``idx`` (no terms on the pose), with the
        resampled targets of every view at each scale already computed taken from this one."""
        idx = [int(i) for i in idx]
        sub = SilhouetteObjective(self.pyramid, self.compared.scene.subset(idx), self.loss_name, self.robust,
                                  self.detail, self.depth, self.edges,
                                  None if self.region is None else self.region.subset(idx))
        for (scale, max_views), lv in self._levels.items():
            if max_views is None:
                sub._levels[(scale, None)] = LevelViews(
                    [lv.cameras[i] for i in idx], [lv.targets[i] for i in idx], lv.totals[idx],
                    None if lv.ignore is None else [lv.ignore[i] for i in idx], [lv.full_cameras[i] for i in idx],
                    [lv.full_targets[i] for i in idx], None if lv.depths is None else [lv.depths[i] for i in idx],
                    None if lv.photos is None else [lv.photos[i] for i in idx])
        return sub

    def use_cameras(self, cameras: list[Camera]) -> None:
        """Render through ``cameras`` (one per view of the scene, e.g. corrected ones) from now on."""
        self.compared = self.compared.through(cameras)
        self._levels.clear()

    def fragments(self, T_wm: NDArray[np.float64], level: Level, with_derivatives: bool = True) -> Fragments:
        """One render at ``level`` (:class:`~autoalign.losses.term.Fragments`), the scene's ignored pixels off."""
        views = self.at_scale(level.scale, level.max_views)
        rasterizer = self.pyramid.at(level.scale, self.detail)
        sil = rasterizer.render(T_wm, views.cameras, level.sigma, with_jacobian=with_derivatives)
        self._renders[0] += 1
        frags = Fragments(T_wm, transform_points(T_wm, self.centre_m[None])[0], level.scale, views, sil, rasterizer)
        return frags if views.ignore is None else frags.hiding(views.ignore)

    def evaluate(self, T_wm: NDArray[np.float64], level: Level, weights: NDArray[np.float64] | None = None,
                 with_derivatives: bool = True) -> Evaluation:
        """Render at ``level`` once and evaluate every term; without ``weights`` they are computed
        here (robust or 1)."""
        frags, values = evaluate_terms(self.terms, self.fragments(T_wm, level, with_derivatives))
        return self.combine(values, frags.silhouettes, weights)

    def combine(self, values: tuple[TermValues, ...], sil: Silhouettes,
                weights: NDArray[np.float64] | None = None) -> Evaluation:
        """The terms summed (:func:`~autoalign.losses.term.sum_terms`), the per-view part weighted;
        without ``weights`` they are computed from the fit."""
        terms, pose = sum_terms(values)
        if weights is None:
            weights = self.view_weights(terms)
        value = float(weights @ terms.loss)
        grad = np.einsum("i,ij->j", weights, terms.grad)
        gn = np.einsum("i,ijk->jk", weights, terms.gn)
        if pose is not None:
            value, grad, gn = value + pose.value, grad + pose.grad, gn + pose.gn
        return Evaluation(value, grad, gn, terms, weights, sil, values)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        """The same render with weights re-computed from its own fit (IRLS step; no new render)."""
        return self.combine(ev.values, ev.silhouettes) if self.robust else ev

    def view_weights(self, terms: ViewTerms) -> NDArray[np.float64]:
        """Per-view weights for the current fit (:func:`~autoalign.losses.robust_view_weights`; 1 if not robust)."""
        assert terms.iou is not None
        return robust_view_weights(terms.iou) if self.robust else np.ones(len(terms.iou))
