"""Synthetic BOP scenes with photos: textured objects on a textured table, rendered with mitsuba.

Every pixel's ray (through the pixel centre) is cast with mitsuba (:class:`~autoalign.rasterizers.ray_casting.RayCaster`)
at the table and at each object; the nearest hit colours the pixel with that surface's own solid
texture (:class:`~autoalign.experiments.scenes.stream.SolidTexture`; each object carries its own
base colour with colour texture, the table a wood-like brown varying in brightness), shaded by the angle to the ray, plus sensor noise. The
masks are cast independently with open3d (:func:`~autoalign.experiments.scenes.synthetic.raycast_visible_masks`),
and optionally the depth (mm) of the nearest hit.

The world frame has z up and the table top at z = 0; objects rest on their lowest point on a ring.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from autoalign.experiments.scenes.path_traced import (
    SEE_THROUGH,
    SPECULAR,
    PathTracing,
    facing_backdrop,
    path_traced_photos,
)
from autoalign.experiments.scenes.stream import DEPTH_SCALE, SolidTexture, table_mesh
from autoalign.experiments.scenes.synthetic import (
    pixel_rays,
    random_rotation,
    ring_cameras,
    write_multi_scene,
)
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import make_pose
from autoalign.rasterizers.ray_casting import RayCaster


@dataclass
class PhotoScene:
    """A written scene: its folder, cameras, meshes and true world-from-model poses (mm)."""

    folder: Path
    cameras: list[Camera]
    meshes: list[Mesh]
    poses: list[NDArray[np.float64]]
    masks: list[list[NDArray[np.bool_]]]


class TintedTexture:
    """A solid texture (:class:`SolidTexture`) around a base colour (RGB in [0, 1]); ``grey``: its
    variation is in brightness only (wood, fabric), else in colour too (print)."""

    def __init__(self, rng: np.random.Generator, base: NDArray[np.float64], contrast: float = 0.35,
                 grey: bool = False) -> None:
        self.tex = SolidTexture(rng)
        self.base = np.asarray(base, dtype=np.float64)
        self.contrast = contrast
        self.grey = grey

    def __call__(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        t = self.tex(X)
        if self.grey:
            return np.clip(self.base * (1.0 - self.contrast + 2.0 * self.contrast * t.mean(1, keepdims=True)), 0.0, 1.0)
        return np.clip(self.base * (1.0 - self.contrast) + self.contrast * t, 0.0, 1.0)


def place_on_table(meshes: Sequence[Mesh], rng: np.random.Generator, radius_mm: float | None = None,
                   upright: Sequence[bool] = (), at_rest: bool = False) -> list[NDArray[np.float64]]:
    """World-from-model poses: each mesh turned at random, resting on its lowest point, on a ring
    (radius 90 mm for up to 4 objects, growing with their number beyond: neighbours ~140 mm apart).
    A mesh whose ``upright`` entry is true stands on its model's -z side (glassware), turned about
    the vertical only. With ``at_rest`` every other mesh lies on one of its three likeliest stable
    faces (:attr:`Mesh.resting_downs`), as objects put down on a table do, turned about the vertical."""
    radius_mm = radius_mm if radius_mm is not None else 90.0 * max(1.0, len(meshes) / 4.0)
    poses = []
    for j, m in enumerate(meshes):
        a = 2 * np.pi * j / len(meshes) + rng.uniform(-0.2, 0.2)
        if j < len(upright) and upright[j]:
            c, s = np.cos(t := rng.uniform(0, 2 * np.pi)), np.sin(t)
            R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        elif at_rest and len(m.resting_downs):
            down = m.resting_downs[rng.integers(min(3, len(m.resting_downs)))]
            on_face = Rotation.align_vectors([[0.0, 0.0, -1.0]], [down])[0]
            R = (Rotation.from_rotvec([0.0, 0.0, rng.uniform(0, 2 * np.pi)]) * on_face).as_matrix()
        else:
            R = random_rotation(rng)
        low = float((m.vertices @ R.T)[:, 2].min())
        r = 0.0 if len(meshes) == 1 else radius_mm
        poses.append(make_pose(R, np.array([r * np.cos(a), r * np.sin(a), -low])))
    return poses


def render_photos(meshes: Sequence[Mesh], poses: Sequence[NDArray[np.float64]], cameras: Sequence[Camera],
                  rng: np.random.Generator, noise: float = 2.0, see_through: Sequence[int] = (),
                  clear: bool = False) -> tuple[list[NDArray[np.uint8]], list[NDArray[np.float64]]]:
    """Photos (BGR uint8) and depth (mm along the optical axis, 0 = nothing) of the meshes at
    ``poses`` on a table, each object with its own texture (module doc). The depth passes through
    the meshes at positions ``see_through`` onto what is behind them, as a structured-light or
    time-of-flight sensor's does through glass; the photos show them textured, or with ``clear`` as
    clear glass without refraction (:func:`_through_clear_glass`)."""
    table = table_mesh(700.0)
    shapes = [(table, np.eye(4), TintedTexture(rng, np.array([0.55, 0.42, 0.3]), 0.5, grey=True))]
    hues = rng.permutation(np.linspace(0, 179, len(meshes), endpoint=False) + rng.uniform(0, 180 / len(meshes)))
    for m, T, h in zip(meshes, poses, hues):
        hsv = np.uint8([[[int(h) % 180, int(rng.uniform(120, 230)), int(rng.uniform(120, 230))]]])
        base = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
        shapes.append((m, np.asarray(T, dtype=np.float64), TintedTexture(rng, base)))
    casters = [RayCaster(m) for m, _, _ in shapes]
    photos, depths = [], []
    for cam in cameras:
        o, d = pixel_rays(cam)
        dn = d / np.linalg.norm(d, axis=1, keepdims=True)
        hits = [c.first_hits(T, o, dn.astype(np.float32)) for c, (_, T, _) in zip(casters, shapes)]
        t_all = np.stack([h.t for h in hits]).astype(np.float64)
        near = np.argmin(t_all, 0)
        t = t_all[near, np.arange(len(dn))]
        rgb = np.full((len(dn), 3), 0.15)
        for j, ((mesh, T, tex), h) in enumerate(zip(shapes, hits)):
            sel = (near == j) & np.isfinite(t)
            if not sel.any():
                continue
            P = o + dn[sel] * t[sel, None]
            n = mesh.face_normals[h.prim[sel]] @ T[:3, :3].T
            shade = 0.35 + 0.65 * np.abs(np.einsum("ij,ij->i", n, dn[sel]))
            rgb[sel] = tex(P) * shade[:, None]
        if see_through:
            opaque = [j for j in range(len(shapes)) if j - 1 not in see_through]
            t_opaque = t_all[opaque].min(0)
            if clear:
                rgb = _through_clear_glass(rgb, shapes, hits, t_all, near, opaque, o, dn)
            t = t_opaque
        img = np.clip(rgb * 255.0 + rng.normal(0.0, noise, rgb.shape), 0, 255).round().astype(np.uint8)
        photos.append(img.reshape(cam.height, cam.width, 3)[:, :, ::-1].copy())
        z = np.where(np.isfinite(t), t * (dn @ cam.R_w2c[2]), 0.0)
        depths.append(z.reshape(cam.height, cam.width))
    return photos, depths


def _through_clear_glass(rgb: NDArray[np.float64], shapes: list, hits: list, t_all: NDArray[np.float64],
                         near: NDArray[np.int64], opaque: list[int], o: NDArray[np.float64],
                         dn: NDArray[np.float64]) -> NDArray[np.float64]:
    """``rgb`` where a see-through shape is nearest replaced by what lies behind it (the nearest
    opaque surface, shaded as :func:`render_photos` does), dimmed by 10%, brightened towards white
    where the glass is seen at a grazing angle (a Fresnel-like rim): clear glass without refraction."""
    out = rgb.copy()
    glass = ~np.isin(near, opaque) & np.isfinite(t_all.min(0))
    if not glass.any():
        return out
    behind = np.array(opaque)[np.argmin(t_all[opaque][:, glass], 0)]
    idx = np.nonzero(glass)[0]
    for j in np.unique(behind):
        sel = idx[behind == j]
        mesh, T, tex = shapes[j]
        t = t_all[j, sel]
        ok = np.isfinite(t)
        colour = np.full((len(sel), 3), 0.15)
        if ok.any():
            P = o + dn[sel[ok]] * t[ok, None]
            n = mesh.face_normals[hits[j].prim[sel[ok]]] @ T[:3, :3].T
            colour[ok] = tex(P) * (0.35 + 0.65 * np.abs(np.einsum("ij,ij->i", n, dn[sel[ok]])))[:, None]
        out[sel] = colour
    for j in set(range(len(shapes))) - set(opaque):  # the rim of each glass in front
        sel = np.nonzero(near == j)[0]
        if len(sel):
            mesh, T, _ = shapes[j]
            n = mesh.face_normals[hits[j].prim[sel]] @ T[:3, :3].T
            rim = (1.0 - np.abs(np.einsum("ij,ij->i", n, dn[sel]))) ** 3
            out[sel] = 0.9 * out[sel] + rim[:, None] * (1.0 - 0.9 * out[sel])
    return out


def near_one_viewpoint(n_views: int, rng: np.random.Generator, distance_mm: float = 700.0, elevation_deg: float = 40.0,
                       spread_deg: float = 8.0, width: int = 640, height: int = 480) -> list[Camera]:
    """``n_views`` cameras from nearly one viewpoint, as an RGB-D frame sequence held still (the
    YCB-Video kind): direction jittered by up to ``spread_deg``, distance by 5%."""
    from autoalign.experiments.scenes.synthetic import default_K
    from autoalign.geometry.camera import look_at

    cams = []
    for _ in range(n_views):
        az = np.radians(rng.uniform(-spread_deg, spread_deg))
        el = np.radians(elevation_deg + rng.uniform(-spread_deg, spread_deg) / 2)
        d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        target = np.array([0.0, 0.0, 30.0]) + rng.uniform(-20, 20, 3)
        cams.append(look_at(target + distance_mm * rng.uniform(0.95, 1.05) * d, target,
                            default_K(width, height, 0.9 * width), width, height, up=np.array([0.0, 0.0, 1.0])))
    return cams


def sensor_depth(z: NDArray[np.float64], rng: np.random.Generator, holes: float = 0.03,
                 blobs_on: NDArray[np.bool_] | None = None, blob_share: float = 0.3) -> NDArray[np.float64]:
    """Depth as a Kinect-class sensor measures it: noise growing with z squared
    (:class:`~autoalign.losses.depth.DepthNoise`), a share ``holes`` of pixels without a
    measurement, and the image registered one pixel off the colour camera. ``blobs_on``: pixels
    (H, W) where blobs of holes cover about ``blob_share`` of them (glass and metal return no
    measurement in patches)."""
    from autoalign.losses.depth import DepthNoise

    noisy = np.where(z > 0, z + rng.normal(0.0, 1.0, z.shape) * DepthNoise().sigma(z), 0.0)
    noisy[rng.random(z.shape) < holes] = 0.0
    if blobs_on is not None and blobs_on.any():
        field = cv2.GaussianBlur(rng.random(z.shape).astype(np.float32), (0, 0), 6.0)  # smooth noise: blobs
        noisy[blobs_on & (field < np.quantile(field[blobs_on], blob_share))] = 0.0
    return np.roll(noisy, 1, axis=1)


def write_photo_scene(folder: str | Path, meshes: Sequence[Mesh], n_views: int, seed: int = 0,
                      width: int = 640, height: int = 480, depth: bool = False,
                      dist_range: tuple[float, float] = (350.0, 600.0),
                      cameras: Sequence[Camera] | None = None, see_through: Sequence[int] = (),
                      clear: bool = False, materials: Sequence[str] = (), tracing: PathTracing | None = None,
                      upright: Sequence[bool] = (), at_rest: bool = False) -> PhotoScene:
    """A BOP scene folder (``scene_camera.json``, ``scene_gt.json``, ``mask_visib/``, ``rgb/``,
    optionally ``depth/`` with ``depth_scale``, measured as :func:`sensor_depth`) of ``meshes``
    (obj_id = position + 1) on a table, seen by ``cameras``, or by ``n_views`` cameras on a ring
    at 25-60 degrees elevation. The depth passes through the meshes at positions ``see_through``
    (glass: :func:`render_photos`, drawn ``clear`` or not), with blobs of holes on them (:func:`sensor_depth`).

    With ``materials`` (one of :data:`~.path_traced.MATERIALS` per mesh) the depth passes through
    the glass, has blobs of holes on glass and metal, and with ``tracing`` the photos are
    path-traced (:func:`~.path_traced.path_traced_photos`; with a backdrop, the ring's cameras in
    front of it, ``n_views`` of them). ``upright``: which meshes stand, ``at_rest``: the others lie on
    stable faces (:func:`place_on_table`)."""
    import json

    folder = Path(folder)
    rng = np.random.default_rng(seed)
    poses = place_on_table(meshes, rng, upright=upright, at_rest=at_rest)
    if cameras is not None:
        cams = list(cameras)
    else:
        backdrop = tracing.backdrop_y_mm if tracing is not None else None
        cams = ring_cameras(n_views if backdrop is None else 3 * n_views, rng, (25.0, 60.0), dist_range, None, width,
                            height, (0.0, 0.0, 30.0), jitter_mm=30.0)
        cams = cams if backdrop is None else facing_backdrop(cams, backdrop)[:n_views]
    if materials:
        see_through = [j for j, m in enumerate(materials) if m in SEE_THROUGH]
    masks = write_multi_scene(folder, meshes, list(range(1, len(meshes) + 1)), poses, cams)
    photos, depths = render_photos(meshes, poses, cams, rng, see_through=see_through, clear=clear)
    if tracing is not None:
        photos = path_traced_photos(meshes, poses, materials or ["opaque"] * len(meshes), cams, rng, tracing)
    (folder / "rgb").mkdir(exist_ok=True)
    for i, img in enumerate(photos):
        cv2.imwrite(str(folder / "rgb" / f"{i:06d}.png"), img)
    if depth:
        (folder / "depth").mkdir(exist_ok=True)
        holey = [j for j, m in enumerate(materials) if m in SPECULAR] if materials else list(see_through)
        glass = [np.any([masks[i][j] for j in holey], axis=0) if holey else None for i in range(len(cams))]
        for i, z in enumerate(sensor_depth(z, rng, blobs_on=g) for z, g in zip(depths, glass)):
            cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), np.round(z / DEPTH_SCALE).astype(np.uint16))
        cams_json = json.loads((folder / "scene_camera.json").read_text())
        for entry in cams_json.values():
            entry["depth_scale"] = DEPTH_SCALE
        (folder / "scene_camera.json").write_text(json.dumps(cams_json))
    return PhotoScene(folder, cams, list(meshes), poses, masks)
