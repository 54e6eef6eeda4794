"""Reading and writing BOP scene folders, with validation that names the file and the fix.

Layout read: ``SCENE/scene_camera.json`` (per image ``cam_K`` [9, px], ``cam_R_w2c`` [9, row-major],
``cam_t_w2c`` [3, mm]) and instance masks ``SCENE/mask_visib/{im_id:06d}_{inst:06d}.png``.
Layout written: ``scene_gt.json`` with ``cam_R_m2c`` / ``cam_t_m2c`` (mm) per image.

``cam_K`` is in the OpenCV / BOP pixel convention (centre of pixel (0, 0) at (0, 0)); it is
converted to autoalign's internal one on import and back on export (see :mod:`autoalign.geometry.camera`).

Mask files: a pixel is the object where the mask is non-zero (in any colour channel of a colour
image, or in the alpha channel of an image whose alpha is not the same everywhere). Grey-level
(0/255), 0/1, colour and alpha masks are all read correctly, but one scene must use one kind: a
mixture means files from different tools and is an error naming one file of each kind. A mask
that is empty everywhere is treated as missing (the segmenter found nothing), not as "the object
is absent", and is listed in ``Scene.empty``.
"""

from __future__ import annotations

import json
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import invert, make_pose
from autoalign.io.block_mean import Pad, block_mean


@dataclass(frozen=True)
class View:
    """What one view of one instance holds: what a pose is compared with there.

    Attributes:
        camera: the view's camera (world frame of ``scene_camera.json``, mm; internal pixel centres).
        mask: (H, W) float32 in [0, 1] (1 = object).
        image_id: the BOP image id.
        ignore: the pixels not compared (``None``: none).
        depth: measured depth (H, W) float32, mm along the optical axis, 0 = none (``None``: no depth).
        photo: (H, W, 3) uint8 BGR (``None``: not used as evidence).
    """

    camera: Camera
    mask: NDArray[np.float32]
    image_id: int
    ignore: NDArray[np.bool_] | None = None
    depth: NDArray[np.float32] | None = None
    photo: NDArray[np.uint8] | None = None


@dataclass
class Scene:
    """Calibrated views of one object instance.

    Attributes:
        cameras: one :class:`Camera` per view (world frame of ``scene_camera.json``, mm).
        masks: one (H, W) float32 array in [0, 1] per view (1 = object).
        image_ids: BOP image id of each view.
        path: the scene folder, if read from disk.
        skipped: image ids that had a camera but no mask file.
        empty: image ids whose mask file is empty (treated as missing, not used).
        image_scale: the masks and cameras are this fraction of the files' resolution (large
            images are downscaled on reading, see :data:`MAX_IMAGE_PIXELS`).
        ignore: per view, the pixels where the silhouette is not compared with the mask (``None``:
            none): those that another instance's mask claims, where this object may be hidden
            behind that one, or that mask may have strayed onto this object.
        depths: per view, the measured depth (H, W) float32 in mm along the optical axis at the
            masks' resolution, 0 where there is no measurement (``None``: no depth; see :func:`with_depth`).
        photos: per view, the photo (H, W, 3) uint8 BGR at the masks' resolution (``None``: the photos
            are not used as evidence; see :func:`autoalign.io.photos.with_photos`).
    """

    cameras: list[Camera]
    masks: list[NDArray[np.float32]]
    image_ids: list[int]
    path: Path | None = None
    skipped: tuple[int, ...] = ()
    empty: tuple[int, ...] = ()
    image_scale: float = 1.0
    ignore: list[NDArray[np.bool_]] | None = None
    depths: list[NDArray[np.float32]] | None = None
    photos: list[NDArray[np.uint8]] | None = None

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def views(self) -> list[View]:
        """One :class:`View` per view, in order: its camera, mask, image id, ignored pixels, depth and photo."""
        return [View(self.cameras[k], self.masks[k], self.image_ids[k],
                     None if self.ignore is None else self.ignore[k], None if self.depths is None else self.depths[k],
                     None if self.photos is None else self.photos[k]) for k in range(len(self))]

    @property
    def has_masks(self) -> bool:
        """Whether any view's mask is non-empty (> 0.5 somewhere)."""
        return any(np.any(np.asarray(m) > 0.5) for m in self.masks)

    def spread(self, k: int) -> NDArray[np.int64]:
        """Positions of at most ``k`` views evenly spread through the scene's order."""
        return np.unique(np.linspace(0, len(self) - 1, min(k, len(self))).round().astype(np.int64))

    def without_empty_masks(self) -> "Scene":
        """The views whose mask is not empty; the others' image ids are added to ``empty``.

        An empty mask means the segmenter found nothing there, not that the object is absent:
        compared as a target it would pull the silhouette out of that view.
        """
        keep = [i for i, m in enumerate(self.masks) if np.any(np.asarray(m) > 0.5)]
        if len(keep) == len(self):
            return self
        dropped = tuple(self.image_ids[i] for i in range(len(self)) if i not in set(keep))
        return replace(self.subset(keep), empty=tuple(sorted(self.empty + dropped)))

    def subset(self, idx: list[int] | NDArray[np.int64]) -> "Scene":
        """A scene with only the views at positions ``idx``."""
        idx = [int(i) for i in idx]
        return replace(self, cameras=[self.cameras[i] for i in idx], masks=[self.masks[i] for i in idx],
                       image_ids=[self.image_ids[i] for i in idx],
                       ignore=None if self.ignore is None else [self.ignore[i] for i in idx],
                       depths=None if self.depths is None else [self.depths[i] for i in idx],
                       photos=None if self.photos is None else [self.photos[i] for i in idx])

    def compared(self, k: int) -> NDArray[np.bool_] | None:
        """View ``k``'s pixels where the silhouette is compared with the mask (``None``: all)."""
        return None if self.ignore is None else ~self.ignore[k]


class _RepeatedKey(Exception):
    """A JSON object names one key twice (Python's json keeps the last silently)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(key)
        out[key] = value
    return out


def read_json_file(path: str | os.PathLike[str], what: str) -> Any:
    """The JSON document in ``path``; an error naming the file and ``what`` it should be if it is
    missing, not JSON, or names one key twice in an object (one of the two would be lost)."""
    path = Path(path)
    if not path.is_file():
        raise AutoalignError(f"{path}: not found; {what}")
    try:
        with open(path) as f:
            return json.load(f, object_pairs_hook=_unique_keys)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise AutoalignError(f"{path}: not valid JSON ({exc.msg if hasattr(exc, 'msg') else exc}); fix or regenerate the file") from None
    except _RepeatedKey as exc:
        raise AutoalignError(f"{path}: the key '{exc.args[0]}' appears twice in one object, and only one of them would "
                             "be read; merge or remove one") from None


def whole_number_keys(data: dict[str, Any], path: Path, what: str) -> dict[int, Any]:
    """``data`` keyed by the whole numbers its keys spell (``what`` names them: "image id"); an error
    for a key that is no whole number or two keys that spell the same one (``"0"`` and ``"00"``)."""
    out: dict[int, Any] = {}
    spelled: dict[int, str] = {}
    for key, value in data.items():
        try:
            k = int(key)
        except ValueError:
            raise AutoalignError(f"{path}: key '{key}' is not an {what}; keys must be whole numbers") from None
        if k in spelled:
            raise AutoalignError(f"{path}: keys '{spelled[k]}' and '{key}' both name {what} {k}; keep one of them")
        spelled[k], out[k] = key, value
    return out


def read_depth_png(path: Path, size: tuple[int, int], frame: str = "the image is") -> NDArray[Any]:
    """The raw values of the single-channel depth PNG ``path`` (times the scene's ``depth_scale`` =
    mm), which must be ``size = (W, H)`` like its colour image (``frame`` names that in the error)."""
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.ndim != 2:
        raise AutoalignError(f"{path}: not a single-channel depth image; write 16-bit PNG depth (times depth_scale = mm)")
    if d.dtype == np.uint8:  # 256 levels: at 1 mm a step, nothing beyond 25 cm; scaled, steps of centimetres
        raise AutoalignError(f"{path}: 8-bit depth (values 0-255) cannot hold the distances; write the sensor's "
                             "16-bit PNG depth (times depth_scale = mm)")
    if (d.shape[1], d.shape[0]) != tuple(size):
        raise AutoalignError(f"{path}: depth is {d.shape[1]}x{d.shape[0]} but {frame} {size[0]}x{size[1]}; "
                             "register the depth to the colour camera at its resolution")
    return d


def read_depth(scene_dir: str | os.PathLike[str], image_id: int, depth_scale: float,
               size: tuple[int, int]) -> NDArray[np.float64] | None:
    """The depth image of ``image_id`` in mm (``depth/{id:06d}.png`` times ``depth_scale``), or ``None``."""
    p = Path(scene_dir) / "depth" / f"{image_id:06d}.png"
    if not p.is_file():
        return None
    return read_depth_png(p, size).astype(np.float64) * depth_scale


def depth_scales(scene_dir: str | os.PathLike[str]) -> dict[int, float]:
    """``depth_scale`` per image id from ``scene_camera.json`` (BOP: depth times it is mm; default 1),
    each a positive number (else an error naming the image)."""
    path = Path(scene_dir) / "scene_camera.json"
    data = read_json_file(path, "a BOP scene folder needs scene_camera.json")
    out = {}
    for im, v in whole_number_keys(data if isinstance(data, dict) else {}, path, "image id").items():
        scale = v.get("depth_scale", 1.0) if isinstance(v, dict) else 1.0
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (0 < scale < float("inf")):
            raise AutoalignError(f"{path}: image {im} depth_scale {scale!r} is not a positive number; write the factor "
                                 "that makes a depth value mm (0.1 for 0.1 mm units)")
        out[im] = float(scale)
    return out


def with_depth(scene: Scene, read: dict[int, NDArray[np.float32] | None] | None = None) -> Scene:
    """``scene`` with the measured depth of each view (:attr:`Scene.depths`) from its folder's
    ``depth/{im:06d}.png`` and ``scene_camera.json``'s ``depth_scale``, resampled to the masks'
    resolution (nearest: depth is not averaged across an object's edge); ``scene`` unchanged
    when the folder has no ``depth/`` or a view has no depth file (then no view uses depth).
    ``read`` (image id -> depth at the masks' resolution) keeps what was read for the next scene
    of the same folder."""
    if scene.path is None or not (scene.path / "depth").is_dir():
        return scene
    read = {} if read is None else read
    scales = None
    for im, cam in zip(scene.image_ids, scene.cameras):
        if im not in read:
            scales = depth_scales(scene.path) if scales is None else scales
            size = (int(round(cam.width / scene.image_scale)), int(round(cam.height / scene.image_scale)))
            d = read_depth(scene.path, im, scales.get(im, 1.0), size)
            if d is not None and scene.image_scale != 1.0:
                d = cv2.resize(d, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
            read[im] = None if d is None else d.astype(np.float32)
    depths = [read[im] for im in scene.image_ids]
    if any(d is None for d in depths):
        return scene
    check_depth_units(scene, depths)
    return replace(scene, depths=depths)


DEPTH_UNITS_TOLERANCE = 2.0
"""The depth inside the masks may be at most this many times nearer or farther than where the masks'
rays meet: an object's surface lies well within that of its centre, while depth in the wrong unit
(0.1 mm read as mm, metres) is 10 or 1000 times off."""


def check_depth_units(scene: Scene, depths: list[NDArray[np.float32]]) -> None:
    """Raise, naming ``depth_scale``, when the median measured depth inside the masks is more than
    :data:`DEPTH_UNITS_TOLERANCE` times off the distance from the cameras to the point where the
    rays through the masks' centroids meet; the depth would pull every pose off (or fail it)."""
    X = masks_meeting_point(scene)
    if X is None:
        return
    ratios = []
    for view, d in zip(scene.views, depths):
        inside = (np.asarray(view.mask) > 0.5) & (d > 0)
        z = float(view.camera.to_camera(X[None])[0, 2])
        if inside.sum() >= 20 and z > 0:
            ratios.append(float(np.median(d[inside])) / z)
    if not ratios:
        return
    ratio = float(np.median(ratios))
    if 1.0 / DEPTH_UNITS_TOLERANCE <= ratio <= DEPTH_UNITS_TOLERANCE:
        return
    assert scene.path is not None  # with_depth reads only scenes read from a folder
    scale = depth_scales(scene.path).get(scene.image_ids[0], 1.0)
    raise AutoalignError(f"{scene.path / 'depth'}: the measured depth inside the masks is {ratio:.3g} times the "
                         f"cameras' distance to the object, so its unit is wrong; set depth_scale in "
                         f"{scene.path / 'scene_camera.json'} to the factor that makes a depth value mm (now {scale:g}; "
                         f"about {scale / ratio:.2g} would fit), or pass --depth off")


def masks_meeting_point(scene: Scene) -> NDArray[np.float64] | None:
    """The point (world, mm) nearest in least squares to the rays through the masks' centroids;
    ``None`` with fewer than two masks or rays too nearly parallel (within some 8 degrees) to meet."""
    A, b, n = np.zeros((3, 3)), np.zeros(3), 0
    for view in scene.views:
        ys, xs = np.nonzero(np.asarray(view.mask) > 0.5)
        if len(xs) == 0:
            continue
        d = view.camera.pixel_rays(xs.mean(), ys.mean())[0]
        P = np.eye(3) - np.outer(d, d)  # off the ray
        A, b, n = A + P, b + P @ view.camera.centre, n + 1
    if n < 2 or np.linalg.eigvalsh(A)[0] < 0.005 * n:
        return None
    return np.linalg.solve(A, b)
def json_floats(entry: dict[str, Any], key: str, n: int, path: Path, where: str, fix: str) -> NDArray[np.float64]:
    if key not in entry:
        raise AutoalignError(f"{path}: {where} has no '{key}'; {fix}")
    try:
        a = np.asarray(entry[key], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.size != n or not np.all(np.isfinite(a)):
        raise AutoalignError(f"{path}: {where} '{key}' must be {n} finite numbers; {fix}")
    return a


def read_cameras(scene_dir: str | os.PathLike[str]) -> dict[int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
    """``{im_id: (K, R_w2c, t_w2c)}`` from ``scene_dir/scene_camera.json`` (:func:`read_camera_file`)."""
    return read_camera_file(Path(scene_dir) / "scene_camera.json")


def read_camera_file(path: str | os.PathLike[str]) -> dict[int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
    """``{im_id: (K, R_w2c, t_w2c)}`` from a BOP ``scene_camera.json``, validated; ``K`` as in the
    file (OpenCV / BOP convention: build cameras with :meth:`Camera.from_opencv`)."""
    path = Path(path)
    fix = "every image needs cam_K (9 numbers), cam_R_w2c (9, row-major) and cam_t_w2c (3, mm)"
    data = read_json_file(path, f"a BOP scene folder needs scene_camera.json ({fix})")
    if not isinstance(data, dict) or not data:
        raise AutoalignError(f"{path}: expected an object mapping image ids to cameras; {fix}")
    out = {}
    for im_id, entry in whole_number_keys(data, path, "image id").items():
        key = str(im_id)
        if not isinstance(entry, dict):
            raise AutoalignError(f"{path}: image {key} is not an object; {fix}")
        where = f"image {key}"
        K = json_floats(entry, "cam_K", 9, path, where, fix).reshape(3, 3)
        R = json_floats(entry, "cam_R_w2c", 9, path, where, fix).reshape(3, 3)
        t = json_floats(entry, "cam_t_w2c", 3, path, where, fix)
        if not (K[0, 0] > 0 and K[1, 1] > 0) or np.any(K[2] != [0.0, 0.0, 1.0]) or K[1, 0] != 0:
            raise AutoalignError(f"{path}: image {key} cam_K must be [fx, s, cx, 0, fy, cy, 0, 0, 1] with "
                                 f"fx, fy > 0 (got fx={K[0, 0]:g}, fy={K[1, 1]:g}); fix the calibration")
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise AutoalignError(f"{path}: image {key} cam_R_w2c is not a rotation matrix; write it row-major with det +1")
        out[im_id] = (K, R, t)
    return dict(sorted(out.items()))


PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def find_photo(scene_dir: str | os.PathLike[str], image_id: int) -> Path | None:
    """The photo of an image, ``rgb/{image_id:06d}`` with suffix .png, .jpg, .jpeg, .tif or .tiff, if there
    is one; an error if there are two (which of them the labels were made on cannot be told)."""
    base = Path(scene_dir) / "rgb" / f"{image_id:06d}"
    found = [base.with_suffix(s) for s in PHOTO_SUFFIXES if base.with_suffix(s).is_file()]
    if len(found) > 1:  # which one is the photo of the labels is not ours to guess
        raise AutoalignError(f"{found[0]} and {found[1]}: two photos of image {image_id}; keep one of them in "
                             f"{base.parent} (remove or move the other)")
    return found[0] if found else None


def photo_path(scene_dir: str | os.PathLike[str], image_id: int) -> Path:
    """The photo of an image (:func:`find_photo`); an error if it has none."""
    found = find_photo(scene_dir, image_id)
    if found is not None:
        return found
    base = Path(scene_dir) / "rgb" / f"{image_id:06d}"
    raise AutoalignError(f"{base}.png (or .jpg): not found; the check compares renderings with the photos, "
                         f"put image {image_id}'s photo in {base.parent}")


def read_photo(path: str | os.PathLike[str]) -> NDArray[np.uint8]:
    """A photo as (H, W, 3) uint8 BGR (OpenCV order)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise AutoalignError(f"{path}: cannot read the photo; replace it with a PNG or JPEG")
    return img


def mask_path(scene_dir: str | os.PathLike[str], im_id: int, instance: int) -> Path:
    """BOP visible-mask path of one instance in one image."""
    return Path(scene_dir) / "mask_visib" / f"{im_id:06d}_{instance:06d}.png"


def read_mask(path: Path) -> tuple[NDArray[np.bool_], str]:
    """A mask file as a boolean image (non-zero = object) and its kind.

    Kinds: ``"0/N"`` for a single-channel image holding 0 and one other value N (0/255, 0/1,
    0/65535), ``"grey levels"`` for one with more values, ``"alpha"`` for an image with an alpha
    channel that is not the same everywhere (non-zero alpha is the object, whatever the colours: a
    cut-out's colours are the photo's), ``"colour"`` for a colour image otherwise (any non-zero
    colour channel is the object; an opaque alpha channel says nothing), ``"empty"`` for all zero.
    """
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise AutoalignError(f"{path}: cannot read the mask image; replace it with a PNG (white or 1 = object)")
    if m.ndim == 3 and m.shape[2] == 4 and m[..., 3].min() != m[..., 3].max():
        obj = m[..., 3] != 0  # the alpha channel carries the mask (a cut-out, or a mask stored only there)
        return obj, ("alpha" if obj.any() else "empty")
    if m.ndim == 3:
        obj = np.any(m[..., :3] != 0, axis=2)
        return obj, ("colour" if obj.any() else "empty")
    obj = m != 0
    top = int(m.max())
    if top == 0:
        return obj, "empty"
    return obj, (f"0/{top}" if not np.any(obj & (m != top)) else "grey levels")


_MASK_NAME = re.compile(r"^(\d+)_(\d+)\.png$")


def mask_files(scene_dir: str | os.PathLike[str]) -> dict[tuple[int, int], Path]:
    """``{(im_id, instance): path}`` of the files in ``mask_visib/`` named ``{im_id:06d}_{inst:06d}.png``."""
    folder = Path(scene_dir) / "mask_visib"
    out = {}
    if folder.is_dir():
        for p in folder.iterdir():
            m = _MASK_NAME.match(p.name)
            if m:
                out[(int(m.group(1)), int(m.group(2)))] = p
    return dict(sorted(out.items()))


def check_masks_have_cameras(scene_dir: str | os.PathLike[str], image_ids: set[int]) -> None:
    """Raise if a mask file names an image that ``scene_camera.json`` has no camera for."""
    scene_dir = Path(scene_dir)
    orphans = [p for (im, _), p in mask_files(scene_dir).items() if im not in image_ids]
    if orphans:
        raise AutoalignError(f"{orphans[0]}: image {int(_MASK_NAME.match(orphans[0].name).group(1))} has no entry in "
                             f"{scene_dir / 'scene_camera.json'} ({len(orphans)} mask file(s) like this); add its "
                             "camera or remove the mask")


def check_mask_kinds(kinds: dict[str, Path]) -> None:
    """Raise if the masks of one scene come in more than one kind (see :func:`read_mask`)."""
    if len(kinds) > 1:
        listed = ", ".join(f"{p} is {k}" for k, p in sorted(kinds.items()))
        raise AutoalignError(f"masks of mixed kinds in one scene ({listed}); write every mask the same way "
                             "(e.g. 0/255 single-channel PNGs, white = object)")


MAX_IMAGE_PIXELS = 3_200_000
"""Masks larger than this (pixels) are read downscaled by a whole factor, cameras with them: at
this size a silhouette is still over a thousand pixels across, and 24 views of 12-megapixel
photos (read at 4000 x 3000 / 2) keep the whole command under 2 GB (README, "Large images")."""


def downscale_factor(width: int, height: int, max_pixels: int | None = MAX_IMAGE_PIXELS) -> int:
    """The smallest whole factor that brings a ``width x height`` image to at most ``max_pixels``."""
    if max_pixels is None or width * height <= max_pixels:
        return 1
    return int(np.ceil(np.sqrt(width * height / max_pixels)))


@dataclass
class MaskSet:
    """Mask files read together (one size, one kind): the non-empty ones as boolean images at
    ``1 / factor`` of the files' resolution, keyed by ``(im_id, instance)``, and the empty ones."""

    masks: dict[tuple[int, int], NDArray[np.bool_]]
    empty: list[tuple[int, int]]
    size: tuple[int, int] | None  # (H, W) of the files
    factor: int = 1


def _read_mask_at(path: Path, max_pixels: int | None) -> tuple[NDArray[np.bool_], str, tuple[int, int]]:
    """A mask file (:func:`read_mask`) downscaled by its own :func:`downscale_factor`, its kind, and
    the file's (height, width)."""
    m, kind = read_mask(path)
    f = downscale_factor(m.shape[1], m.shape[0], max_pixels)
    if f > 1 and kind != "empty":  # whole blocks, so that the scale is exactly 1 / factor
        return block_mean(m.astype(np.float32), f, Pad.ZEROS) > 0.5, kind, m.shape
    return m, kind, m.shape


def read_masks(paths: dict[tuple[int, int], Path], max_pixels: int | None = MAX_IMAGE_PIXELS) -> MaskSet:
    """Read mask files (:func:`read_mask`); images of more than ``max_pixels`` are downscaled by
    :func:`downscale_factor` (area-averaged, then thresholded at half). Raises unless all share one
    size and one kind.

    The files are decoded by a few threads (OpenCV lets go of the GIL while it decodes a PNG), each
    downscaled as soon as it is read; the checks go in the files' order, so that the error names
    the same file as reading them one by one would."""
    out = MaskSet({}, [], None)
    kinds: dict[str, Path] = {}
    first: Path | None = None
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        read = pool.map(_read_mask_at, paths.values(), [max_pixels] * len(paths))
        for key, p in paths.items():
            m, kind, shape = next(read)
            if out.size is None:
                out.size, first = shape, p
                out.factor = downscale_factor(shape[1], shape[0], max_pixels)
            elif shape != out.size:
                raise AutoalignError(f"{p}: mask is {shape[1]}x{shape[0]} but {first.name} is "
                                     f"{out.size[1]}x{out.size[0]}; all masks of a scene must have the image size")
            if kind == "empty":
                out.empty.append(key)
                continue
            kinds.setdefault(kind, p)
            out.masks[key] = m
    check_mask_kinds(kinds)
    return out


def read_scene(scene_dir: str | Path, instance: int = 0, max_pixels: int | None = MAX_IMAGE_PIXELS) -> Scene:
    """Read cameras and the masks of instance ``instance`` from a BOP scene folder (the photos and
    the depth too: :func:`autoalign.io.evidence.read_evidence`).

    Images without a mask file are skipped (listed in ``Scene.skipped``), empty masks are treated
    as missing (``Scene.empty``); all masks must share one size and one kind (:func:`read_mask`), and
    every mask file must have a camera. At least one mask must be non-empty. Images of more than
    ``max_pixels`` are read downscaled (area-averaged, then thresholded at half), with their cameras
    (``Scene.image_scale``); ``None`` keeps them as they are.
    """
    scene_dir = check_scene_dir(scene_dir)
    cams = read_cameras(scene_dir)
    check_masks_have_cameras(scene_dir, set(cams))
    paths = {(im, instance): mask_path(scene_dir, im, instance) for im in cams}
    skipped = [im for (im, _), p in paths.items() if not p.is_file()]
    read = read_masks({k: p for k, p in paths.items() if p.is_file()}, max_pixels)
    if not read.masks and not read.empty:
        raise AutoalignError(f"{scene_dir / 'mask_visib'}: no mask files named {{im_id:06d}}_{instance:06d}.png; "
                             "write the instance masks there or choose the instance with --instance")
    if not read.masks:
        raise AutoalignError(f"{scene_dir / 'mask_visib'}: the masks of instance {instance} are empty in every view; "
                             "check the segmentation or the --instance number")
    ids = [im for im, _ in read.masks]
    return Scene(scene_cameras(cams, ids, read), [m.astype(np.float32) for m in read.masks.values()], ids, scene_dir,
                 tuple(skipped), tuple(im for im, _ in read.empty), 1.0 / read.factor)


def check_scene_dir(scene_dir: str | Path) -> Path:
    """``scene_dir`` as a path, or an error if it is not a folder."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise AutoalignError(f"{scene_dir}: scene folder not found; pass a BOP scene folder with scene_camera.json and mask_visib/")
    return scene_dir


def scene_cameras(cams: dict[int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
                  ids: list[int], read: MaskSet) -> list[Camera]:
    """The cameras of images ``ids`` (file intrinsics from :func:`read_cameras`) at the masks' scale."""
    H, W = read.size
    return [Camera.from_opencv(*cams[im], W, H).scaled(1.0 / read.factor) for im in ids]


INIT_FIX = ('an --init file maps image ids to lists of {"obj_id", "cam_R_m2c": 9 numbers, "cam_t_m2c": 3 numbers '
            '(mm)}, each pose in the camera of its image')


def read_init_file(path: str | os.PathLike[str]) -> dict[int, list[dict[str, Any]]]:
    """Image id -> pose entries of a coarse BOP ``scene_gt.json`` (``--init``), in image order; an
    error naming the file and the fix if it is not shaped so (a bare entry or list of entries, with
    no image to say whose camera the pose is in, is named as such)."""
    path = Path(path)
    data = read_json_file(path, f"pass an existing BOP scene_gt.json to --init ({INIT_FIX})")
    if isinstance(data, list) or (isinstance(data, dict) and "cam_R_m2c" in data):
        raise AutoalignError(f'{path}: its poses are not keyed by image id; write {{"0": [...]}} with the id of the '
                             f"image whose camera each pose is in ({INIT_FIX})")
    if not isinstance(data, dict) or not data:
        raise AutoalignError(f"{path}: holds no poses; {INIT_FIX}")
    images = whole_number_keys(data, path, "image id")
    for im, entries in images.items():
        entries = [entries] if isinstance(entries, dict) else entries
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise AutoalignError(f"{path}: image {im} must hold a list of pose entries; {INIT_FIX}")
        images[im] = entries
    return dict(sorted(images.items()))


def id_list(ids: Any) -> str:
    """Image ids for a message: all of a few, else the first ones, the last and how many."""
    ids = sorted(ids)
    return ", ".join(map(str, ids)) if len(ids) <= 6 else f"{', '.join(map(str, ids[:4]))}, ..., {ids[-1]} ({len(ids)})"


def init_images_without_camera(path: Path, images: dict[int, Any], cameras: Any) -> AutoalignError:
    """The error for an --init file none of whose images has a camera in the scene."""
    return AutoalignError(f"{path}: gives poses in image(s) {id_list(images)}, but the scene has cameras only for "
                          f"image(s) {id_list(cameras)}; key each pose by the id of the image whose camera it is in")


def read_init_pose(path: str | Path, scene: Scene, obj_id: int = 1, instance: int = 0) -> NDArray[np.float64]:
    """World-from-model pose (4x4, mm) from a coarse BOP ``scene_gt.json``.

    Uses the first image (lowest id) that lists ``obj_id`` and is a view of ``scene`` (else the
    first with a camera in its ``scene_camera.json``); within it the entry at position ``instance``
    if it has ``obj_id`` (a whole BOP ``scene_gt.json``), else the ``instance``-th entry with
    ``obj_id``. A file with no entry for ``obj_id`` is an error: another object's pose is no seed.
    """
    path = Path(path)
    images = read_init_file(path)
    T_cw = {im: cam.T_cw for im, cam in zip(scene.image_ids, scene.cameras)}
    if scene.path is not None:  # an image without a mask still has a camera to place its pose
        T_cw = {**{im: make_pose(R, t) for im, (_, R, t) in read_cameras(scene.path).items()}, **T_cw}
    placed = [im for im in images if im in T_cw]
    if not placed:
        raise init_images_without_camera(path, images, T_cw)
    holding = [im for im in placed if any(e.get("obj_id") == obj_id for e in images[im])]
    if not holding:
        listed = sorted({str(e.get("obj_id")) for im in placed for e in images[im]})
        raise AutoalignError(f"{path}: no entry has obj_id {obj_id} (it lists obj_id {', '.join(listed)}); pass "
                             "--obj-id with the object's id in that file, or add an entry for it")
    im = next((i for i in holding if i in scene.image_ids), holding[0])
    entries = images[im]
    if instance < len(entries) and entries[instance].get("obj_id") == obj_id:
        e = entries[instance]  # BOP: the instance is the entry's position (as in mask_visib's file names)
    else:
        same = [e for e in entries if e.get("obj_id") == obj_id]
        if instance >= len(same):
            raise AutoalignError(f"{path}: image {im} has {len(same)} entries with obj_id {obj_id}, no instance "
                                 f"{instance}; use --instance")
        e = same[instance]
    return invert(T_cw[im]) @ pose_of_entry(e, path, f"image {im}", INIT_FIX)


def pose_of_entry(e: dict[str, Any], path: Path, where: str, fix: str) -> NDArray[np.float64]:
    """Camera-from-model pose (4x4, mm) of a ``scene_gt.json`` entry, its rotation re-orthonormalised
    (BOP files store few decimals); an error naming ``path`` and ``where`` if it is malformed."""
    R = json_floats(e, "cam_R_m2c", 9, path, where, fix).reshape(3, 3)
    t = json_floats(e, "cam_t_m2c", 3, path, where, fix)
    if abs(np.linalg.det(R) - 1.0) > 1e-2:
        raise AutoalignError(f"{path}: {where} cam_R_m2c is not a rotation matrix; write it row-major with det +1")
    U, _, Vt = np.linalg.svd(R)
    return make_pose(U @ Vt, t)


@dataclass(frozen=True)
class Label:
    """One labelled instance in one image: its position ``instance`` in the image's ``scene_gt.json``
    list and the model-to-camera pose (``x_cam = R_m2c x_model + t_m2c``, mm)."""

    image_id: int
    instance: int
    obj_id: int
    R_m2c: NDArray[np.float64]
    t_m2c: NDArray[np.float64]

    @property
    def T_cm(self) -> NDArray[np.float64]:
        """Camera-from-model pose (4x4, mm)."""
        return make_pose(self.R_m2c, self.t_m2c)


def read_labels(path: str | Path) -> dict[int, list[Label]]:
    """``{image_id: [Label, ...]}`` (instance order) from a BOP ``scene_gt.json``, validated, image ids sorted."""
    path = Path(path)
    fix = ('every image id needs a list of {"obj_id": K, "cam_R_m2c": 9 numbers (row-major), '
           '"cam_t_m2c": 3 numbers (mm)}')
    data = read_json_file(path, f"--labels must be a BOP scene_gt.json ({fix})")
    if not isinstance(data, dict) or not data:
        raise AutoalignError(f"{path}: expected an object mapping image ids to lists of poses; {fix}")
    out: dict[int, list[Label]] = {}
    for im_id, entries in whole_number_keys(data, path, "image id").items():
        key = str(im_id)
        if not isinstance(entries, list):
            raise AutoalignError(f"{path}: image {key} is not a list; {fix}")
        labels = []
        for k, e in enumerate(entries):
            where = f"image {key} entry {k}"
            if not isinstance(e, dict):
                raise AutoalignError(f"{path}: {where} is not an object; {fix}")
            obj = e.get("obj_id")
            if isinstance(obj, bool) or not isinstance(obj, int) or obj < 0:
                raise AutoalignError(f"{path}: {where} needs a whole-number 'obj_id'; {fix}")
            T = pose_of_entry(e, path, where, fix)
            labels.append(Label(im_id, k, int(obj), T[:3, :3], T[:3, 3]))
        out[im_id] = labels
    return dict(sorted(out.items()))


def pose_in_camera(T_wm: NDArray[np.float64], cam: Camera) -> tuple[list[float], list[float]]:
    """BOP ``cam_R_m2c`` (9, row-major) and ``cam_t_m2c`` (3, mm) of a world-from-model pose."""
    T_cm = cam.T_cw @ T_wm
    return [float(x) for x in T_cm[:3, :3].ravel()], [float(x) for x in T_cm[:3, 3]]


def scene_gt_of(objects: list[tuple[int, NDArray[np.float64]]], cameras: list[Camera],
                image_ids: list[int]) -> dict[str, list[dict[str, Any]]]:
    """A BOP ``scene_gt.json`` object: in every image, one entry per ``(obj_id, T_wm)`` of
    ``objects`` (world-from-model, mm), in that order."""
    out = {}
    for im, cam in zip(image_ids, cameras):
        entries = []
        for obj_id, T_wm in objects:
            R, t = pose_in_camera(np.asarray(T_wm, dtype=np.float64), cam)
            entries.append({"obj_id": int(obj_id), "cam_R_m2c": R, "cam_t_m2c": t})
        out[str(im)] = entries
    return out


def scene_gt_dict(T_wm: NDArray[np.float64], cameras: list[Camera], image_ids: list[int],
                  obj_id: int = 1) -> dict[str, list[dict[str, Any]]]:
    """A BOP ``scene_gt.json`` object: one entry per image for the given world pose."""
    return scene_gt_of([(obj_id, T_wm)], cameras, image_ids)

