"""OpenCV pinhole cameras in BOP convention.

* Camera frame: x right, y down, z forward (optical axis). Millimetres.
* ``x_cam = R_w2c @ x_world + t_w2c`` (BOP ``cam_R_w2c`` / ``cam_t_w2c``).
* Continuous pixel coordinates: ``(u, v) = (fx x/z + cx, fy y/z + cy)``.

Two conventions for where a pixel sits in those coordinates are in use, and autoalign keeps them
apart explicitly:

* **Internal** (:class:`Camera`, the renderer, the overlay): pixel ``(row i, col j)`` covers
  ``[j, j+1) x [i, i+1)``, its centre at ``(j + 0.5, i + 0.5)`` (COLMAP's convention). Pixel edges
  on integers make resampling exact: ``K' = diag(f, f, 1) K`` at any scale.
* **OpenCV / BOP** (every file and every pixel coordinate a user types): the centre of pixel
  ``(row i, col j)`` is at ``(j, i)``. This is what ``cv2.projectPoints`` and OpenCV calibrations
  give and what the bop_toolkit assumes (its renderers and ``misc.project_pts`` use ``cam_K`` with
  integer pixel indices as centres), so BOP's ``cam_K`` means it too.

The conversion happens once, on import and export (:func:`K_from_opencv`, :func:`K_to_opencv`,
:func:`uv_from_opencv`): an OpenCV ``cx`` is an internal ``cx + 0.5``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from autoalign.geometry.se3 import make_pose

OPENCV_TO_INTERNAL_PX = 0.5
"""Internal continuous pixel coordinate minus the OpenCV / BOP one, along u and v."""

PIXEL_CONVENTION = {
    "files": "OpenCV/BOP: cam_K and pixel coordinates put the centre of pixel (row i, col j) at (j, i)",
    "internal": "pixel (row i, col j) covers [j, j+1) x [i, i+1), centre (j + 0.5, i + 0.5); "
                "internal cx, cy = file cx, cy + 0.5",
}
"""The pixel conventions, as recorded in ``refine.json``."""


def K_from_opencv(K: NDArray[np.float64]) -> NDArray[np.float64]:
    """Internal intrinsics from OpenCV / BOP ``cam_K`` (3x3): the principal point moves by +0.5 px."""
    K = np.array(K, dtype=np.float64).reshape(3, 3)
    K[:2, 2] += OPENCV_TO_INTERNAL_PX * K[2, 2]
    return K


def K_to_opencv(K: NDArray[np.float64]) -> NDArray[np.float64]:
    """OpenCV / BOP ``cam_K`` (3x3) from internal intrinsics (inverse of :func:`K_from_opencv`)."""
    K = np.array(K, dtype=np.float64).reshape(3, 3)
    K[:2, 2] -= OPENCV_TO_INTERNAL_PX * K[2, 2]
    return K


def uv_from_opencv(uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Internal continuous pixel coordinates from OpenCV / BOP ones (``(..., 2)``, pixels)."""
    return np.asarray(uv, dtype=np.float64) + OPENCV_TO_INTERNAL_PX


def uv_to_opencv(uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """OpenCV / BOP pixel coordinates from internal ones (inverse of :func:`uv_from_opencv`): a
    pixel's index is the OpenCV coordinate of its centre, so this also maps an internal coordinate
    to pixel-index units (``floor(uv_to_opencv(uv) + 0.5)`` is the pixel it falls in)."""
    return np.asarray(uv, dtype=np.float64) - OPENCV_TO_INTERNAL_PX


def pixel_centres(cols: ArrayLike, rows: ArrayLike) -> NDArray[np.float64]:
    """Internal continuous coordinates (N, 2) ``(u, v)`` of the centres of the pixels in columns
    ``cols`` and rows ``rows`` (same shape, flattened): ``(j + 0.5, i + 0.5)``, a pixel's index
    being the OpenCV coordinate of its centre. Every pixel index becomes a coordinate here."""
    return uv_from_opencv(np.column_stack([np.ravel(cols), np.ravel(rows)]))


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole view: intrinsics ``K`` (pixels, internal convention: pixel centres at
    +0.5), world-to-camera pose (mm), image size. Build one from file intrinsics with
    :meth:`from_opencv`."""

    K: NDArray[np.float64]
    R_w2c: NDArray[np.float64]
    t_w2c: NDArray[np.float64]
    width: int
    height: int

    @staticmethod
    def from_opencv(K: NDArray[np.float64], R_w2c: NDArray[np.float64], t_w2c: NDArray[np.float64],
                    width: int, height: int) -> "Camera":
        """A camera from OpenCV / BOP intrinsics ``K`` (centre of pixel (0, 0) at (0, 0))."""
        return Camera(K_from_opencv(K), np.asarray(R_w2c, dtype=np.float64), np.asarray(t_w2c, dtype=np.float64),
                      int(width), int(height))

    @property
    def K_opencv(self) -> NDArray[np.float64]:
        """The intrinsics in the OpenCV / BOP convention, as written to ``cam_K``."""
        return K_to_opencv(self.K)

    @property
    def T_cw(self) -> NDArray[np.float64]:
        """4x4 camera-from-world transform."""
        return make_pose(self.R_w2c, self.t_w2c)

    @property
    def centre(self) -> NDArray[np.float64]:
        """Camera centre in world coordinates (mm)."""
        return -self.R_w2c.T @ self.t_w2c

    def to_camera(self, X_w: NDArray[np.float64]) -> NDArray[np.float64]:
        """World points (N, 3) to camera-frame points (N, 3)."""
        return np.asarray(X_w, dtype=np.float64) @ self.R_w2c.T + self.t_w2c

    def project(self, X_w: NDArray[np.float64]) -> NDArray[np.float64]:
        """World points (N, 3) to internal continuous pixel coordinates (N, 2); centres at +0.5."""
        Xc = self.to_camera(X_w)
        uvw = Xc @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def pixel_rays(self, cols: ArrayLike, rows: ArrayLike) -> NDArray[np.float64]:
        """Unit world-frame directions (N, 3) of the rays through the centres of the pixels in
        columns ``cols`` and rows ``rows`` (:func:`pixel_centres`)."""
        return self.ray_directions(pixel_centres(cols, rows))

    def depth_rays(self, cols: ArrayLike, rows: ArrayLike) -> NDArray[np.float64]:
        """World-frame directions (N, 3) of the rays through the centres of the pixels in columns
        ``cols`` and rows ``rows``, scaled to unit z in the camera: a point ``centre + t d`` lies at
        depth ``t`` (mm along the optical axis), as a depth image measures it."""
        pix = np.column_stack([pixel_centres(cols, rows), np.ones(np.size(cols))])
        return (pix @ np.linalg.inv(self.K).T) @ self.R_w2c  # rows R_c2w K^-1 [u, v, 1]

    def ray_directions(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit world-frame directions of the rays through continuous pixel coordinates (N, 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        d_c = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(self.K).T
        d_w = d_c @ self.R_w2c  # R_w2c^T applied to each row
        return d_w / np.linalg.norm(d_w, axis=1, keepdims=True)

    def scaled(self, factor: float) -> "Camera":
        """The same view rendered at ``factor`` times the resolution (0.5 halves it).

        Continuous pixel coordinates scale exactly (pixel edges stay on integers), so
        ``K' = diag(f, f, 1) K``; the image size is rounded up to whole pixels.
        """
        S = np.diag([factor, factor, 1.0])
        return Camera(S @ self.K, self.R_w2c, self.t_w2c,
                      int(np.ceil(self.width * factor)), int(np.ceil(self.height * factor)))


def look_at(eye: NDArray[np.float64], target: NDArray[np.float64], K: NDArray[np.float64],
            width: int, height: int, up: NDArray[np.float64] | None = None) -> Camera:
    """A camera at ``eye`` (mm, world) whose +z axis points at ``target``; image y follows -``up``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    if abs(z @ up) > 0.999 * np.linalg.norm(up):
        up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)  # right = forward x up ... with y down this gives a right-handed frame
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_c2w = np.column_stack([x, y, z])
    R_w2c = R_c2w.T
    return Camera(np.asarray(K, dtype=np.float64), R_w2c, -R_w2c @ eye, int(width), int(height))
