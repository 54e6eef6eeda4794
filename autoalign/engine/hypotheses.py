"""Orientation hypotheses: cheap scoring of many at low resolution (hard ray-cast IoU), a hill
climb over small turns that sharpens the best of them, and the extra candidates a search needs on
near-symmetric objects (half-turn flips, cyclic orbits).

Every hypothesis is first re-centred so that its silhouettes' centroids match the masks'
centroids (a least-squares 3-D shift from the 2-D centroid offsets of all views), then scored
by the robust mean IoU of its hard silhouettes. A few millimetres of error in the seed's position
would otherwise decide the ranking more than the orientation does.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import pixel_centres
from autoalign.geometry.se3 import invert, make_pose, so3_exp, so3_log
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.overlap import iou_from_counts
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer


def _turn_about(R: NDArray[np.float64], point: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 4x4 rigid motion turning by ``R`` about ``point`` (which stays fixed)."""
    return make_pose(R, point - R @ point)


def flips(T_wm: NDArray[np.float64], axes_m: NDArray[np.float64], centre_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """(len(axes), 4, 4): ``T_wm`` turned half a turn about each model axis through ``centre_m``.

    The silhouettes of an elongated or flat object barely change under these turns from far
    away, so a search can settle on one of them; trying all of them costs a few refinements.
    """
    out = []
    for a in axes_m:
        R = 2.0 * np.outer(a, a) - np.eye(3)  # rotation by pi about the unit axis a
        out.append(T_wm @ _turn_about(R, centre_m))
    return np.stack(out)


def turns(T_wm: NDArray[np.float64], axis_m: NDArray[np.float64], centre_m: NDArray[np.float64],
          angles_deg: tuple[float, ...]) -> NDArray[np.float64]:
    """``T_wm`` turned by each of ``angles_deg`` about the model axis ``axis_m`` through the model
    point ``centre_m``, (K, 4, 4)."""
    a = np.asarray(axis_m, dtype=np.float64) / np.linalg.norm(axis_m)
    return np.stack([T_wm @ _turn_about(so3_exp(a * np.radians(t)), centre_m) for t in angles_deg])


def turn_scores(rast: SoftSilhouetteRasterizer, views: ComparedViews, T_wm: NDArray[np.float64],
                axes_m: list[NDArray[np.float64]], centre_m: NDArray[np.float64],
                angles_deg: tuple[float, ...]) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """The robust hard-IoU score (:func:`score_poses` at 1/4 resolution) of ``T_wm`` and of its
    turns about each model axis of ``axes_m`` through ``centre_m`` by ``angles_deg``: its score,
    the turns' scores and the turned poses (K, 4, 4)."""
    cands = np.concatenate([turns(T_wm, a, centre_m, angles_deg) for a in axes_m])
    scores, _ = score_poses(rast, views, np.concatenate([T_wm[None], cands]), scale=0.25, recentre=False)
    return float(scores[0]), scores[1:], cands


def orbit(T_a: NDArray[np.float64], T_b: NDArray[np.float64], max_order: int = 12,
          tol_deg: float = 3.0) -> NDArray[np.float64]:
    """The other poses of the cyclic group that two near-equal fits suggest, (K, 4, 4).

    When ``T_b = T_a D`` and ``D`` turns by about ``360/n`` degrees (``3 <= n <= max_order``,
    within ``tol_deg``), the object looks nearly the same under ``D``: a gear with ``n`` teeth, a
    cross. Then ``T_a E^k`` for ``k = 2 .. n-1`` are the remaining candidates, where ``E`` is ``D``
    made an exact symmetry: a turn by exactly ``360/n`` degrees about ``D``'s axis, with no slide
    along it (the runner-up's own error, a tenth of a degree, would otherwise grow k-fold along
    the orbit). Otherwise none.

    A runner-up shows a subgroup only: a keyed gear of 12 teeth whose runner-up came two teeth
    away looks 6-fold. So the turns of each multiple of ``n`` up to ``max_order`` follow those
    ``n - 2`` (each turn once): 10 more for ``n = 6``.
    """
    D = invert(T_a) @ T_b
    w = so3_log(D[:3, :3])
    theta = float(np.degrees(np.linalg.norm(w)))
    n = int(round(360.0 / theta)) if theta > 1e-6 else 0
    if not 3 <= n <= max_order or abs(n * theta - 360.0) > tol_deg * n:
        return np.zeros((0, 4, 4))
    axis = w / np.linalg.norm(w)
    R = so3_exp(axis * np.radians(360.0 / n))
    p = np.linalg.lstsq(np.eye(3) - R, D[:3, 3], rcond=None)[0]  # a point on the axis
    E = _turn_about(R, p)
    out = [T_a @ np.linalg.matrix_power(E, k) for k in range(2, n)]
    seen = {360 * k / n for k in range(n)}  # degrees, each a correctly rounded k/n: equal turns compare equal
    for order in range(2 * n, max_order + 1, n):
        for k in range(1, order):
            if 360 * k / order not in seen:
                seen.add(360 * k / order)
                out.append(T_a @ _turn_about(so3_exp(axis * np.radians(360.0 * k / order)), p))
    return np.stack(out)


def poses_at(rotations: NDArray[np.float64], centre_w: NDArray[np.float64], centre_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """World-from-model poses (K, 4, 4) with the given rotations that put the model point ``centre_m`` at ``centre_w``."""
    return np.stack([make_pose(R, centre_w - R @ centre_m) for R in rotations])


ANCHOR_REACH = 0.5
"""Re-centring keeps a hypothesis's centre within this fraction of the model's radius of the seed's
centre (the click's or the visual hull's). On the real LM-O scenes, unbounded, the search steps'
re-centrings carried it 115-250 mm away from a seed 11-42 mm off (a mask's centroid is not the
visible silhouette's where parts are missed or hidden by an unmodelled occluder)."""

class _LowResViews:
    """Crop pixels of a subset of views at low resolution, shared by all hypotheses."""

    def __init__(self, views: ComparedViews, centre_w: NDArray[np.float64],
                 reach: float, scale: float, max_views: int) -> None:
        idx = views.spread(max_views)
        centres, dirs, pix, tgt, view, J, g_cent, t_tot, care = [], [], [], [], [], [], [], [], []
        for k in idx:
            cam = views.cameras[k].scaled(scale)
            mask = cv2.resize(views.targets[k].astype(np.float32, copy=False), (cam.width, cam.height),
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
            uv = pixel_centres(*np.meshgrid(np.arange(x0, x1), np.arange(y0, y1)))
            n = len(t_tot)
            centres.append(cam.centre)
            dirs.append(cam.ray_directions(uv))
            pix.append(uv)
            tgt.append(mask[y0:y1, x0:x1].ravel())
            if views.ignore is not None:  # rays there count neither as silhouette nor as overlap
                ign = cv2.resize(views.ignore[k].astype(np.float32), (cam.width, cam.height),
                                 interpolation=cv2.INTER_AREA) > 0.5
                care.append(~ign[y0:y1, x0:x1].ravel())
            else:
                care.append(np.ones(len(uv), bool))
            view.append(np.full(len(uv), n))
            t_tot.append(float(mask.sum()))
            ys, xs = np.nonzero(mask)
            g_cent.append(pixel_centres(xs.mean(), ys.mean())[0])
            # d(pixel)/d(world shift) at the object centre, (2, 3)
            z = Xc[2]
            P = np.array([[cam.K[0, 0], cam.K[0, 1], cam.K[0, 2] - uc[0]], [0.0, cam.K[1, 1], cam.K[1, 2] - uc[1]]]) / z
            J.append(P @ cam.R_w2c)
        self.n = len(t_tot)
        self.centres = np.array(centres).reshape(-1, 3)
        self.D = np.concatenate(dirs) if dirs else np.zeros((0, 3))
        self.tgt = np.concatenate(tgt) if tgt else np.zeros(0, bool)
        self.view = np.concatenate(view) if view else np.zeros(0, np.int64)
        self.pix = np.concatenate(pix) if pix else np.zeros((0, 2))
        self.t_tot = np.array(t_tot)
        self.g_cent = np.array(g_cent)
        self.J = np.array(J)
        # per ray: what a hit adds to its view's area, overlap, sum of x and sum of y
        self._weights = np.column_stack([np.ones(len(self.view)), self.tgt, self.pix])
        if care:
            self._weights *= np.concatenate(care)[:, None]

    def overlap_stats(self, rast: SoftSilhouetteRasterizer, poses: NDArray[np.float64]) -> NDArray[np.float64]:
        """(K, 4, V) per pose and view: silhouette area, overlap with the mask, and the sums of
        the silhouette's pixel x and y (px, this resolution)."""
        return rast.caster.posed_hit_sums(poses, self.centres, self.D, self.view, self._weights)


CENTROID_OUTLIER = 2.5
"""Re-centring leaves out a view whose centroid offset exceeds this many times the median offset
over the views (at least one pixel of the scoring resolution). A mask on another object puts its
centroid far away, and one such view pulled the least-squares shift along: on the real LM-O scenes,
each object's true orientation placed at its visual hull's centre was re-centred 28-109 mm from the
truth, and with these views left out 12-68 mm, closer in 7 of 8 (factors 2 to 3 left the same views out)."""


def _centroid_inliers(offsets: NDArray[np.float64], ok: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(K, V): the views whose centroid offset (K, V, 2, px) is no outlier among the views ``ok`` of its pose."""
    size = np.linalg.norm(offsets, axis=2)
    med = np.array([np.median(s[m]) if m.any() else 0.0 for s, m in zip(size, ok)])
    return ok & (size <= CENTROID_OUTLIER * np.maximum(med, 1.0)[:, None])


def score_poses(rast: SoftSilhouetteRasterizer, views: ComparedViews, poses: NDArray[np.float64],
                scale: float = 0.125, max_views: int = 20, trim: float = 0.2,
                recentre: bool = True, anchor: NDArray[np.float64] | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Robust mean hard IoU of each pose against the targets of ``views``, at ``scale`` of the image size.

    Returns ``(scores, poses)``: with ``recentre`` each pose's translation is first corrected so
    its silhouette centroids match the targets' (the returned poses carry that correction), its
    object centre kept within :data:`ANCHOR_REACH` of the model's radius from ``anchor`` (world,
    mm; the seed's centre) if given.
    Every pose is ray-cast in the same crop per view: the projection of a sphere enclosing all
    poses. The worst ``trim`` fraction of views is ignored per pose.
    """
    poses = np.array(poses, dtype=np.float64)
    radius = float(np.linalg.norm(rast.hull - rast.mesh.centre, axis=1).max())
    centres = poses[:, :3, 3] + np.einsum("kij,j->ki", poses[:, :3, :3], rast.mesh.centre)
    centre_w = centres.mean(0)
    reach = radius + float(np.linalg.norm(centres - centre_w, axis=1).max()) + (0.5 * radius if recentre else 0.0)
    low = _LowResViews(views, centre_w, reach, scale, max_views)
    if low.n == 0:
        return np.zeros(len(poses)), poses
    stats = low.overlap_stats(rast, poses)
    if recentre:
        area = stats[:, 0]
        ok = area > 0
        cent = stats[:, 2:4] / np.maximum(area, 1.0)[:, None]  # (K, 2, V)
        r = (low.g_cent.T[None] - cent).transpose(0, 2, 1)  # (K, V, 2)
        ok &= _centroid_inliers(r, ok)
        r = np.where(ok[:, :, None], r, 0.0)
        # rows of left-out views zeroed
        J = np.where(ok[:, :, None, None], low.J[None], 0.0).reshape(len(poses), -1, 3)
        JtJ = np.einsum("kri,krj->kij", J, J)
        Jtr = np.einsum("kri,kr->ki", J, r.reshape(len(poses), -1))
        solvable = ok.sum(1) >= 2
        shifts = np.zeros((len(poses), 3))
        if solvable.any():
            shifts[solvable] = [np.linalg.lstsq(A, b, rcond=None)[0] for A, b in zip(JtJ[solvable], Jtr[solvable])]
        shifts = np.clip(shifts, -0.5 * radius, 0.5 * radius)
        if anchor is not None:  # each search step re-centres again: unbounded, the steps add up
            away = centres + shifts - anchor
            dist = np.linalg.norm(away, axis=1, keepdims=True)
            shifts = anchor + away * np.minimum(1.0, ANCHOR_REACH * radius / np.maximum(dist, 1e-9)) - centres
        poses[:, :3, 3] += shifts
        stats = low.overlap_stats(rast, poses)
    area, inter = stats[:, 0], stats[:, 1]
    iou = iou_from_counts(inter, area, low.t_tot[None])
    scores = np.sort(iou, axis=1)[:, int(np.floor(trim * low.n)):].mean(1)
    return scores, poses


def best_poses(rast: SoftSilhouetteRasterizer, views: ComparedViews, poses: NDArray[np.float64], n: int,
               scale: float = 0.125, shortlist: int = 48, shortlist_views: int = 12,
               anchor: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """The ``n`` best poses by :func:`score_poses` (re-centred, best first), found coarse to fine.

    All poses are scored at half of ``scale`` in ``shortlist_views`` views (a quarter of the
    rays); only the best ``shortlist`` are scored again at ``scale``. On the procedural models
    the top 8 came out the same as scoring every pose at ``scale``, at a quarter of the time.
    """
    if len(poses) > shortlist:
        scores, _ = score_poses(rast, views, poses, scale=scale / 2, max_views=shortlist_views, anchor=anchor)
        poses = poses[np.argsort(-scores)[:shortlist]]
    scores, poses = score_poses(rast, views, poses, scale=scale, anchor=anchor)
    return poses[np.argsort(-scores)[:n]]


def climb_poses(rast: SoftSilhouetteRasterizer, views: ComparedViews, poses: NDArray[np.float64],
                steps_deg: tuple[float, ...] = (10.0, 5.0), scale: float = 0.125,
                max_views: int = 20, anchor: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Each pose (K, 4, 4) moved uphill on its hard IoU (:func:`score_poses`) by small turns.

    For each step ``d`` in ``steps_deg`` in turn, a pose is replaced by the best of itself and its
    six turns by ``+-d`` degrees about the model's x, y and z axes through the mesh centre, each
    re-centred (without that, a candidate's translation error decides more than its turn does).
    The orientation grid's best poses are typically 15-30 degrees off; the optimiser's iterations
    from the climbed ones are fewer (see the simulation results in docs/results.md).
    """
    poses = np.array(poses, dtype=np.float64)
    c = rast.mesh.centre
    for d in steps_deg:
        turns = []
        for axis in np.eye(3):
            for sign in (1.0, -1.0):
                R = so3_exp(sign * np.radians(d) * axis)
                turns.append(_turn_about(R, c))
        cand = np.concatenate([poses[:, None], poses[:, None] @ np.stack(turns)[None]], axis=1)  # (K, 7, 4, 4)
        scores, cand = score_poses(rast, views, cand.reshape(-1, 4, 4), scale=scale, max_views=max_views,
                                   anchor=anchor)
        cand = cand.reshape(len(poses), -1, 4, 4)
        poses = cand[np.arange(len(poses)), np.argmax(scores.reshape(len(poses), -1), axis=1)]
    return poses
