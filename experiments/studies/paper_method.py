"""The paper's simulated labelling procedure: discrete argmax-IoU moves, one camera per iteration.

ProgressLabeller, eqs. (iterate) and (range): in iteration ``k + 1``, in the frame of one camera
``i``, the pose moves to

    T_{k+1} = argmax_f IoU(I_i, Proj(T_i, f[T_k])),   f[T_k] = exp(xi1 theta1) exp(xi2 theta2) T_k,

with ``xi1 = [-w x v_o; w]`` a rotation about the axis ``w`` through the object centre ``v_o``
and ``xi2 = [v; 0]`` a translation along a direction ``v`` in the plane through ``v_o`` parallel to
the image plane; ``v``, ``theta1`` and ``theta2`` are discretised. The figure puts ``w`` parallel to
the camera's x axis (the text says "rotated about z-axis"): ``rot_axis = "x"`` is the default,
``"z"`` the alternative. The IoU is that of view ``i`` alone (``I^{i}`` in the equation).

Silhouettes come from the same ray caster as autoalign's
(:meth:`RayCaster.posed_hit_sums`, mitsuba on the CPU: each candidate's rays are
moved to its model frame, cast and counted in one kernel), scored against the same target masks. The argmax over ~1700 candidates per iteration is computed in one batched ray-cast
per stage:

1. every candidate's projected-hull bounding box bounds its silhouette, and the largest image
   displacement ``D`` of a hull point bounds how far its outline moves (pixels);
2. *small* moves (``D <= small_px``) are scored exactly at full resolution, casting only the pixels
   within ``D + 1.5`` px of the current pose's projected contour edges and of the edges of faces
   close enough to edge-on to flip (elsewhere the silhouette cannot change, so the current mask
   is reused);
3. *medium* moves (up to ``mid_disp_px``) are pre-screened at a low resolution (the object about
   ``mid_px`` across), *large* ones at a lower one (``prescreen_px`` across); the ``top_k`` best
   of each group are scored exactly at full resolution over their whole bounding box;
4. the move with the highest exact IoU is taken if it beats the current IoU, else the pose stays.

With ``top_k`` at least the number of candidates and ``band=False`` every candidate is scored
exactly (brute force); tests check the fast path against it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import transform_points
from autoalign.io.bop import Scene
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

_NEAR_MM = 1.0
_MAX_RAYS = 2_000_000  # rays per ray-cast call (memory bound)


def _ray_batches(counts: NDArray[np.int64], limit: int = _MAX_RAYS) -> Iterator[tuple[int, int]]:
    """``(start, stop)`` runs of consecutive items whose ray counts sum to at most ``limit``
    (an item larger than ``limit`` gets a run of its own)."""
    start, K = 0, len(counts)
    while start < K:
        stop, total = start + 1, int(counts[start])
        while stop < K and total + counts[stop] <= limit:
            total += int(counts[stop])
            stop += 1
        yield start, stop
        start = stop


@dataclass(frozen=True)
class Discretisation:
    """Discrete move set: rotation angles (degrees, each used with + and -), translation step
    lengths (mm) along ``n_directions`` directions evenly spread in the image-parallel plane.
    Zero rotation and zero translation are always included; candidates are all combinations."""

    angles_deg: tuple[float, ...]
    steps_mm: tuple[float, ...]
    n_directions: int = 8

    @property
    def n_candidates(self) -> int:
        return (1 + 2 * len(self.angles_deg)) * (1 + self.n_directions * len(self.steps_mm))


_GEO2 = tuple(0.25 * 2.0 ** k for k in range(10))  # 0.25 ... 128
DISCRETISATIONS: dict[str, Discretisation] = {
    # default: doubling ladders 0.25..128 degrees and 0.25..128 mm, 8 directions (21 x 81 = 1701 moves)
    "geo2": Discretisation(_GEO2, _GEO2, 8),
    # coarser alternative: x4 ladders 0.25..64, 8 directions (11 x 41 = 451 moves)
    "geo4": Discretisation((0.25, 1.0, 4.0, 16.0, 64.0), (0.25, 1.0, 4.0, 16.0, 64.0), 8),
    # finer alternative: x sqrt(2) ladders 0.25..128, 12 directions (39 x 229 moves) - slow
    "geo1.4": Discretisation(tuple(0.25 * np.sqrt(2.0) ** k for k in range(19)),
                             tuple(0.25 * np.sqrt(2.0) ** k for k in range(19)), 12),
}


@dataclass(frozen=True)
class PaperOptions:
    """Settings of :func:`refine_paper`.

    Attributes:
        rot_axis: ``"x"`` (rotation axis parallel to the camera's x axis, the paper's figure) or
            ``"z"`` (about the optical axis, the paper's text).
        discretisation: a key of :data:`DISCRETISATIONS`.
        camera_order: ``"cycle"`` (view ``k mod n`` in iteration ``k``; the views are in random
            order already), ``"random"`` (uniform each iteration) or ``"best"`` (every view is
            tried and the move with the largest IoU gain in its own view is taken; n times dearer).
        max_iters: iteration budget.
        stall_views: stop (``"stall"``) after this many consecutive iterations without a move, or
            in which the pose never left a ``stall_mm`` / ``stall_deg`` neighbourhood of where it
            was before them (small moves back and forth at a wrong optimum). Default: the number
            of views, i.e. a full cycle (1 for ``best``: no view can improve).
        stall_mm, stall_deg: the neighbourhood of that second test (mm of the model centre, degrees).
        top_k: moves of each pre-screened group re-scored at full resolution.
        prescreen_px: object diameter in pixels at the pre-screen resolution of large moves.
        mid_px: the same for medium moves (outline moves of ``small_px`` to ``mid_disp_px`` px).
        mid_disp_px: the largest outline displacement (px) of a medium move.
        small_px: moves whose outline moves at most this many pixels are scored exactly.
        band: cast only the pixels near the current contour for small moves.
    """

    rot_axis: str = "x"
    discretisation: str = "geo2"
    camera_order: str = "cycle"
    max_iters: int = 150
    stall_views: int | None = None
    stall_mm: float = 1.0
    stall_deg: float = 1.0
    top_k: int = 8
    prescreen_px: float = 24.0
    mid_px: float = 64.0
    mid_disp_px: float = 16.0
    small_px: float = 4.0
    band: bool = True

    def __post_init__(self) -> None:
        if self.rot_axis not in ("x", "z"):
            raise ValueError(f"rot_axis must be 'x' or 'z', not {self.rot_axis!r}")
        if self.discretisation not in DISCRETISATIONS:
            raise ValueError(f"unknown discretisation {self.discretisation!r}; choose one of {sorted(DISCRETISATIONS)}")
        if self.camera_order not in ("cycle", "random", "best"):
            raise ValueError(f"camera_order must be cycle, random or best, not {self.camera_order!r}")


@dataclass
class PaperResult:
    """Outcome of :func:`refine_paper`.

    Attributes:
        T_wm: final world-from-model pose (mm).
        poses: pose after each iteration (``poses[k]`` after iteration ``k + 1``).
        views: view index used in each iteration (-1 for ``best`` iterations without a move).
        moved: whether each iteration changed the pose.
        ious: IoU in the iteration's view after the move.
        iterations: iterations run.
        stopped: ``"success"`` (the ``stop`` callback fired), ``"stall"`` or ``"max_iters"``.
        view_renders: single-view silhouettes evaluated (pre-screen and exact).
        rays: rays cast.
        seconds: wall time.
    """

    T_wm: NDArray[np.float64]
    poses: list[NDArray[np.float64]] = field(default_factory=list)
    views: list[int] = field(default_factory=list)
    moved: list[bool] = field(default_factory=list)
    ious: list[float] = field(default_factory=list)
    iterations: int = 0
    stopped: str = "max_iters"
    view_renders: int = 0
    rays: int = 0
    seconds: float = 0.0


# ----------------------------------------------------------------------------------------------
# Candidate moves
# ----------------------------------------------------------------------------------------------

def candidate_parameters(disc: Discretisation) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """``(theta1 [rad], direction index (-1 = none), theta2 [mm])`` of every move; index 0 is no move."""
    th1 = np.radians(np.concatenate([[0.0], np.ravel([[a, -a] for a in disc.angles_deg])]))
    dirs = np.concatenate([[-1], np.tile(np.arange(disc.n_directions), len(disc.steps_mm))])
    th2 = np.concatenate([[0.0], np.repeat(np.asarray(disc.steps_mm, dtype=np.float64), disc.n_directions)])
    a, b = np.meshgrid(np.arange(len(th1)), np.arange(len(dirs)), indexing="ij")
    return th1[a.ravel()], dirs[b.ravel()], th2[b.ravel()]


def _rodrigues(axis: NDArray[np.float64], angles: NDArray[np.float64]) -> NDArray[np.float64]:
    A = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3)[None] + s * A[None] + (1.0 - c) * (A @ A)[None]


def candidate_poses(T_wm: NDArray[np.float64], cam: Camera, centre_m: NDArray[np.float64], rot_axis: str,
                    theta1: NDArray[np.float64], dirs: NDArray[np.int64], theta2: NDArray[np.float64],
                    n_directions: int) -> NDArray[np.float64]:
    """``exp(xi1 theta1) exp(xi2 theta2) T_wm`` for every move, (K, 4, 4), in ``cam``'s frame.

    ``xi1 = [-w x v_o; w]`` with ``w`` the camera's x (or z) axis in world coordinates and ``v_o``
    the current object centre (mm, world); ``xi2 = [v; 0]`` with
    ``v = cos(2 pi j / n) x_cam + sin(2 pi j / n) y_cam`` for direction index ``j``.
    """
    R_T, t_T = T_wm[:3, :3], T_wm[:3, 3]
    c_w = R_T @ centre_m + t_T
    w = cam.R_w2c[2] if rot_axis == "z" else cam.R_w2c[0]
    alpha = 2.0 * np.pi * np.maximum(dirs, 0) / n_directions
    v = np.cos(alpha)[:, None] * cam.R_w2c[0] + np.sin(alpha)[:, None] * cam.R_w2c[1]
    v[dirs < 0] = 0.0
    R = _rodrigues(w, theta1)
    out = np.zeros((len(theta1), 4, 4))
    out[:, :3, :3] = R @ R_T
    moved = t_T[None] + v * theta2[:, None] - c_w[None]
    out[:, :3, 3] = np.einsum("kij,kj->ki", R, moved) + c_w[None]
    out[:, 3, 3] = 1.0
    return out


def contour_distance(rast: SoftSilhouetteRasterizer, T_wm: NDArray[np.float64], cam: Camera,
                     graze_rad: float) -> NDArray[np.float32] | None:
    """Distance (px) of every pixel of ``cam``'s image to the edges of ``rast``'s mesh whose image
    can bound the silhouette during a move.

    Those are the contour edges at ``T_wm`` (front/back flips and open boundaries) and the edges
    of faces within ``graze_rad`` of edge-on (they may flip while the viewing direction turns by
    up to ``graze_rad``). If every point's image moves by at most ``D`` px, coverage can change
    only within ``D`` px of these edges. None when the object straddles the camera plane.
    """
    mesh = rast.mesh
    V_w = transform_points(T_wm, mesh.vertices)
    Vc = cam.to_camera(V_w)
    if np.any(Vc[:, 2] < _NEAR_MM):
        return None
    uv = Vc @ cam.K.T
    uv = uv[:, :2] / uv[:, 2:3]
    lim = 4.0 * max(cam.width, cam.height)
    pts = np.round(np.clip(uv, -lim, lim) * 16.0).astype(np.int32)  # 4 fractional bits
    img = np.full((cam.height, cam.width), 255, dtype=np.uint8)
    e = np.flatnonzero(rast.outlines.contour_matrix(T_wm, CameraBatch.of([cam]))[:, 0])  # contour generator
    if len(e):
        cv2.polylines(img, list(pts[mesh.edges[e]]), False, 0, thickness=1, lineType=cv2.LINE_8, shift=4)
    n_w = mesh.face_normals @ T_wm[:3, :3].T
    to_cam = cam.centre - V_w[mesh.faces[:, 0]]
    cosang = np.abs(np.einsum("ij,ij->i", n_w, to_cam)) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-9)
    graze = np.flatnonzero(cosang <= np.sin(min(graze_rad, np.pi / 2)))
    if len(graze):
        cv2.polylines(img, list(pts[mesh.faces[graze]]), True, 0, thickness=1, lineType=cv2.LINE_8, shift=4)
    return cv2.distanceTransform(img, cv2.DIST_L2, 5)


# ----------------------------------------------------------------------------------------------
# Scoring many candidate poses in one view
# ----------------------------------------------------------------------------------------------

class CandidateScorer:
    """Hard-mask IoU of many poses in one view at a time, by batched ray casting (see module docstring).

    Args:
        rast: the ray caster (model frame).
        scene: cameras and target masks (> 0.5 = object).
        top_k, prescreen_px, small_px, band: see :class:`PaperOptions`.
        max_hull: hull points used for projected bounds (a subsample; its distance to the full
            hull is added as a margin, so the bounds stay conservative).
    """

    def __init__(self, rast: SoftSilhouetteRasterizer, scene: Scene, top_k: int = 12, prescreen_px: float = 24.0,
                 small_px: float = 4.0, band: bool = True, max_hull: int = 256, mid_px: float = 64.0,
                 mid_disp_px: float = 16.0) -> None:
        self.rast = rast
        self.scene = scene
        self.top_k = int(top_k)
        self.prescreen_px = float(prescreen_px)
        self.mid_px = float(mid_px)
        self.mid_disp_px = float(mid_disp_px)
        self.small_px = float(small_px)
        self.band = bool(band)
        mesh = rast.mesh
        hull = np.asarray(mesh.trimesh.convex_hull.vertices, dtype=np.float64) if len(mesh.vertices) > 4 else mesh.vertices
        if len(hull) > max_hull:
            sub = hull[np.random.default_rng(0).choice(len(hull), max_hull, replace=False)]
            self.hull_eps = float(cKDTree(sub).query(hull)[0].max())
            hull = sub
        else:
            self.hull_eps = 0.0
        self.hull = hull
        self.diameter = float(mesh.diameter)
        self.targets = [np.asarray(m) > 0.5 for m in scene.masks]
        self._views: dict[tuple[int, float], tuple[Camera, NDArray[np.bool_], float, NDArray[np.float32]]] = {}
        self.view_renders = 0
        self.rays = 0

    # -------------------------------------------------------------- geometry
    def project_bounds(self, poses: NDArray[np.float64], cam: Camera) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Per pose: the (x0, y0, w, h) box bounding its silhouette, and the largest outline
        displacement (px) relative to ``poses[0]`` (inf when the object straddles the camera)."""
        Xw = np.einsum("hj,kij->khi", self.hull, poses[:, :3, :3]) + poses[:, None, :3, 3]
        Xc = Xw @ cam.R_w2c.T + cam.t_w2c
        z = Xc[..., 2]
        zmin = z.min(axis=1)
        near = zmin < _NEAR_MM
        zs = np.where(z > _NEAR_MM, z, 1.0)
        u = cam.K[0, 0] * Xc[..., 0] / zs + cam.K[0, 1] * Xc[..., 1] / zs + cam.K[0, 2]
        v = cam.K[1, 1] * Xc[..., 1] / zs + cam.K[1, 2]
        f = max(cam.K[0, 0], cam.K[1, 1])
        margin = 2.0 + self.hull_eps * f / np.maximum(zmin, _NEAR_MM)
        x0 = np.floor(u.min(1) - margin)
        x1 = np.ceil(u.max(1) + margin)
        y0 = np.floor(v.min(1) - margin)
        y1 = np.ceil(v.max(1) + margin)
        x0 = np.where(near, 0, np.clip(x0, 0, cam.width))
        y0 = np.where(near, 0, np.clip(y0, 0, cam.height))
        x1 = np.where(near, cam.width, np.clip(x1, 0, cam.width))
        y1 = np.where(near, cam.height, np.clip(y1, 0, cam.height))
        boxes = np.stack([x0, y0, np.maximum(x1 - x0, 0), np.maximum(y1 - y0, 0)], 1).astype(np.int64)
        disp = np.sqrt(((u - u[:1]) ** 2 + (v - v[:1]) ** 2).max(axis=1)) + 2.0 * (margin - 2.0)
        disp = np.where(near | near[0], np.inf, disp)
        return boxes, disp

    # -------------------------------------------------------------- ray casting
    def _dir_matrix(self, cam: Camera) -> NDArray[np.float64]:
        """``M`` with world ray direction ``M @ (u, v, 1)`` for continuous pixel coordinates."""
        return cam.R_w2c.T @ np.linalg.inv(cam.K)

    def view_at(self, view: int, scale: float) -> tuple[Camera, NDArray[np.bool_], float, NDArray[np.float32]]:
        """Camera, target mask, target area and (H*W, 3) world ray directions of ``view`` at ``scale``.

        Targets are area-resampled and thresholded at 0.5; everything is cached (a few views' worth).
        """
        key = (view, scale)
        if key not in self._views:
            if len(self._views) >= 8:
                self._views.pop(next(iter(self._views)))
            cam = self.scene.cameras[view]
            tgt = self.targets[view]
            if scale != 1.0:
                cam = cam.scaled(scale)
                tgt = cv2.resize(tgt.astype(np.float32), (cam.width, cam.height), interpolation=cv2.INTER_AREA) > 0.5
            M = self._dir_matrix(cam)
            xs = np.arange(cam.width, dtype=np.float64) + 0.5
            ys = np.arange(cam.height, dtype=np.float64) + 0.5
            d = (ys[:, None, None] * M[:, 1] + M[:, 2]) + xs[None, :, None] * M[:, 0]
            self._views[key] = (cam, tgt, float(tgt.sum()), d.reshape(-1, 3).astype(np.float32))
        return self._views[key]

    def box_scores(self, view: int, scale: float, poses: NDArray[np.float64],
                   boxes: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(intersection, area)`` in pixels of each pose's silhouette in ``view`` at ``scale``,
        casting every pixel of its box (boxes in pixels of that scale)."""
        K = len(poses)
        inter, area = np.zeros(K), np.zeros(K)
        if K == 0:
            return inter, area
        cam, target, _, dimg = self.view_at(view, scale)
        weights = np.column_stack([np.ones(len(dimg)), target.ravel()])  # a hit adds to area and, on target, overlap
        W = cam.width
        sizes = boxes[:, 2] * boxes[:, 3]
        for start, stop in _ray_batches(sizes):
            sz = sizes[start:stop]
            bx = boxes[start:stop]
            n = int(sz.sum())
            if n:
                kid = np.repeat(np.arange(stop - start), sz)
                local = np.arange(n) - np.repeat(np.cumsum(sz) - sz, sz)
                w = bx[kid, 2]
                flat = (bx[kid, 1] + local // w) * W + bx[kid, 0] + local % w
                self.rays += n
                sums = self.rast.caster.posed_hit_sums(poses[start:stop], cam.centre[None], dimg, np.zeros(len(dimg), np.int64),
                                                weights, pairs=(kid, flat))
                area[start:stop] += sums[:, 0, 0]
                inter[start:stop] += sums[:, 1, 0]
        self.view_renders += K
        return inter, area

    def current_mask(self, T_wm: NDArray[np.float64], view: int, box: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Full-resolution hard mask of ``view`` at ``T_wm`` (ray cast inside ``box``)."""
        cam = self.view_at(view, 1.0)[0]
        x0, y0, w, h = (int(a) for a in box)
        m = np.zeros((cam.height, cam.width), dtype=bool)
        if w and h:
            gx, gy = np.meshgrid(np.arange(x0, x0 + w) + 0.5, np.arange(y0, y0 + h) + 0.5)  # pixel centres
            uv = np.column_stack([gx.ravel(), gy.ravel()])
            self.rays += len(uv)
            hits = self.rast.caster.pixel_hits(T_wm, CameraBatch.of([cam]), np.zeros(len(uv), np.int64), uv)
            m[y0:y0 + h, x0:x0 + w] = hits.reshape(h, w)
        self.view_renders += 1
        return m

    def band_scores(self, view: int, current: NDArray[np.bool_], dist: NDArray[np.float32],
                    poses: NDArray[np.float64], radii: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(intersection, area)`` of each pose at full resolution, re-casting only the pixels within
        ``radii[k]`` px of the current contour and keeping the current mask elsewhere."""
        cam, target, _, dimg = self.view_at(view, 1.0)
        K = len(poses)
        inter, area = np.zeros(K), np.zeros(K)
        if K == 0:
            return inter, area
        flat = np.flatnonzero(dist.ravel() <= float(radii.max()))
        dv = dist.ravel()[flat]
        order = np.argsort(dv, kind="stable")
        flat, dv = flat[order], dv[order]
        cur, tgt = current.ravel()[flat], target.ravel()[flat]
        cum_m = np.concatenate([[0], np.cumsum(cur)])
        cum_mt = np.concatenate([[0], np.cumsum(cur & tgt)])
        tot_m, tot_mt = float(current.sum()), float((current & target).sum())
        Dw = dimg[flat]
        weights = np.column_stack([np.ones(len(flat)), tgt])
        counts = np.searchsorted(dv, radii, side="right")
        for start, stop in _ray_batches(counts):
            cs = counts[start:stop]
            n = int(cs.sum())
            if n:  # pose k re-casts the counts[k] pixels nearest the contour
                kid = np.repeat(np.arange(stop - start), cs)
                nearest = np.arange(n) - np.repeat(np.cumsum(cs) - cs, cs)
                self.rays += n
                sums = self.rast.caster.posed_hit_sums(poses[start:stop], cam.centre[None], Dw, np.zeros(len(Dw), np.int64),
                                                weights, pairs=(kid, nearest))
                area[start:stop] += sums[:, 0, 0]
                inter[start:stop] += sums[:, 1, 0]
        inter += tot_mt - cum_mt[counts]
        area += tot_m - cum_m[counts]
        self.view_renders += K
        return inter, area

    def _screen_scale(self, view: int, pose: NDArray[np.float64], px: float) -> float:
        """``1 / n`` (integer n) so that the object spans at most about ``px`` pixels."""
        cam = self.scene.cameras[view]
        c_w = pose[:3, :3] @ self.rast.mesh.centre + pose[:3, 3]
        z = float(cam.to_camera(c_w[None])[0, 2])
        diam_px = max(cam.K[0, 0], cam.K[1, 1]) * self.diameter / max(z, _NEAR_MM)
        return 1.0 / max(1, int(np.ceil(diam_px / px)))

    # -------------------------------------------------------------- the argmax
    def score(self, view: int, poses: NDArray[np.float64], turn_rad: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """IoU in view ``view`` of each pose; ``poses[0]`` must be the current pose.

        Exact (full resolution) for the current pose, all small moves and the ``top_k`` best of
        the medium and of the large moves after their pre-screens; NaN for the moves a
        pre-screen ruled out. ``turn_rad``: each pose's rotation angle from ``poses[0]`` (computed
        when omitted); it bounds how far faces turn towards or away from the camera.
        """
        cam, target, t_total, _ = self.view_at(view, 1.0)
        K = len(poses)
        boxes, disp = self.project_bounds(poses, cam)
        ious = np.full(K, np.nan)
        current = self.current_mask(poses[0], view, boxes[0])
        cur_inter = float((current & target).sum())
        cur_area = float(current.sum())
        ious[0] = cur_inter / max(cur_area + t_total - cur_inter, 1.0)
        rest = np.arange(1, K)
        small = rest[disp[rest] <= self.small_px]
        medium = rest[(disp[rest] > self.small_px) & (disp[rest] <= self.mid_disp_px)]
        large = rest[~(disp[rest] <= self.mid_disp_px)]
        exact: list[int] = []
        if len(small):
            if turn_rad is None:
                rel = np.einsum("kji,jl->kil", poses[small, :3, :3], poses[0, :3, :3])
                turn = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
            else:
                turn = np.asarray(turn_rad)[small]
            f = max(cam.K[0, 0], cam.K[1, 1])
            # the viewing direction of a surface point turns by at most the rotation angle plus
            # (image displacement / focal length); 0.5 degree of slack on top
            graze = float(turn.max() + (disp[small].max() + 2.0) / f + np.radians(0.5))
            dist = contour_distance(self.rast, poses[0], cam, graze) if self.band else None
            if dist is None:
                exact.extend(small.tolist())
            else:
                inter, area = self.band_scores(view, current, dist, poses[small], disp[small] + 1.5)
                ious[small] = inter / np.maximum(area + t_total - inter, 1.0)
        for group, px in ((medium, self.mid_px), (large, self.prescreen_px)):
            if len(group) <= self.top_k:
                exact.extend(group.tolist())
                continue
            scale = self._screen_scale(view, poses[0], px)
            if scale == 1.0:
                exact.extend(group.tolist())
                continue
            cam_s, _, tot_s, _ = self.view_at(view, scale)
            boxes_s, _ = self.project_bounds(poses[group], cam_s)
            inter, area = self.box_scores(view, scale, poses[group], boxes_s)
            coarse = inter / np.maximum(area + tot_s - inter, 1.0)
            exact.extend(group[np.argsort(-coarse, kind="stable")[: self.top_k]].tolist())
        if exact:
            idx = np.asarray(exact, dtype=np.int64)
            inter, area = self.box_scores(view, 1.0, poses[idx], boxes[idx])
            ious[idx] = inter / np.maximum(area + t_total - inter, 1.0)
        return ious


# ----------------------------------------------------------------------------------------------
# The iterative procedure
# ----------------------------------------------------------------------------------------------

def _wandering(poses: list[NDArray[np.float64]], T_init: NDArray[np.float64], window: int,
               centre_m: NDArray[np.float64], mm: float, deg: float) -> bool:
    """Whether the last ``window`` poses all stayed within ``mm`` / ``deg`` of the pose before them."""
    if window < 2 or len(poses) < window:
        return False
    anchor = poses[-window - 1] if len(poses) > window else np.asarray(T_init, dtype=np.float64)
    last = np.stack(poses[-window:])
    c0 = anchor[:3, :3] @ centre_m + anchor[:3, 3]
    c = np.einsum("kij,j->ki", last[:, :3, :3], centre_m) + last[:, :3, 3]
    if np.linalg.norm(c - c0, axis=1).max() >= mm:
        return False
    rel = np.einsum("kji,jl->kil", last[:, :3, :3], anchor[:3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(ang.max() < deg)


def refine_paper(rast: SoftSilhouetteRasterizer, scene: Scene, T_init: NDArray[np.float64],
                 options: PaperOptions | None = None, rng: np.random.Generator | None = None,
                 stop: Callable[[NDArray[np.float64]], bool] | None = None,
                 scorer: CandidateScorer | None = None) -> PaperResult:
    """Run the paper's greedy argmax-IoU procedure from ``T_init`` (world-from-model, mm).

    Args:
        rast: ray caster of the object mesh.
        scene: calibrated views with target masks.
        options: see :class:`PaperOptions`.
        rng: drives ``camera_order="random"`` (default: a fixed seed).
        stop: called with the pose after every iteration; True ends the run as ``"success"``
            (the simulation's oracle stop: the paper counts iterations until convergence).
        scorer: a prepared :class:`CandidateScorer` (made from ``options`` when omitted).
    """
    opts = options or PaperOptions()
    rng = rng or np.random.default_rng(0)
    t0 = time.perf_counter()
    disc = DISCRETISATIONS[opts.discretisation]
    th1, dirs, th2 = candidate_parameters(disc)
    turn = np.abs(th1)
    sc = scorer or CandidateScorer(rast, scene, opts.top_k, opts.prescreen_px, opts.small_px, opts.band,
                                   mid_px=opts.mid_px, mid_disp_px=opts.mid_disp_px)
    centre_m = rast.mesh.centre
    n = len(scene)
    stall = opts.stall_views if opts.stall_views is not None else (1 if opts.camera_order == "best" else n)
    T = np.asarray(T_init, dtype=np.float64).copy()
    res = PaperResult(T_wm=T)
    if stop is not None and stop(T):
        res.stopped = "success"
        res.seconds = time.perf_counter() - t0
        return res
    idle = 0
    for it in range(opts.max_iters):
        if opts.camera_order == "best":
            views = list(range(n))
        elif opts.camera_order == "random":
            views = [int(rng.integers(n))]
        else:
            views = [it % n]
        best_gain, best_T, best_view, best_iou = 0.0, None, views[0] if len(views) == 1 else -1, np.nan
        for v in views:
            cands = candidate_poses(T, scene.cameras[v], centre_m, opts.rot_axis, th1, dirs, th2, disc.n_directions)
            ious = sc.score(v, cands, turn)
            k = int(np.nanargmax(ious))
            gain = float(ious[k] - ious[0])
            if len(views) == 1:
                best_iou = float(ious[0])
            if k != 0 and gain > 1e-9 and gain > best_gain:
                best_gain, best_T, best_view, best_iou = gain, cands[k], v, float(ious[k])
        moved = best_T is not None
        if moved:
            T = best_T
            idle = 0
        else:
            idle += 1
        res.poses.append(T.copy())
        res.views.append(best_view)
        res.moved.append(moved)
        res.ious.append(best_iou)
        res.iterations = it + 1
        if stop is not None and stop(T):
            res.stopped = "success"
            break
        if idle >= stall or _wandering(res.poses, T_init, stall, centre_m, opts.stall_mm, opts.stall_deg):
            res.stopped = "stall"
            break
    res.T_wm = T
    res.view_renders = sc.view_renders
    res.rays = sc.rays
    res.seconds = time.perf_counter() - t0
    return res
