"""Pose errors of the study: symmetry-aware rotation error, the paper's axis-dot test, ADD / ADD-S, AUC.

Units: millimetres and degrees. Poses are 4x4 world-from-model matrices. Symmetries follow the
BOP ``models_info`` convention: ``symmetries_discrete`` are model-frame 4x4 transforms ``S``
(identity excluded) and ``symmetries_continuous`` are ``{"axis", "offset"}`` rotations; a pose
``T`` is equivalent to ``T @ S`` for every element ``S = S_cont(phi) @ S_disc`` of the group
(as ``bop_toolkit.misc.get_symmetry_transformations`` combines them). Rotation errors,
positions and axis dots are measured against the equivalent ground truth closest in rotation.

The paper's success test ("within 1mm location error and dot product larger than 0.99 between
ground truth and converged rotation axes") is ambiguous about which axes; both readings are here:

* ``cols`` (default): each body axis (column of R) of the estimate against the same axis of the
  ground truth, the smallest of the three dot products > 0.99 (all axes within 8.1 degrees);
* ``axis_angle``: the unit rotation axes of R_est and R_gt as axis-angle vectors, dot > 0.99
  (says nothing about the rotation angle: a weak test).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import make_pose, so3_log, transform_points

POS_TOL_MM = 1.0
DOT_TOL = 0.99


@dataclass(frozen=True)
class Symmetries:
    """A model's symmetry group generators: discrete 4x4 (identity excluded) and continuous axes."""

    discrete: tuple[NDArray[np.float64], ...] = ()
    continuous: tuple[tuple[NDArray[np.float64], NDArray[np.float64]], ...] = ()  # (unit axis, offset mm)

    @property
    def symmetric(self) -> bool:
        return bool(self.discrete or self.continuous)

    @staticmethod
    def from_info(info: dict[str, Any] | None) -> "Symmetries":
        """From a ``models_info`` entry (raw JSON lists or the arrays of ``load_bop_models_info``)."""
        if not info:
            return Symmetries()
        disc = tuple(np.asarray(T, dtype=np.float64).reshape(4, 4) for T in info.get("symmetries_discrete", []))
        cont = []
        for c in info.get("symmetries_continuous", []):
            a = np.asarray(c["axis"], dtype=np.float64)
            cont.append((a / np.linalg.norm(a), np.asarray(c.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)))
        return Symmetries(disc, tuple(cont))


def _axis_rotation(axis: NDArray[np.float64], phi: float) -> NDArray[np.float64]:
    A = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(phi) * A + (1.0 - np.cos(phi)) * A @ A


def _best_phi(M: NDArray[np.float64], axis: NDArray[np.float64]) -> float:
    """The angle maximising ``trace(M @ Rot(axis, phi))`` (closed form)."""
    A = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    aMa = float(axis @ M @ axis)
    return float(np.arctan2(np.trace(M @ A), np.trace(M) - aMa))


def rotation_error_deg(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Geodesic angle between two rotations, degrees."""
    R = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64)
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def closest_equivalent(T_est: ArrayLike, T_gt: ArrayLike, sym: Symmetries) -> NDArray[np.float64]:
    """The pose ``T_gt @ S`` over the symmetry group closest in rotation to ``T_est``.

    Discrete elements are enumerated (with the identity); a continuous axis is optimised in
    closed form for each of them (only the first continuous axis is used: BOP models have one).
    """
    T_est = np.asarray(T_est, dtype=np.float64)
    T_gt = np.asarray(T_gt, dtype=np.float64)
    if not sym.symmetric:
        return T_gt
    best, best_tr = T_gt, -np.inf
    for S_d in (np.eye(4),) + tuple(sym.discrete):
        S = S_d
        if sym.continuous:
            axis, off = sym.continuous[0]
            # trace(R_est^T R_gt R_c R_d) = trace((R_d R_est^T R_gt) R_c)
            M = S_d[:3, :3] @ T_est[:3, :3].T @ T_gt[:3, :3]
            Rc = _axis_rotation(axis, _best_phi(M, axis))
            S_c = make_pose(Rc, off - Rc @ off)
            S = S_c @ S_d
        T = T_gt @ S
        tr = float(np.trace(T_est[:3, :3].T @ T[:3, :3]))
        if tr > best_tr + 1e-12:
            best, best_tr = T, tr
    return best


def axis_dot_axis_angle(R_est: ArrayLike, R_gt: ArrayLike) -> float:
    """Dot product of the unit axis-angle axes of two rotations (1 when both are the identity)."""
    a, b = so3_log(R_est), so3_log(R_gt)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 and nb < 1e-9:
        return 1.0
    if na < 1e-9 or nb < 1e-9:
        return 0.0
    return float(a @ b / (na * nb))


def axis_dot_columns(R_est: ArrayLike, R_gt: ArrayLike) -> float:
    """Smallest dot product between corresponding body axes (columns) of two rotations."""
    return float(np.min(np.sum(np.asarray(R_est) * np.asarray(R_gt), axis=0)))


def add_mm(points_m: NDArray[np.float64], T_est: ArrayLike, T_gt: ArrayLike) -> float:
    """ADD: mean distance of corresponding model points (mm)."""
    return float(np.linalg.norm(transform_points(T_est, points_m) - transform_points(T_gt, points_m), axis=1).mean())


def adds_mm(points_m: NDArray[np.float64], T_est: ArrayLike, T_gt: ArrayLike) -> float:
    """ADD-S: mean distance from each estimated point to the closest ground-truth point (mm)."""
    tree = cKDTree(transform_points(T_gt, points_m))
    d, _ = tree.query(transform_points(T_est, points_m), k=1)
    return float(np.mean(d))


@dataclass
class PoseErrors:
    """Errors of one estimate (mm, degrees); rotation quantities are modulo symmetries.

    ``rot_err_raw_deg`` ignores symmetries. ``add_mm`` is plain ADD, ``adds_mm`` ADD-S;
    ``addx_mm`` is ADD for asymmetric and ADD-S for symmetric models (BOP's ADD(-S)).
    """

    pos_err_mm: float
    rot_err_deg: float
    rot_err_raw_deg: float
    dot_cols: float
    dot_axis_angle: float
    add_mm: float
    adds_mm: float
    addx_mm: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def pose_errors(T_est: ArrayLike, T_gt: ArrayLike, centre_m: ArrayLike, points_m: NDArray[np.float64] | None,
                sym: Symmetries) -> PoseErrors:
    """All errors of ``T_est`` against ``T_gt`` for a model with centre ``centre_m`` (mm, model frame).

    Position error is the distance between the model centre under ``T_est`` and under the closest
    symmetric equivalent of ``T_gt``. Without ``points_m`` the ADD values are NaN.
    """
    T_est = np.asarray(T_est, dtype=np.float64)
    T_gt = np.asarray(T_gt, dtype=np.float64)
    T_eq = closest_equivalent(T_est, T_gt, sym)
    c = np.asarray(centre_m, dtype=np.float64)[None]
    pos = float(np.linalg.norm(transform_points(T_est, c) - transform_points(T_eq, c)))
    rot = rotation_error_deg(T_est[:3, :3], T_eq[:3, :3])
    raw = rotation_error_deg(T_est[:3, :3], T_gt[:3, :3])
    if points_m is not None:
        a, s = add_mm(points_m, T_est, T_gt), adds_mm(points_m, T_est, T_gt)
    else:
        a = s = float("nan")
    return PoseErrors(pos, rot, raw, axis_dot_columns(T_est[:3, :3], T_eq[:3, :3]),
                      axis_dot_axis_angle(T_est[:3, :3], T_eq[:3, :3]), a, s, s if sym.symmetric else a)


CRITERIA: dict[str, str] = {
    "cols": "position < 1 mm and min over the 3 body axes of dot(R_est e_i, R_gt e_i) > 0.99 (headline)",
    "axis_angle": "position < 1 mm and dot of the axis-angle rotation axes > 0.99",
    "strict": "position < 1 mm and rotation error < 1 degree",
    "addx": "ADD(-S) < 0.1 diameter",
}


@dataclass(frozen=True)
class LabelDifference:
    """Two labels of one object in one image (model-to-camera poses, mm), against the symmetric
    equivalent of the reference closest to the other: the centres' distance (mm) and the rotation
    (degrees); that distance split along the reference centre's viewing ray (signed, + farther)
    and across it (mm); the model points' projection distance (px): mean, and largest (BOP's MSPD)."""

    pos_mm: float
    rot_deg: float
    along_ray_mm: float
    across_ray_mm: float
    mean_px: float
    mspd_px: float


def label_difference(T_cm: ArrayLike, T_ref_cm: ArrayLike, K: ArrayLike, centre_m: ArrayLike,
                     points_m: NDArray[np.float64], sym: Symmetries) -> LabelDifference:
    """How far label ``T_cm`` is from ``T_ref_cm`` in an image with OpenCV / BOP intrinsics ``K``
    (model-to-camera, mm; model centre and points in the model frame). In an image the depth along
    the viewing ray is what a label shows least: a few px of MSPD can be tens of mm along the ray."""
    T_cm = np.asarray(T_cm, dtype=np.float64)
    T_ref = closest_equivalent(T_cm, T_ref_cm, sym)
    eye = Camera.from_opencv(np.asarray(K, dtype=np.float64), np.eye(3), np.zeros(3), 1, 1)  # labels: camera frame
    px = np.linalg.norm(eye.project(transform_points(T_cm, points_m)) - eye.project(transform_points(T_ref, points_m)),
                        axis=1)
    c = np.asarray(centre_m, dtype=np.float64)[None]
    c_ref, c_lab = transform_points(T_ref, c)[0], transform_points(T_cm, c)[0]
    ray = c_ref / np.linalg.norm(c_ref)
    along = float((c_lab - c_ref) @ ray)
    return LabelDifference(float(np.linalg.norm(c_lab - c_ref)), rotation_error_deg(T_cm[:3, :3], T_ref[:3, :3]),
                           along, float(np.linalg.norm(c_lab - c_ref - along * ray)), float(px.mean()),
                           float(px.max()))


def success(err: PoseErrors | dict[str, float], criterion: str = "cols", diameter_mm: float | None = None,
            pos_tol_mm: float = POS_TOL_MM, dot_tol: float = DOT_TOL) -> bool:
    """Whether an estimate passes ``criterion`` (a key of :data:`CRITERIA`)."""
    e = err.as_dict() if isinstance(err, PoseErrors) else err
    if criterion == "cols":
        return bool(e["pos_err_mm"] < pos_tol_mm and e["dot_cols"] > dot_tol)
    if criterion == "axis_angle":
        return bool(e["pos_err_mm"] < pos_tol_mm and e["dot_axis_angle"] > dot_tol)
    if criterion == "strict":
        return bool(e["pos_err_mm"] < pos_tol_mm and e["rot_err_deg"] < 1.0)
    if criterion == "addx":
        if diameter_mm is None:
            raise ValueError("the addx criterion needs the model diameter")
        return bool(e["addx_mm"] < 0.1 * diameter_mm)
    raise ValueError(f"unknown criterion {criterion!r}; choose one of {sorted(CRITERIA)}")


def auc(rel_errors: ArrayLike, max_rel: float = 0.1, steps: int = 1000) -> float:
    """Area under the accuracy-threshold curve for thresholds in ``[0, max_rel]``, normalised to [0, 1].

    ``rel_errors`` are errors divided by the model diameter (e.g. ADD / diameter); NaN counts
    as a failure.
    """
    e = np.asarray(rel_errors, dtype=np.float64)
    if e.size == 0:
        return float("nan")
    e = np.where(np.isfinite(e), e, np.inf)
    th = (np.arange(steps) + 0.5) / steps * max_rel
    return float(np.mean((e[None, :] < th[:, None]).mean(axis=1)))


@dataclass(frozen=True)
class TrackFit:
    """How well a set of cameras explains the photos' own feature tracks (px, OpenCV pixels).

    Each track (one scene point seen by at least ``min_views`` cameras) is triangulated with the
    cameras held fixed, and every observation's reprojection error is measured. A camera set that
    is consistent with the photos reaches the keypoints' noise (about half a pixel for SIFT); a
    camera that is off shows as a large error in its own views. ``per_view_px``: per image id, the
    median error of its observations; ``tracks``: how many tracks were triangulated.
    """

    median_px: float
    mean_px: float
    p90_px: float
    per_view_px: dict[int, float]
    tracks: int


def track_fit(observations: dict[int, tuple[NDArray[np.float64], NDArray[np.int64]]],
              T_cw: dict[int, NDArray[np.float64]], K: ArrayLike, min_views: int = 3) -> TrackFit:
    """:class:`TrackFit` of cameras ``T_cw`` (per image id, camera-from-world 4x4, any unit) and
    intrinsics ``K`` (OpenCV convention) on ``observations`` (per image id, keypoints ``(M, 2)`` in
    OpenCV pixels and the index of the track each belongs to, as ``recon.sfm.SfmResult`` holds
    them). Triangulation: pycolmap's linear multi-view solve on the keypoints' bearing vectors;
    images without a camera in ``T_cw`` are left out."""
    import pycolmap

    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    Kinv = np.linalg.inv(K)
    tracks: dict[int, list[tuple[int, NDArray[np.float64]]]] = {}
    for im, (uv, idx) in observations.items():
        if im in T_cw:
            for p, q in zip(idx.tolist(), np.asarray(uv, dtype=np.float64)):
                tracks.setdefault(p, []).append((im, q))
    errors: list[float] = []
    per_view: dict[int, list[float]] = {}
    n = 0
    for obs in tracks.values():
        if len(obs) < min_views:
            continue
        uv = np.array([q for _, q in obs])
        rays = np.c_[uv, np.ones(len(uv))] @ Kinv.T
        X = pycolmap.triangulate_multi_view_point([T_cw[im][:3, :4] for im, _ in obs],
                                                  rays / np.linalg.norm(rays, axis=1, keepdims=True))
        if X is None:
            continue
        n += 1
        X = np.asarray(X, dtype=np.float64).ravel()
        for im, q in obs:
            x = K @ (T_cw[im][:3, :3] @ X + T_cw[im][:3, 3])
            e = float(np.hypot(*(x[:2] / x[2] - q))) if x[2] > 0 else float("inf")
            errors.append(e)
            per_view.setdefault(im, []).append(e)
    if not errors:
        raise ValueError(f"no track is seen by {min_views} of the given cameras")
    e = np.array(errors)
    return TrackFit(float(np.median(e)), float(np.mean(e[np.isfinite(e)])), float(np.percentile(e, 90)),
                    {im: float(np.median(v)) for im, v in sorted(per_view.items())}, n)
