"""Every instance's pose, and optionally a correction of every camera, solved together on the
occlusion-aware loss of :mod:`autoalign.scene.occlusion` (Levenberg-Marquardt with IRLS view weights).

Unknowns: a twist ``(v [mm], w [rad])`` per instance about its centre, with cameras a twist
per view (:mod:`autoalign.scene.cameras` says how one enters the images, its prior and its
gauge), and with the scale one more: the log of a factor by which the whole scene (cameras and
instances) grows about the world origin, which stays where it is (``autoalign recon`` puts the
table there), for cameras known only up to scale
(:mod:`autoalign.scene.scale`). Growing it by ``1 + s`` moves instance ``i`` away from camera
``v`` by ``s (c_i - C_v)`` as that camera sees it, which is the instance twist ``(s (c_i - C_v), 0)``;
only the objects' fixed size in the images makes it observable. Each view's loss of an instance depends on the twists of that instance, of the instances
in front of it, and of its camera; the Gauss-Newton blocks of all of them are summed into one
system. The covariance of each pose is the cluster-robust sandwich with one cluster per view
(:mod:`autoalign.engine.uncertainty`), marginalised over everything else solved with it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Level
from autoalign.engine.solver import FTOL
from autoalign.engine.uncertainty import Uncertainty, sandwich, uncertainty_of
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import apply_twist, transform_points
from autoalign.io.instances import InstanceScenes
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer
from autoalign.scene.cameras import CameraPrior, camera_block
from autoalign.scene.occlusion import JointEvaluation, OcclusionObjective
from autoalign.scene.scale import grown_pose, scaled_cameras

LEVEL = Level(1.0, 0.5, 20)
"""Full resolution: the instances come to this stage already refined one by one."""

Progress = Callable[[str, int, int], None]


@dataclass
class JointRefinement:
    """What :func:`refine_jointly` found.

    Attributes:
        poses: world-from-model poses (4x4, mm) per instance, in ``found.instances`` order.
        evaluation: the final fit (per instance and view: IoU, weights, loss).
        uncertainties: per instance, from the joint system.
        image_ids: the views, in the order of ``views_of``.
        cameras: the cameras used at the end, by image id (corrected ones if asked for).
        corrections: per image id the 4x4 rigid motion ``E`` with corrected ``T_cw' = T_cw @ E``
            (identity without camera refinement).
        loss_before / loss_after: the weighted loss at the start and end (plus the prior after).
        iterations: steps tried.
        scale: the factor the scene grew by about the world origin (1.0 without ``with_scale``),
            and ``scale_sigma`` its standard deviation (relative, from the same covariance as the
            poses; 0 without it).
    """

    poses: list[NDArray[np.float64]]
    evaluation: JointEvaluation
    uncertainties: list[Uncertainty]
    image_ids: list[int]
    cameras: dict[int, Camera]
    corrections: dict[int, NDArray[np.float64]]
    loss_before: float
    loss_after: float
    iterations: int
    view_misfit_before: dict[int, float]
    view_misfit_after: dict[int, float]
    scale: float = 1.0
    scale_sigma: float = 0.0


def refine_jointly(found: InstanceScenes, meshes: list[Mesh], poses: list[NDArray[np.float64]],
                   with_cameras: bool = False, level: Level = LEVEL, prior: CameraPrior | None = None,
                   fine_faces: int | None = 20000, robust: bool = True, with_scale: bool = False,
                   scale_from: list[bool] | None = None, progress: Progress | None = None) -> JointRefinement:
    """Refine the poses of all instances of ``found`` together from ``poses`` (world from model,
    mm), occlusion-aware, with ``with_cameras`` a correction of every camera and with ``with_scale``
    the scene's scale (``robust``: views weighted by their fit, as in
    :class:`~autoalign.engine.refine.RefineOptions`). ``scale_from`` (per instance, default all): the
    instances whose fit decides the scale; the others move with it but do not pull it."""
    rasts = [SoftSilhouetteRasterizer(m if fine_faces is None else m.simplified(fine_faces)) for m in meshes]
    objective = OcclusionObjective(found, rasts, robust)
    ids = objective.image_ids
    base = dict(zip(ids, objective.cameras))
    prior = prior or CameraPrior()
    n_obj, n_cam = len(meshes), (len(ids) if with_cameras else 0)
    n_scale = 1 if with_scale else 0
    n = 6 * (n_obj + n_cam) + n_scale
    centres_m = [r.mesh.centre for r in rasts]
    p = np.mean([transform_points(T, c[None])[0] for T, c in zip(poses, centres_m)], axis=0)

    def cameras_of(E: dict[int, NDArray[np.float64]], S: float) -> dict[int, Camera]:
        grown = scaled_cameras(base, S) if with_scale else base
        out = {}
        for im in ids:
            T_cw = grown[im].T_cw @ E[im]
            out[im] = replace(base[im], R_w2c=T_cw[:3, :3], t_w2c=T_cw[:3, 3])
        return out

    def system(Ts: list[NDArray[np.float64]], ev: JointEvaluation) -> tuple[NDArray, NDArray, NDArray]:
        """H (n, n), g (n,) and the weighted gradient of each view (V, n)."""
        H, g = np.zeros((n, n)), np.zeros(n)
        per_view = np.zeros((len(ids), n))
        centres_w = [transform_points(T, c[None])[0] for T, c in zip(Ts, centres_m)]
        for i, fits in enumerate(ev.fits):
            for k, (f, w) in enumerate(zip(fits, ev.weights[i])):
                gv = int(objective.views_of[i][k])
                if with_cameras or with_scale:  # object twists = B @ (theirs, the camera's, the scale)
                    m = len(f.instances)
                    B = np.zeros((6 * m, 6 * m + 6 * with_cameras + n_scale))
                    B[:, :6 * m] = np.eye(6 * m)
                    idx = [(6 * f.instances[:, None] + np.arange(6)[None]).ravel()]
                    C_v = objective.cameras[gv].centre
                    for a, inst in enumerate(f.instances):
                        if with_cameras:
                            B[6 * a:6 * a + 6, 6 * m:6 * m + 6] = camera_block(centres_w[inst], p)
                        if with_scale and (scale_from is None or scale_from[inst]):
                            B[6 * a:6 * a + 3, -1] = centres_w[inst] - C_v
                    if with_cameras:
                        idx.append(6 * (n_obj + gv) + np.arange(6))
                    if with_scale:
                        idx.append(np.array([n - 1]))
                    idx = np.concatenate(idx)
                    Hl, gl = B.T @ f.gn @ B, B.T @ f.grad
                else:
                    idx = (6 * f.instances[:, None] + np.arange(6)[None]).ravel()
                    Hl, gl = f.gn, f.grad
                H[np.ix_(idx, idx)] += w * Hl
                g[idx] += w * gl
                per_view[gv, idx] += w * gl
        return H, g, per_view

    Ts = [np.asarray(T, dtype=np.float64).copy() for T in poses]
    E = {im: np.eye(4) for im in ids}
    S = 1.0
    d = np.zeros(6 * n_cam)  # the camera corrections as twists, for the prior
    ev = objective.evaluate(Ts, level)
    loss_before, misfit_before = ev.value, _misfit(objective, ev)
    value = ev.value + (prior.cost(d) if with_cameras else 0.0)
    lam, iterations = 1e-3, 0
    stage = "joint refinement" + (" with cameras" if with_cameras else "") + (" and scale" if with_scale else "")
    H, g, per_view = system(Ts, ev)
    for it in range(level.max_iters):
        if progress is not None:
            progress(stage, it, level.max_iters)
        if with_cameras:
            Hp, gp = prior.system(d)
            H[6 * n_obj:n - n_scale, 6 * n_obj:n - n_scale] += Hp
            g[6 * n_obj:n - n_scale] += gp
        D = np.diag(np.maximum(np.diag(H), 1e-12))
        accepted = False
        while lam <= 1e8:
            step = -np.linalg.solve(H + lam * D, g)
            predicted = -(g @ step + 0.5 * step @ H @ step)
            if predicted < (level.ftol if level.ftol is not None else FTOL) * value:
                break
            iterations += 1
            Ts_new = [apply_twist(T, step[6 * k:6 * k + 6], transform_points(T, centres_m[k][None])[0])
                      for k, T in enumerate(Ts)]
            E_new, d_new, S_new = E, d, S
            if with_cameras:
                E_new = {im: apply_twist(np.eye(4), -step[6 * (n_obj + c):6 * (n_obj + c) + 6], p) @ E[im]
                         for c, im in enumerate(ids)}
                d_new = d + step[6 * n_obj:n - n_scale]
            if with_scale:  # the instances grow with the scene
                grow = float(np.exp(step[-1]))
                S_new = S * grow
                Ts_new = [grown_pose(T, c, grow) for T, c in zip(Ts_new, centres_m)]
            if with_cameras or with_scale:
                objective.use_cameras(cameras_of(E_new, S_new))
            ev_new = objective.evaluate(Ts_new, level, ev.weights)
            v_new = ev_new.value + (prior.cost(d_new) if with_cameras else 0.0)
            if v_new <= value:
                Ts, E, d, S, lam = Ts_new, E_new, d_new, S_new, max(lam / 3.0, 1e-7)
                ev = ev_new.reweighted()
                value = ev.value + (prior.cost(d) if with_cameras else 0.0)
                accepted = True
                break
            if with_cameras or with_scale:
                objective.use_cameras(cameras_of(E, S))
            lam *= 4.0
        H, g, per_view = system(Ts, ev)
        if not accepted:
            break
    if progress is not None:
        progress(stage, level.max_iters, level.max_iters)
    if with_cameras:
        H[6 * n_obj:n - n_scale, 6 * n_obj:n - n_scale] += prior.system(d)[0]
    H_inv = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    cov = sandwich(H_inv, per_view)
    n_band = sum(f.n_band for fits in ev.fits for f in fits)
    naive = H_inv * (2.0 * ev.value / max(n_band - n, 1))
    unc = [uncertainty_of(cov[6 * k:6 * k + 6, 6 * k:6 * k + 6], naive[6 * k:6 * k + 6, 6 * k:6 * k + 6], T[:3, :3])
           for k, T in enumerate(Ts)]
    return JointRefinement(Ts, ev, unc, ids, cameras_of(E, S), E, loss_before, value, iterations,
                           misfit_before, _misfit(objective, ev), S,
                           float(np.sqrt(max(cov[-1, -1], 0.0))) if with_scale else 0.0)


def _misfit(objective: OcclusionObjective, ev: JointEvaluation) -> dict[int, float]:
    """Per image id, the mean ``1 - IoU`` over the instances seen there."""
    acc: dict[int, list[float]] = {}
    for i, fits in enumerate(ev.fits):
        for g, f in zip(objective.views_of[i], fits):
            acc.setdefault(objective.image_ids[int(g)], []).append(1.0 - f.iou)
    return {im: float(np.mean(v)) for im, v in acc.items()}
