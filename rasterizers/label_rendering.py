"""The labelled instances of one image ray-cast into one colour image (mitsuba, the product's ray
caster :class:`~autoalign.rasterizers.ray_casting.RayCaster`).

Every labelled object's mesh is placed at its label's pose (model-to-camera, mm) and one ray per
pixel centre is cast; the nearest surface wins. Pixels: the rays go through the pixel centres of
autoalign's internal convention (:mod:`autoalign.geometry.camera`: pixel (row i, col j) centred at
``(j + 0.5, i + 0.5)``) with the internal intrinsics ``K_from_opencv(cam_K)``, which is the ray
through ``cam_K^-1 [j, i, 1]`` of the OpenCV / BOP convention the files use
(tests/test_pixel_convention.py checks it against ``cv2.projectPoints``). The refine's renderer
(:mod:`autoalign.rasterizers`) casts its rays in the same convention; this one also gives each
pixel's instance, depth and colour, which the check needs for several objects at once.
tests/test_label_rendering.py checks it against open3d's ``RaycastingScene``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import K_from_opencv, uv_from_opencv, uv_to_opencv
from autoalign.geometry.se3 import make_pose
from autoalign.geometry.mesh import ColouredMesh
from autoalign.rasterizers.ray_casting import RayCaster, RayHits

Box = tuple[int, int, int, int]
"""Pixels ``(u0, v0, u1, v1)``: columns ``u0..u1 - 1``, rows ``v0..v1 - 1``."""


@dataclass
class Rendering:
    """A colour rendering of the labelled instances of one image (pixel grid of the photo).

    ``rgb``: (H, W, 3) uint8, background black. ``instance``: (H, W) int32, the instance number
    seen at each pixel (-1: background). ``depth``: (H, W) float32, camera z (mm) of the visible
    surface, inf on the background.
    """

    rgb: NDArray[np.uint8]
    instance: NDArray[np.int32]
    depth: NDArray[np.float32]


@dataclass
class PlacedMesh:
    """One labelled instance to render: its number, its mesh (model frame, mm) and its label's pose
    ``x_cam = R_m2c x_model + t_m2c`` (mm)."""

    instance: int
    mesh: ColouredMesh
    R_m2c: NDArray[np.float64]
    t_m2c: NDArray[np.float64]


def pixel_rays(K_internal: NDArray[np.float64], width: int, height: int, box: Box | None = None) -> NDArray[np.float32]:
    """Camera-frame ray directions (h*w, 3), row-major, through the centres ``(j + 0.5, i + 0.5)`` of the
    pixels of ``box`` (default: the whole ``width x height`` image), internal intrinsics
    ``K_internal``; unit z component, so the hit distance is the depth z (mm)."""
    u0, v0, u1, v1 = box if box is not None else (0, 0, width, height)
    Kinv = np.linalg.inv(np.asarray(K_internal, dtype=np.float64).reshape(3, 3))
    u, v = uv_from_opencv(np.arange(u0, u1)), uv_from_opencv(np.arange(v0, v1))  # the pixels' centres
    d = (v[:, None, None] * Kinv[:, 1] + Kinv[:, 2]) + u[None, :, None] * Kinv[:, 0]
    d = d / d[..., 2:3]
    return d.reshape(-1, 3).astype(np.float32)


def _projected_box(vertices_c: Sequence[NDArray[np.float64]], K_internal: NDArray[np.float64], width: int,
                   height: int) -> Box | None:
    """The pixels that rays may hit: the box of the vertices' projections (camera frame, mm) and a
    pixel more, within the image; the whole image when a vertex is not in front of the camera; None
    when the box misses the image. A ray hits a triangle only inside its projection, the hull of its
    vertices' projections."""
    V = np.concatenate([np.asarray(v, dtype=np.float64) for v in vertices_c]) if vertices_c else np.zeros((0, 3))
    if len(V) == 0:
        return None
    if not np.all(V[:, 2] > 1e-6) or not np.all(np.isfinite(V)):
        return 0, 0, width, height
    uvw = V @ K_internal.T
    u, v = uv_to_opencv(uvw[:, :2] / uvw[:, 2:3]).T  # pixel-index units
    box = (max(int(np.floor(u.min())) - 1, 0), max(int(np.floor(v.min())) - 1, 0),
           min(int(np.ceil(u.max())) + 2, width), min(int(np.ceil(v.max())) + 2, height))
    return box if box[0] < box[2] and box[1] < box[3] else None


@dataclass
class LabelHits:
    """The nearest labelled surface seen through each pixel of ``box`` (row-major, n pixels):
    ``index`` (n,) int32, the placed mesh's position in the list given (-1: none), and ``hits`` its
    triangle, barycentric coordinates and ray parameter ``t``, the depth z (mm; inf: none)."""

    box: Box
    index: NDArray[np.int32]
    hits: RayHits


class _CasterCache:
    """The ray casters of the last meshes rendered, by mesh identity: the check renders the same
    few models in every image, and a caster's BVH costs about 3 us a triangle to build."""

    def __init__(self, size: int = 32) -> None:
        self._size = size
        self._casters: OrderedDict[int, tuple[ColouredMesh, RayCaster]] = OrderedDict()

    def get(self, mesh: ColouredMesh) -> RayCaster:
        """The caster of ``mesh`` (kept alive here, so its id stays its own)."""
        key = id(mesh)
        if key in self._casters:
            self._casters.move_to_end(key)
        else:
            self._casters[key] = (mesh, RayCaster(mesh, watertight=True))
            if len(self._casters) > self._size:
                self._casters.popitem(last=False)
        return self._casters[key][1]


_CASTERS = _CasterCache()


def cast_labels(placed: Sequence[PlacedMesh], K: NDArray[np.float64], width: int, height: int) -> LabelHits | None:
    """One ray per pixel (:func:`pixel_rays`) of ``width x height`` with OpenCV / BOP ``cam_K`` ``K``
    (px), cast at each instance of ``placed`` within the box of its projection
    (:func:`_projected_box`: the other rays cannot hit it); the nearest hit wins. None when no
    instance's box meets the image."""
    K_internal = K_from_opencv(K)  # the one conversion from the file convention
    poses = [make_pose(np.asarray(p.R_m2c, dtype=np.float64), np.asarray(p.t_m2c, dtype=np.float64)) for p in placed]
    boxes = [_projected_box([p.mesh.vertices @ T[:3, :3].T + T[:3, 3]], K_internal, width, height)
             for p, T in zip(placed, poses, strict=True)]
    within = [b for b in boxes if b is not None]
    if not within:
        return None
    box = (min(b[0] for b in within), min(b[1] for b in within), max(b[2] for b in within), max(b[3] for b in within))
    rays = pixel_rays(K_internal, width, height, box)
    n, w = len(rays), box[2] - box[0]
    index = np.full(n, -1, dtype=np.int32)
    nearest = RayHits(np.full(n, np.inf, np.float32), np.zeros(n, np.int64), np.zeros((n, 2), np.float32))
    for k, (p, T, b) in enumerate(zip(placed, poses, boxes, strict=True)):
        if b is None:
            continue
        sel = ((np.arange(b[1], b[3]) - box[1])[:, None] * w + (np.arange(b[0], b[2]) - box[0])[None, :]).ravel()
        h = _CASTERS.get(p.mesh).first_hits(T, np.zeros(3), rays[sel])
        closer = h.t < nearest.t[sel]
        s = sel[closer]
        nearest.t[s], nearest.prim[s], nearest.bary[s], index[s] = h.t[closer], h.prim[closer], h.bary[closer], k
    return LabelHits(box, index, nearest)


def render_labels(placed: Sequence[PlacedMesh], K: NDArray[np.float64], width: int, height: int) -> Rendering:
    """Ray-cast the labelled instances ``placed`` into one colour image of ``width x height`` pixels,
    OpenCV / BOP ``cam_K`` ``K`` (px).

    The nearest surface among all objects at each pixel (:func:`cast_labels`); its colour is the
    barycentric blend ``(1-u-v) c0 + u c1 + v c2`` of the hit triangle's vertex colours. The rays'
    unit z component makes the hit's ray parameter its depth z (mm). Background is black with
    instance -1.
    """
    full = Rendering(np.zeros((height, width, 3), np.uint8), np.full((height, width), -1, np.int32),
                     np.full((height, width), np.inf, np.float32))
    cast = cast_labels(placed, K, width, height)
    if cast is None:
        return full
    u0, v0, u1, v1 = cast.box
    rgb, inst = _shade(cast, placed)
    full.rgb[v0:v1, u0:u1] = rgb.reshape(v1 - v0, u1 - u0, 3)
    full.instance[v0:v1, u0:u1] = inst.reshape(v1 - v0, u1 - u0)
    full.depth[v0:v1, u0:u1] = cast.hits.t.reshape(v1 - v0, u1 - u0)
    return full


def _shade(cast: LabelHits, placed: Sequence[PlacedMesh]) -> tuple[NDArray[np.uint8], NDArray[np.int32]]:
    """Per ray (n,): colour (n, 3) uint8 and instance number (-1: none) of the hits."""
    rgb = np.zeros((len(cast.index), 3), dtype=np.float32)
    inst = np.full(len(cast.index), -1, dtype=np.int32)
    for k, p in enumerate(placed):
        sel = np.flatnonzero(cast.index == k)
        if sel.size == 0:
            continue
        tri = p.mesh.faces[cast.hits.prim[sel]]
        u, v = cast.hits.bary[sel, 0:1], cast.hits.bary[sel, 1:2]
        C = p.mesh.colours
        rgb[sel] = (1.0 - u - v) * C[tri[:, 0]] + u * C[tri[:, 1]] + v * C[tri[:, 2]]
        inst[sel] = p.instance
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8), inst
