"""The calibration of many views stacked into arrays, for vectorised projection and ray casting."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera


@dataclass
class CameraBatch:
    """N views' ``K`` (N, 3, 3; internal pixel convention), its inverse, world-to-camera ``R``/``t``
    (mm), camera-to-world ``R``, camera centres (N, 3; world, mm) and image sizes (N, 2: width, height)."""

    K: NDArray[np.float64]
    K_inv: NDArray[np.float64]
    R_w2c: NDArray[np.float64]
    t_w2c: NDArray[np.float64]
    R_c2w: NDArray[np.float64]
    centres: NDArray[np.float64]
    sizes: NDArray[np.int64]

    @staticmethod
    def of(cameras: list[Camera]) -> "CameraBatch":
        K = np.stack([c.K for c in cameras])
        R = np.stack([c.R_w2c for c in cameras])
        t = np.stack([c.t_w2c for c in cameras])
        sizes = np.array([[c.width, c.height] for c in cameras], dtype=np.int64)
        return CameraBatch(K, np.linalg.inv(K), R, t, R.transpose(0, 2, 1), -np.einsum("nji,nj->ni", R, t), sizes)


def per_view_matvec(M: NDArray[np.float64], view: NDArray[np.int64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``M[view[k]] @ x[k]`` for every row ``k`` of ``x`` (n, 3), one matrix product per view.

    Fast when rows come grouped by view (they are sorted first otherwise).
    """
    out = np.empty((len(x), M.shape[1]))
    if len(x) == 0:
        return out
    order = None if np.all(view[1:] >= view[:-1]) else np.argsort(view, kind="stable")
    v = view if order is None else view[order]
    xs = x if order is None else x[order]
    bounds = np.searchsorted(v, np.arange(len(M) + 1))
    res = np.empty_like(out)
    for i in np.flatnonzero(np.diff(bounds)):
        res[bounds[i]:bounds[i + 1]] = xs[bounds[i]:bounds[i + 1]] @ M[i].T
    if order is None:
        return res
    out[order] = res
    return out
