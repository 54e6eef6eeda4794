"""The table plane's RANSAC fit (``recon/plane.py``) against the plane the points were drawn on, and the
same fits run on threads at once (instances refined side by side) against each run alone."""

from __future__ import annotations

import threading

import numpy as np

from autoalign.recon.plane import fit_table_plane

CAMERAS = np.array([[0.0, 0.0, 1000.0]])


def _table_and_clutter(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """20,000 points on a tilted table (2 mm noise) and 8,000 above it; the table's unit normal."""
    rng = np.random.default_rng(seed)
    normal = np.array([0.1 * (seed + 1), -0.05 * seed, 1.0])
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    a, b = rng.uniform(-300, 300, (2, 20000))
    table = a[:, None] * u + b[:, None] * v + rng.normal(0, 2.0, 20000)[:, None] * normal
    clutter = rng.uniform(-300, 300, (8000, 3)) + rng.uniform(20, 200, 8000)[:, None] * normal
    return np.vstack([table, clutter]), normal


def test_the_fit_finds_the_table_and_fits_on_threads_at_once_are_each_the_fit_alone() -> None:
    clouds = [_table_and_clutter(k) for k in range(4)]
    alone = [fit_table_plane(points, CAMERAS) for points, _ in clouds]
    for plane, (_, normal) in zip(alone, clouds):
        # the table is 5/7 of the points, about 80% of them within the inlier distance (1% of the extent)
        assert np.degrees(np.arccos(min(1.0, plane.normal @ normal))) < 0.5 and 0.5 < plane.inliers < 5 / 7
    for _ in range(10):
        got: dict[int, object] = {}
        threads = [threading.Thread(target=lambda k=k: got.__setitem__(k, fit_table_plane(clouds[k][0], CAMERAS)))
                   for k in range(len(clouds))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for k, plane in enumerate(alone):  # open3d's one random generator: seeded and drawn by one fit at a time
            assert np.array_equal(got[k].normal, plane.normal) and got[k].inliers == plane.inliers, k
