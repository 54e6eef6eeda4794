"""The labelled instances of one image ray-cast into one colour image (open3d ``RaycastingScene``).

Every labelled object's mesh is placed at its label's pose (model-to-camera, mm) and one ray per
pixel centre is cast; the nearest surface wins. Pixels: the rays go through the pixel centres of
autoalign's internal convention (:mod:`autoalign.geometry.camera`: pixel (row i, col j) centred at
``(j + 0.5, i + 0.5)``) with the internal intrinsics ``K_from_opencv(cam_K)``, which is the ray
through ``cam_K^-1 [j, i, 1]`` of the OpenCV / BOP convention the files use
(tests/test_pixel_convention.py checks it against ``cv2.projectPoints``). The refine's renderer
(:mod:`autoalign.rasterizers`) casts its rays in the same convention; this one also gives each
pixel's instance, depth and colour, which the check needs for several objects at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from autoalign.geometry.camera import K_from_opencv
from autoalign.io.models import ColouredMesh

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
    u = np.arange(u0, u1, dtype=np.float64) + 0.5
    v = np.arange(v0, v1, dtype=np.float64) + 0.5
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
    u, v = uvw[:, 0] / uvw[:, 2] - 0.5, uvw[:, 1] / uvw[:, 2] - 0.5  # nearest pixel centre: round(u - 0.5)
    box = (max(int(np.floor(u.min())) - 1, 0), max(int(np.floor(v.min())) - 1, 0),
           min(int(np.ceil(u.max())) + 2, width), min(int(np.ceil(v.max())) + 2, height))
    return box if box[0] < box[2] and box[1] < box[3] else None


def render_labels(placed: Sequence[PlacedMesh], K: NDArray[np.float64], width: int, height: int) -> Rendering:
    """Ray-cast the labelled instances ``placed`` into one colour image of ``width x height`` pixels,
    OpenCV / BOP ``cam_K`` ``K`` (px).

    One ray per pixel (:func:`pixel_rays`), cast only within the box of the objects' projections
    (:func:`_projected_box`: the other rays cannot hit); the nearest surface among all objects
    wins, its colour is the barycentric blend ``(1-u-v) c0 + u c1 + v c2`` of the hit triangle's
    vertex colours (open3d's ``primitive_uvs``). Background is black with instance -1.
    """
    K_internal = K_from_opencv(K)  # the one conversion from the file convention
    scene = o3d.t.geometry.RaycastingScene()
    gid_to_index: dict[int, int] = {}
    vertices_c = []
    for idx, p in enumerate(placed):
        V_c = p.mesh.vertices @ np.asarray(p.R_m2c, dtype=np.float64).T + np.asarray(p.t_m2c, dtype=np.float64)
        vertices_c.append(V_c)
        gid = scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(V_c, dtype=np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(p.mesh.faces, dtype=np.uint32)))
        gid_to_index[int(gid)] = idx
    full = Rendering(np.zeros((height, width, 3), np.uint8), np.full((height, width), -1, np.int32),
                     np.full((height, width), np.inf, np.float32))
    box = _projected_box(vertices_c, K_internal, width, height)
    if box is None:
        return full
    u0, v0, u1, v1 = box
    rays = np.zeros(((u1 - u0) * (v1 - v0), 6), dtype=np.float32)
    rays[:, 3:] = pixel_rays(K_internal, width, height, box)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    del rays
    rgb, inst, depth = _shade(hits, placed, gid_to_index)
    full.rgb[v0:v1, u0:u1] = rgb.reshape(v1 - v0, u1 - u0, 3)
    full.instance[v0:v1, u0:u1] = inst.reshape(v1 - v0, u1 - u0)
    full.depth[v0:v1, u0:u1] = depth.reshape(v1 - v0, u1 - u0)
    return full


def _shade(hits: dict[str, o3d.core.Tensor], placed: Sequence[PlacedMesh], gid_to_index: dict[int, int]
           ) -> tuple[NDArray[np.uint8], NDArray[np.int32], NDArray[np.float32]]:
    """Per ray (n,): colour (n, 3) uint8, instance (-1: none) and depth (mm, inf: none) of open3d's hits."""
    t_hit = hits["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    gids = hits["geometry_ids"].numpy().astype(np.int64)
    prims = hits["primitive_ids"].numpy().astype(np.int64)
    uvs = hits["primitive_uvs"].numpy()
    n = len(t_hit)
    rgb = np.zeros((n, 3), dtype=np.float32)
    inst = np.full(n, -1, dtype=np.int32)
    for gid, idx in gid_to_index.items():
        sel = np.flatnonzero(hit & (gids == gid))
        if sel.size == 0:
            continue
        p = placed[idx]
        tri = p.mesh.faces[prims[sel]]
        u, v = uvs[sel, 0:1], uvs[sel, 1:2]
        C = p.mesh.colours
        rgb[sel] = (1.0 - u - v) * C[tri[:, 0]] + u * C[tri[:, 1]] + v * C[tri[:, 2]]
        inst[sel] = p.instance
    depth = np.where(hit, t_hit, np.inf).astype(np.float32)
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8), inst, depth
