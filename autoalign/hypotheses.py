"""Cheap scoring of many orientation hypotheses at low resolution (hard ray-cast IoU)."""

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


def score_poses(rast: SoftSilhouetteRasterizer, scene: Scene, poses: NDArray[np.float64],
                scale: float = 0.125, max_views: int = 20, trim: float = 0.2,
                batch_rays: int = 4_000_000) -> NDArray[np.float64]:
    """Robust mean hard IoU of each pose against the masks, at ``scale`` of the image size.

    Every pose is ray-cast in the same crop: the projection of the sphere around the object
    that encloses all poses. The worst ``trim`` fraction of views is ignored per pose.
    """
    idx = np.linspace(0, len(scene) - 1, min(max_views, len(scene))).round().astype(int)
    radius = float(np.linalg.norm(rast._hull - rast.mesh.centre, axis=1).max())
    centre_w = poses[0, :3, :3] @ rast.mesh.centre + poses[0, :3, 3]
    spread = float(np.linalg.norm(poses[:, :3, 3] + np.einsum("kij,j->ki", poses[:, :3, :3], rast.mesh.centre)
                                  - centre_w, axis=1).max())
    o_list, d_list, t_list, view_of_ray = [], [], [], []
    t_tot = []
    for k in idx:
        cam = scene.cameras[k].scaled(scale)
        tgt = cv2.resize(scene.masks[k].astype(np.float32), (cam.width, cam.height), interpolation=cv2.INTER_AREA) > 0.5
        Xc = cam.to_camera(centre_w[None])[0]
        if Xc[2] <= radius + spread:
            continue
        f = max(cam.K[0, 0], cam.K[1, 1])
        r_px = f * (radius + spread) / (Xc[2] - radius - spread) + 2
        uc = (cam.K @ Xc)[:2] / Xc[2]
        x0, y0 = int(max(np.floor(uc[0] - r_px), 0)), int(max(np.floor(uc[1] - r_px), 0))
        x1, y1 = int(min(np.ceil(uc[0] + r_px), cam.width)), int(min(np.ceil(uc[1] + r_px), cam.height))
        if x1 <= x0 or y1 <= y0:
            continue
        gx, gy = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
        uv = np.column_stack([gx.ravel(), gy.ravel()])
        d_list.append(cam.ray_directions(uv))
        o_list.append(np.broadcast_to(cam.centre, (len(uv), 3)))
        t_list.append(tgt[y0:y1, x0:x1].ravel())
        t_tot.append(tgt.sum())
        view_of_ray.append(np.full(len(uv), len(t_tot) - 1))
    if not o_list:
        return np.zeros(len(poses))
    O, D = np.concatenate(o_list), np.concatenate(d_list)
    tg, vr = np.concatenate(t_list), np.concatenate(view_of_ray)
    t_tot = np.array(t_tot, dtype=np.float64)
    n_v = len(t_tot)
    scores = np.zeros(len(poses))
    per = max(1, batch_rays // len(O))
    for b0 in range(0, len(poses), per):
        chunk = poses[b0:b0 + per]
        Om, Dm = [], []
        for T in chunk:
            R, t = T[:3, :3], T[:3, 3]
            Om.append((O - t) @ R)  # R^T (o - t)
            Dm.append(D @ R)
        hits = rast.model_ray_hits(np.concatenate(Om), np.concatenate(Dm)).reshape(len(chunk), -1)
        for j, h in enumerate(hits):
            inter = np.bincount(vr, weights=(h & tg), minlength=n_v)
            area = np.bincount(vr, weights=h, minlength=n_v)
            iou = inter / np.maximum(area + t_tot - inter, 1.0)
            keep = np.sort(iou)[int(np.floor(trim * len(iou))):]
            scores[b0 + j] = keep.mean()
    return scores
