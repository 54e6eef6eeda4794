"""Silhouette bundle adjustment: every instance's pose and a small 6-DoF correction of every camera,
solved together (``autoalign refine --models --refine-cameras``).

A camera correction of view ``v`` is a twist ``d_v = (u [mm], om [rad])`` that moves every world
point as that camera sees it by ``X -> X - u - om x (X - p)`` to first order (``p``: the centre of
the instances, the same for all views). For instance ``i`` with centre ``c_i`` that is the object
twist ``M_iv d_v`` with ``M = [[-I, [c_i - p]x], [0, -I]]`` in the renderer's convention (object
twist ``(v, w)`` about ``c_i``), so the view's residuals, Jacobians and Gauss-Newton blocks from
each instance's objective give the joint system over objects and cameras without a new renderer.

The prior ``0.5 PRIOR_WEIGHT sum_v (|u_v|^2 / sigma_mm^2 + |om_v|^2 / sigma_rad^2)`` keeps the
corrections small, and a far stiffer one on their mean (``GAUGE_WEIGHT``) fixes the gauge: moving
every camera and every object together changes no image, so the world frame stays that of the
given cameras on average. Several objects seen together pin a camera down; a view that sees one object alone can
only lean on the prior, so its misfit is shared between its camera and that object.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from autoalign.camera import Camera
from autoalign.instances import InstanceScenes
from autoalign.mesh import Mesh
from autoalign.objective import Evaluation, Level, SilhouetteObjective
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer
from autoalign.se3 import apply_twist, hat3, transform_points

SIGMA_MM = 5.0
"""Prior standard deviation of a camera's position correction (mm) ..."""
SIGMA_DEG = 1.0
"""... and of its orientation correction (degrees)."""
PRIOR_WEIGHT = 0.001
"""The prior's cost of a one-sigma correction, in units of the per-view silhouette loss (a view's
L2 loss is about half its misfit fraction: 0.005 at IoU 0.99)."""
GAUGE_WEIGHT = 1e4
"""The weight, relative to the prior, that holds the corrections' mean at zero: moving every camera
one way and every object with them changes no image, and on the real LM-O scenes (four objects,
half the masks wrong) the prior alone let the whole scene drift by 20-30 mm."""
LEVEL = Level(1.0, 0.5, 40)
MIN_MISFIT_GAIN = 0.25
"""Corrections are trusted only if they lower the median per-view misfit by this fraction: where
the cameras are what is off, they explain most of it (a synthetic scene with cameras 5 mm / 1 deg
off: 0.10 -> 0.015, -85%); on the real LM-O scenes, whose misfit is mostly wrong masks, they
took it from 0.39 to 0.37 (-6%) while moving the labels 4-17 mm further from the dataset's."""


@dataclass
class CameraRefinement:
    """What :func:`refine_cameras` found.

    Attributes:
        poses: world-from-model poses (4x4, mm) per instance, in ``found.instances`` order.
        corrections: per image id, the 4x4 rigid motion ``E`` applied before each camera:
            corrected ``T_cw' = T_cw @ E``.
        cameras: the corrected cameras by image id.
        loss_before / loss_after: the summed silhouette loss (plus prior after).
        view_misfit_before / view_misfit_after: per image id, the mean ``1 - IoU`` over its instances.
        iterations: Levenberg-Marquardt steps tried.
        accepted: whether the corrections lowered the median per-view misfit by ``MIN_MISFIT_GAIN``.
    """

    poses: list[NDArray[np.float64]]
    corrections: dict[int, NDArray[np.float64]]
    cameras: dict[int, Camera]
    loss_before: float
    loss_after: float
    view_misfit_before: dict[int, float]
    view_misfit_after: dict[int, float]
    iterations: int

    @property
    def accepted(self) -> bool:
        before = float(np.median(list(self.view_misfit_before.values())))
        after = float(np.median(list(self.view_misfit_after.values())))
        return after <= (1.0 - MIN_MISFIT_GAIN) * before


def _camera_block(c_i: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    """``M`` with object twist ``= M @ camera twist`` for an object centred at ``c_i`` (see module doc)."""
    M = np.zeros((6, 6))
    M[:3, :3] = -np.eye(3)
    M[:3, 3:] = hat3(c_i - p)
    M[3:, 3:] = -np.eye(3)
    return M


def refine_cameras(found: InstanceScenes, meshes: list[Mesh], poses: list[NDArray[np.float64]],
                   max_iters: int = LEVEL.max_iters, sigma_mm: float = SIGMA_MM, sigma_deg: float = SIGMA_DEG,
                   fine_faces: int | None = 20000) -> CameraRefinement:
    """Refine instance poses and per-view camera corrections together, from ``poses``
    (world from model, mm; e.g. each instance refined alone), at full resolution."""
    objs = [SilhouetteObjective(SoftSilhouetteRasterizer(m if fine_faces is None else m.simplified(fine_faces)), s)
            for m, s in zip(meshes, found.scenes)]
    base = {im: cam for im, cam in zip(found.image_ids, found.cameras)}
    views = sorted({im for s in found.scenes for im in s.image_ids})
    col = {im: k for k, im in enumerate(views)}
    n_obj, n_cam = len(objs), len(views)
    centres_m = [m.centre for m in meshes]
    p = np.mean([transform_points(T, c[None])[0] for T, c in zip(poses, centres_m)], axis=0)
    prior = PRIOR_WEIGHT * np.r_[np.full(3, 1.0 / sigma_mm ** 2), np.full(3, 1.0 / np.radians(sigma_deg) ** 2)]

    def cameras_of(E: dict[int, NDArray[np.float64]]) -> dict[int, Camera]:
        out = {}
        for im in views:
            T_cw = base[im].T_cw @ E[im]
            out[im] = replace(base[im], R_w2c=T_cw[:3, :3], t_w2c=T_cw[:3, 3])
        return out

    def evaluate(Ts: list[NDArray[np.float64]], E: dict[int, NDArray[np.float64]],
                 weights: list[NDArray[np.float64]] | None = None) -> tuple[float, list[Evaluation]]:
        cams = cameras_of(E)
        evs = []
        for k, (o, T) in enumerate(zip(objs, Ts)):
            o.use_cameras([cams[im] for im in o.scene.image_ids])
            evs.append(o.evaluate(T, LEVEL, weights=None if weights is None else weights[k]))
        return float(sum(ev.value for ev in evs)), evs

    gauge = GAUGE_WEIGHT * np.diag(prior)

    def prior_cost(d: NDArray[np.float64]) -> float:
        mean = d.reshape(n_cam, 6).mean(0)
        return 0.5 * float(np.sum(d.reshape(n_cam, 6) ** 2 * prior)) + 0.5 * n_cam * float(mean @ gauge @ mean)

    def misfit(evs: list[Evaluation]) -> dict[int, float]:
        acc: dict[int, list[float]] = {}
        for o, ev in zip(objs, evs):
            for im, iou in zip(o.scene.image_ids, ev.terms.iou):
                acc.setdefault(im, []).append(1.0 - float(iou))
        return {im: float(np.mean(v)) for im, v in acc.items()}

    Ts = [np.asarray(T, dtype=np.float64).copy() for T in poses]
    E = {im: np.eye(4) for im in views}
    d_total = np.zeros(6 * n_cam)  # the corrections as twists, for the prior
    value, evs = evaluate(Ts, E)
    loss_before, misfit_before = value, misfit(evs)
    value += prior_cost(d_total)
    lam, iterations = 1e-3, 0
    n = 6 * (n_obj + n_cam)
    for _ in range(max_iters):
        H = np.zeros((n, n))
        g = np.zeros(n)
        for k, (o, ev) in enumerate(zip(objs, evs)):
            c_w = transform_points(Ts[k], centres_m[k][None])[0]
            M = _camera_block(c_w, p)
            a = slice(6 * k, 6 * k + 6)
            for j, im in enumerate(o.scene.image_ids):
                w = ev.weights[j]
                Hv, gv = w * ev.terms.gn[j], w * ev.terms.grad[j]
                b = slice(6 * (n_obj + col[im]), 6 * (n_obj + col[im]) + 6)
                H[a, a] += Hv
                H[a, b] += Hv @ M
                H[b, a] += M.T @ Hv
                H[b, b] += M.T @ Hv @ M
                g[a] += gv
                g[b] += M.T @ gv
        H[6 * n_obj:, 6 * n_obj:] += np.diag(np.tile(prior, n_cam)) + np.kron(np.ones((n_cam, n_cam)), gauge) / n_cam
        g[6 * n_obj:] += np.tile(prior, n_cam) * d_total + np.tile(gauge @ d_total.reshape(n_cam, 6).mean(0), n_cam)
        D = np.diag(np.maximum(np.diag(H), 1e-12))
        accepted = False
        while lam <= 1e8:
            step = -np.linalg.solve(H + lam * D, g)
            predicted = -(g @ step + 0.5 * step @ H @ step)
            if predicted < 1e-3 * value:
                break
            iterations += 1
            Ts_new = [apply_twist(T, step[6 * k:6 * k + 6], transform_points(T, centres_m[k][None])[0])
                      for k, T in enumerate(Ts)]
            E_new = {im: apply_twist(np.eye(4), -step[6 * (n_obj + col[im]):6 * (n_obj + col[im]) + 6], p) @ E[im]
                     for im in views}
            d_new = d_total + step[6 * n_obj:]
            v_new, evs_new = evaluate(Ts_new, E_new, [ev.weights for ev in evs])
            v_new += prior_cost(d_new)
            if v_new <= value:
                Ts, E, d_total, lam = Ts_new, E_new, d_new, max(lam / 3.0, 1e-7)
                evs = [o.reweighted(ev) for o, ev in zip(objs, evs_new)]  # robust weights from the new fit (IRLS)
                value = float(sum(ev.value for ev in evs)) + prior_cost(d_total)
                accepted = True
                break
            lam *= 4.0
        if not accepted:
            break
    return CameraRefinement(Ts, E, cameras_of(E), loss_before, value, misfit_before, misfit(evs), iterations)
