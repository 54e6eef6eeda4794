"""A capture to reconstruct: its frames (a folder of images or a video), optional aligned depth
and optional intrinsics, validated with errors that name the file and the fix."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.io.bop import read_depth_png, read_json_file
from autoalign.recon.fusion import DEPTH_TRUNC_MM

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
INTRINSICS_FIX = ('an intrinsics file is JSON {"cam_K": 9 numbers (row-major, px, OpenCV convention: the centre '
                  'of the top-left pixel at 0,0)} or {"fx", "fy", "cx", "cy"}')


@dataclass
class Capture:
    """The frames to reconstruct.

    Attributes:
        frames: image file of each frame (a video is first written out as PNGs).
        ids: the frame number of each (its BOP image id).
        size: image ``(W, H)`` shared by every frame.
        depth: aligned depth file of each frame (``None`` without depth).
        depth_scale: depth file value times this is mm.
        K_opencv: given intrinsics (OpenCV convention), or ``None`` to estimate them.
    """

    frames: list[Path]
    ids: list[int]
    size: tuple[int, int]
    depth: list[Path] | None
    depth_scale: float
    K_opencv: NDArray[np.float64] | None


def read_intrinsics(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """``K`` (3x3, OpenCV convention) from an intrinsics JSON file (see :data:`INTRINSICS_FIX`)."""
    data = read_json_file(path, f"pass an existing intrinsics file ({INTRINSICS_FIX})")
    try:
        if isinstance(data, dict) and "cam_K" in data:
            K = np.asarray(data["cam_K"], dtype=np.float64).reshape(3, 3)
        else:
            K = np.array([[data["fx"], 0.0, data["cx"]], [0.0, data["fy"], data["cy"]], [0.0, 0.0, 1.0]], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise AutoalignError(f"{path}: wrong shape; {INTRINSICS_FIX}") from None
    if not np.all(np.isfinite(K)) or not (K[0, 0] > 0 and K[1, 1] > 0):  # NaN too
        raise AutoalignError(f"{path}: the focal lengths must be positive and every number finite; {INTRINSICS_FIX}")
    return K


def _frames_of_video(video: Path, every: int, workdir: Path) -> list[Path]:
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # FFmpeg's own messages: ours says it in one line
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise AutoalignError(f"{video}: cannot open the video (OpenCV could not decode it); convert it to MP4 "
                             "(H.264) or pass a folder of frames")
    out, n = [], 0
    (workdir / "frames").mkdir(parents=True, exist_ok=True)
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if n % every == 0:
                p = workdir / "frames" / f"{n:06d}.png"
                cv2.imwrite(str(p), img)
                out.append(p)
            n += 1
    finally:
        cap.release()
    if not out:
        raise AutoalignError(f"{video}: the video has no readable frame; check the file")
    return out


def read_capture(capture: str | os.PathLike[str], workdir: str | os.PathLike[str],
                 depth_dir: str | os.PathLike[str] | None = None, depth_scale: float = 1.0,
                 intrinsics: str | os.PathLike[str] | None = None, every: int = 1) -> Capture:
    """The frames of ``capture`` (a folder of images, its ``rgb/`` if it has one, or a video file),
    every ``every``-th; depth from ``depth_dir`` (default ``capture/depth`` if present), one file
    per frame with the frame's name; every frame read once to check it."""
    capture, workdir = Path(capture), Path(workdir)
    if capture.is_file():
        frames = _frames_of_video(capture, every, workdir)
    elif capture.is_dir():
        folder = capture / "rgb" if (capture / "rgb").is_dir() else capture
        frames = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)[::every]
        if not frames:
            raise AutoalignError(f"{folder}: no image files ({', '.join(IMAGE_SUFFIXES)}); pass a folder of frames "
                                 "or a video file")
    else:
        raise AutoalignError(f"{capture}: not found; pass a folder of frames or a video file")
    ids = [int(p.stem) if p.stem.isdigit() else k for k, p in enumerate(frames)]
    if len(set(ids)) != len(ids):
        ids = list(range(len(frames)))
    size = None
    for p in frames:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise AutoalignError(f"{p}: cannot read the frame; replace or remove it")
        s = (int(img.shape[1]), int(img.shape[0]))
        if size is None:
            size = s
        elif s != size:
            raise AutoalignError(f"{p}: {s[0]}x{s[1]} but the first frame is {size[0]}x{size[1]}; one capture, one size")
    assert size is not None
    if depth_dir is None and capture.is_dir() and (capture / "depth").is_dir():
        depth_dir = capture / "depth"
    depth = None if depth_dir is None else _depth_files(Path(depth_dir), frames, size, depth_scale)
    K = read_intrinsics(Path(intrinsics)) if intrinsics is not None else None
    return Capture(frames, ids, size, depth, float(depth_scale), K)


DEPTH_RANGE_MM = (50.0, DEPTH_TRUNC_MM)
"""Where the median measured depth of a capture may lie (mm): a sensor sees little nearer, and the
fusion keeps nothing farther; outside it the depth is in another unit than ``--depth-scale`` says."""


def _depth_files(depth_dir: Path, frames: list[Path], size: tuple[int, int], depth_scale: float) -> list[Path]:
    """The depth PNG of every frame in ``depth_dir`` (same name), each read once to check it, and their
    unit checked against ``depth_scale`` (:func:`check_depth_unit`)."""
    files, medians = [], []
    for p in frames:
        d = depth_dir / f"{p.stem}.png"
        if not d.is_file():
            raise AutoalignError(f"{d}: no depth for frame {p.name}; give every frame a depth PNG of the same name "
                                 "or leave out --depth")
        values = read_depth_png(d, size, "the frames are")
        if np.any(values > 0):
            medians.append(float(np.median(values[values > 0])))
        files.append(d)
    check_depth_unit(depth_dir, medians, depth_scale)
    return files


def check_depth_unit(depth_dir: Path, medians: list[float], depth_scale: float) -> None:
    """Raise, naming ``--depth-scale``, when the frames' median depth values times ``depth_scale``
    fall outside :data:`DEPTH_RANGE_MM` (0.1 mm units read as mm put a table 5 m away, where the
    fusion finds nothing)."""
    if not medians:
        raise AutoalignError(f"{depth_dir}: every depth image is 0 (no measurement); give the sensor's depth or leave "
                             "out --depth")
    mm = float(np.median(medians)) * depth_scale
    if DEPTH_RANGE_MM[0] <= mm <= DEPTH_RANGE_MM[1]:
        return
    guess = depth_scale * 10.0 ** round(np.log10(600.0 / mm))  # a tabletop some 0.6 m away, in a power-of-ten unit
    raise AutoalignError(f"{depth_dir}: the median depth is {mm:.4g} mm with --depth-scale {depth_scale:g}, not "
                         f"{DEPTH_RANGE_MM[0]:g}-{DEPTH_RANGE_MM[1]:g} mm as a capture's; pass the --depth-scale that "
                         f"makes a depth value mm (probably {guess:g}: 0.1 for 0.1 mm units, 1000 for metres)")
