"""The pose derivatives of autoalign's soft silhouettes as full images, for the framework ops
(:mod:`autoalign.torch`, :mod:`autoalign.jax`): the host side they share, numpy only.

The renderer gives, for each band pixel, the derivatives of its value w.r.t. the world positions
of the two end points of its outline edge (``render(..., wrt="vertices")``). The end points are
``T[:3, :3] x + T[:3, 3]`` of their model positions ``x``, so the derivatives w.r.t. the pose
matrix ``T`` follow by the chain rule, exactly for any change of its top three rows (rigid or
not), with the outline and the hard mask held fixed as in autoalign's own Gauss-Newton steps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

Renderers = Mesh | SoftSilhouetteRasterizer | Sequence[Mesh | SoftSilhouetteRasterizer]


def renderers_for(meshes: Renderers, n: int) -> list[SoftSilhouetteRasterizer]:
    """One renderer per pose: ``meshes`` is one mesh or renderer for all ``n`` poses, or one each."""
    items = list(meshes) if isinstance(meshes, Sequence) else [meshes] * n
    if len(items) != n:
        raise ValueError(f"{len(items)} meshes for {n} poses: give one mesh for all, or one per pose")
    return [m if isinstance(m, SoftSilhouetteRasterizer) else SoftSilhouetteRasterizer(m) for m in items]


def image_size(cameras: Sequence[Camera]) -> tuple[int, int]:
    """``(H, W)`` shared by all ``cameras`` (the op stacks their images)."""
    sizes = {(c.height, c.width) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"the cameras have different image sizes {sorted(sizes)}; render each size separately")
    return sizes.pop()


class RenderedPose:
    """What the backward pass needs of one object's forward pass: the flat indices of its band
    pixels in the (V, H, W) images, their derivatives w.r.t. their edges' world end points
    (B, 6), and those end points in the model frame (B, 2, 3)."""

    def __init__(self, index: NDArray[np.int64], jac: NDArray[np.float64], ends_m: NDArray[np.float64]) -> None:
        self.index, self.jac, self.ends_m = index, jac, ends_m

    def matrix_gradient(self, grad_images: NDArray[np.float64]) -> NDArray[np.float64]:
        """dL/dT (4, 4) from dL/d(images) (V*H*W,): the end points are ``T[:3, :3] x + T[:3, 3]``."""
        g = grad_images[self.index]
        gA, gB = g[:, None] * self.jac[:, :3], g[:, None] * self.jac[:, 3:]
        out = np.zeros((4, 4))
        out[:3, :3] = gA.T @ self.ends_m[:, 0] + gB.T @ self.ends_m[:, 1]
        out[:3, 3] = gA.sum(0) + gB.sum(0)
        return out

    def image_tangent(self, dT: NDArray[np.float64], size: int) -> NDArray[np.float64]:
        """d(images)/dT applied to ``dT`` (4, 4): the flat images' (``size`` = V*H*W) change."""
        dT = np.asarray(dT, dtype=np.float64)
        dA = self.ends_m[:, 0] @ dT[:3, :3].T + dT[:3, 3]
        dB = self.ends_m[:, 1] @ dT[:3, :3].T + dT[:3, 3]
        out = np.zeros(size)
        change = np.einsum("bi,bi->b", self.jac[:, :3], dA) + np.einsum("bi,bi->b", self.jac[:, 3:], dB)
        np.add.at(out, self.index, change)
        return out


def render_with_vertex_jacobian(rast: SoftSilhouetteRasterizer, T_wm: NDArray[np.float64], cameras: Sequence[Camera],
                                sigma: float) -> tuple[NDArray[np.float64], RenderedPose]:
    """Full soft silhouettes (V, H, W) of one object and what its backward pass needs."""
    H, W = image_size(cameras)
    sil = rast.render(np.asarray(T_wm, dtype=np.float64), list(cameras), sigma, wrt="vertices")
    images = np.zeros((len(cameras), H, W))
    for i in range(len(cameras)):
        x0, y0, w, h = (int(v) for v in sil.crops[i])
        crop = sil.soft[sil.offsets[i]:sil.offsets[i + 1]].reshape(h, w)
        ys, xs = slice(max(y0, 0), min(y0 + h, H)), slice(max(x0, 0), min(x0 + w, W))
        images[i, ys, xs] = crop[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    v = sil.view_of_band
    local = sil.band - sil.offsets[v]
    w_b = sil.crops[v, 2]
    row, col = sil.crops[v, 1] + local // w_b, sil.crops[v, 0] + local % w_b
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    index = (v * H + row) * W + col
    ends = rast.mesh.vertices[sil.edge_vertices[inside]] if sil.edge_vertices is not None else np.zeros((0, 2, 3))
    return images, RenderedPose(index[inside], sil.jac[inside], ends)
