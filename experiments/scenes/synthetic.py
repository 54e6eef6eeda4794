"""Synthetic BOP-style scenes whose masks come from an independent renderer (open3d ray casting).

Conventions are those of :mod:`autoalign.geometry.camera`: OpenCV pinhole cameras, millimetres, pixel
``(row i, col j)`` centred at continuous coordinate ``(j + 0.5, i + 0.5)``, poses as 4x4
"a from b" matrices (``T_wm`` = world-from-model). The masks here are made by casting one ray
per pixel centre with open3d's ``RaycastingScene`` -- no autoalign renderer is involved, so
the scenes can serve as ground truth for the autoalign rasterizers and the refinement.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from autoalign.geometry.camera import Camera, look_at
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import Scene, mask_path, scene_gt_dict, scene_gt_of

MaskCorruption = Callable[[NDArray[np.bool_], np.random.Generator], NDArray[np.bool_]]


def default_K(width: int = 640, height: int = 480, f: float = 600.0) -> NDArray[np.float64]:
    """Pinhole intrinsics (pixels) with ``fx = fy = f`` and the principal point at the image centre."""
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def _unit_vectors(n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """``n`` directions uniform on the unit sphere."""
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sphere_cameras(n: int, rng: np.random.Generator, dist_range: tuple[float, float] = (300.0, 750.0),
                   K: ArrayLike | None = None, width: int = 640, height: int = 480,
                   target: ArrayLike = (0.0, 0.0, 0.0)) -> list[Camera]:
    """``n`` cameras all around ``target`` (world, mm), each looking straight at it.

    Viewing directions are uniform on the sphere, distances (mm) uniform in ``dist_range``.
    ``K`` defaults to ``fx = fy = 600``, ``cx = 320``, ``cy = 240``; ``target`` projects to the
    principal point of every camera.
    """
    K = default_K() if K is None else np.asarray(K, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    dirs = _unit_vectors(n, rng)
    dists = rng.uniform(dist_range[0], dist_range[1], size=n)
    return [look_at(target + d * r, target, K, width, height) for d, r in zip(dirs, dists)]


def ring_cameras(n: int, rng: np.random.Generator, elev_range_deg: tuple[float, float] = (20.0, 50.0),
                 dist_range: tuple[float, float] = (300.0, 750.0), K: ArrayLike | None = None,
                 width: int = 640, height: int = 480, target: ArrayLike = (0.0, 0.0, 0.0),
                 jitter_mm: float = 0.0) -> list[Camera]:
    """``n`` cameras on a ring above a table (world z up) looking down at ``target`` (mm).

    Azimuths cover 360 degrees (one per equal sector, random within the sector, random start);
    elevations (degrees above the xy-plane through ``target``) are uniform in ``elev_range_deg``
    and distances (mm) uniform in ``dist_range``. With ``jitter_mm > 0`` each camera looks at
    ``target`` plus a uniform offset in ``[-jitter_mm, jitter_mm]^3`` (its distance is measured to
    that jittered point), so the object is not always centred. Image y points downwards in
    world terms (``up = +z``).
    """
    K = default_K() if K is None else np.asarray(K, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    az = (rng.uniform(0.0, 2 * np.pi) + 2 * np.pi * (np.arange(n) + rng.uniform(0.0, 1.0, n)) / n) % (2 * np.pi)
    el = np.radians(rng.uniform(elev_range_deg[0], elev_range_deg[1], size=n))
    dists = rng.uniform(dist_range[0], dist_range[1], size=n)
    jit = rng.uniform(-jitter_mm, jitter_mm, size=(n, 3)) if jitter_mm > 0 else np.zeros((n, 3))
    cams = []
    for a, e, r, j in zip(az, el, dists, jit):
        d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        look = target + j
        cams.append(look_at(look + r * d, look, K, width, height, up=np.array([0.0, 0.0, 1.0])))
    return cams


# --------------------------------------------------------------------------------------------
# Ray-cast masks
# --------------------------------------------------------------------------------------------

def pixel_rays(cam: Camera) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World-frame ray origin (3,) and directions (H*W, 3) through every pixel centre.

    Row-major pixel order; pixel ``(i, j)`` uses continuous coordinate ``(u, v) = (j + 0.5, i + 0.5)``.
    Directions are ``R_w2c^T K^-1 (u, v, 1)`` (not normalised: unit camera-z component), evaluated
    as ``a u + b v + c`` with ``[a b c] = R_w2c^T K^-1`` (separable, no large matrix products).
    """
    return cam.centre, _box_ray_directions(cam, (0, 0, cam.width, cam.height))


def _box_ray_directions(cam: Camera, box: tuple[int, int, int, int]) -> NDArray[np.float64]:
    """:func:`pixel_rays`' directions of the pixels of ``box`` (``x0, y0, x1, y1``, row-major): the
    same operations on the same numbers, so each ray is the one the whole image's would be."""
    M = cam.R_w2c.T @ np.linalg.inv(cam.K)
    x0, y0, x1, y1 = box
    u = np.arange(x0, x1, dtype=np.float64) + 0.5
    v = np.arange(y0, y1, dtype=np.float64) + 0.5
    d = (v[:, None, None] * M[:, 1] + M[:, 2]) + u[None, :, None] * M[:, 0]
    return d.reshape(-1, 3)


def _hit_box(cam: Camera, points_w: NDArray[np.float64]) -> tuple[int, int, int, int]:
    """The pixels (``x0, y0, x1, y1``) whose centres can see ``points_w``' convex hull: every ray that
    hits a triangle of those points passes through its projection, inside their projections' box
    (plus a pixel); the whole image when a point is not in front of the camera."""
    X = points_w @ cam.R_w2c.T + cam.t_w2c
    if len(X) == 0 or np.any(X[:, 2] <= 1e-6):
        return 0, 0, cam.width, cam.height
    uv = (X @ cam.K.T)[:, :2] / X[:, 2:3]
    lo, hi = np.floor(uv.min(0) - 0.5) - 1, np.ceil(uv.max(0) - 0.5) + 2
    x0, y0 = (int(np.clip(c, 0, n)) for c, n in zip(lo, (cam.width, cam.height)))
    x1, y1 = (int(np.clip(c, 0, n)) for c, n in zip(hi, (cam.width, cam.height)))
    return x0, y0, max(x0, x1), max(y0, y1)


def _cast_box(scene: o3d.t.geometry.RaycastingScene, cam: Camera,
              box: tuple[int, int, int, int]) -> dict[str, NDArray]:
    """open3d's hits (``t_hit``, ``geometry_ids``) of the rays through the pixel centres of ``box``, as
    whole images (no hit outside the box: ``t_hit`` inf, ``geometry_ids`` invalid)."""
    x0, y0, x1, y1 = box
    t_hit = np.full((cam.height, cam.width), np.inf, dtype=np.float32)
    geom = np.full((cam.height, cam.width), o3d.t.geometry.RaycastingScene.INVALID_ID, dtype=np.uint32)
    if x1 > x0 and y1 > y0:
        d = _box_ray_directions(cam, box)
        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = cam.centre
        rays[:, 3:] = d
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t_hit[y0:y1, x0:x1] = hit["t_hit"].numpy().reshape(y1 - y0, x1 - x0)
        geom[y0:y1, x0:x1] = hit["geometry_ids"].numpy().reshape(y1 - y0, x1 - x0)
    return {"t_hit": t_hit, "geometry_ids": geom}


def _raycasting_scene(vertices_w: NDArray[np.float64], faces: NDArray[np.int64]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices_w, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


def raycast_masks(mesh: Mesh, T_wm: ArrayLike, cameras: Sequence[Camera]) -> list[NDArray[np.bool_]]:
    """Boolean (H, W) silhouettes of ``mesh`` (model frame, mm) placed by ``T_wm`` in each camera.

    One ray per pixel centre ``(j + 0.5, i + 0.5)``, built from ``K^-1`` and the camera pose and
    cast with open3d's ``RaycastingScene`` against the mesh transformed to the world frame;
    a pixel is set when the ray hits (finite ``t_hit``) in front of the camera. Only the pixels of
    the box around the mesh's projection are cast (:func:`_hit_box`): no other ray can hit it.
    """
    V_w = transform_points(T_wm, mesh.vertices)
    scene = _raycasting_scene(V_w, mesh.faces)
    # only the rays that can hit are cast (the box of the mesh's projection): each one is the ray
    # the whole image's casting would have cast, so the masks are the same, for a tenth of the rays
    return [np.isfinite(_cast_box(scene, cam, _hit_box(cam, V_w))["t_hit"]) for cam in cameras]


def make_scene(mesh: Mesh, T_wm: ArrayLike, cameras: Sequence[Camera]) -> Scene:
    """A :class:`autoalign.io.bop.Scene` of ray-cast masks (float32 0/1), image ids ``0..n-1``."""
    masks = [m.astype(np.float32) for m in raycast_masks(mesh, T_wm, cameras)]
    return Scene(list(cameras), masks, list(range(len(cameras))))


def write_scene(out_dir: str | Path, scene: Scene, T_wm: NDArray[np.float64], obj_id: int = 1,
                write_masks: bool = True) -> None:
    """Write ``scene`` as a BOP folder: ``scene_camera.json`` (OpenCV ``cam_K``), ``mask_visib`` PNGs of
    instance 0 (0/255) and ``scene_gt.json`` of the world-from-model pose ``T_wm`` (mm)."""
    out_dir = Path(out_dir)
    (out_dir / "mask_visib").mkdir(parents=True, exist_ok=True)
    cams = {}
    for im, cam in zip(scene.image_ids, scene.cameras):
        cams[str(im)] = {"cam_K": [float(x) for x in cam.K_opencv.ravel()],
                         "cam_R_w2c": [float(x) for x in cam.R_w2c.ravel()],
                         "cam_t_w2c": [float(x) for x in cam.t_w2c], "depth_scale": 1.0}
    if write_masks:
        for im, m in zip(scene.image_ids, scene.masks):
            cv2.imwrite(str(mask_path(out_dir, im, 0)), (np.asarray(m) > 0.5).astype(np.uint8) * 255)
    write_json_atomic(out_dir / "scene_camera.json", cams)
    write_json_atomic(out_dir / "scene_gt.json", scene_gt_dict(T_wm, scene.cameras, scene.image_ids, obj_id))


def write_synthetic_scene(out_dir: str | Path, mesh: Mesh, T_wm: ArrayLike, cameras: Sequence[Camera],
                          obj_id: int = 1) -> Scene:
    """Ray-cast a scene and write it as a BOP folder with :func:`write_scene`.

    Writes ``scene_camera.json``, ``scene_gt.json`` (the true ``T_wm``) and ``mask_visib/``.
    """
    scene = make_scene(mesh, T_wm, cameras)
    write_scene(out_dir, scene, np.asarray(T_wm, dtype=np.float64), obj_id=obj_id)
    scene.path = Path(out_dir)
    return scene


# --------------------------------------------------------------------------------------------
# Mask corruptions (each: (bool mask, rng) -> new bool mask)
# --------------------------------------------------------------------------------------------

def _bbox(mask: NDArray[np.bool_]) -> tuple[int, int, int, int] | None:
    """Inclusive-exclusive pixel bbox ``(r0, r1, c0, c1)`` of the set pixels, or None."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def translate_mask(mask: NDArray[np.bool_], dx: int, dy: int) -> NDArray[np.bool_]:
    """The mask moved by integer pixels ``dx`` (columns, right) and ``dy`` (rows, down); zero fill."""
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    out = np.zeros_like(mask)
    if abs(dx) >= W or abs(dy) >= H:
        return out
    out[max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] = \
        mask[max(-dy, 0):H + min(-dy, 0), max(-dx, 0):W + min(-dx, 0)]
    return out


def shift_mask(mask: NDArray[np.bool_], rng: np.random.Generator,
               shift_px: tuple[float, float] = (10.0, 30.0)) -> NDArray[np.bool_]:
    """Translate the mask by an integer offset of length in ``shift_px`` (pixels), random direction."""
    while True:
        ang = rng.uniform(0.0, 2 * np.pi)
        r = rng.uniform(*shift_px)
        dx, dy = int(round(r * np.cos(ang))), int(round(r * np.sin(ang)))
        if shift_px[0] <= np.hypot(dx, dy) <= shift_px[1]:
            return translate_mask(mask, dx, dy)


def _kernel(rng: np.random.Generator, sizes: Sequence[int]) -> NDArray[np.uint8]:
    k = int(rng.choice(np.asarray(sizes)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))


def erode_mask(mask: NDArray[np.bool_], rng: np.random.Generator,
               sizes: Sequence[int] = (7, 9, 11, 13, 15)) -> NDArray[np.bool_]:
    """Erode with an elliptical (disc) kernel of random odd size in 7..15 px (shrinks by (k-1)/2 px)."""
    m = np.asarray(mask, dtype=np.uint8)
    return cv2.erode(m, _kernel(rng, sizes), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def dilate_mask(mask: NDArray[np.bool_], rng: np.random.Generator,
                sizes: Sequence[int] = (7, 9, 11, 13, 15)) -> NDArray[np.bool_]:
    """Dilate with an elliptical (disc) kernel of random odd size in 7..15 px (grows by (k-1)/2 px)."""
    m = np.asarray(mask, dtype=np.uint8)
    return cv2.dilate(m, _kernel(rng, sizes), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def occluder_blob(mask: NDArray[np.bool_], rng: np.random.Generator,
                  coverage: tuple[float, float] = (0.2, 0.5), mode: str | None = None) -> NDArray[np.bool_]:
    """Remove (an occluder) or add (a false-positive blob) a filled axis-aligned ellipse.

    The ellipse lies inside the object's bounding box and its area is a random fraction in
    ``coverage`` of the bbox area. ``mode`` is ``"remove"``, ``"add"`` or None (random).
    An empty mask is returned unchanged.
    """
    mask = np.asarray(mask, dtype=bool)
    out = mask.copy()
    bb = _bbox(mask)
    if bb is None:
        return out
    r0, r1, c0, c1 = bb
    h, w = r1 - r0, c1 - c0
    frac = rng.uniform(*coverage)
    s = 4.0 * frac / np.pi  # product of the two semi-axis fractions: pi/4 sx sy = frac
    sx = rng.uniform(s, 1.0)
    sy = s / sx
    a, b = sx * w / 2.0, sy * h / 2.0  # semi-axes in pixels (x = columns, y = rows)
    cx = rng.uniform(c0 + a, c1 - a)
    cy = rng.uniform(r0 + b, r1 - b)
    jj, ii = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
    inside = ((jj - cx) / a) ** 2 + ((ii - cy) / b) ** 2 <= 1.0
    if mode is None:
        mode = "remove" if rng.uniform() < 0.5 else "add"
    if mode not in ("remove", "add"):
        raise ValueError(f"mode must be 'remove', 'add' or None, not {mode!r}")
    out[r0:r1, c0:c1][inside] = mode == "add"
    return out


CORRUPTIONS: dict[str, MaskCorruption] = {
    "shift": shift_mask,
    "erode": erode_mask,
    "dilate": dilate_mask,
    "occluder": occluder_blob,
}


def wiggle_mask(mask: NDArray[np.bool_], rng: np.random.Generator, amplitude_px: float = 1.0,
                correlation_px: float = 6.0) -> NDArray[np.bool_]:
    """``mask`` with a noisy outline, like a segmenter's: its signed distance (px, positive inside)
    plus a smooth random field of standard deviation ``amplitude_px`` whose bumps are about
    ``correlation_px`` wide, thresholded at zero. The outline moves in and out along its length."""
    m = mask.astype(np.uint8)
    sdf = cv2.distanceTransform(m, cv2.DIST_L2, 5) - cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    field = cv2.GaussianBlur(rng.standard_normal(mask.shape).astype(np.float32), (0, 0), correlation_px)
    field *= amplitude_px / max(float(field.std()), 1e-9)
    return (sdf + field) > 0


def corrupt_views(masks: Sequence[NDArray], fraction: float, rng: np.random.Generator,
                  kinds: Sequence[str | MaskCorruption] = ("shift", "erode", "dilate", "occluder"),
                  ) -> tuple[list[NDArray], list[int]]:
    """Corrupt exactly ``round(fraction * n)`` randomly chosen views with a random kind each.

    ``kinds`` are names in :data:`CORRUPTIONS` or callables ``(bool mask, rng) -> bool mask``.
    Masks may be bool or float (> 0.5 = object); each output keeps its input's kind (bool stays
    bool, anything else becomes float32 0/1). Returns the new list (all copies) and the sorted
    indices of the corrupted views.
    """
    n = len(masks)
    k = int(round(fraction * n))
    if not 0 <= k <= n:
        raise ValueError(f"fraction {fraction} of {n} views is out of range")
    fns = [CORRUPTIONS[c] if isinstance(c, str) else c for c in kinds]
    idx = sorted(int(i) for i in rng.choice(n, size=k, replace=False)) if k else []
    out = []
    for i, m in enumerate(masks):
        m = np.asarray(m)
        is_bool = m.dtype == bool
        b = m if is_bool else m > 0.5
        if i in idx:
            b = fns[int(rng.integers(len(fns)))](b, rng)
        out.append(b.copy() if is_bool else b.astype(np.float32))
    return out, idx


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------

def random_rotation(rng: np.random.Generator) -> NDArray[np.float64]:
    """A 3x3 rotation uniform on SO(3) (normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def axis_angle_matrix(axis: ArrayLike, angle_rad: float) -> NDArray[np.float64]:
    """Rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    A = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * A + (1.0 - np.cos(angle_rad)) * A @ A


def perturb_pose(T_wm: ArrayLike, trans_mm: float, rot_deg: float, rng: np.random.Generator,
                 centre: ArrayLike | None = None) -> NDArray[np.float64]:
    """A world-from-model pose off ``T_wm`` by exactly ``trans_mm`` and ``rot_deg``.

    ``centre`` is a model-frame point (mm; default the model origin, the bbox centre in BOP).
    The new pose maps it ``trans_mm`` away from where ``T_wm`` maps it, in a uniformly random
    direction, and its rotation differs by ``rot_deg`` about a uniformly random axis through that
    centre: ``T' = Tr(c_w + t) Rot(axis, rot) Tr(-c_w) T_wm`` with ``c_w = T_wm centre``.
    """
    T_wm = np.asarray(T_wm, dtype=np.float64)
    c_m = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    c_w = transform_points(T_wm, c_m[None])[0]
    t_dir, r_axis = _unit_vectors(2, rng)
    R = axis_angle_matrix(r_axis, np.radians(rot_deg))
    delta = make_pose(R, c_w + trans_mm * t_dir - R @ c_w)
    return delta @ T_wm


# --------------------------------------------------------------------------------------------
# Multi-object scenes
# --------------------------------------------------------------------------------------------

def raycast_visible_masks(meshes: Sequence[Mesh], poses: Sequence[ArrayLike],
                          cameras: Sequence[Camera]) -> list[list[NDArray[np.bool_]]]:
    """Visible masks ``[view][instance]`` of several meshes placed by ``poses``: open3d casts one
    ray per pixel centre against all of them, and a pixel belongs to the nearest surface hit."""
    scene, ids = _objects_scene(meshes, poses)
    V_w = np.concatenate([transform_points(T, m.vertices) for m, T in zip(meshes, poses)])
    out = []
    for cam in cameras:
        hit = _cast_box(scene, cam, _hit_box(cam, V_w))
        hit_any = np.isfinite(hit["t_hit"])
        out.append([hit_any & (hit["geometry_ids"] == g) for g in ids])
    return out


def _objects_scene(meshes: Sequence[Mesh],
                   poses: Sequence[ArrayLike]) -> tuple[o3d.t.geometry.RaycastingScene, list[int]]:
    scene = o3d.t.geometry.RaycastingScene()
    ids = [scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(transform_points(T, m.vertices), np.float32)),
                               o3d.core.Tensor(np.ascontiguousarray(m.faces, np.uint32)))
           for m, T in zip(meshes, poses)]
    return scene, ids


def _cast_pixels(scene: o3d.t.geometry.RaycastingScene, cam: Camera) -> dict[str, o3d.core.Tensor]:
    o, d = pixel_rays(cam)
    rays = np.empty((len(d), 6), dtype=np.float32)
    rays[:, :3] = o
    rays[:, 3:] = d
    return scene.cast_rays(o3d.core.Tensor(rays))


def shaded_photos(meshes: Sequence[Mesh], poses: Sequence[ArrayLike], cameras: Sequence[Camera],
                  colours_bgr: Sequence[tuple[int, int, int]]) -> list[NDArray[np.uint8]]:
    """Stand-in photos (BGR, H x W x 3) of the meshes placed by ``poses``: each object in its colour,
    shaded by the cosine between its surface normal and the pixel's ray (open3d ray casting), on
    a grey floor gradient; for pages and figures, not for measuring anything."""
    scene, ids = _objects_scene(meshes, poses)
    out = []
    for cam in cameras:
        hit = _cast_pixels(scene, cam)
        _, d = pixel_rays(cam)
        n = hit["primitive_normals"].numpy()
        cosine = np.abs((n * d).sum(1)) / np.linalg.norm(d, axis=1)
        geom = hit["geometry_ids"].numpy()
        hit_any = np.isfinite(hit["t_hit"].numpy())
        img = np.repeat(np.linspace(70, 110, cam.height)[:, None, None], cam.width, 1).repeat(3, 2)
        flat = img.reshape(-1, 3)
        for g, colour in zip(ids, colours_bgr):
            sel = hit_any & (geom == g)
            flat[sel] = (0.25 + 0.75 * cosine[sel, None]) * np.asarray(colour, np.float64)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def write_multi_scene(out_dir: str | Path, meshes: Sequence[Mesh], obj_ids: Sequence[int],
                      poses: Sequence[ArrayLike], cameras: Sequence[Camera],
                      masks: list[list[NDArray[np.bool_]]] | None = None) -> list[list[NDArray[np.bool_]]]:
    """A BOP scene folder of several objects: ``scene_camera.json``, ``scene_gt.json`` (every
    instance in every image, entry k = instance k) and ``mask_visib/{im:06d}_{k:06d}.png`` visible
    masks (written only where non-empty): ``masks`` ``[view][instance]`` if given (e.g. corrupted
    ones), else ray-cast with :func:`raycast_visible_masks`; returns the masks written."""
    out_dir = Path(out_dir)
    (out_dir / "mask_visib").mkdir(parents=True, exist_ok=True)
    if masks is None:
        masks = raycast_visible_masks(meshes, poses, cameras)
    ids = list(range(len(cameras)))
    write_scene(out_dir, Scene(list(cameras), [np.zeros((c.height, c.width), np.float32) for c in cameras], ids),
                np.eye(4), write_masks=False)
    for im, per_view in zip(ids, masks):
        for k, m in enumerate(per_view):
            if m.any():
                cv2.imwrite(str(out_dir / "mask_visib" / f"{im:06d}_{k:06d}.png"), m.astype(np.uint8) * 255)
    write_json_atomic(out_dir / "scene_gt.json", scene_gt_of(list(zip(obj_ids, poses)), list(cameras), ids))
    return masks
