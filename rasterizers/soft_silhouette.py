"""Soft silhouettes of a mesh in many views at once, with derivatives w.r.t. a 6-D pose twist.

The pipeline, per call, for all views together:

1. **Crop** each view to the projected bounding region of the object plus a margin.
2. **Hard mask** by ray casting (mitsuba, LLVM backend) through every crop pixel centre. The
   scene holds the mesh in its model frame once; rays are moved into the model frame instead of
   re-building the BVH for each pose.
3. **Contour edges**: mesh edges whose two faces point to opposite sides of the camera, plus open
   boundary edges. They are split into sub-pixel segments, and each segment is kept only if a pair
   of rays just either side of it disagree (one hits, one misses): that is the visible outline.
4. **Band**: the pixels within ``2 sigma + 1.5`` px of an outline segment (a distance transform
   with labels gives each pixel its nearest segment). Only these pixels can have a soft value
   strictly between 0 and 1, so the cost follows the silhouette's length, not pixels x faces.
5. **Soft value** of a band pixel: ``smoothstep(sign * dist / (2 sigma))`` where ``dist`` is the
   distance from the pixel centre to the nearest outline edge and ``sign`` is +1 inside the hard
   mask. Outside the band the soft value equals the hard mask exactly. Its derivatives w.r.t. the
   twist are taken by drjit forward-mode AD through the projection of the edge end points.

Twist convention: ``xi = (v [mm], w [rad])`` moves every world point ``X`` of the object to
``X + v + w x (X - c)`` to first order, ``c`` being the object centre in the world frame — the
paper's left-multiplied exponential ``exp(hat(xi')) T`` with ``xi' = (v - w x c, w)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.backend import drjit, jit_array, mitsuba
from autoalign.camera import Camera
from autoalign.mesh import Mesh
from autoalign.se3 import invert, transform_points

_NEAR_MM = 1.0  # points closer than this to a camera plane are not projected
# A band pixel's nearest outline segment is chosen among those nearest to it and to its 4 neighbours.
_CANDIDATE_OFFSETS = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))


@dataclass
class Silhouettes:
    """Soft silhouettes of all views, stored as one flat array of crop pixels.

    Attributes:
        crops: (N, 4) int ``x0, y0, w, h`` of each view's crop in its (scaled) image, pixels.
        offsets: (N + 1,) start of each view's pixels in the flat arrays (row-major in its crop).
        soft: (P,) soft mask values in [0, 1].
        hard: (P,) ray-cast hard mask at pixel centres.
        band: (B,) flat indices of the pixels whose soft value depends on the pose.
        jac: (B, 6) derivatives of ``soft[band]`` w.r.t. the twist ``(v [mm], w [rad])``.
        view_of_band: (B,) view index of each band pixel.
        n_outline: (N,) outline segments found per view (diagnostics).
    """

    crops: NDArray[np.int64]
    offsets: NDArray[np.int64]
    soft: NDArray[np.float64]
    hard: NDArray[np.bool_]
    band: NDArray[np.int64]
    jac: NDArray[np.float64]
    view_of_band: NDArray[np.int64]
    n_outline: NDArray[np.int64]

    @property
    def n_views(self) -> int:
        return len(self.crops)

    def without(self, ignored: NDArray[np.bool_]) -> "Silhouettes":
        """These silhouettes with the flat pixels ``ignored`` (P,) set to 0 and fixed (out of the band):
        where a pixel is not compared with its target, it must not weigh in the loss either way."""
        if not ignored.any():
            return self
        keep = ~ignored[self.band]
        soft, hard = self.soft.copy(), self.hard.copy()
        soft[ignored] = 0.0
        hard[ignored] = False
        return replace(self, soft=soft, hard=hard, band=self.band[keep], jac=self.jac[keep],
                       view_of_band=self.view_of_band[keep])

    def view_of_pixel(self) -> NDArray[np.int64]:
        """(P,) view index of every flat pixel."""
        return np.repeat(np.arange(self.n_views), np.diff(self.offsets))

    def image(self, i: int, which: str = "soft", size: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """View ``i`` as a full (H, W) image (``size = (W, H)``) or, without ``size``, as its crop."""
        x0, y0, w, h = self.crops[i]
        arr = getattr(self, which)[self.offsets[i]:self.offsets[i + 1]].reshape(h, w).astype(np.float64)
        if size is None:
            return arr
        full = np.zeros((size[1], size[0]))
        full[y0:y0 + h, x0:x0 + w] = arr
        return full


@dataclass
class CameraBatch:
    """The calibration of N views stacked into arrays, for vectorised projection and ray casting."""

    K: NDArray[np.float64]
    K_inv: NDArray[np.float64]
    R_w2c: NDArray[np.float64]
    t_w2c: NDArray[np.float64]
    R_c2w: NDArray[np.float64]
    centres: NDArray[np.float64]
    sizes: NDArray[np.int64]  # (N, 2) image width, height

    @staticmethod
    def of(cameras: list[Camera]) -> "CameraBatch":
        K = np.stack([c.K for c in cameras])
        R = np.stack([c.R_w2c for c in cameras])
        t = np.stack([c.t_w2c for c in cameras])
        sizes = np.array([[c.width, c.height] for c in cameras], dtype=np.int64)
        return CameraBatch(K, np.linalg.inv(K), R, t, R.transpose(0, 2, 1), -np.einsum("nji,nj->ni", R, t), sizes)


def per_view_matvec(M: NDArray[np.float64], view: NDArray[np.int64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``M[view[k]] @ x[k]`` for every row ``k`` of ``x`` (n, 3), one matrix product per view.

    Fast when rows come grouped by view (they are sorted first otherwise).
    """
    out = np.empty((len(x), M.shape[1]))
    if len(x) == 0:
        return out
    order = None if np.all(view[1:] >= view[:-1]) else np.argsort(view, kind="stable")
    v = view if order is None else view[order]
    xs = x if order is None else x[order]
    bounds = np.searchsorted(v, np.arange(len(M) + 1))
    res = np.empty_like(out)
    for i in np.flatnonzero(np.diff(bounds)):
        res[bounds[i]:bounds[i + 1]] = xs[bounds[i]:bounds[i + 1]] @ M[i].T
    if order is None:
        return res
    out[order] = res
    return out


def smoothstep_edge(z: NDArray[np.float64] | float) -> NDArray[np.float64]:
    """The edge profile: 0 for ``z <= -1``, 1 for ``z >= 1``, C1 cubic in between (numpy)."""
    u = np.clip((np.asarray(z, dtype=np.float64) + 1.0) / 2.0, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


class SoftSilhouetteRasterizer:
    """Renders soft silhouettes of one mesh in many calibrated views (see module docstring).

    Args:
        mesh: the object, model frame, mm.
        segment_px: length of the outline segments the contour edges are split into, pixels.
    """

    def __init__(self, mesh: Mesh, segment_px: float = 0.75) -> None:
        self.mesh = mesh
        self.segment_px = float(segment_px)
        mi = mitsuba()
        self._mi = mi
        self._dr = drjit()
        m = mi.Mesh(mesh.name, vertex_count=len(mesh.vertices), face_count=len(mesh.faces),
                    has_vertex_normals=False, has_vertex_texcoords=False)
        params = mi.traverse(m)
        params["vertex_positions"] = jit_array(mi.Float, mesh.vertices.ravel(), np.float32)
        params["faces"] = jit_array(mi.UInt32, mesh.faces.ravel(), np.uint32)
        params.update()
        self._scene = mi.load_dict({"type": "scene", "object": m})
        hull = mesh.trimesh.convex_hull.vertices if len(mesh.vertices) > 4 else mesh.vertices
        self._hull = np.asarray(hull, dtype=np.float64)
        # Per-face constants for the facing test n.(c - v0) > 0  <=>  n.c > n.v0
        self._n = mesh.face_normals
        self._nv0 = np.einsum("ij,ij->i", mesh.face_normals, mesh.vertices[mesh.faces[:, 0]])
        ef = mesh.edge_faces
        self._interior = ef[:, 1] >= 0
        self._ef0, self._ef1 = ef[:, 0], np.where(ef[:, 1] >= 0, ef[:, 1], ef[:, 0])

    # ------------------------------------------------------------------ ray casting
    def ray_hits(self, T_wm: NDArray[np.float64], origins_w: NDArray[np.float64],
                 dirs_w: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether world-frame rays hit the object posed at ``T_wm`` (any hit, no shading)."""
        if len(origins_w) == 0:
            return np.zeros(0, dtype=bool)
        T_mw = invert(T_wm)
        return self.model_ray_hits(origins_w @ T_mw[:3, :3].T + T_mw[:3, 3], dirs_w @ T_mw[:3, :3].T)

    def model_ray_hits(self, origins_m: NDArray[np.float64], dirs_m: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether model-frame rays (N, 3) hit the mesh; one vectorised mitsuba call."""
        if len(origins_m) == 0:
            return np.zeros(0, dtype=bool)
        mi = self._mi
        o = [jit_array(mi.Float, origins_m[:, i], np.float32) for i in range(3)]
        d = [jit_array(mi.Float, dirs_m[:, i], np.float32) for i in range(3)]
        return np.array(self._scene.ray_test(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d))), dtype=bool)

    def posed_hit_sums(self, poses: NDArray[np.float64], centres_w: NDArray[np.float64], dirs_w: NDArray[np.float64],
                       ray_view: NDArray[np.int64], weights: NDArray[np.float64],
                       pairs: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None) -> NDArray[np.float64]:
        """Weighted hit counts of world rays cast at many poses of the mesh, per pose and view, in one drjit kernel.

        Args:
            poses: (K, 4, 4) world-from-model poses of the mesh.
            centres_w: (V, 3) camera centres (the rays' origins), world frame, mm.
            dirs_w: (R, 3) ray directions (any length), world frame.
            ray_view: (R,) the view (row of ``centres_w``) each ray starts from.
            weights: (R, C) per-ray weights.
            pairs: ``(pose_index, ray_index)``, (N,) each: cast just these rays at these poses
                (``None``: every ray at every pose).

        Returns:
            (K, C, V): ``sum of weights[r, c]`` over the rays ``r`` of view ``v`` cast at ``poses[k]``
            that hit the mesh. The model-frame rays are formed, cast and reduced inside the kernel,
            never as arrays (sums in double precision: exact for counts and pixel coordinates).
        """
        dr, mi = self._dr, self._mi
        K, V, R, C = len(poses), len(centres_w), len(dirs_w), weights.shape[1]
        if K == 0 or R == 0 or (pairs is not None and len(pairs[0]) == 0):
            return np.zeros((K, C, V))
        Rt = poses[:, :3, :3].transpose(0, 2, 1)  # model from world
        o_m = np.einsum("kij,kvj->kvi", Rt, centres_w[None] - poses[:, None, :3, 3]).reshape(K * V, 3)
        UInt, Float = mi.UInt32, mi.Float
        if pairs is None:
            flat = dr.arange(UInt, K * R)  # k * R + r: ray r cast at pose k
            k = flat // dr.opaque(UInt, R)  # opaque sizes: one compiled kernel for all of them
            r = flat - k * dr.opaque(UInt, R)
        else:
            k, r = jit_array(UInt, pairs[0], np.uint32), jit_array(UInt, pairs[1], np.uint32)
        kv = k * dr.opaque(UInt, V) + dr.gather(UInt, jit_array(UInt, ray_view, np.uint32), r)
        o = [dr.gather(Float, jit_array(Float, o_m[:, i], np.float32), kv) for i in range(3)]
        rot = [dr.gather(Float, jit_array(Float, Rt[:, i, j], np.float32), k) for i in range(3) for j in range(3)]
        d = [dr.gather(Float, jit_array(Float, dirs_w[:, j], np.float32), r) for j in range(3)]
        d_m = [rot[3 * i] * d[0] + rot[3 * i + 1] * d[1] + rot[3 * i + 2] * d[2] for i in range(3)]
        hit = self._scene.ray_test(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d_m)))
        sums = dr.zeros(mi.Float64, K * V * C)
        for c in range(C):
            w = dr.gather(mi.Float64, jit_array(mi.Float64, weights[:, c], np.float64), r)
            dr.scatter_reduce(dr.ReduceOp.Add, sums, w, kv * dr.opaque(UInt, C) + c, active=hit)
        return np.array(sums, dtype=np.float64).reshape(K, V, C).transpose(0, 2, 1)

    def hits_at(self, T_wm: NDArray[np.float64], cams: "CameraBatch", view: NDArray[np.int64],
                uv: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Hard hits of the rays through continuous pixel coordinates ``uv`` (N, 2) of views ``view`` (N,)."""
        if len(view) == 0:
            return np.zeros(0, dtype=bool)
        return np.array(self._scene.ray_test(self._pixel_rays(T_wm, cams, view, uv)), dtype=bool)

    def depths_at(self, T_wm: NDArray[np.float64], cams: "CameraBatch", view: NDArray[np.int64],
                  uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (mm) from the camera centre to the first surface along the rays through ``uv``
        (N, 2) of views ``view`` (N,); ``inf`` where the ray misses the object."""
        if len(view) == 0:
            return np.zeros(0)
        t = np.array(self._scene.ray_intersect_preliminary(self._pixel_rays(T_wm, cams, view, uv)).t, dtype=np.float64)
        t[~np.isfinite(t)] = np.inf
        return t

    def _pixel_rays(self, T_wm: NDArray[np.float64], cams: "CameraBatch", view: NDArray[np.int64],
                    uv: NDArray[np.float64]) -> object:
        """Model-frame unit rays through ``uv`` of views ``view``, formed inside the kernel (double
        precision, then rounded to the caster's single precision) from per-view tables, never as arrays."""
        dr, mi = self._dr, self._mi
        F64 = mi.Float64
        T_mw = invert(T_wm)
        M = np.einsum("ij,njk,nkl->nil", T_mw[:3, :3], cams.R_c2w, cams.K_inv).reshape(-1, 9)  # pixel -> model dir
        C_m = cams.centres @ T_mw[:3, :3].T + T_mw[:3, 3]  # (V, 3) camera centres, model frame
        v = jit_array(mi.UInt32, view, np.uint32)
        u, w = jit_array(F64, uv[:, 0], np.float64), jit_array(F64, uv[:, 1], np.float64)
        m = [dr.gather(F64, jit_array(F64, M[:, j], np.float64), v) for j in range(9)]
        d = [m[3 * i] * u + m[3 * i + 1] * w + m[3 * i + 2] for i in range(3)]
        inv_norm = dr.rsqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        o = [dr.gather(mi.Float, jit_array(mi.Float, C_m[:, i], np.float32), v) for i in range(3)]
        return mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*(mi.Float(x * inv_norm) for x in d)))

    def pixel_hits(self, T_wm: NDArray[np.float64], cameras: list[Camera],
                   uv: list[NDArray[np.float64]]) -> list[NDArray[np.bool_]]:
        """Hard hits for continuous pixel coordinates ``uv[i]`` (N_i, 2) of each camera."""
        counts = [len(x) for x in uv]
        view = np.repeat(np.arange(len(cameras)), counts)
        alluv = np.concatenate(uv) if sum(counts) else np.zeros((0, 2))
        hits = self.hits_at(T_wm, CameraBatch.of(cameras), view, alluv)
        return np.split(hits, np.cumsum(counts)[:-1])

    def hard_masks(self, T_wm: NDArray[np.float64], cameras: list[Camera]) -> list[NDArray[np.bool_]]:
        """Full-image hard masks (H, W) by ray casting at pixel centres."""
        crops = self.crops(T_wm, cameras, margin=2)
        uv = [_crop_pixel_centres(c) for c in crops]
        hits = self.pixel_hits(T_wm, cameras, uv)
        out = []
        for cam, (x0, y0, w, h), hv in zip(cameras, crops, hits):
            m = np.zeros((cam.height, cam.width), dtype=bool)
            m[y0:y0 + h, x0:x0 + w] = hv.reshape(h, w)
            out.append(m)
        return out

    # ------------------------------------------------------------------ geometry helpers
    def crops(self, T_wm: NDArray[np.float64], cameras: list[Camera], margin: int) -> NDArray[np.int64]:
        """(N, 4) ``x0, y0, w, h`` covering the projected convex hull plus ``margin`` px, clipped.

        A view whose camera plane cuts the object gets the whole image.
        """
        return self._crops(T_wm, CameraBatch.of(cameras), margin)

    def _crops(self, T_wm: NDArray[np.float64], cams: CameraBatch, margin: int) -> NDArray[np.int64]:
        Xw = transform_points(T_wm, self._hull)
        Xc = np.einsum("nij,hj->nhi", cams.R_w2c, Xw) + cams.t_w2c[:, None, :]  # (N, H, 3)
        behind = np.any(Xc[..., 2] < _NEAR_MM, axis=1)
        uvw = np.einsum("nij,nhj->nhi", cams.K, Xc)
        uv = uvw[..., :2] / np.where(np.abs(uvw[..., 2:3]) > 1e-9, uvw[..., 2:3], 1e-9)
        size = cams.sizes
        lo = np.where(behind[:, None], 0, np.floor(uv.min(1)).astype(np.int64) - margin)
        hi = np.where(behind[:, None], size, np.ceil(uv.max(1)).astype(np.int64) + margin)
        lo = np.clip(lo, 0, size)
        hi = np.clip(hi, 0, size)
        return np.concatenate([lo, np.maximum(hi - lo, 0)], axis=1)

    def contour_edges(self, T_wm: NDArray[np.float64], cameras: list[Camera]) -> list[NDArray[np.int64]]:
        """Per view, indices of mesh edges on the contour generator (front/back flip or open boundary)."""
        flip = self._contour_matrix(T_wm, CameraBatch.of(cameras))
        return [np.flatnonzero(flip[:, i]) for i in range(len(cameras))]

    def _contour_matrix(self, T_wm: NDArray[np.float64], cams: "CameraBatch") -> NDArray[np.bool_]:
        """(E, N) whether edge e is a contour-generator edge in view n."""
        T_mw = invert(T_wm)
        C_m = cams.centres @ T_mw[:3, :3].T + T_mw[:3, 3]  # (N, 3) camera centres, model frame
        facing = (self._n @ C_m.T) > self._nv0[:, None]  # (F, N)
        flip = facing[self._ef0] != facing[self._ef1]  # (E, N)
        flip |= ~self._interior[:, None]
        return flip

    # ------------------------------------------------------------------ rendering
    def render(self, T_wm: NDArray[np.float64], cameras: list[Camera], sigma: float = 1.0,
               with_jacobian: bool = True) -> Silhouettes:
        """Soft silhouettes (and twist derivatives) of the object at pose ``T_wm`` in all ``cameras``.

        Args:
            T_wm: world-from-model pose, mm.
            cameras: the views (already scaled to the working resolution).
            sigma: edge softness in pixels of these cameras; the profile spans ``+-2 sigma``.
            with_jacobian: also compute ``jac`` (6 forward AD passes over the band pixels).
        """
        sigma = float(sigma)
        half = 2.0 * sigma
        band_r = half + 1.5
        margin = int(np.ceil(band_r)) + 2
        cams = CameraBatch.of(cameras)
        crops = self._crops(T_wm, cams, margin)
        sizes = crops[:, 2] * crops[:, 3]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        seg = self._outline_segments(T_wm, cams, crops)
        n_out = np.bincount(seg["view"], minlength=len(cameras)).astype(np.int64)
        band, bseg, region, samples = self._band_pixels(seg, crops, offsets, band_r)
        hard = self._hard_from_regions(T_wm, cams, crops, offsets, band, region, samples)
        soft = hard.astype(np.float64)
        view_of_band = np.searchsorted(offsets, band, side="right") - 1
        if len(band) == 0:
            return Silhouettes(crops, offsets, soft, hard, band, np.zeros((0, 6)), view_of_band, n_out)
        local = band - offsets[view_of_band]
        w_b = crops[view_of_band, 2]
        px = crops[view_of_band, 0] + local % w_b + 0.5
        py = crops[view_of_band, 1] + local // w_b + 0.5
        sign = np.where(hard[band], 1.0, -1.0)
        ends = self.mesh.edges[seg["edge"][bseg]]
        A_w = transform_points(T_wm, self.mesh.vertices[ends[:, 0]])
        B_w = transform_points(T_wm, self.mesh.vertices[ends[:, 1]])
        centre_w = transform_points(T_wm, self.mesh.centre[None])[0]
        value, jac = self._band_values(cams, view_of_band, px, py, sign, A_w, B_w,
                                       seg["t0"][bseg], seg["t1"][bseg], centre_w, half, with_jacobian)
        soft[band] = value
        return Silhouettes(crops, offsets, soft, hard, band, jac, view_of_band, n_out)

    def _hits_at_flat(self, T_wm: NDArray[np.float64], cams: CameraBatch, crops: NDArray[np.int64],
                      offsets: NDArray[np.int64], flat: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Ray-cast hard hits at the centres of the given flat crop pixels (any views, any order)."""
        view = np.searchsorted(offsets, flat, side="right") - 1
        local = flat - offsets[view]
        w = crops[view, 2]
        uv = np.column_stack([crops[view, 0] + local % w + 0.5, crops[view, 1] + local // w + 0.5])
        return self.hits_at(T_wm, cams, view, uv)

    def _hard_from_regions(self, T_wm: NDArray[np.float64], cams: CameraBatch, crops: NDArray[np.int64],
                           offsets: NDArray[np.int64], band: NDArray[np.int64], region: NDArray[np.int64],
                           samples: NDArray[np.int64]) -> NDArray[np.bool_]:
        """The hard mask of all crop pixels from rays at band pixels and a few per off-band region.

        Off the band no outline passes, so each connected off-band region is wholly inside or
        wholly outside: three rays decide it. A region whose rays disagree (an outline the
        segment test missed) is ray-cast pixel by pixel.
        """
        hard = np.zeros(int(offsets[-1]), dtype=bool)
        hits = self._hits_at_flat(T_wm, cams, crops, offsets, np.concatenate([band, samples.ravel()]))
        hard[band] = hits[:len(band)]
        if samples.size:
            sv = hits[len(band):].reshape(samples.shape)
            value = sv[:, 0]
            off = np.flatnonzero(region >= 0)
            hard[off] = value[region[off]]
            mixed = np.flatnonzero(~np.all(sv == sv[:, :1], axis=1))
            if len(mixed):
                redo = off[np.isin(region[off], mixed)]
                hard[redo] = self._hits_at_flat(T_wm, cams, crops, offsets, redo)
        return hard

    def _band_pixels(self, seg: dict[str, NDArray], crops: NDArray[np.int64], offsets: NDArray[np.int64],
                     band_r: float) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """Band pixels (within ``band_r`` px of the outline) with their nearest segment, and off-band regions.

        Returns flat band indices, their segment ids, a region id per flat pixel (-1 in the band)
        and (R, 3) sample pixels per region.

        All crops are stacked into one atlas image, separated by gaps wider than the band, so that
        one distance transform (with labels) and one connected-components pass serve every view.
        The labels propose, for every pixel, the segments nearest to it and to its 4 neighbours;
        the exact point-to-segment distance picks the nearest of them. Taking the minimum over
        several nearby candidates keeps the distance continuous as the outline moves.
        """
        P = int(offsets[-1])
        region = np.full(P, -1, dtype=np.int64)
        atlas = _Atlas(crops, offsets, gap=int(np.ceil(band_r)) + 2)
        src = np.ones(atlas.shape, dtype=np.uint8)
        n_seg = len(seg["view"])
        if n_seg:
            sv = seg["view"]
            cx = np.clip(np.floor(seg["mid"][:, 0] - crops[sv, 0]).astype(np.int64), 0, crops[sv, 2] - 1)
            cy = np.clip(np.floor(seg["mid"][:, 1] - crops[sv, 1]).astype(np.int64), 0, crops[sv, 3] - 1)
            ay = atlas.row0[sv] + cy
            src[ay, cx] = 0
            # Several segments (of different edges) can fall in one cell: the cell keeps the one
            # whose visible edge interval passes nearest to the cell centre.
            centre = np.stack([crops[sv, 0] + cx + 0.5, crops[sv, 1] + cy + 0.5], 1)
            d_cell = _point_segment_dist2(centre, seg["a"], seg["b"])
            cell = ay * atlas.shape[1] + cx
            order = np.lexsort((-d_cell, cell))  # within a cell, nearest last: the last write wins
            owner = np.full(atlas.shape, -1, dtype=np.int64)
            owner[ay[order], cx[order]] = order
            dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
            lut = np.full(int(labels.max()) + 1, -1, dtype=np.int64)
            lut[labels[ay, cx]] = owner[ay, cx]
            in_band = (dist <= band_r) & atlas.valid
        else:
            in_band = np.zeros(atlas.shape, dtype=bool)
        off_band = atlas.valid & ~in_band
        n_lab, lab = cv2.connectedComponents(off_band.astype(np.uint8), connectivity=4)
        off = np.flatnonzero(off_band.ravel())  # atlas pixels, row-major
        flat_off = atlas.flat.ravel()[off]
        lab_off = lab.ravel()[off].astype(np.int64) - 1
        region[flat_off] = lab_off
        # three sample pixels per region without sorting: its first and last pixel in row-major
        # order, and its first in column-major order (later writes win in a fancy assignment)
        samples = np.zeros((n_lab - 1, 3), dtype=np.int64)
        samples[lab_off[::-1], 0] = flat_off[::-1]
        samples[lab_off, 1] = flat_off
        lab_t = lab.T.ravel()  # column-major copies
        in_t = np.flatnonzero(lab_t)
        samples[lab_t[in_t[::-1]].astype(np.int64) - 1, 2] = atlas.flat.T.ravel()[in_t[::-1]]
        rr, cc = np.nonzero(in_band)
        if len(rr) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), region, samples
        band = atlas.flat[rr, cc]
        view = atlas.view_of_row[rr]
        nearest = np.pad(lut[labels], 1, mode="edge")
        cand = np.stack([nearest[rr + 1 + dy, cc + 1 + dx] for dy, dx in _CANDIDATE_OFFSETS], 1)
        p = np.stack([crops[view, 0] + cc + 0.5, crops[view, 1] + rr - atlas.row0[view] + 0.5], 1)
        # Distances only where a candidate differs from the best so far (mostly all five agree);
        # a neighbour across a gap belongs to another view and is never taken.
        best = cand[:, 0].copy()
        d_best = _point_segment_dist2(p, seg["a"][best], seg["b"][best])
        d_best[seg["view"][best] != view] = np.inf
        for k in range(1, cand.shape[1]):
            alt = cand[:, k]
            i = np.flatnonzero((alt != best) & (seg["view"][alt] == view))
            d = _point_segment_dist2(p[i], seg["a"][alt[i]], seg["b"][alt[i]])
            m = d < d_best[i]
            best[i[m]] = alt[i[m]]
            d_best[i[m]] = d[m]
        return band, best, region, samples

    def _outline_segments(self, T_wm: NDArray[np.float64], cams: CameraBatch,
                          crops: NDArray[np.int64]) -> dict[str, NDArray]:
        """Sub-pixel segments of contour edges that lie on the visible outline, all views."""
        flip = self._contour_matrix(T_wm, cams)  # (E, N)
        flip[:, crops[:, 2] * crops[:, 3] == 0] = False
        view, edge = np.nonzero(flip.T)  # grouped by view
        empty = {"view": np.zeros(0, np.int64), "edge": np.zeros(0, np.int64), "mid": np.zeros((0, 2)),
                 "t0": np.zeros(0), "t1": np.zeros(0), "a": np.zeros((0, 2)), "b": np.zeros((0, 2))}
        if len(edge) == 0:
            return empty
        used = np.unique(self.mesh.edges[edge])
        V_w = np.zeros_like(self.mesh.vertices)
        V_w[used] = transform_points(T_wm, self.mesh.vertices[used])
        ends = self.mesh.edges[edge]
        t = cams.t_w2c[view]
        Xa = per_view_matvec(cams.R_w2c, view, V_w[ends[:, 0]]) + t
        Xb = per_view_matvec(cams.R_w2c, view, V_w[ends[:, 1]]) + t
        ok = (Xa[:, 2] > _NEAR_MM) & (Xb[:, 2] > _NEAR_MM)
        view, edge, Xa, Xb = view[ok], edge[ok], Xa[ok], Xb[ok]
        ua, ub = per_view_matvec(cams.K, view, Xa), per_view_matvec(cams.K, view, Xb)
        A, B = ua[:, :2] / ua[:, 2:3], ub[:, :2] / ub[:, 2:3]
        d = B - A
        L = np.linalg.norm(d, axis=1)
        good = L > 1e-9
        view, edge, A, d, L = view[good], edge[good], A[good], d[good], L[good]
        n_sub = np.maximum(1, np.ceil(L / self.segment_px).astype(np.int64))
        rep = np.repeat(np.arange(len(L)), n_sub)
        k = np.arange(len(rep)) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)
        t = (k + 0.5) / n_sub[rep]
        mid = A[rep] + t[:, None] * d[rep]
        nrm = np.column_stack([-d[:, 1], d[:, 0]]) / L[:, None]
        delta = 0.3
        p_plus = mid + delta * nrm[rep]
        p_minus = mid - delta * nrm[rep]
        sv = view[rep]
        hits = self.hits_at(T_wm, cams, np.concatenate([sv, sv]), np.concatenate([p_plus, p_minus]))
        outline = hits[:len(rep)] != hits[len(rep):]
        # The visible interval [t0, t1] of each (view, edge): from its first to its last outline
        # segment. Distances are taken to that whole interval, so that the nearest outline point
        # moves continuously while the pose changes.
        pair = np.flatnonzero(outline)
        owner = rep[pair]
        t0 = np.full(len(L), np.inf)
        t1 = np.full(len(L), -np.inf)
        np.minimum.at(t0, owner, k[pair] / n_sub[owner])
        np.maximum.at(t1, owner, (k[pair] + 1.0) / n_sub[owner])
        t0, t1 = t0[owner], t1[owner]
        a, b = A[owner] + t0[:, None] * d[owner], A[owner] + t1[:, None] * d[owner]
        return {"view": sv[pair], "edge": edge[owner], "mid": mid[pair],
                "t0": t0, "t1": t1, "a": a, "b": b}

    def _band_values(self, cams: CameraBatch, view: NDArray[np.int64], px: NDArray[np.float64],
                     py: NDArray[np.float64], sign: NDArray[np.float64], A_w: NDArray[np.float64],
                     B_w: NDArray[np.float64], t0: NDArray[np.float64], t1: NDArray[np.float64],
                     centre_w: NDArray[np.float64], half: float,
                     with_jacobian: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Soft values of band pixels and their twist derivatives (drjit, forward-mode AD)."""
        dr, mi = self._dr, self._mi
        Float, UInt = mi.Float64, mi.UInt32
        N = len(cams.K)
        P = np.concatenate([cams.R_w2c.reshape(N, 9), cams.t_w2c, cams.K[:, :2].reshape(N, 6)], 1)  # (N, 18)
        vid = jit_array(UInt, view, np.uint32)
        cam = [dr.gather(Float, jit_array(Float, P[:, j], np.float64), vid) for j in range(18)]
        xi = [Float(0.0) for _ in range(6)]
        if with_jacobian:
            for x in xi:
                dr.enable_grad(x)
        c = [dr.opaque(Float, float(x)) for x in centre_w]  # opaque: one compiled kernel for all poses

        def moved(X: NDArray[np.float64]) -> list:
            # X + v + w x (X - c), to first order in the twist (exact derivative at xi = 0)
            x = [jit_array(Float, X[:, j], np.float64) for j in range(3)]
            r = [x[0] - c[0], x[1] - c[1], x[2] - c[2]]
            wx = [xi[4] * r[2] - xi[5] * r[1], xi[5] * r[0] - xi[3] * r[2], xi[3] * r[1] - xi[4] * r[0]]
            return [x[j] + xi[j] + wx[j] for j in range(3)]

        def project(X: list) -> tuple:
            R, t = cam[:9], cam[9:12]
            xc = [R[3 * r + 0] * X[0] + R[3 * r + 1] * X[1] + R[3 * r + 2] * X[2] + t[r] for r in range(3)]
            k = cam[12:18]  # fx, s, cx, 0, fy, cy
            u = (k[0] * xc[0] + k[1] * xc[1]) / xc[2] + k[2]
            v = (k[3] * xc[0] + k[4] * xc[1]) / xc[2] + k[5]
            return u, v

        eu, ev = project(moved(A_w))
        fu, fv = project(moved(B_w))
        s0, s1 = jit_array(Float, t0, np.float64), jit_array(Float, t1, np.float64)
        au, av = eu + s0 * (fu - eu), ev + s0 * (fv - ev)  # the sub-segment [t0, t1] of the edge
        bu, bv = eu + s1 * (fu - eu), ev + s1 * (fv - ev)
        qx, qy = jit_array(Float, px, np.float64), jit_array(Float, py, np.float64)
        dx, dy = bu - au, bv - av
        t = ((qx - au) * dx + (qy - av) * dy) / dr.maximum(dx * dx + dy * dy, 1e-18)
        t = dr.clip(t, 0.0, 1.0)
        ex, ey = au + t * dx - qx, av + t * dy - qy
        dist = dr.sqrt(dr.maximum(ex * ex + ey * ey, 1e-18))
        z = jit_array(Float, sign, np.float64) * dist / dr.opaque(Float, half)
        u = dr.clip((z + 1.0) * 0.5, 0.0, 1.0)
        s = u * u * (3.0 - 2.0 * u)
        outputs = [dr.detach(s)]
        if with_jacobian:
            for k in range(6):  # one forward pass per twist coordinate; kept lazy, evaluated together
                dr.set_grad(s, 0.0)
                dr.forward_from(xi[k], flags=dr.ADFlag.ClearInterior)
                outputs.append(dr.grad(s))
            for x in xi:
                dr.disable_grad(x)
        dr.eval(*outputs)  # a single fused kernel for the values and all six derivative columns
        value = np.array(outputs[0], dtype=np.float64)
        jac = np.stack([np.array(o, dtype=np.float64) for o in outputs[1:]], 1) if with_jacobian \
            else np.zeros((len(px), 6))
        return value, jac


class _Atlas:
    """All crops stacked top to bottom in one image, ``gap`` rows apart, left-aligned.

    ``flat[y, x]`` is the flat pixel index of atlas pixel (y, x) (-1 in gaps), ``valid`` marks crop
    pixels, ``row0[i]`` is the first atlas row of view ``i`` and ``view_of_row`` the view of each row.
    """

    def __init__(self, crops: NDArray[np.int64], offsets: NDArray[np.int64], gap: int) -> None:
        heights = crops[:, 3] + gap
        self.row0 = np.concatenate([[0], np.cumsum(heights)[:-1]]).astype(np.int64)
        H = int(heights.sum()) if len(crops) else 1
        W = int(crops[:, 2].max()) + gap if len(crops) else 1
        self.shape = (max(H, 1), max(W, 1))
        self.flat = np.full(self.shape, -1, dtype=np.int64)
        self.view_of_row = np.full(self.shape[0], -1, dtype=np.int64)
        for i, (x0, y0, w, h) in enumerate(crops):
            r0 = self.row0[i]
            self.flat[r0:r0 + h, :w] = offsets[i] + np.arange(w * h).reshape(h, w)
            self.view_of_row[r0:r0 + h] = i
        self.valid = self.flat >= 0


def _point_segment_dist2(p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared distance from points ``p`` to segments ``[a, b]`` (broadcast over leading axes)."""
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    qx, qy = p[..., 0] - a[..., 0], p[..., 1] - a[..., 1]
    t = np.clip((qx * dx + qy * dy) / np.maximum(dx * dx + dy * dy, 1e-18), 0.0, 1.0)
    ex, ey = t * dx - qx, t * dy - qy
    return ex * ex + ey * ey


def _crop_pixel_centres(crop: NDArray[np.int64]) -> NDArray[np.float64]:
    """Continuous coordinates (N, 2) of the pixel centres of a crop, row-major."""
    x0, y0, w, h = (int(v) for v in crop)
    xs = np.arange(x0, x0 + w) + 0.5
    ys = np.arange(y0, y0 + h) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])
