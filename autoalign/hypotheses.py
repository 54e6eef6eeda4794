"""Cheap scoring of many orientation hypotheses at low resolution (hard ray-cast IoU).

Every hypothesis is first re-centred so that its silhouettes' centroids match the masks'
centroids (a least-squares 3-D shift from the 2-D centroid offsets of all views), then scored
by the robust mean IoU of its hard silhouettes. A few millimetres of error in the seed's position
would otherwise decide the ranking more than the orientation does.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.bop import Scene
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer
from autoalign.se3 import make_pose


def poses_at(rotations: NDArray[np.float64], centre_w: NDArray[np.float64], centre_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """World-from-model poses (K, 4, 4) with the given rotations that put the model point ``centre_m`` at ``centre_w``."""
    return np.stack([make_pose(R, centre_w - R @ centre_m) for R in rotations])


class _LowResViews:
    """Crop pixels of a subset of views at low resolution, shared by all hypotheses."""

    def __init__(self, scene: Scene, centre_w: NDArray[np.float64],
                 reach: float, scale: float, max_views: int) -> None:
        idx = np.linspace(0, len(scene) - 1, min(max_views, len(scene))).round().astype(int)
        origins, dirs, pix, tgt, view, J, g_cent, t_tot = [], [], [], [], [], [], [], []
        for k in idx:
            cam = scene.cameras[k].scaled(scale)
            mask = cv2.resize(scene.masks[k].astype(np.float32), (cam.width, cam.height),
                              interpolation=cv2.INTER_AREA) > 0.5
            Xc = cam.to_camera(centre_w[None])[0]
            if Xc[2] <= reach or not mask.any():
                continue
            r_px = max(cam.K[0, 0], cam.K[1, 1]) * reach / (Xc[2] - reach) + 2
            uc = (cam.K @ Xc)[:2] / Xc[2]
            x0, y0 = int(max(np.floor(uc[0] - r_px), 0)), int(max(np.floor(uc[1] - r_px), 0))
            x1, y1 = int(min(np.ceil(uc[0] + r_px), cam.width)), int(min(np.ceil(uc[1] + r_px), cam.height))
            if x1 <= x0 or y1 <= y0:
                continue
            gx, gy = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
            uv = np.column_stack([gx.ravel(), gy.ravel()])
            n = len(t_tot)
            origins.append(np.broadcast_to(cam.centre, (len(uv), 3)))
            dirs.append(cam.ray_directions(uv))
            pix.append(uv)
            tgt.append(mask[y0:y1, x0:x1].ravel())
            view.append(np.full(len(uv), n))
            t_tot.append(float(mask.sum()))
            ys, xs = np.nonzero(mask)
            g_cent.append([xs.mean() + 0.5, ys.mean() + 0.5])
            # d(pixel)/d(world shift) at the object centre, (2, 3)
            z = Xc[2]
            P = np.array([[cam.K[0, 0], cam.K[0, 1], cam.K[0, 2] - uc[0]], [0.0, cam.K[1, 1], cam.K[1, 2] - uc[1]]]) / z
            J.append(P @ cam.R_w2c)
        self.n = len(t_tot)
        self.O = np.concatenate(origins) if origins else np.zeros((0, 3))
        self.D = np.concatenate(dirs) if dirs else np.zeros((0, 3))
        self.tgt = np.concatenate(tgt) if tgt else np.zeros(0, bool)
        self.view = np.concatenate(view) if view else np.zeros(0, np.int64)
        self.pix = np.concatenate(pix) if pix else np.zeros((0, 2))
        self.t_tot = np.array(t_tot)
        self.g_cent = np.array(g_cent)
        self.J = np.array(J)

    def cast(self, rast: SoftSilhouetteRasterizer, poses: NDArray[np.float64], batch_rays: int) -> NDArray[np.bool_]:
        """(K, n_rays) hits of every pose."""
        out = np.zeros((len(poses), len(self.O)), dtype=bool)
        per = max(1, batch_rays // max(len(self.O), 1))
        for b0 in range(0, len(poses), per):
            chunk = poses[b0:b0 + per]
            Om = np.concatenate([(self.O - T[:3, 3]) @ T[:3, :3] for T in chunk])  # R^T (o - t)
            Dm = np.concatenate([self.D @ T[:3, :3] for T in chunk])
            out[b0:b0 + len(chunk)] = rast.model_ray_hits(Om, Dm).reshape(len(chunk), -1)
        return out


def score_poses(rast: SoftSilhouetteRasterizer, scene: Scene, poses: NDArray[np.float64],
                scale: float = 0.125, max_views: int = 20, trim: float = 0.2,
                batch_rays: int = 4_000_000, recentre: bool = True) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Robust mean hard IoU of each pose against the masks, at ``scale`` of the image size.

    Returns ``(scores, poses)``: with ``recentre`` each pose's translation is first corrected so
    its silhouette centroids match the masks' (the returned poses carry that correction).
    Every pose is ray-cast in the same crop per view: the projection of a sphere enclosing all
    poses. The worst ``trim`` fraction of views is ignored per pose.
    """
    poses = np.array(poses, dtype=np.float64)
    radius = float(np.linalg.norm(rast._hull - rast.mesh.centre, axis=1).max())
    centres = poses[:, :3, 3] + np.einsum("kij,j->ki", poses[:, :3, :3], rast.mesh.centre)
    centre_w = centres.mean(0)
    reach = radius + float(np.linalg.norm(centres - centre_w, axis=1).max()) + (0.5 * radius if recentre else 0.0)
    views = _LowResViews(scene, centre_w, reach, scale, max_views)
    if views.n == 0:
        return np.zeros(len(poses)), poses
    pix = views.pix
    hits = views.cast(rast, poses, batch_rays)
    if recentre:
        shifts = np.zeros((len(poses), 3))
        for j, h in enumerate(hits):
            cnt = np.bincount(views.view, weights=h, minlength=views.n)
            ok = cnt > 0
            if ok.sum() < 2:
                continue
            cx = np.bincount(views.view, weights=h * pix[:, 0], minlength=views.n)[ok] / cnt[ok]
            cy = np.bincount(views.view, weights=h * pix[:, 1], minlength=views.n)[ok] / cnt[ok]
            r = (views.g_cent[ok] - np.column_stack([cx, cy])).ravel()
            shifts[j] = np.linalg.lstsq(views.J[ok].reshape(-1, 3), r, rcond=None)[0]
        shifts = np.clip(shifts, -0.5 * radius, 0.5 * radius)
        poses[:, :3, 3] += shifts
        hits = views.cast(rast, poses, batch_rays)
    scores = np.zeros(len(poses))
    for j, h in enumerate(hits):
        inter = np.bincount(views.view, weights=h & views.tgt, minlength=views.n)
        area = np.bincount(views.view, weights=h, minlength=views.n)
        iou = inter / np.maximum(area + views.t_tot - inter, 1.0)
        scores[j] = np.sort(iou)[int(np.floor(trim * len(iou))):].mean()
    return scores, poses
