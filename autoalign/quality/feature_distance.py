"""Ground-truth-free quality check of 6-DoF pose labels: the "feature distance" of ProgressLabeller.

For every image and every labelled instance the object's vertex-coloured mesh is rendered at the
label's pose (on black, occluded by the other labelled instances of the image), SIFT keypoints
are detected in the rendering and in the photo, matched (brute force, Lowe's ratio test 0.8), and
the matches whose keypoints lie within ``MAX_MATCH_PX`` (10 px) of each other are kept. The mean
image distance of the kept matches is the feature distance: a label that puts the object where
the photo shows it gives a small one (ProgressLabeller reports 1.95 px for its labels against
2.28 px for the dataset's own on HOPE). Objects without texture give few matches and are flagged
``too_few_matches`` instead of getting a number. Every view also gets the outline-to-edge distance
(:mod:`autoalign.quality.edge_distance`), which needs no texture.

Large photos: a photo of more than :data:`autoalign.io.bop.MAX_IMAGE_PIXELS` is read downscaled by the
same whole factor as ``autoalign refine`` reads its masks (area-averaged over whole blocks, its
masks and ``cam_K`` with it, so the pixel grid stays exact), and SIFT and the edge maps see only the
region around the labels' renderings, SIFT at most ``MAX_SIFT_PIXELS``: 24 views of 12-megapixel
photos are checked in well under 2 GB (README, "Large images"). Every distance, coordinate and px
parameter is then in the pixels of the photo as checked (``image_scale`` times the file's); a
photo the size of LM-O's (640 x 480) is checked whole and at full size, as before.

Conventions (as the BOP files):

* millimetres; OpenCV camera frame (x right, y down, z forward);
* ``scene_camera.json``: per image ``cam_K`` (9, px), ``cam_R_w2c`` (9, row-major), ``cam_t_w2c``
  (3, mm) with ``x_cam = R_w2c x_world + t_w2c`` (only ``cam_K`` is needed here);
* labels (a BOP ``scene_gt.json``): per image id a list of ``{"obj_id", "cam_R_m2c", "cam_t_m2c"}``,
  the model-to-camera pose ``x_cam = R_m2c x_model + t_m2c``; entry ``k`` of an image's list is
  instance ``k``, whose visible mask (optional) is ``mask_visib/{im_id:06d}_{k:06d}.png``;
* pixels: ``cam_K`` in the OpenCV / BOP convention, the centre of pixel (row i, col j) is at
  continuous coordinate ``(u, v) = (j, i)``; the ray of pixel (i, j) goes through ``K^-1 [j, i, 1]``.
  Keypoint positions (OpenCV) use the same convention.

Nothing here imports torch or jax.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
import trimesh
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import K_from_opencv, K_to_opencv
from autoalign.io.bop import (
    MAX_IMAGE_PIXELS,
    Label,
    downscale_factor,
    mask_path,
    photo_path,
    read_cameras,
    read_labels,
    read_masks,
    read_photo,
)
from autoalign.quality.edge_distance import (
    BLUR_SIGMA_PX,
    CANNY_HIGH,
    CANNY_LOW,
    MAX_EDGE_PX,
    MIN_OUTLINE_PX,
    ORIENTATION_BINS,
    PhotoEdges,
    outline_edge_distances,
    outline_pixels,
    photo_edges,
)
from autoalign.quality.overlap import iou_from_counts

RATIO_TEST = 0.8
"""Lowe's ratio: a match is kept when its descriptor distance is below this times the second best's."""
MAX_MATCH_PX = 10.0
"""A kept match's keypoints are closer than this in the image (px)."""
BBOX_MARGIN_PX = 10
"""The rendered object's bounding box is dilated by this many pixels on every side."""
SILHOUETTE_MARGIN_PX = 3
"""Rendering keypoints must lie within this many pixels of the instance's own visible silhouette
(not on another instance that occludes it, nor on the black background far from it)."""
UPSAMPLE = 2
"""Both images are enlarged this many times (bilinear) before SIFT: LM-O-sized objects (50-150 px
across at 640x480) give three to four times more matches than at native size (measured on LM-O
scene 2); keypoint positions are mapped back to the original pixels."""
MAX_SIFT_PIXELS = 640 * 480 * UPSAMPLE ** 2
"""SIFT sees at most this many pixels (an LM-O photo enlarged ``UPSAMPLE`` times): a photo larger than
640 x 480 is searched only in its region around the labels (``CONTEXT_PX``), enlarged ``UPSAMPLE``
times while that fits and reduced to fit otherwise (SIFT's own pyramid of a 12-megapixel photo
enlarged twice took 11 GB and 24 s)."""
CONTEXT_PX = 32
"""The region searched in a photo larger than 640 x 480: the labels' rendered pixels' box dilated by
this many pixels (more than ``BBOX_MARGIN_PX`` plus ``MAX_EDGE_PX`` and SIFT's border, so that the
features and edges near the outlines are those of the whole photo)."""
MIN_MATCHES = 10
"""An instance with fewer kept matches than this over all its views is flagged ``too_few_matches``."""
N_BOOTSTRAP = 1000
"""Bootstrap resamples for the 95% confidence intervals."""
GREY = (0.5, 0.5, 0.5)
"""Colour (RGB, 0..1) of a mesh without vertex colours."""


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------

@dataclass
class ColouredMesh:
    """A triangle mesh in its model frame (mm) with one RGB colour (0..1) per vertex."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    colours: NDArray[np.float32]
    has_colours: bool
    path: Path | None = None


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
class ViewInstanceCheck:
    """The check of one instance in one image.

    ``iou``: IoU of the rendered visible silhouette with ``mask_visib`` (None without a mask file).
    ``n_matches``: kept matches; ``mean_px``: their mean keypoint distance (px, None without
    matches); ``ci95``: its 95% bootstrap interval over the matches (None below 2 matches);
    ``offset_px``: mean (du, dv) photo keypoint minus rendering keypoint (px; a systematic offset
    hints at a translation error). ``bbox``: (u0, v0, u1, v1) pixel box (exclusive end) of the
    rendered visible silhouette dilated by ``BBOX_MARGIN_PX``, None when nothing is visible.
    ``matches``: (n, 4) float (u_render, v_render, u_photo, v_photo) of the kept matches (OpenCV px).
    ``edge_px``: mean outline-to-edge distance (px, :mod:`autoalign.quality.edge_distance`; None below
    ``MIN_OUTLINE_PX`` outline pixels); ``edge_distances``: per outline pixel; ``outline_rc``: the
    outline pixels (row, col).
    """

    image_id: int
    instance: int
    obj_id: int
    iou: float | None
    n_matches: int
    mean_px: float | None
    ci95: tuple[float, float] | None = None
    offset_px: tuple[float, float] | None = None
    visible_px: int = 0
    bbox: tuple[int, int, int, int] | None = None
    n_render_keypoints: int = 0
    n_photo_keypoints: int = 0
    matches: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)), repr=False, compare=False)
    edge_px: float | None = None
    edge_distances: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False, compare=False)
    outline_rc: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64), repr=False,
                                          compare=False)

    @property
    def distances_px(self) -> NDArray[np.float64]:
        """Image distance (px) of each kept match."""
        return np.hypot(self.matches[:, 2] - self.matches[:, 0], self.matches[:, 3] - self.matches[:, 1])

    def record(self) -> dict[str, Any]:
        """A JSON-ready dict (without the match list)."""
        return {"image_id": self.image_id, "instance": self.instance, "obj_id": self.obj_id,
                "iou": _num(self.iou), "n_matches": self.n_matches, "mean_px": _num(self.mean_px),
                "ci95": _pair(self.ci95), "offset_px": _pair(self.offset_px), "visible_px": self.visible_px,
                "bbox": list(self.bbox) if self.bbox is not None else None,
                "n_render_keypoints": self.n_render_keypoints, "n_photo_keypoints": self.n_photo_keypoints,
                "edge_px": _num(self.edge_px), "outline_px": int(len(self.edge_distances))}


@dataclass
class InstanceSummary:
    """One instance over all checked images.

    ``mean_px``: mean distance (px) of all its kept matches, pooled over the views; None when
    ``too_few_matches`` (fewer than ``MIN_MATCHES`` kept matches: an untextured object, or a bad
    label). ``ci95``: 95% bootstrap interval of ``mean_px`` over the views (over the matches when
    only one view has any). ``views``: images where the instance is labelled; ``views_with_matches``:
    those with at least one kept match. ``median_iou``: over the views with a mask (None if none).
    ``offset_px``: mean (du, dv) photo minus rendering over the kept matches (px).
    ``edge_px``: mean outline-to-edge distance (px) pooled over the views' outline pixels, with its
    95% bootstrap interval over the views ``edge_ci95``; None when no view has an outline to judge.
    """

    instance: int
    obj_id: int
    mean_px: float | None
    ci95: tuple[float, float] | None
    n_matches: int
    views: int
    median_iou: float | None
    too_few_matches: bool
    views_with_matches: int = 0
    offset_px: tuple[float, float] | None = None
    edge_px: float | None = None
    edge_ci95: tuple[float, float] | None = None
    views_with_outline: int = 0

    def record(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {"instance": self.instance, "obj_id": self.obj_id, "mean_px": _num(self.mean_px),
                "ci95": _pair(self.ci95), "n_matches": self.n_matches, "views": self.views,
                "views_with_matches": self.views_with_matches, "median_iou": _num(self.median_iou),
                "too_few_matches": self.too_few_matches, "offset_px": _pair(self.offset_px),
                "edge_px": _num(self.edge_px), "edge_ci95": _pair(self.edge_ci95),
                "views_with_outline": self.views_with_outline}


@dataclass
class CheckReport:
    """The check of a scene: every (image, instance), the per-instance summaries, and the pooled
    mean feature distance (px) over the instances with enough matches, with its 95% bootstrap
    interval over the (image, instance) views; ``edge_px`` / ``edge_ci95`` the same for the
    outline-to-edge distance over every judged view."""

    scene_dir: Path
    labels_path: Path
    models_dir: Path
    image_ids: list[int]
    views: list[ViewInstanceCheck]
    instances: list[InstanceSummary]
    mean_px: float | None
    ci95: tuple[float, float] | None
    n_matches: int
    seed: int = 0
    warnings: list[str] = field(default_factory=list)
    edge_px: float | None = None
    edge_ci95: tuple[float, float] | None = None
    image_scales: dict[int, float] = field(default_factory=dict)
    max_pixels: int | None = MAX_IMAGE_PIXELS

    @property
    def image_scale(self) -> float | None:
        """The photos as checked over the files' resolution when all images share it (else None):
        1 unless they have more than ``max_pixels`` pixels (then 1/2, 1/3, ...)."""
        scales = set(self.image_scales.values()) or {1.0}
        return scales.pop() if len(scales) == 1 else None

    def record(self) -> dict[str, Any]:
        """The JSON-ready contents of ``check.json``."""
        return {
            "scene": str(self.scene_dir), "labels": str(self.labels_path), "models": str(self.models_dir),
            "image_ids": list(self.image_ids),
            "image_scale": self.image_scale,
            "pixels": "every px value, pixel coordinate and px parameter is in pixels of the photos as checked: "
                      "image_scale times the files' resolution (photos over max_image_pixels are read downscaled "
                      "by a whole factor, area-averaged, masks and cam_K with them, as autoalign refine reads "
                      "masks); divide by image_scale for the files' pixels",
            "mean_px": _num(self.mean_px), "ci95": _pair(self.ci95), "n_matches": self.n_matches,
            "edge_px": _num(self.edge_px), "edge_ci95": _pair(self.edge_ci95),
            "instances": [s.record() for s in self.instances],
            "views": [{**v.record(), "image_scale": self.image_scales.get(v.image_id, 1.0)} for v in self.views],
            "parameters": {"ratio_test": RATIO_TEST, "max_match_px": MAX_MATCH_PX, "bbox_margin_px": BBOX_MARGIN_PX,
                           "silhouette_margin_px": SILHOUETTE_MARGIN_PX, "upsample": UPSAMPLE, "min_matches": MIN_MATCHES,
                           "n_bootstrap": N_BOOTSTRAP, "seed": self.seed,
                           "canny_low": CANNY_LOW, "canny_high": CANNY_HIGH, "blur_sigma_px": BLUR_SIGMA_PX,
                           "orientation_bins": ORIENTATION_BINS, "max_edge_px": MAX_EDGE_PX,
                           "min_outline_px": MIN_OUTLINE_PX, "max_image_pixels": self.max_pixels,
                           "max_sift_pixels": MAX_SIFT_PIXELS, "context_px": CONTEXT_PX},
            "pixel_convention": "OpenCV/BOP: cam_K and keypoint positions put the centre of pixel (row i, col j) at (j, i)",
            "warnings": list(self.warnings),
        }


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _pair(p: tuple[float, float] | None) -> list[float | None] | None:
    return None if p is None else [_num(p[0]), _num(p[1])]


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def load_coloured_mesh(path: str | Path) -> ColouredMesh:
    """A mesh file (mm) with its per-vertex colours (``trimesh.load(path, process=False)`` keeps
    them in their vertex order); face colours are spread to the vertices, and a mesh without
    colours is grey (``has_colours`` False)."""
    path = Path(path)
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds
        raise AutoalignError(f"{path}: cannot read the mesh ({exc}); give a PLY/OBJ/GLB mesh in mm") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise AutoalignError(f"{path}: has no triangles; the check renders the object, give a triangle mesh")
    V = np.asarray(loaded.vertices, dtype=np.float64)
    F = np.asarray(loaded.faces, dtype=np.int64)
    colours: NDArray[np.float32] | None = None
    visual = loaded.visual
    kind = getattr(visual, "kind", None)
    try:
        if kind == "texture":
            visual = visual.to_color()
            kind = getattr(visual, "kind", None)
        if kind in ("vertex", "face"):
            c = np.asarray(visual.vertex_colors)
            if c.shape[0] == len(V):
                colours = (c[:, :3].astype(np.float32) / 255.0)
    except Exception:  # a broken texture: fall back to grey
        colours = None
    has = colours is not None
    if colours is None:
        colours = np.tile(np.asarray(GREY, dtype=np.float32), (len(V), 1))
    return ColouredMesh(V, F, colours, has, path)


def model_path(models_dir: Path, obj_id: int) -> Path:
    """BOP model file of an object: ``MODELS_DIR/obj_{obj_id:06d}.ply``."""
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


def load_models(models_dir: str | Path, obj_ids: Sequence[int], labels_path: Path | None = None) -> dict[int, ColouredMesh]:
    """The coloured meshes of ``obj_ids`` from a BOP models folder (``obj_{id:06d}.ply``, mm)."""
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise AutoalignError(f"{models_dir}: not a folder; --models must be a BOP models folder with "
                             "obj_XXXXXX.ply meshes (mm)")
    out = {}
    for obj in sorted(set(obj_ids)):
        p = model_path(models_dir, obj)
        if not p.is_file():
            named = f" (named in {labels_path})" if labels_path is not None else ""
            raise AutoalignError(f"{p}: not found; every obj_id of the labels{named} needs its mesh "
                                 f"{p.name} (mm) in --models")
        out[obj] = load_coloured_mesh(p)
    return out


@dataclass
class ScaledPhoto:
    """A photo as checked: ``bgr`` (h, w, 3) uint8 at ``1 / factor`` of the file's ``size`` (H, W)."""

    bgr: NDArray[np.uint8]
    factor: int
    size: tuple[int, int]


def read_photo_scaled(path: Path, max_pixels: int | None = MAX_IMAGE_PIXELS) -> ScaledPhoto:
    """A photo (BGR) downscaled by :func:`autoalign.io.bop.downscale_factor` when it has more than
    ``max_pixels`` pixels: each output pixel is the mean of a ``factor x factor`` block, the last
    blocks padded with the edge pixels, so that output pixel (i, j) covers exactly the file's
    pixels ``[j f, (j+1) f) x [i f, (i+1) f)`` as :meth:`autoalign.geometry.camera.Camera.scaled` assumes
    (:func:`autoalign.io.bop.read_masks` does the same to the masks, padding with zeros)."""
    img = read_photo(path)
    H, W = img.shape[:2]
    f = downscale_factor(W, H, max_pixels)
    if f > 1:
        h, w = -(-H // f), -(-W // f)
        if (h * f, w * f) != (H, W):
            img = cv2.copyMakeBorder(img, 0, h * f - H, 0, w * f - W, cv2.BORDER_REPLICATE)
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)  # exact block means at a whole factor
    return ScaledPhoto(img, f, (H, W))


def scaled_K(K: NDArray[np.float64], factor: int) -> NDArray[np.float64]:
    """OpenCV / BOP ``cam_K`` of the image read at ``1 / factor`` (:func:`read_photo_scaled`): scaled in
    autoalign's internal convention (pixel edges on integers, see :mod:`autoalign.geometry.camera`), so a file
    ``cx`` becomes ``(cx + 0.5) / factor - 0.5``."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if factor == 1:
        return K
    return K_to_opencv(np.diag([1.0 / factor, 1.0 / factor, 1.0]) @ K_from_opencv(K))


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------

def pixel_rays(K: NDArray[np.float64], width: int, height: int,
               box: tuple[int, int, int, int] | None = None) -> NDArray[np.float32]:
    """Camera-frame ray directions (H*W, 3), row-major, of every pixel (of ``box`` = (u0, v0, u1, v1),
    end exclusive, if given); pixel (i, j) goes through ``K^-1 [j, i, 1]`` (OpenCV / BOP: pixel
    centres at integer coordinates); unit z component, so the hit distance is the depth z (mm)."""
    u0, v0, u1, v1 = box if box is not None else (0, 0, width, height)
    Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64).reshape(3, 3))
    u = np.arange(u0, u1, dtype=np.float64)
    v = np.arange(v0, v1, dtype=np.float64)
    d = (v[:, None, None] * Kinv[:, 1] + Kinv[:, 2]) + u[None, :, None] * Kinv[:, 0]
    d = d / d[..., 2:3]
    return d.reshape(-1, 3).astype(np.float32)


def _projected_box(vertices_c: Sequence[NDArray[np.float64]], K: NDArray[np.float64], width: int,
                   height: int) -> tuple[int, int, int, int] | None:
    """The pixels (u0, v0, u1, v1), end exclusive, that rays may hit: the box of the vertices'
    projections (camera frame, mm) and a pixel more, within the image; the whole image when a
    vertex is not in front of the camera; None when the box misses the image. A ray hits a
    triangle only inside its projection, the hull of its vertices' projections."""
    V = np.concatenate([np.asarray(v, dtype=np.float64) for v in vertices_c]) if vertices_c else np.zeros((0, 3))
    if len(V) == 0:
        return None
    if not np.all(V[:, 2] > 1e-6) or not np.all(np.isfinite(V)):
        return 0, 0, width, height
    uvw = V @ np.asarray(K, dtype=np.float64).reshape(3, 3).T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    box = (max(int(np.floor(u.min())) - 1, 0), max(int(np.floor(v.min())) - 1, 0),
           min(int(np.ceil(u.max())) + 2, width), min(int(np.ceil(v.max())) + 2, height))
    return box if box[0] < box[2] and box[1] < box[3] else None


def render_labels(objects: Sequence[tuple[int, ColouredMesh, NDArray[np.float64], NDArray[np.float64]]],
                  K: NDArray[np.float64], width: int, height: int) -> Rendering:
    """Ray-cast ``(instance, mesh, R_m2c, t_m2c)`` objects into one colour image (camera frame, mm).

    One ray per pixel (:func:`pixel_rays`), cast only within the box of the objects' projections
    (:func:`_projected_box`: the other rays cannot hit); the nearest surface among all objects
    wins, its colour is the barycentric blend ``(1-u-v) c0 + u c1 + v c2`` of the hit triangle's
    vertex colours (open3d's ``primitive_uvs``). Background is black with instance -1.
    """
    scene = o3d.t.geometry.RaycastingScene()
    gid_to_index: dict[int, int] = {}
    placed = []
    for idx, (_, mesh, R, t) in enumerate(objects):
        V_c = mesh.vertices @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64)
        placed.append(V_c)
        gid = scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(V_c, dtype=np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
        gid_to_index[int(gid)] = idx
    full = Rendering(np.zeros((height, width, 3), np.uint8), np.full((height, width), -1, np.int32),
                     np.full((height, width), np.inf, np.float32))
    box = _projected_box(placed, K, width, height)
    if box is None:
        return full
    u0, v0, u1, v1 = box
    w, h = u1 - u0, v1 - v0
    n = w * h
    rays = np.zeros((n, 6), dtype=np.float32)
    rays[:, 3:] = pixel_rays(K, width, height, box)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    del rays
    t_hit = ans["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    gids = ans["geometry_ids"].numpy().astype(np.int64)
    prims = ans["primitive_ids"].numpy().astype(np.int64)
    uvs = ans["primitive_uvs"].numpy()
    rgb = np.zeros((n, 3), dtype=np.float32)
    inst = np.full(n, -1, dtype=np.int32)
    for gid, idx in gid_to_index.items():
        sel = np.flatnonzero(hit & (gids == gid))
        if sel.size == 0:
            continue
        instance, mesh, _, _ = objects[idx]
        tri = mesh.faces[prims[sel]]
        u, v = uvs[sel, 0:1], uvs[sel, 1:2]
        C = mesh.colours
        rgb[sel] = (1.0 - u - v) * C[tri[:, 0]] + u * C[tri[:, 1]] + v * C[tri[:, 2]]
        inst[sel] = instance
    depth = np.where(hit, t_hit, np.inf).astype(np.float32)
    img = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    full.rgb[v0:v1, u0:u1] = img.reshape(h, w, 3)
    full.instance[v0:v1, u0:u1] = inst.reshape(h, w)
    full.depth[v0:v1, u0:u1] = depth.reshape(h, w)
    return full


# --------------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------------

@dataclass
class Features:
    """SIFT keypoint positions (n, 2) (u, v OpenCV px) and descriptors (n, 128) float32."""

    uv: NDArray[np.float64]
    descriptors: NDArray[np.float32]

    def subset(self, keep: NDArray[np.bool_]) -> "Features":
        return Features(self.uv[keep], self.descriptors[keep])

    def moved(self, du: float, dv: float) -> "Features":
        """The same keypoints with (du, dv) px added to their positions (a crop's to the photo's)."""
        return Features(self.uv + [du, dv], self.descriptors)


def sift_features(gray: NDArray[np.uint8], upsample: float = UPSAMPLE) -> Features:
    """SIFT keypoints (``cv2.SIFT_create`` defaults) of a grey image resized ``upsample`` times
    (bilinear when enlarged, area-averaged when reduced; pixel centres aligned); positions in the
    original image's OpenCV pixels."""
    s = float(upsample)
    big = gray if s == 1 else cv2.resize(gray, None, fx=s, fy=s,
                                         interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
    kps, desc = cv2.SIFT_create().detectAndCompute(big, None)
    del big
    if desc is None or not kps:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    uv = np.array([k.pt for k in kps], dtype=np.float64)
    return Features((uv + 0.5) / s - 0.5, desc.astype(np.float32))


def sift_scale(width: int, height: int) -> float:
    """How many times an image region ``width x height`` is resized for SIFT: ``UPSAMPLE`` while the
    result has at most ``MAX_SIFT_PIXELS``, else the factor (below ``UPSAMPLE``) that brings it there."""
    if width * height * UPSAMPLE ** 2 <= MAX_SIFT_PIXELS:
        return float(UPSAMPLE)
    return math.sqrt(MAX_SIFT_PIXELS / (width * height))


def photo_sift(photo_bgr: NDArray[np.uint8]) -> Features:
    """:func:`sift_features` of a BGR photo (grey levels)."""
    return sift_features(cv2.cvtColor(photo_bgr, cv2.COLOR_BGR2GRAY))


def match_features(render: Features, photo: Features, ratio: float = RATIO_TEST,
                   max_px: float = MAX_MATCH_PX) -> NDArray[np.float64]:
    """Matches (n, 4) ``(u_r, v_r, u_p, v_p)``: each rendering keypoint's nearest photo descriptor
    (``cv2.BFMatcher``, L2) that passes Lowe's ratio test and lies closer than ``max_px`` (px)."""
    if len(render.uv) == 0 or len(photo.uv) < 2:
        return np.zeros((0, 4))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(render.descriptors, photo.descriptors, k=2)
    rows = []
    for pair in pairs:
        if len(pair) < 2:
            continue
        m, second = pair
        if m.distance < ratio * second.distance:
            rows.append((*render.uv[m.queryIdx], *photo.uv[m.trainIdx]))
    if not rows:
        return np.zeros((0, 4))
    out = np.asarray(rows, dtype=np.float64)
    d = np.hypot(out[:, 2] - out[:, 0], out[:, 3] - out[:, 1])
    return out[d < max_px]


def _in_box(uv: NDArray[np.float64], box: tuple[int, int, int, int]) -> NDArray[np.bool_]:
    u0, v0, u1, v1 = box
    return (uv[:, 0] >= u0 - 0.5) & (uv[:, 0] < u1 - 0.5) & (uv[:, 1] >= v0 - 0.5) & (uv[:, 1] < v1 - 0.5)


def _at_pixels(uv: NDArray[np.float64], image: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``image`` at the pixel nearest each (u, v) (OpenCV: pixel centres at integers)."""
    H, W = image.shape
    j = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, W - 1)
    i = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, H - 1)
    return image[i, j]


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------

def bootstrap_mean_ci(values: NDArray[np.float64], rng: np.random.Generator,
                      n_boot: int = N_BOOTSTRAP) -> tuple[float, float] | None:
    """95% percentile bootstrap interval of the mean of ``values`` (None below 2 values)."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < 2:
        return None
    idx = rng.integers(0, values.size, size=(n_boot, values.size))
    means = values[idx].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def bootstrap_pooled_ci(groups: Sequence[NDArray[np.float64]], rng: np.random.Generator,
                        n_boot: int = N_BOOTSTRAP) -> tuple[float, float] | None:
    """95% bootstrap interval of the pooled mean of several groups (views), resampling whole
    groups; with a single non-empty group it resamples that group's values instead."""
    groups = [np.asarray(g, dtype=np.float64) for g in groups if len(g) > 0]
    if not groups:
        return None
    if len(groups) == 1:
        return bootstrap_mean_ci(groups[0], rng, n_boot)
    sums = np.array([g.sum() for g in groups])
    counts = np.array([g.size for g in groups], dtype=np.float64)
    idx = rng.integers(0, len(groups), size=(n_boot, len(groups)))
    means = sums[idx].sum(axis=1) / counts[idx].sum(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def pooled_mean_ci(groups: Sequence[NDArray[np.float64]], rng: np.random.Generator
                   ) -> tuple[float | None, tuple[float, float] | None]:
    """The mean of all values of ``groups`` (views) pooled, and its :func:`bootstrap_pooled_ci`;
    ``(None, None)`` without groups."""
    if not groups:
        return None, None
    return float(np.concatenate(groups).mean()), bootstrap_pooled_ci(groups, rng)


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------

def check_image(image_id: int, photo_bgr: NDArray[np.uint8], K: NDArray[np.float64], labels: Sequence[Label],
                meshes: Mapping[int, ColouredMesh], masks: Mapping[int, NDArray[np.bool_]] | None = None,
                seed: int = 0, photo_features: Features | None = None,
                edges: PhotoEdges | None = None) -> tuple[Rendering, list[ViewInstanceCheck]]:
    """Check every label of one image against its photo (BGR, OpenCV ``cam_K`` in px, poses in mm).

    ``masks``: instance -> visible mask (H, W) bool, for the IoU (instances without one get None).
    ``photo_features``: the photo's :func:`sift_features` (photo pixels), when already computed
    (several label sets checked against one photo); ``edges``: its
    :func:`autoalign.quality.edge_distance.photo_edges`, likewise (covering the labels' outlines). A photo
    of 640 x 480 or less is searched whole; a larger one only in the box of the labels' rendered
    pixels dilated by ``CONTEXT_PX`` (:func:`sift_scale` sets SIFT's resolution there). Returns the
    rendering of all labels together and one :class:`ViewInstanceCheck` per label.
    """
    H, W = photo_bgr.shape[:2]
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    objects = [(lab.instance, meshes[lab.obj_id], lab.R_m2c, lab.t_m2c) for lab in labels]
    rendering = render_labels(objects, K, W, H)
    region = _search_region(rendering.instance)
    u0, v0, u1, v1 = region if region is not None else (0, 0, 0, 0)
    inst_map = rendering.instance[v0:v1, u0:u1]  # the labels' pixels all lie in the region
    render_feats = photo_feats = Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    if region is not None:
        scale = sift_scale(u1 - u0, v1 - v0)
        crop = np.ascontiguousarray(rendering.rgb[v0:v1, u0:u1])
        render_feats = sift_features(cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY), scale).moved(u0, v0)
        if photo_features is None:
            crop = np.ascontiguousarray(photo_bgr[v0:v1, u0:u1])
            photo_feats = sift_features(cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY), scale).moved(u0, v0)
        if edges is None:
            edges = photo_edges(photo_bgr[v0:v1, u0:u1], (v0, u0))
        del crop
    if photo_features is not None:
        photo_feats = photo_features
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SILHOUETTE_MARGIN_PX + 1,) * 2)
    out = []
    for lab in labels:
        sil = inst_map == lab.instance
        visible = int(np.count_nonzero(sil))
        iou = None
        if masks is not None and lab.instance in masks:
            m = np.asarray(masks[lab.instance], dtype=bool)
            area = int(np.count_nonzero(m))
            if area or visible:
                iou = float(iou_from_counts(np.count_nonzero(m[v0:v1, u0:u1] & sil), area, visible))
        check = ViewInstanceCheck(lab.image_id, lab.instance, lab.obj_id, iou, 0, None, visible_px=visible)
        if visible:
            rc = outline_pixels(inst_map, lab.instance)  # the region's border is the photo's or off the labels
            check.edge_distances = outline_edge_distances(edges, inst_map, lab.instance, rc, (v0, u0))
            check.outline_rc = rc + [v0, u0]
        if len(check.edge_distances) >= MIN_OUTLINE_PX:
            check.edge_px = float(check.edge_distances.mean())
        if visible:
            rows, cols = np.flatnonzero(sil.any(axis=1)) + v0, np.flatnonzero(sil.any(axis=0)) + u0
            box = (max(int(cols[0]) - BBOX_MARGIN_PX, 0), max(int(rows[0]) - BBOX_MARGIN_PX, 0),
                   min(int(cols[-1]) + 1 + BBOX_MARGIN_PX, W), min(int(rows[-1]) + 1 + BBOX_MARGIN_PX, H))
            near = cv2.dilate(sil.astype(np.uint8), kernel).astype(bool)
            r = render_feats.subset(_in_box(render_feats.uv, box))
            r = r.subset(_at_pixels(r.uv - [u0, v0], near))
            p = photo_feats.subset(_in_box(photo_feats.uv, box))
            matches = match_features(r, p)
            check.bbox, check.n_render_keypoints, check.n_photo_keypoints = box, len(r.uv), len(p.uv)
            check.matches, check.n_matches = matches, len(matches)
            if len(matches):
                d = check.distances_px
                check.mean_px = float(d.mean())
                check.offset_px = (float((matches[:, 2] - matches[:, 0]).mean()),
                                   float((matches[:, 3] - matches[:, 1]).mean()))
                check.ci95 = bootstrap_mean_ci(d, np.random.default_rng([seed, image_id, lab.instance]))
        out.append(check)
    return rendering, out


def _search_region(instance_map: NDArray[np.int32]) -> tuple[int, int, int, int] | None:
    """The region (u0, v0, u1, v1), end exclusive, of a photo that SIFT and the edge maps see: all of
    a photo of at most 640 x 480 (``MAX_SIFT_PIXELS / UPSAMPLE**2``); of a larger one, the box of the
    labels' rendered pixels dilated by ``CONTEXT_PX``, None when no label is in view."""
    H, W = instance_map.shape
    if W * H * UPSAMPLE ** 2 <= MAX_SIFT_PIXELS:
        return 0, 0, W, H
    seen = instance_map >= 0
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if rows.size == 0:
        return None
    return (max(int(cols[0]) - CONTEXT_PX, 0), max(int(rows[0]) - CONTEXT_PX, 0),
            min(int(cols[-1]) + 1 + CONTEXT_PX, W), min(int(rows[-1]) + 1 + CONTEXT_PX, H))


def summarize(views: Sequence[ViewInstanceCheck], seed: int = 0) -> list[InstanceSummary]:
    """Per-instance summaries (sorted by instance, then obj_id) of per-view checks."""
    keys = sorted({(v.instance, v.obj_id) for v in views})
    out = []
    for inst, obj in keys:
        mine = [v for v in views if v.instance == inst and v.obj_id == obj]
        groups = [v.distances_px for v in mine if v.n_matches]
        n = int(sum(v.n_matches for v in mine))
        ious = [v.iou for v in mine if v.iou is not None]
        too_few = n < MIN_MATCHES
        mean = ci = offset = None
        if not too_few:
            allm = np.concatenate([v.matches for v in mine if v.n_matches])
            mean, ci = pooled_mean_ci(groups, np.random.default_rng([seed, 1_000_003, inst, obj]))
            offset = (float((allm[:, 2] - allm[:, 0]).mean()), float((allm[:, 3] - allm[:, 1]).mean()))
        edges = [v.edge_distances for v in mine if v.edge_px is not None]
        edge, edge_ci = pooled_mean_ci(edges, np.random.default_rng([seed, 3_000_017, inst, obj]))
        out.append(InstanceSummary(inst, obj, mean, ci, n, len(mine), float(np.median(ious)) if ious else None,
                                   too_few, len(groups), offset, edge, edge_ci, len(edges)))
    return out


def select_images(image_ids: Sequence[int], n: int | None) -> list[int]:
    """``n`` image ids spread evenly over ``image_ids`` (sorted; first and last included), or all."""
    ids = sorted(image_ids)
    if n is None or n >= len(ids):
        return ids
    if n <= 1:
        return ids[:max(n, 0)]
    picks = np.unique(np.rint(np.linspace(0, len(ids) - 1, n)).astype(int))
    return [ids[i] for i in picks]


@dataclass
class CheckInputs:
    """Everything a check reads before its first image, validated (:func:`prepare_check`): the labels
    (BOP ``scene_gt.json``, mm), the scene's cameras (file ``cam_K``, px), the images to check, their
    photos' paths and the meshes (mm) of the objects labelled there."""

    scene_dir: Path
    labels_path: Path
    models_dir: Path
    labels: dict[int, list[Label]]
    cameras: dict[int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
    image_ids: list[int]
    photos: dict[int, Path]
    meshes: dict[int, ColouredMesh]
    warnings: list[str] = field(default_factory=list)


def prepare_check(scene_dir: str | Path, labels_path: str | Path, models_dir: str | Path,
                  images: int | None = None, image_ids: Sequence[int] | None = None,
                  labels: Mapping[int, list[Label]] | None = None) -> CheckInputs:
    """Read and validate the inputs of a check (no photo is read, nothing is rendered).

    ``images``: check only that many images, spread evenly over the labelled ones (default all);
    ``image_ids``: or exactly these labelled images (then ``images`` is ignored); ``labels``: the
    labels file as :func:`autoalign.io.bop.read_labels` read it, if already read. Raises
    :class:`AutoalignError` (naming the file and the fix) for missing or malformed inputs.
    """
    scene_dir, labels_path, models_dir = Path(scene_dir), Path(labels_path), Path(models_dir)
    if not scene_dir.is_dir():
        raise AutoalignError(f"{scene_dir}: not a folder; give a BOP scene folder with scene_camera.json and rgb/")
    labels = dict(labels) if labels is not None else read_labels(labels_path)
    cameras = read_cameras(scene_dir)
    missing = [i for i in labels if i not in cameras]
    if missing:
        raise AutoalignError(f"{labels_path}: image {missing[0]} has no camera in {scene_dir / 'scene_camera.json'} "
                             f"({len(missing)} image(s) like this); label only images of the scene or add their cameras")
    labelled = [i for i, labs in labels.items() if labs]
    if not labelled:
        raise AutoalignError(f"{labels_path}: no image has a label; give a scene_gt.json with at least one pose")
    if image_ids is not None:
        unknown = [i for i in image_ids if i not in labelled]
        if unknown:
            raise AutoalignError(f"{labels_path}: image {unknown[0]} has no label; choose labelled images")
        chosen = sorted(set(int(i) for i in image_ids))
    else:
        chosen = select_images(labelled, images)
    photos = {im: photo_path(scene_dir, im) for im in chosen}
    meshes = load_models(models_dir, [lab.obj_id for i in chosen for lab in labels[i]], labels_path)
    warnings = [f"{m.path}: no vertex colours; rendered grey, so few matches are expected"
                for m in meshes.values() if not m.has_colours]
    return CheckInputs(scene_dir, labels_path, models_dir, labels, cameras, chosen, photos, meshes, warnings)


def check_prepared(inputs: CheckInputs, seed: int = 0, progress: Any = None,
                   max_pixels: int | None = MAX_IMAGE_PIXELS) -> CheckReport:
    """Check the labels of :func:`prepare_check`'s ``inputs`` on their photos, one image at a time
    (only one photo, its masks and its rendering are held at once).

    Photos and masks of more than ``max_pixels`` are read downscaled by a whole factor, ``cam_K``
    with them (:func:`read_photo_scaled`; ``None``: full size). ``progress``: optional
    ``callable(done, total)`` called before the first image and after each.
    """
    views: list[ViewInstanceCheck] = []
    scales: dict[int, float] = {}
    chosen = inputs.image_ids
    if progress is not None:
        progress(0, len(chosen))
    for n_done, im in enumerate(chosen, 1):
        photo = read_photo_scaled(inputs.photos[im], max_pixels)
        paths = {(im, lab.instance): mask_path(inputs.scene_dir, im, lab.instance) for lab in inputs.labels[im]}
        read = read_masks({k: p for k, p in paths.items() if p.is_file()}, max_pixels)
        if read.size is not None and read.size != photo.size:
            p = next(p for p in paths.values() if p.is_file())
            raise AutoalignError(f"{p}: mask is {read.size[1]}x{read.size[0]} but the photo is {photo.size[1]}x"
                                 f"{photo.size[0]}; masks must have the photo's size")
        masks = {inst: m for (_, inst), m in read.masks.items()}  # empty masks: none, as in autoalign.io.bop
        K = scaled_K(inputs.cameras[im][0], photo.factor)
        _, checks = check_image(im, photo.bgr, K, inputs.labels[im], inputs.meshes, masks, seed)
        views.extend(checks)
        scales[im] = 1.0 / photo.factor
        del photo, read, masks  # before the next image's are read
        if progress is not None:
            progress(n_done, len(chosen))
    instances = summarize(views, seed)
    ok = {(s.instance, s.obj_id) for s in instances if not s.too_few_matches}
    groups = [v.distances_px for v in views if v.n_matches and (v.instance, v.obj_id) in ok]
    n = int(sum(len(g) for g in groups))
    mean, ci = pooled_mean_ci(groups, np.random.default_rng([seed, 2_000_003]))
    edge, edge_ci = pooled_mean_ci([v.edge_distances for v in views if v.edge_px is not None],
                                   np.random.default_rng([seed, 4_000_037]))
    return CheckReport(inputs.scene_dir, inputs.labels_path, inputs.models_dir, chosen, views, instances, mean, ci, n,
                       seed, list(inputs.warnings), edge, edge_ci, scales, max_pixels)


def check_scene(scene_dir: str | Path, labels_path: str | Path, models_dir: str | Path,
                images: int | None = None, seed: int = 0, image_ids: Sequence[int] | None = None,
                progress: Any = None, max_pixels: int | None = MAX_IMAGE_PIXELS) -> CheckReport:
    """Check the labels of ``labels_path`` (BOP scene_gt.json, mm) on the photos of ``scene_dir``:
    :func:`prepare_check` then :func:`check_prepared` (see them for the arguments)."""
    return check_prepared(prepare_check(scene_dir, labels_path, models_dir, images, image_ids), seed, progress,
                          max_pixels)


# --------------------------------------------------------------------------------------------
# Figure
# --------------------------------------------------------------------------------------------

def _colour(instance: int) -> tuple[int, int, int]:
    """A distinct BGR colour per instance."""
    hue = (instance * 47) % 180
    hsv = np.uint8([[[hue, 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def match_figure(report: CheckReport, max_views: int = 4) -> NDArray[np.uint8]:
    """A BGR image of up to ``max_views`` checked photos (those with the most kept matches, in image
    order; read as they were checked, downscaled if large) with the kept matches: a line from the
    rendering keypoint (dot) to the photo keypoint,
    the label's visible outline, the dilated bounding box, and ``obj id: mean px (n), edge px`` per
    instance, in one colour per instance; two photos per row."""
    counts = {im: 0 for im in report.image_ids}
    for v in report.views:
        counts[v.image_id] = counts.get(v.image_id, 0) + v.n_matches
    ids = sorted(sorted(counts, key=lambda im: (-counts[im], im))[:max_views])
    tiles = []
    for im in ids:
        img = read_photo_scaled(photo_path(report.scene_dir, im), report.max_pixels).bgr  # as checked
        img = (img.astype(np.float32) * 0.6).astype(np.uint8)
        for v in (c for c in report.views if c.image_id == im):
            col = _colour(v.instance)
            img[v.outline_rc[:, 0], v.outline_rc[:, 1]] = col
            if v.bbox is not None:
                u0, v0, u1, v1 = v.bbox
                cv2.rectangle(img, (u0, v0), (u1 - 1, v1 - 1), col, 1)
                text = f"{v.obj_id}: " + (f"{v.mean_px:.1f}px ({v.n_matches})" if v.mean_px is not None else "no match")
                text += f", edge {v.edge_px:.1f}px" if v.edge_px is not None else ""
                cv2.putText(img, text, (u0 + 2, max(v0 - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
            for ur, vr, up, vp in v.matches:
                a = (int(round(ur * 16)), int(round(vr * 16)))
                b = (int(round(up * 16)), int(round(vp * 16)))
                cv2.line(img, a, b, col, 1, cv2.LINE_AA, shift=4)
                cv2.circle(img, a, 2 * 16, col, -1, cv2.LINE_AA, shift=4)
        cv2.putText(img, f"image {im}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    if not tiles:
        return np.zeros((32, 32, 3), np.uint8)
    H = max(t.shape[0] for t in tiles)
    W = max(t.shape[1] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, H - t.shape[0], 0, W - t.shape[1], cv2.BORDER_CONSTANT) for t in tiles]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0])) if len(tiles) > 1 else None
    rows = [np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles), 2)]
    return np.vstack(rows)
