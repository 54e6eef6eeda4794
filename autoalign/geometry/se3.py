"""Rigid transforms as 4x4 numpy matrices, and the SE(3) exponential/logarithm of twists.

Conventions
-----------
* A pose ``T`` is a 4x4 homogeneous matrix mapping points of one frame into another,
  ``x_a = T_ab @ x_b`` (``T_ab`` reads "a from b"). Translations are in millimetres.
* A twist is ``xi = (v, w)``: translation part ``v`` first (mm), rotation part ``w`` second
  (radians, axis times angle), as in the ProgressLabeller paper, ``xi = [-w x v_o; w]``.
* ``exp(xi)`` is the matrix exponential of ``hat(xi) = [[hat(w), v], [0, 0]]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

_SMALL = 1e-8


def hat3(w: ArrayLike) -> NDArray[np.float64]:
    """3x3 skew matrix with ``hat3(w) @ x == cross(w, x)``."""
    w = np.asarray(w, dtype=np.float64)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix of the axis-angle vector ``w`` (radians), by Rodrigues' formula."""
    w = np.asarray(w, dtype=np.float64)
    th = float(np.linalg.norm(w))
    W = hat3(w)
    if th < _SMALL:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(th) / th * W + (1.0 - np.cos(th)) / th**2 * W @ W


def so3_log(R: ArrayLike) -> NDArray[np.float64]:
    """Axis-angle vector (radians, angle in [0, pi]) of a rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # atan2 keeps the angle accurate near 0 and pi, where arccos loses half the digits.
    th = float(np.arctan2(0.5 * np.linalg.norm(vee), cos))
    if th < 1e-6:
        return 0.5 * vee
    if np.pi - th < 1e-4:
        # Near pi the antisymmetric part vanishes; read the axis off the symmetric part,
        # (R + R^T)/2 - cos(th) I = (1 - cos(th)) a a^T exactly.
        B = 0.5 * (R + R.T) - cos * np.eye(3)
        i = int(np.argmax(np.diag(B)))
        a = B[:, i] / np.linalg.norm(B[:, i])
        if vee @ a < 0:  # keep the sign consistent with the small antisymmetric part
            a = -a
        return th * a
    return th / (2.0 * np.sin(th)) * vee


def _left_jacobian(w: NDArray[np.float64]) -> NDArray[np.float64]:
    th = float(np.linalg.norm(w))
    W = hat3(w)
    if th < 1e-5:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return np.eye(3) + (1.0 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W


def se3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """4x4 transform ``exp(hat(xi))`` of a twist ``xi = (v [mm], w [rad])``."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = _left_jacobian(w) @ v
    return T


def make_pose(R: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
    """4x4 pose from a 3x3 rotation and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


def transform_points(T: ArrayLike, X: ArrayLike) -> NDArray[np.float64]:
    """Apply a 4x4 transform to an (N, 3) array of points."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(X, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def twist_about(xi: ArrayLike, centre: ArrayLike) -> NDArray[np.float64]:
    """The world-frame twist of a motion whose rotation ``w`` turns about ``centre`` (mm).

    ``xi = (v, w)`` moves a body by ``v`` and rotates it by ``w`` about the point ``centre``;
    the returned twist is ``(v - w x centre, w)``, the paper's ``[-w x v_o; w]`` plus ``v``.
    """
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[:3], xi[3:]
    return np.concatenate([v - np.cross(w, np.asarray(centre, dtype=np.float64)), w])


def apply_twist(T_wm: ArrayLike, xi: ArrayLike, centre: ArrayLike) -> NDArray[np.float64]:
    """Left-multiplied update ``exp(hat(xi')) @ T_wm`` with ``xi' = twist_about(xi, centre)``.

    ``centre`` is the world point (mm) the rotation turns about, normally the object centre,
    so that rotation and translation steps decouple.
    """
    return se3_exp(twist_about(xi, centre)) @ np.asarray(T_wm, dtype=np.float64)


def rotation_angle_deg(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Geodesic angle between two rotations in degrees."""
    R = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64)
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def pose_change(A: ArrayLike, B: ArrayLike, centre_m: ArrayLike) -> tuple[float, float]:
    """How far pose ``B`` is from ``A`` (world from model): the distance (mm) between the model
    point ``centre_m`` under each, and the angle (degrees) between their rotations."""
    A, B, c = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64), np.asarray(centre_m, dtype=np.float64)
    return (float(np.linalg.norm(A[:3, :3] @ c + A[:3, 3] - B[:3, :3] @ c - B[:3, 3])),
            rotation_angle_deg(A[:3, :3], B[:3, :3]))


@dataclass(frozen=True)
class Symmetries:
    """A model's symmetries, as BOP's ``models_info.json`` lists them: ``discrete`` 4x4 transforms
    (model frame, mm) and ``continuous`` (unit axis, a point on it; model frame, mm)."""

    discrete: tuple[NDArray[np.float64], ...] = ()
    continuous: tuple[tuple[NDArray[np.float64], NDArray[np.float64]], ...] = ()

    def __bool__(self) -> bool:
        return bool(self.discrete or self.continuous)

    @property
    def axes(self) -> tuple[NDArray[np.float64], ...]:
        """The axes of the continuous symmetries (model frame), about which every turn is as good."""
        return tuple(np.asarray(axis, dtype=np.float64) for axis, _ in self.continuous)


def closest_symmetric_pose(A: ArrayLike, B: ArrayLike, discrete: Sequence[ArrayLike] = (),
                           continuous: Sequence[tuple[ArrayLike, ArrayLike]] = ()) -> NDArray[np.float64]:
    """The equivalent of pose ``B`` (world from model) nearest in rotation to ``A`` under the model's
    symmetries: ``B @ S`` for ``S`` the identity and each of ``discrete`` (4x4, model frame, as BOP's
    ``symmetries_discrete``), each turned about the first of ``continuous`` (unit axis, point on it;
    model frame, mm) by the angle that brings it closest to ``A`` (closed form: the trace of
    ``A_R^T B_R R_axis(phi)`` is ``alpha + beta cos(phi) + gamma sin(phi)``)."""
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    best, best_angle = B, np.inf
    for S in [np.eye(4), *(np.asarray(d, dtype=np.float64).reshape(4, 4) for d in discrete)]:
        T = B @ S
        if continuous:
            a = np.asarray(continuous[0][0], dtype=np.float64)
            a = a / np.linalg.norm(a)
            o = np.asarray(continuous[0][1], dtype=np.float64)
            N = A[:3, :3].T @ T[:3, :3]
            phi = float(np.arctan2(np.trace(N @ hat3(a)), np.trace(N) - a @ N @ a))
            R = so3_exp(a * phi)
            T = T @ make_pose(R, o - R @ o)
        angle = rotation_angle_deg(A[:3, :3], T[:3, :3])
        if angle < best_angle:
            best, best_angle = T, angle
    return best


def symmetric_pose_change(A: ArrayLike, B: ArrayLike, centre_m: ArrayLike,
                          discrete: Sequence[ArrayLike] = (),
                          continuous: Sequence[tuple[ArrayLike, ArrayLike]] = ()) -> tuple[float, float]:
    """:func:`pose_change` from ``A`` to :func:`closest_symmetric_pose` of ``B``."""
    return pose_change(A, closest_symmetric_pose(A, B, discrete, continuous), centre_m)
