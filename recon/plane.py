"""The table plane (RANSAC, open3d) and the world frame it defines: z up, the table at z = 0."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.se3 import make_pose

INLIER_FRACTION_OF_EXTENT = 0.01
"""A point is on the plane when it is closer than this fraction of the points' median distance
from their centroid (a fraction, since without depth the reconstruction has no unit)."""


@dataclass(frozen=True)
class TablePlane:
    """``normal`` (unit, towards the cameras) and ``point`` (on the plane), in the reconstruction's
    world frame; ``inliers``: fraction of the points on it; ``rms``: their distance to it (same unit)."""

    normal: NDArray[np.float64]
    point: NDArray[np.float64]
    inliers: float
    rms: float


def fit_table_plane(points: NDArray[np.float64], camera_centres: NDArray[np.float64], seed: int = 0) -> TablePlane:
    """The dominant plane of ``points`` (N, 3) by RANSAC (open3d ``segment_plane``), its normal
    turned towards the mean of ``camera_centres``."""
    import open3d as o3d

    if len(points) < 50:
        raise AutoalignError(f"only {len(points)} points were reconstructed; too few to find the table plane "
                             "(film the table with more texture)")
    o3d.utility.random.seed(seed)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    extent = float(np.median(np.linalg.norm(points - points.mean(0), axis=1)))
    (a, b, c, d), inl = pcd.segment_plane(INLIER_FRACTION_OF_EXTENT * extent, 3, 2000)
    n = np.array([a, b, c], dtype=np.float64)
    norm = float(np.linalg.norm(n))
    n, d = n / norm, d / norm
    inl = np.asarray(inl, dtype=np.int64)
    P = points[inl]
    # refine by least squares on the inliers (RANSAC's plane comes from three of them)
    centre = P.mean(0)
    n_ls = np.linalg.svd(P - centre, full_matrices=False)[2][2]  # not the (N, N) U of a full SVD
    n = n_ls if n_ls @ n > 0 else -n_ls
    if (camera_centres.mean(0) - centre) @ n < 0:
        n = -n
    rms = float(np.sqrt(np.mean(((P - centre) @ n) ** 2)))
    return TablePlane(n, centre, len(inl) / len(points), rms)


def table_frame(plane: TablePlane, x_hint: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_table_world`` (4x4): maps the reconstruction's world to the table frame, whose z is the
    plane normal, origin the plane point, and x the direction of ``x_hint`` in the plane."""
    z = plane.normal
    x = x_hint - (x_hint @ z) * z
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x = x / np.linalg.norm(x)
    R_wt = np.column_stack([x, np.cross(z, x), z])  # table axes in the world
    return np.linalg.inv(make_pose(R_wt, plane.point))
