"""Metric scale of a structure-from-motion reconstruction from aligned depth images."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.recon.sfm import SfmResult


@dataclass(frozen=True)
class ScaleEstimate:
    """``scale``: mm per reconstruction unit (median of sensor depth / reconstructed depth at the
    keypoints); ``spread``: half the 16-84 percentile range of those ratios, relative to the median;
    ``n``: ratios used."""

    scale: float
    spread: float
    n: int


def scale_from_depth(sfm: SfmResult, depth_mm: dict[int, NDArray[np.float64]]) -> ScaleEstimate | None:
    """The scale from every registered frame's keypoints that see a 3D point and have a depth
    measurement at their pixel (``depth_mm[frame id]``: (H, W) z in mm, 0 = none); ``None`` if none do.
    The median makes it robust to keypoints on depth edges, where the sensor sees another surface."""
    ratios = []
    for fid, T in sfm.T_cw.items():
        if fid not in depth_mm or fid not in sfm.observations:
            continue
        uv, idx = sfm.observations[fid]
        if len(idx) == 0:
            continue
        d = depth_mm[fid]
        j = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, d.shape[1] - 1)
        i = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, d.shape[0] - 1)
        z_sfm = sfm.points[idx] @ T[2, :3] + T[2, 3]
        z_mm = d[i, j]
        ok = (z_mm > 0) & (z_sfm > 1e-9)
        ratios.append(z_mm[ok] / z_sfm[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(r) < 10:
        return None
    med = float(np.median(r))
    lo, hi = np.percentile(r, [16, 84])
    return ScaleEstimate(med, float((hi - lo) / 2.0 / med), len(r))
