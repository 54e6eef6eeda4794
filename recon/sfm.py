"""Camera poses of a capture by structure from motion (pycolmap: SIFT, matching, incremental mapping).

COLMAP puts pixel centres at +0.5 (its principal point is OpenCV's plus 0.5); intrinsics are
converted both ways here, so everything outside this module is in the OpenCV / BOP convention.
Matching is exhaustive up to :data:`EXHAUSTIVE_MAX` frames, and sequential beyond (pycolmap's
quadratic overlap: each frame with the frames 1, 2, 4, ... 2^(:data:`SEQUENTIAL_OVERLAP` - 1)
after it): loop detection needs a vocabulary tree file, which cannot be downloaded here.

Beyond :data:`EXHAUSTIVE_MAX` frames, incremental mapping (whose bundle adjustments are most of
the time) runs on keyframes only, every :data:`KEYFRAME_EVERY`-th frame, and every other frame is
then registered to the keyframes' points by its verified matches with its neighbouring keyframes
(LO-RANSAC PnP and refinement, pycolmap's ``estimate_and_refine_absolute_pose``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import K_from_opencv, K_to_opencv, uv_to_opencv
from autoalign.geometry.se3 import make_pose
from autoalign.recon.capture import Capture

if TYPE_CHECKING:
    import pycolmap

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

KEYFRAME_EVERY = 4
"""With more than :data:`EXHAUSTIVE_MAX` frames, every this many-th frame (and the last) is a
keyframe: a power of two, so that the quadratic sequential matching links each keyframe with the
keyframes 1, 2, 4, ... keyframes on, and every other frame with a keyframe next to it. On the
200-frame 640x480 benchmark stream, mapping took 149 s with every frame, 45 s with every 2nd and
16 s with every 4th, and the cameras were as accurate (median 0.12 mm / 0.015 deg after Sim(3)
alignment, keyframes and registered frames alike)."""
MIN_PNP_POINTS = 30
"""A frame registered to the keyframes needs this many 2D-3D correspondences and PnP inliers."""

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


def run_sfm(capture: Capture, workdir: str | os.PathLike[str], progress: Progress | None = None) -> SfmResult:
    """Reconstruct the cameras of ``capture`` (files in ``workdir``: COLMAP's database and model)."""
    import pycolmap

    pycolmap.logging.minloglevel = 3  # fatal only: COLMAP logs every step, and its failures are reported here

    def step(stage: str, done: int) -> None:
        if progress is not None:
            progress(stage, done, 3)

    workdir = Path(workdir)
    folder, names = _frame_folder(capture)
    workdir.mkdir(parents=True, exist_ok=True)
    db = workdir / "database.db"
    if db.exists():
        db.unlink()
    step("structure from motion: features", 0)
    _extract_features(db, folder, names, capture.K_opencv)
    step("structure from motion: matching", 1)
    _match(db, len(names))
    step("structure from motion: mapping", 2)
    keyframes = _keyframes(names)
    rec = _map_keyframes(db, folder, workdir / "sparse", keyframes, len(names), fixed_K=capture.K_opencv is not None)
    step("structure from motion: mapping", 3)
    if rec is None:
        raise AutoalignError(f"{folder}: too few matches between the frames to reconstruct the cameras; film the "
                             "scene with more overlap and texture, slower, or give --intrinsics")
    extra = _register_to_keyframes(rec, db, names, progress) if len(keyframes) < len(names) else {}
    return _result(rec, dict(zip(names, capture.ids)), extra, len(names))


def _frame_folder(capture: Capture) -> tuple[Path, list[str]]:
    """The one folder that holds the capture's frames, and the frames' file names in order."""
    folder = capture.frames[0].parent
    if any(p.parent != folder for p in capture.frames):
        raise AutoalignError(f"{folder}: the frames must be in one folder")
    return folder, [p.name for p in capture.frames]


def _extract_features(db: Path, folder: Path, names: list[str], K: NDArray[np.float64] | None) -> None:
    """SIFT features of every frame into the database, one camera for all (fixed to ``K``, OpenCV
    convention, when given; else a simple pinhole whose focal length mapping estimates)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    if K is not None:
        reader.camera_model = "PINHOLE"
        Kc = K_from_opencv(K)  # COLMAP's pixel centres are the internal convention's
        reader.camera_params = f"{Kc[0, 0]},{Kc[1, 1]},{Kc[0, 2]},{Kc[1, 2]}"
    else:
        reader.camera_model = "SIMPLE_PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = MAX_FEATURES
    pycolmap.extract_features(db, folder, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def _match(db: Path, n_frames: int) -> None:
    """Verified matches between the frames: exhaustive up to :data:`EXHAUSTIVE_MAX` frames, else sequential."""
    import pycolmap

    if n_frames <= EXHAUSTIVE_MAX:
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.quadratic_overlap = True
        pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)


def _keyframes(names: list[str]) -> list[str]:
    """The frames incremental mapping runs on: all up to :data:`EXHAUSTIVE_MAX`, else every
    :data:`KEYFRAME_EVERY`-th and the last."""
    return names if len(names) <= EXHAUSTIVE_MAX else sorted(set(names[::KEYFRAME_EVERY]) | {names[-1]})


def _map_keyframes(db: Path, folder: Path, sparse: Path, keyframes: list[str], n_frames: int,
                   fixed_K: bool) -> pycolmap.Reconstruction | None:
    """Incremental mapping of ``keyframes`` (of ``n_frames``), in ``sparse``: the model with the most
    frames registered, None when there is none; the intrinsics stay as given when ``fixed_K``."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    if fixed_K:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    options.multiple_models = False
    if len(keyframes) < n_frames:
        options.image_names = keyframes
    options.ba_global_frames_ratio = options.ba_global_points_ratio = GLOBAL_BA_GROWTH
    options.ba_global_max_num_iterations = GLOBAL_BA_ITERATIONS
    sparse.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(db, folder, sparse, options)
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


def _result(rec: pycolmap.Reconstruction, id_of: dict[str, int],
            extra: dict[str, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]],
            n_frames: int) -> SfmResult:
    """The cameras, points and observations of ``rec`` and of the frames registered to it
    (``extra``, see :func:`_register_to_keyframes`), by frame id (``id_of``: file name -> frame id),
    in the OpenCV pixel convention; ``n_frames``: the frames given."""
    cam = next(iter(rec.cameras.values()))
    f = cam.focal_length_x, cam.focal_length_y
    K = K_to_opencv(np.array([[f[0], 0.0, cam.principal_point_x], [0.0, f[1], cam.principal_point_y], [0.0, 0.0, 1.0]]))
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
                uv.append(uv_to_opencv(p2.xy))
                idx.append(index[p2.point3D_id])
        obs[fid] = (np.array(uv, dtype=np.float64).reshape(-1, 2), np.array(idx, dtype=np.int64))
    for name, (T, xy, pids) in extra.items():
        T_cw[id_of[name]] = T
        obs[id_of[name]] = (uv_to_opencv(xy), np.array([index[p] for p in pids], dtype=np.int64))
    return SfmResult(dict(sorted(T_cw.items())), K, points, colors, obs, float(rec.compute_mean_reprojection_error()),
                     n_frames)


def _register_to_keyframes(rec: pycolmap.Reconstruction, db_path: Path, names: list[str],
                           progress: Progress | None = None) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]]:
    """Per frame name not in ``rec``: its camera-from-world pose, and the keypoints (COLMAP pixel
    convention) and point ids of its PnP inliers, from its verified matches with the registered
    frames within :data:`SEQUENTIAL_OVERLAP` of it in ``names``; frames that cannot be registered
    are left out."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        image_id = {im.name: im.image_id for im in db.read_all_images()}
        posed = {im.name: im for im in rec.images.values() if im.has_pose}
        camera = next(iter(rec.cameras.values()))
        todo = [n for n in names if n not in posed]
        out = {}
        for k, name in enumerate(todo):
            i = names.index(name)
            keypoints = db.read_keypoints(image_id[name])[:, :2]
            seen: dict[int, int] = {}  # keypoint -> 3D point id
            for other in names[max(0, i - SEQUENTIAL_OVERLAP):i + SEQUENTIAL_OVERLAP + 1]:
                if other not in posed or not db.exists_two_view_geometry(image_id[name], image_id[other]):
                    continue
                matches = db.read_two_view_geometry(image_id[name], image_id[other]).inlier_matches
                key = posed[other].points2D
                for a, b in np.asarray(matches, dtype=np.int64).reshape(-1, 2):
                    if a not in seen and key[b].has_point3D():
                        seen[int(a)] = int(key[b].point3D_id)
            if progress is not None:
                progress("registering frames to the keyframes", k + 1, len(todo))
            if len(seen) < MIN_PNP_POINTS:
                continue
            kp = np.fromiter(seen, dtype=np.int64)
            pids = np.array([seen[a] for a in kp], dtype=np.int64)
            xy = keypoints[kp].astype(np.float64)
            X = np.array([rec.points3D[p].xyz for p in pids], dtype=np.float64)
            found = pycolmap.estimate_and_refine_absolute_pose(xy, X, camera)
            if found is None or int(found["num_inliers"]) < MIN_PNP_POINTS:
                continue
            pose, keep = found["cam_from_world"], np.asarray(found["inlier_mask"], dtype=bool)
            out[name] = (make_pose(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)), xy[keep], pids[keep])
        return out
    finally:
        db.close()
