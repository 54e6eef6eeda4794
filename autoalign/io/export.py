"""BOP labels for every frame of a scene from its poses (``autoalign export``): ``scene_gt.json``,
``scene_gt_info.json``, ``mask/``, ``mask_visib/`` and optionally COCO annotations.

The definitions are the bop_toolkit's (``scripts/calc_gt_info.py``, ``calc_gt_masks.py``,
``calc_gt_coco.py``, ``bop_toolkit_lib/misc.py`` and ``visibility.py``), in image pixels whose
centres are at integer coordinates (OpenCV / BOP):

* ``mask``: the object's own silhouette in the image (rays cast through the pixel centres).
* ``mask_visib``: where the object's surface is the nearest of all labelled objects and, where a
  depth image exists, at most :data:`DELTA_MM` behind the measured surface (distances along the
  pixel's ray; a pixel without a measurement counts as visible, the toolkit's ``bop19`` mode).
* ``px_count_all``: silhouette pixels, including the part outside the image (the toolkit renders
  on a canvas three times the image's width and height; so does this);
  ``px_count_valid``: silhouette pixels in the image with a depth measurement (all of them when
  the scene has no depth); ``px_count_visib``: pixels of ``mask_visib``;
  ``visib_fract = px_count_visib / px_count_all``.
* ``bbox_obj`` / ``bbox_visib``: ``[x, y, w, h]`` with ``w = x_max - x_min`` (the toolkit's
  ``calc_2d_bbox``) over the whole silhouette (it may reach outside the image) / over
  ``mask_visib``; ``[-1, -1, -1, -1]`` for both when nothing is visible, as the toolkit does.

An object with no silhouette pixel in an image is out of view there: it gets no entry and no
mask, and the entries left are renumbered, so that mask file ``k`` is always entry ``k`` of that
image's ``scene_gt.json`` list (ProgressLabeller's export let the names drift from the list).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera, pixel_centres, uv_to_opencv
from autoalign.io.bop import (
    Label,
    depth_scales,
    photo_path,
    read_camera_file,
    read_depth,
)
from autoalign.io.models import ModelSet
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.outline import NEAR_MM
from autoalign.rasterizers.ray_casting import RayCaster

DELTA_MM = 15.0
"""Visibility tolerance against measured depth (mm): the bop_toolkit's default ``delta``."""

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class GtInfo:
    """One entry of ``scene_gt_info.json`` (see the module doc for the definitions)."""

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float

    def record(self) -> dict[str, Any]:
        return {"bbox_obj": list(self.bbox_obj), "bbox_visib": list(self.bbox_visib),
                "px_count_all": self.px_count_all, "px_count_valid": self.px_count_valid,
                "px_count_visib": self.px_count_visib, "visib_fract": self.visib_fract}


@dataclass
class FrameExport:
    """One image's exported labels: the in-view ones (renumbered) with their masks and info."""

    image_id: int
    labels: list[Label]
    masks: list[NDArray[np.bool_]]
    visib: list[NDArray[np.bool_]]
    info: list[GtInfo]
    out_of_view: int


def bop_bbox(xs: NDArray[np.int64], ys: NDArray[np.int64]) -> tuple[int, int, int, int]:
    """``[x, y, w, h]`` of pixel coordinates with ``w = x_max - x_min`` (bop_toolkit's ``calc_2d_bbox``)."""
    if len(xs) == 0:
        return (-1, -1, -1, -1)
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min()))


class FrameRenderer:
    """Ray-casts the labelled objects of one image at a time (mitsuba, one caster per model)."""

    def __init__(self, models: ModelSet, delta_mm: float = DELTA_MM) -> None:
        self.models = models
        self.delta_mm = float(delta_mm)
        self._casters: dict[int, RayCaster] = {}

    def _caster(self, obj_id: int) -> RayCaster:
        if obj_id not in self._casters:
            self._casters[obj_id] = RayCaster(self.models.mesh(obj_id))
        return self._casters[obj_id]

    def render(self, image_id: int, labels: list[Label], K_opencv: NDArray[np.float64], size: tuple[int, int],
               depth_mm: NDArray[np.float64] | None = None) -> FrameExport:
        """Masks and info of ``labels`` (model-to-camera poses) in an image of ``size`` (W, H) with
        intrinsics ``K_opencv``; ``depth_mm`` (H, W) is the measured depth (z, mm; 0 = none)."""
        W, H = size
        cam = Camera.from_opencv(K_opencv, np.eye(3), np.zeros(3), W, H)
        batch = CameraBatch.of([cam])
        silhouettes = []  # per label: (x0, y0, hit crop, distance crop) on the 3x canvas
        dist = np.full((len(labels), H, W), np.inf, dtype=np.float32)
        for k, lab in enumerate(labels):
            caster = self._caster(lab.obj_id)
            x0, y0, x1, y1 = _canvas_crop(cam, lab.T_cm, self.models.mesh(lab.obj_id).hull)
            gx, gy = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
            uv = pixel_centres(gx, gy)
            d = caster.pixel_depths(lab.T_cm, batch, np.zeros(len(uv), dtype=np.int64), uv).reshape(gy.shape)
            silhouettes.append((x0, y0, np.isfinite(d), d))
            ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
            if ix1 > ix0 and iy1 > iy0:
                dist[k, iy0:iy1, ix0:ix1] = d[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0]
        nearest = dist.min(axis=0) if len(labels) else np.full((H, W), np.inf, np.float32)
        measured = None
        if depth_mm is not None:
            centres = pixel_centres(*np.meshgrid(np.arange(W), np.arange(H)))
            rays = np.linalg.inv(cam.K) @ np.vstack([centres.T, np.ones(H * W)])
            measured = (depth_mm.ravel() * np.linalg.norm(rays, axis=0)).reshape(H, W)  # distance along the ray
        kept, masks, visib, info = [], [], [], []
        for k, (lab, (x0, y0, hit, d)) in enumerate(zip(labels, silhouettes)):
            mask = np.isfinite(dist[k])
            if not mask.any():
                continue  # out of view: no entry
            vis = mask & (dist[k] <= nearest)
            valid = int(np.count_nonzero(mask))
            if measured is not None:
                has = depth_mm > 0
                vis &= ~has | (dist[k] - measured <= self.delta_mm)
                valid = int(np.count_nonzero(mask & has))
            n_all, n_vis = int(np.count_nonzero(hit)), int(np.count_nonzero(vis))
            ys, xs = np.nonzero(hit)
            vys, vxs = np.nonzero(vis)
            nothing = (-1, -1, -1, -1)
            info.append(GtInfo(bop_bbox(xs + x0, ys + y0) if n_vis else nothing, bop_bbox(vxs, vys) if n_vis else nothing,
                               n_all, valid, n_vis, n_vis / n_all if n_all else 0.0))
            kept.append(replace(lab, instance=len(kept)))
            masks.append(mask)
            visib.append(vis)
        return FrameExport(image_id, kept, masks, visib, info, len(labels) - len(kept))


def _canvas_crop(cam: Camera, T_cm: NDArray[np.float64], hull: NDArray[np.float64]) -> tuple[int, int, int, int]:
    """``x0, y0, x1, y1`` (pixels, end exclusive) around the projected hull on the canvas three times
    the image's size (``[-W, 2W) x [-H, 2H)``); the whole canvas when the object reaches behind the camera."""
    W, H = cam.width, cam.height
    X = hull @ T_cm[:3, :3].T + T_cm[:3, 3]
    if np.any(X[:, 2] < NEAR_MM):
        return -W, -H, 2 * W, 2 * H
    uv = X @ cam.K.T
    uv = uv_to_opencv(uv[:, :2] / uv[:, 2:3])  # pixel-index units
    x0, y0 = np.floor(uv.min(0)).astype(int) - 1
    x1, y1 = np.ceil(uv.max(0)).astype(int) + 2
    return max(x0, -W), max(y0, -H), min(x1, 2 * W), min(y1, 2 * H)


# ---------------------------------------------------------------------------------------- files

def image_size(scene_dir: str | os.PathLike[str], image_id: int) -> tuple[int, int]:
    """``(W, H)`` of an image from its photo, else one of its masks, else its depth image (which
    :func:`~autoalign.io.bop.read_depth` then checks against it)."""
    scene_dir = Path(scene_dir)
    candidates = []
    try:
        candidates.append(photo_path(scene_dir, image_id))
    except AutoalignError:
        pass
    candidates += [*sorted((scene_dir / "mask_visib").glob(f"{image_id:06d}_*.png")), scene_dir / "depth" / f"{image_id:06d}.png"]
    for p in candidates:
        if p.is_file():
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise AutoalignError(f"{p}: cannot read the image; replace it with a readable PNG or JPEG")
            return int(img.shape[1]), int(img.shape[0])
    raise AutoalignError(f"{scene_dir}: image {image_id} has no rgb/, mask_visib/ or depth/ file to take its size "
                         "from; add its photo")


def export_frames(scene_dir: str | os.PathLike[str], labels: dict[int, list[Label]], models: ModelSet,
                  labels_path: str | os.PathLike[str], delta_mm: float = DELTA_MM, progress: Progress | None = None,
                  cameras_path: str | os.PathLike[str] | None = None) -> list[FrameExport]:
    """Render every image of ``labels`` (see :func:`autoalign.io.bop.read_labels`) of the scene, with
    the intrinsics of ``cameras_path`` (default ``scene_dir/scene_camera.json``)."""
    scene_dir, labels_path = Path(scene_dir), Path(labels_path)
    cameras_path = Path(cameras_path) if cameras_path is not None else scene_dir / "scene_camera.json"
    cams = read_camera_file(cameras_path)
    missing = sorted(set(labels) - set(cams))
    if missing:
        raise AutoalignError(f"{labels_path}: image(s) {', '.join(map(str, missing[:10]))} have no camera in "
                             f"{cameras_path}; label only the scene's images")
    for obj in sorted({lab.obj_id for ls in labels.values() for lab in ls}):
        if not models.path(obj).is_file():
            raise AutoalignError(f"{labels_path}: object {obj} has no model {models.path(obj)}; add it to --models "
                                 "or remove its entries")
    scales = depth_scales(scene_dir)
    renderer = FrameRenderer(models, delta_mm)
    out = []
    for n, (im, ls) in enumerate(labels.items()):
        size = image_size(scene_dir, im)
        out.append(renderer.render(im, ls, cams[im][0], size, read_depth(scene_dir, im, scales.get(im, 1.0), size)))
        if progress is not None:
            progress("rendering masks", n + 1, len(labels))
    return out


def _png(mask: NDArray[np.bool_]) -> bytes:
    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:
        raise AutoalignError("cannot encode a mask as PNG")
    return buf.tobytes()


def bop_files(frames: list[FrameExport]) -> dict[str, bytes]:
    """``scene_gt.json``, ``scene_gt_info.json``, ``mask/`` and ``mask_visib/`` of the frames."""
    gt, gt_info, files = {}, {}, {}
    for f in frames:
        gt[str(f.image_id)] = [{"obj_id": lab.obj_id, "cam_R_m2c": [float(x) for x in lab.R_m2c.ravel()],
                                "cam_t_m2c": [float(x) for x in lab.t_m2c]} for lab in f.labels]
        gt_info[str(f.image_id)] = [i.record() for i in f.info]
        for k, (m, v) in enumerate(zip(f.masks, f.visib)):
            files[f"mask/{f.image_id:06d}_{k:06d}.png"] = _png(m)
            files[f"mask_visib/{f.image_id:06d}_{k:06d}.png"] = _png(v)
    files["scene_gt.json"] = json.dumps(gt, indent=1).encode()
    files["scene_gt_info.json"] = json.dumps(gt_info, indent=1).encode()
    return files


def coco_annotations(frames: list[FrameExport], scene_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """COCO instance annotations of the visible masks (RLE, pycocotools), one image per BOP image
    (COCO image id = BOP image id); entries with no visible pixel get none, as in the bop_toolkit."""
    scene_dir = Path(scene_dir)
    from pycocotools import mask as coco_mask

    images, annotations, categories = [], [], set()
    for f in frames:
        H, W = f.visib[0].shape if f.visib else image_size(scene_dir, f.image_id)[::-1]
        try:
            name = str(photo_path(scene_dir, f.image_id).relative_to(scene_dir))
        except AutoalignError:
            name = f"rgb/{f.image_id:06d}.png"
        images.append({"id": f.image_id, "file_name": name, "width": int(W), "height": int(H)})
        for k, (lab, v) in enumerate(zip(f.labels, f.visib)):
            categories.add(lab.obj_id)
            if not v.any():
                continue
            rle = coco_mask.encode(np.asfortranarray(v.astype(np.uint8)))
            annotations.append({"id": len(annotations) + 1, "image_id": f.image_id, "category_id": lab.obj_id,
                                "segmentation": {"size": [int(x) for x in rle["size"]],
                                                 "counts": rle["counts"].decode("ascii")},
                                "area": int(coco_mask.area(rle)), "bbox": [float(x) for x in coco_mask.toBbox(rle)],
                                "iscrowd": 0, "bop_gt_index": k})
    return {"info": {"description": f"autoalign export of {scene_dir.name}"}, "licenses": [],
            "categories": [{"id": c, "name": str(c), "supercategory": "object"} for c in sorted(categories)],
            "images": images, "annotations": annotations}


def cameras_to_export(scene: str | os.PathLike[str], labels_path: str | os.PathLike[str],
                      given: str | os.PathLike[str] | None) -> Path:
    """The ``scene_camera.json`` to export: ``given``, else the one beside the labels (refine writes
    the cameras it corrected or scaled there), else the scene's. Cameras without a metric scale
    (the scene's ``recon.json`` says so) are refused: a BOP scene's translations are in mm."""
    from autoalign.scene.scale import cameras_up_to_scale

    scene, labels_path = Path(scene), Path(labels_path)
    given = Path(given) if given is not None else None
    beside = labels_path.parent / "scene_camera.json"
    path = given or (beside if beside.is_file() else scene / "scene_camera.json")
    if not path.is_file():
        raise AutoalignError(f"--cameras {path}: not found; pass a BOP scene_camera.json")
    if path.resolve() == (scene / "scene_camera.json").resolve() and cameras_up_to_scale(scene):
        raise AutoalignError(f"{scene / 'recon.json'}: the scene's cameras have no metric scale; export with the "
                             "scene_camera.json that 'autoalign refine' wrote beside its scene_gt.json (it solves "
                             "the scale), or give metric cameras with --cameras")
    return path


def cameras_of(cameras_path: str | os.PathLike[str], image_ids: set[int]) -> bytes:
    """``scene_camera.json`` with the entries of the images ``image_ids`` only, as they are in
    ``cameras_path``: a dataset of 12 of a scene's 24 images has 12 cameras."""
    cams = json.loads(Path(cameras_path).read_text())
    return json.dumps({k: v for k, v in cams.items() if int(k) in image_ids}, indent=1).encode()


@dataclass
class ExportedDataset:
    """What :func:`export_dataset` made: every file of the BOP scene folder (name relative to it ->
    bytes; nothing written yet) and the counts in ``export.json``."""

    files: dict[str, bytes]
    images: int
    entries: int
    dropped: int


def export_dataset(scene_dir: str | os.PathLike[str], labels_path: str | os.PathLike[str], models: ModelSet,
                   cameras_path: str | os.PathLike[str], coco: bool = False,
                   progress: Progress | None = None) -> ExportedDataset:
    """The files of a complete BOP scene folder for the labels in ``labels_path`` (a BOP
    ``scene_gt.json``): poses, masks, boxes (:func:`bop_files`), COCO annotations if ``coco``, the
    labelled images' cameras of ``cameras_path`` (see :func:`cameras_to_export`, :func:`cameras_of`),
    copies of their ``rgb/`` and ``depth/``, and ``export.json``. This is ``autoalign export`` and the label page's
    "Export"; the caller writes the files (atomically)."""
    import statistics
    import time

    from autoalign import __version__
    from autoalign.io.bop import read_labels

    scene_dir, labels_path, cameras_path = Path(scene_dir), Path(labels_path), Path(cameras_path)
    t0 = time.perf_counter()
    labels = read_labels(labels_path)
    frames = export_frames(scene_dir, labels, models, labels_path, progress=progress, cameras_path=cameras_path)
    files = bop_files(frames)
    if coco:
        files["scene_gt_coco.json"] = json.dumps(coco_annotations(frames, scene_dir)).encode()
    files["scene_camera.json"] = cameras_of(cameras_path, set(labels))
    for sub in ("rgb", "depth"):
        if (scene_dir / sub).is_dir():
            for f in sorted((scene_dir / sub).iterdir()):
                if f.is_file() and f.stem.isdigit() and int(f.stem) in labels:
                    files[f"{sub}/{f.name}"] = f.read_bytes()
    entries = sum(len(f.labels) for f in frames)
    dropped = sum(f.out_of_view for f in frames)
    summary = {"images": len(frames), "entries": entries, "out_of_view_dropped": dropped,
               "visib_fract_median": statistics.median([i.visib_fract for f in frames for i in f.info] or [0.0]),
               "labels": str(labels_path.absolute()), "models": str(models.folder.absolute()),
               "scene_dir": str(scene_dir.absolute()), "cameras": str(cameras_path.absolute()), "coco": bool(coco),
               "time_s": time.perf_counter() - t0}
    files["export.json"] = json.dumps({"autoalign_version": __version__, **summary}, indent=1).encode()
    return ExportedDataset(files, len(frames), entries, dropped)
