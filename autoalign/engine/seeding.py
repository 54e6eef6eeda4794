"""Coarse starting poses: from a click, from the visual hull of the masks, and rotation hypotheses.

All positions are world-frame millimetres; orientations are rotation matrices (world from model).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import pixel_centres, uv_from_opencv, uv_to_opencv
from autoalign.io.bop import Scene


@dataclass(frozen=True)
class Click:
    """One pixel on the object: image id and internal continuous pixel coordinates ``(u, v)``
    (centres at +0.5; :meth:`parse` converts from the OpenCV coordinates a user types)."""

    image_id: int
    u: float
    v: float

    def scaled(self, factor: float) -> "Click":
        """The same point in the image scaled by ``factor`` (see :meth:`Camera.scaled`)."""
        return Click(self.image_id, self.u * factor, self.v * factor)

    @staticmethod
    def parse(text: str) -> "Click":
        """Parse ``IM_ID:U,V`` with ``U, V`` in OpenCV pixel coordinates (top-left pixel centre at 0,0)."""
        try:
            im, uv = text.split(":")
            u, v = uv_from_opencv(np.array([float(x) for x in uv.split(",")]))
            return Click(int(im), float(u), float(v))
        except ValueError:
            raise AutoalignError(f"--click {text!r}: expected IM_ID:U,V, e.g. --click 0:320,240") from None


def _mask_support(scene: Scene, X: NDArray[np.float64], dilate_px: int = 0) -> NDArray[np.int64]:
    """How many views see each world point ``X`` (N, 3, mm) inside their mask; (N,) counts.

    Only the instance's own masks count, not the pixels other masks claim (``Scene.ignore``): in a
    cluttered scene those cover much of every image, and counting them as support carried the
    hull's centre 127-393 mm away for 6 of the 8 objects of the real LM-O groups (own masks only:
    5-76 mm). Where another object hides this one, its mask is smaller and the support lower; the
    carving keeps voxels seen in most views, not all.

    Projected in single precision: for points within metres of the cameras the error is far
    below a pixel, and the points are voxel centres of a carving grid.
    """
    count = np.zeros(len(X), dtype=np.int64)
    kernel = np.ones((2 * dilate_px + 1,) * 2, np.uint8) if dilate_px else None
    Xh = np.column_stack([X, np.ones(len(X))]).astype(np.float32)
    for view in scene.views:
        cam, m = view.camera, view.mask
        P = cam.K @ np.column_stack([cam.R_w2c, cam.t_w2c])  # world to homogeneous pixels, (3, 4)
        uvw = Xh @ P.T.astype(np.float32)
        z = uvw[:, 2]
        ok = z > 1.0
        zs = np.where(ok, z, 1.0)
        j = np.floor(uvw[:, 0] / zs).astype(np.int64)
        i = np.floor(uvw[:, 1] / zs).astype(np.int64)
        inside = ok & (j >= 0) & (i >= 0) & (j < cam.width) & (i < cam.height)
        mm = cv2.dilate((m > 0.5).astype(np.uint8), kernel) if kernel is not None else (m > 0.5)
        count[inside] += mm[i[inside], j[inside]] > 0
    return count


def closest_point_to_rays(origins: NDArray[np.float64], dirs: NDArray[np.float64],
                          outlier: float | None = None, rounds: int = 3) -> NDArray[np.float64]:
    """Least-squares point nearest to a set of lines (unit ``dirs``). With ``outlier``, the fit is
    repeated ``rounds`` times without the lines farther from the point than ``outlier`` times the
    median distance: a ray through a mask on another object passes far away. That median counts as
    at least a thousandth of the point's median distance from the origins (1 mm at 1 m), in
    whatever unit the origins are (a reconstruction's cameras may be in an unknown one)."""
    origins, dirs = np.asarray(origins, dtype=np.float64), np.asarray(dirs, dtype=np.float64)
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # projections off each line
    keep = np.ones(len(origins), dtype=bool)
    for _ in range(1 + (rounds if outlier is not None else 0)):
        X = np.linalg.lstsq(P[keep].sum(0), np.einsum("kij,kj->i", P[keep], origins[keep]), rcond=None)[0]
        if outlier is None:
            break
        dist = np.linalg.norm(np.einsum("kij,kj->ki", P, X - origins), axis=1)
        floor = 1e-3 * float(np.median(np.linalg.norm(X - origins, axis=1)))
        keep = dist <= outlier * max(float(np.median(dist)), floor)
        if keep.sum() < 2:
            break
    return X


def hull_centre(scene: Scene, diameter: float, grid: int = 40, min_fraction: float = 0.8,
                start: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Centre (mm, world) of the visual hull of the masks, for an object about ``diameter`` mm across.

    The rays through the mask centroids (or ``start``, e.g. a point on a click's ray) give a first
    guess; a voxel grid of 1.5 diameters around it is carved, keeping voxels inside the (slightly
    dilated) mask in at least ``min_fraction`` of the views with a non-empty mask, so a few wrong
    masks do not empty the hull.
    """
    n_views = sum(bool(np.any(m > 0.5)) for m in scene.masks)
    if n_views == 0:
        raise AutoalignError("the masks are empty in every view; check the segmentation or --instance")
    if start is None:
        origins, dirs = [], []
        for view in scene.views:
            ys, xs = np.nonzero(view.mask > 0.5)
            if len(xs):
                origins.append(view.camera.centre)
                dirs.append(view.camera.pixel_rays(xs.mean(), ys.mean())[0])
        centre = closest_point_to_rays(np.array(origins), np.array(dirs))
    else:
        centre = np.asarray(start, float)
    for half in (1.5 * diameter, 0.75 * diameter):
        ax = np.linspace(-half, half, grid)
        X = centre + np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        support = _mask_support(scene, X, dilate_px=1)
        keep = support >= max(1, int(np.ceil(min_fraction * n_views)))
        if not keep.any():
            keep = support >= support.max()
        centre = X[keep].mean(0)
    return centre


CLICK_TOLERANCE_PX = 5.0  # a click may be this far (pixels) outside the mask of its own image


def check_click(scene: Scene, click: Click, tol_px: float = CLICK_TOLERANCE_PX) -> None:
    """Raise :class:`AutoalignError` unless ``click`` is in a view, inside its image and on (or within
    ``tol_px`` of) that image's mask. An empty mask in the clicked view is not held against the click.

    (A click off the object can still have a ray through other views' masks; it would seed a wrong
    position, so it is refused.)
    """
    if click.image_id not in scene.image_ids:
        views = f"views with a mask: {scene.image_ids[0]}..{scene.image_ids[-1]}"
        if click.image_id in scene.empty:
            why = f"the object's mask in image {click.image_id} is empty (the segmenter found nothing there)"
        elif click.image_id in scene.skipped:
            why = f"image {click.image_id} has no mask file for this instance"
        else:
            why = f"image {click.image_id} is not a view of the scene"
        raise AutoalignError(f"--click {click.image_id}:...: {why} ({views}); click in a view where the object "
                             "is masked")
    k = scene.image_ids.index(click.image_id)
    cam = scene.cameras[k]
    typed = "{:g},{:g}".format(*uv_to_opencv(np.array([click.u, click.v])))  # as the user wrote it
    if not (0 <= click.u < cam.width and 0 <= click.v < cam.height):
        raise AutoalignError(f"--click {click.image_id}:{typed}: outside the {cam.width}x{cam.height} "
                             "image; give pixel coordinates inside it")
    ys, xs = np.nonzero(np.asarray(scene.masks[k]) > 0.5)
    if len(xs) == 0:
        return
    c = pixel_centres(xs, ys)
    d = float(np.sqrt(((c[:, 0] - click.u) ** 2 + (c[:, 1] - click.v) ** 2).min()))
    if d > tol_px:
        raise AutoalignError(f"--click {click.image_id}:{typed}: not on the object's mask in image "
                             f"{click.image_id} (the nearest mask pixel is {d:.0f} px away); click on the object")


def click_centre(scene: Scene, click: Click, diameter: float, samples: int = 4000) -> NDArray[np.float64]:
    """Object centre (mm, world) from a click: the visual hull around the middle of the depths along
    the click's ray that fall inside the most masks.

    Raises :class:`AutoalignError` when the click is outside its image, names an unknown image,
    is off the mask of its image (see :func:`check_click`) or its ray falls inside no mask at all.
    """
    check_click(scene, click)
    cam = scene.cameras[scene.image_ids.index(click.image_id)]
    d = cam.ray_directions(np.array([[click.u, click.v]]))[0]
    dist = np.linalg.norm(np.array([c.centre for c in scene.cameras]) - cam.centre, axis=1)
    far = max(float(dist.max()), 10.0 * diameter) * 2.0
    depth = np.linspace(1.0, far, samples)
    X = cam.centre + depth[:, None] * d
    support = _mask_support(scene, X)
    if support.max() == 0:
        raise AutoalignError(f"--click {click.image_id}:{click.u:g},{click.v:g}: the click's ray is off every mask; "
                             "click on the object")
    best = np.flatnonzero(support == support.max())
    # the longest run of best depths (contiguous), its middle
    runs = np.split(best, np.flatnonzero(np.diff(best) > 1) + 1)
    run = max(runs, key=len)
    # the click picks the object; the visual hull around that point centres it
    return hull_centre(scene, diameter, start=X[run[len(run) // 2]])


def rotation_grid(n: int) -> NDArray[np.float64]:
    """``n`` rotation matrices spread evenly over SO(3) (super-Fibonacci spiral, deterministic)."""
    phi = np.sqrt(2.0)
    psi = 1.533751168755204288118041
    i = np.arange(n) + 0.5
    s = i / n
    r = np.sqrt(s)
    R = np.sqrt(1.0 - s)
    alpha = 2.0 * np.pi * i / phi
    beta = 2.0 * np.pi * i / psi
    q = np.stack([r * np.sin(alpha), r * np.cos(alpha), R * np.sin(beta), R * np.cos(beta)], 1)  # x y z w
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
