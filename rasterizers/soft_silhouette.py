"""Soft silhouettes of a mesh in many views at once, with derivatives w.r.t. a 6-D pose twist.

:meth:`SoftSilhouetteRasterizer.render` runs, for all views together, the steps of its own modules:

1. **Crop** each view to the projected convex hull of the object plus a margin.
2. **Outline** (:mod:`~autoalign.rasterizers.outline`): contour edges split into sub-pixel
   segments, kept where rays either side disagree (the visible outline).
3. **Band** (:mod:`~autoalign.rasterizers.band`): the pixels within ``2 sigma + 1.5`` px of the
   outline with their nearest segment, and the hard mask of the crops from rays cast
   (:mod:`~autoalign.rasterizers.ray_casting`) at the band pixels and three pixels per off-band region.
4. **Soft edge** (:mod:`~autoalign.rasterizers.soft_edge`): a band pixel's value is
   ``smoothstep(sign * dist / (2 sigma))`` of its distance to the nearest outline edge (``sign``
   +1 inside the hard mask), with its twist derivatives from drjit forward-mode AD. Off the band
   the soft value equals the hard mask exactly, so the cost follows the silhouette's length.

Twist convention: ``xi = (v [mm], w [rad])`` about the object centre (see :mod:`~autoalign.rasterizers.soft_edge`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera, pixel_centres
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import transform_points
from autoalign.rasterizers.band import find_band, hard_mask
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.hard_mask_cache import CropHits, HardMaskCache
from autoalign.rasterizers.outline import NEAR_MM, OutlineFinder
from autoalign.rasterizers.ray_casting import RayCaster
from autoalign.rasterizers.soft_edge import soft_edge_values


@dataclass
class Silhouettes:
    """Soft silhouettes of all views, stored as one flat array of crop pixels.

    Attributes:
        crops: (N, 4) int ``x0, y0, w, h`` of each view's crop in its (scaled) image, pixels.
        offsets: (N + 1,) start of each view's pixels in the flat arrays (row-major in its crop).
        soft: (P,) soft mask values in [0, 1].
        hard: (P,) ray-cast hard mask at pixel centres.
        band: (B,) flat indices of the pixels whose soft value depends on the pose (grouped by
            view, increasing).
        jac: (B, 6) derivatives of ``soft[band]`` w.r.t. the twist ``(v [mm], w [rad])``, or
            (``render(..., wrt="vertices")``) w.r.t. the world positions (mm) of the two mesh
            vertices ``edge_vertices`` of the band pixel's outline edge.
        view_of_band: (B,) view index of each band pixel.
        n_outline: (N,) outline segments found per view (diagnostics).
        edge_vertices: (B, 2) mesh vertex indices of each band pixel's outline edge.
    """

    crops: NDArray[np.int64]
    offsets: NDArray[np.int64]
    soft: NDArray[np.float64]
    hard: NDArray[np.bool_]
    band: NDArray[np.int64]
    jac: NDArray[np.float64]
    view_of_band: NDArray[np.int64]
    n_outline: NDArray[np.int64]
    edge_vertices: NDArray[np.int64] | None = None

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
                       view_of_band=self.view_of_band[keep],
                       edge_vertices=None if self.edge_vertices is None else self.edge_vertices[keep])

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


class SoftSilhouetteRasterizer:
    """Renders soft silhouettes of one mesh in many calibrated views (see module doc).

    Args:
        mesh: the object, model frame, mm.
        segment_px: length of the outline segments the contour edges are split into, pixels.

    Attributes:
        caster: the mesh's :class:`~autoalign.rasterizers.ray_casting.RayCaster` (hits, depths, hit sums).
        hull: (H, 3) the mesh's convex hull vertices (model frame, mm), for crops and bounds.
    """

    def __init__(self, mesh: Mesh, segment_px: float = 0.75) -> None:
        self.mesh = mesh
        self.caster = RayCaster(mesh)
        self.outlines = OutlineFinder(mesh, self.caster, segment_px)
        self.hull = mesh.hull
        self._held = HardMaskCache()

    def hard_masks(self, T_wm: NDArray[np.float64], cameras: list[Camera]) -> list[NDArray[np.bool_]]:
        """Full-image hard masks (H, W) by ray casting at every pixel centre of the object's crops
        (those of the last poses asked for are held: :class:`HardMaskCache`)."""
        held = self._held.get(T_wm, cameras)
        missing = [k for k, h in enumerate(held) if h is None]
        if missing:
            cast = self._cast_crops(T_wm, [cameras[k] for k in missing])
            self._held.put(T_wm, [cameras[k] for k in missing], cast)
            for k, crop in zip(missing, cast):
                held[k] = crop
        out = []
        for cam, ((x0, y0, w, h), hv) in zip(cameras, held):
            m = np.zeros((cam.height, cam.width), dtype=bool)
            m[y0:y0 + h, x0:x0 + w] = hv
            out.append(m)
        return out

    def _cast_crops(self, T_wm: NDArray[np.float64], cameras: list[Camera]) -> list[CropHits]:
        """Each view's crop box (the projected hull plus 2 px) and the hard mask within it."""
        cams = CameraBatch.of(cameras)
        crops = self.crops(T_wm, cams, margin=2)
        sizes = crops[:, 2] * crops[:, 3]
        view = np.repeat(np.arange(len(cameras)), sizes)
        uv = np.concatenate([_crop_pixel_centres(c) for c in crops]) if sizes.sum() else np.zeros((0, 2))
        hits = np.split(self.caster.pixel_hits(T_wm, cams, view, uv), np.cumsum(sizes)[:-1])
        return [((int(x0), int(y0), int(w), int(h)), hv.reshape(h, w)) for (x0, y0, w, h), hv in zip(crops, hits)]

    def crops(self, T_wm: NDArray[np.float64], cams: CameraBatch, margin: int) -> NDArray[np.int64]:
        """(N, 4) ``x0, y0, w, h`` covering the projected convex hull plus ``margin`` px, clipped.

        A view whose camera plane cuts the object gets the whole image.
        """
        Xw = transform_points(T_wm, self.hull)
        Xc = np.einsum("nij,hj->nhi", cams.R_w2c, Xw) + cams.t_w2c[:, None, :]  # (N, H, 3)
        behind = np.any(Xc[..., 2] < NEAR_MM, axis=1)
        uvw = np.einsum("nij,nhj->nhi", cams.K, Xc)
        uv = uvw[..., :2] / np.where(np.abs(uvw[..., 2:3]) > 1e-9, uvw[..., 2:3], 1e-9)
        size = cams.sizes
        lo = np.where(behind[:, None], 0, np.floor(uv.min(1)).astype(np.int64) - margin)
        hi = np.where(behind[:, None], size, np.ceil(uv.max(1)).astype(np.int64) + margin)
        lo = np.clip(lo, 0, size)
        hi = np.clip(hi, 0, size)
        return np.concatenate([lo, np.maximum(hi - lo, 0)], axis=1)

    def render(self, T_wm: NDArray[np.float64], cameras: list[Camera], sigma: float = 1.0,
               with_jacobian: bool = True, wrt: str = "twist") -> Silhouettes:
        """Soft silhouettes (and twist derivatives) of the object at pose ``T_wm`` in all ``cameras``.

        Args:
            T_wm: world-from-model pose, mm.
            cameras: the views (already scaled to the working resolution).
            sigma: edge softness in pixels of these cameras; the profile spans ``+-2 sigma``.
            with_jacobian: also compute ``jac`` (6 forward AD passes over the band pixels).
            wrt: ``"twist"`` (about the object centre) or ``"vertices"`` (the band pixels'
                outline edge end points, world, mm; see :class:`Silhouettes`).
        """
        if wrt not in ("twist", "vertices"):
            raise ValueError(f"wrt={wrt!r}: 'twist' or 'vertices'")
        half = 2.0 * float(sigma)
        band_r = half + 1.5
        cams = CameraBatch.of(cameras)
        crops = self.crops(T_wm, cams, int(np.ceil(band_r)) + 2)
        offsets = np.concatenate([[0], np.cumsum(crops[:, 2] * crops[:, 3])]).astype(np.int64)
        outline = self.outlines.find(T_wm, cams, crops)
        band = find_band(outline, crops, offsets, band_r)
        hard = hard_mask(self.caster, T_wm, cams, crops, offsets, band)
        soft = hard.astype(np.float64)
        pixels, view_of_band = band.pixels, band.view
        n_out = outline.per_view(len(cameras))
        if len(pixels) == 0:
            return Silhouettes(crops, offsets, soft, hard, pixels, np.zeros((0, 6)), view_of_band, n_out,
                               np.zeros((0, 2), dtype=np.int64))
        ends = self.mesh.edges[outline.edge[band.segment]]
        A_w, B_w = self._world_ends(T_wm, ends)
        value, jac = soft_edge_values(cams, view_of_band, band.px, band.py, np.where(hard[pixels], 1.0, -1.0), A_w, B_w,
                                      outline.t0[band.segment], outline.t1[band.segment],
                                      transform_points(T_wm, self.mesh.centre[None])[0], half, with_jacobian,
                                      wrt == "vertices")
        soft[pixels] = value
        return Silhouettes(crops, offsets, soft, hard, pixels, jac, view_of_band, n_out, ends)

    def _world_ends(self, T_wm: NDArray[np.float64],
                    ends: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World positions (mm; B, 3 each) of the mesh vertices ``ends[:, 0]`` and ``ends[:, 1]`` (B, 2).

        The few distinct vertices are moved once and gathered, instead of one matrix product over
        all B rows (B is up to ~10^5 at full resolution, where a multi-threaded BLAS product was
        slower than everything else in the render). A product of at least two rows gives each
        row the same bits however many rows it has; a single row takes another BLAS path
        (matrix-vector), so one band pixel keeps the direct product.
        """
        V = self.mesh.vertices
        is_used = np.zeros(len(V), dtype=bool)
        is_used[ends] = True
        used = np.flatnonzero(is_used)
        if len(ends) < 2 or len(used) < 2:
            return transform_points(T_wm, V[ends[:, 0]]), transform_points(T_wm, V[ends[:, 1]])
        V_w = np.empty_like(V)
        V_w[used] = transform_points(T_wm, V[used])
        return V_w[ends[:, 0]], V_w[ends[:, 1]]


def _crop_pixel_centres(crop: NDArray[np.int64]) -> NDArray[np.float64]:
    """Continuous coordinates (N, 2) of the pixel centres of a crop, row-major (internal convention)."""
    x0, y0, w, h = (int(v) for v in crop)
    return pixel_centres(*np.meshgrid(np.arange(x0, x0 + w), np.arange(y0, y0 + h)))
