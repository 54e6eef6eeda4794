"""The table plane (RANSAC) and the world frame it defines: z up, the table at z = 0.

The RANSAC is numpy's, with a generator of its own per fit: open3d's ``segment_plane`` draws from
one process-wide generator on OpenMP threads, so two fits at once (instances refined side by side)
gave planes up to 0.3 deg apart, and the same fit differed between threads."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.se3 import make_pose

INLIER_FRACTION_OF_EXTENT = 0.01
"""A point is on the plane when it is closer than this fraction of the points' median distance
from their centroid (a fraction, since without depth the reconstruction has no unit)."""
DRAWS = 2000
"""Planes through three points drawn at random that RANSAC compares."""
CONFIDENCE = 0.99999999
"""RANSAC stops drawing once a better plane than its best would have been drawn with this
probability (open3d's default)."""
SCORED = 20_000
"""Points drawn once on which the drawn planes are scored (all of them when there are fewer)."""
_CHUNK = 128


@dataclass(frozen=True)
class TablePlane:
    """``normal`` (unit, towards the cameras) and ``point`` (on the plane), in the reconstruction's
    world frame; ``inliers``: fraction of the points on it; ``rms``: their distance to it (same unit)."""

    normal: NDArray[np.float64]
    point: NDArray[np.float64]
    inliers: float
    rms: float


def fit_table_plane(points: NDArray[np.float64], camera_centres: NDArray[np.float64], seed: int = 0) -> TablePlane:
    """The dominant plane of ``points`` (N, 3) by RANSAC (:func:`ransac_plane`) refined by least
    squares on its inliers, its normal turned towards the mean of ``camera_centres``. The same
    points and ``seed`` give the same plane, on any thread."""
    if len(points) < 50:
        raise AutoalignError(f"only {len(points)} points were reconstructed; too few to find the table plane "
                             "(film the table with more texture)")
    points = np.asarray(points, dtype=np.float64)
    extent = float(np.median(np.linalg.norm(points - points.mean(0), axis=1)))
    P = points[ransac_plane(points, INLIER_FRACTION_OF_EXTENT * extent, np.random.default_rng(seed))]
    if len(P) < 3:
        raise AutoalignError(f"the {len(points)} points reconstructed lie on no plane (on one line or one point); "
                             "the table plane cannot be found (film the table with more texture)")
    # refine by least squares on the inliers (RANSAC's plane comes from three of them)
    centre = P.mean(0)
    n = np.linalg.svd(P - centre, full_matrices=False)[2][2]  # not the (N, N) U of a full SVD
    if (camera_centres.mean(0) - centre) @ n < 0:
        n = -n
    rms = float(np.sqrt(np.mean(((P - centre) @ n) ** 2)))
    return TablePlane(n, centre, len(P) / len(points), rms)


def ransac_plane(points: NDArray[np.float64], threshold: float, rng: np.random.Generator) -> NDArray[np.bool_]:
    """Which of ``points`` (N, 3) lie within ``threshold`` (their unit) of the plane through three of
    them that the most of :data:`SCORED` points drawn by ``rng`` lie near, of at most :data:`DRAWS`
    such planes (the first of equally good ones; fewer when :data:`CONFIDENCE` is reached). None
    when no three of the points drawn span a plane."""
    origin = points.mean(0)  # distances from centred points lose no digits far from the origin
    centred = points - origin
    n = len(points)
    scored = centred[rng.choice(n, SCORED, replace=False)] if n > SCORED else centred
    triples = centred[rng.integers(0, n, (DRAWS, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 1e-12 * max(float(np.abs(centred).max()), 1e-300) ** 2  # three distinct points
    normals[usable] /= lengths[usable, None]
    offsets = -np.einsum("ij,ij->i", normals, triples[:, 0])
    counts = np.full(DRAWS, -1, dtype=np.int64)
    for lo in range(0, DRAWS, _CHUNK):
        hi = min(lo + _CHUNK, DRAWS)
        near = np.abs(scored @ normals[lo:hi].T + offsets[lo:hi]) < threshold
        counts[lo:hi] = np.where(usable[lo:hi], near.sum(0), -1)
        if hi >= _draws_needed(counts.max() / len(scored)):
            break
    best = int(np.argmax(counts))
    if counts[best] < 0:
        return np.zeros(n, dtype=bool)
    return np.abs(centred @ normals[best] + offsets[best]) < threshold


def _draws_needed(inlier_share: float) -> float:
    """Draws after which a plane through three inliers of a plane holding ``inlier_share`` of the
    points has been drawn with probability :data:`CONFIDENCE`."""
    all_three = inlier_share ** 3
    if all_three <= 0.0:
        return np.inf
    if all_three >= 1.0:
        return 1.0
    return np.log1p(-CONFIDENCE) / np.log1p(-all_three)


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
