"""Robust per-view weights, so that a few wrong masks do not pull the pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def cauchy_weights(residual: NDArray[np.float64], c: float = 2.0, floor: float = 1e-3) -> NDArray[np.float64]:
    """Cauchy (Lorentzian) IRLS weights ``1 / (1 + (r / (c * scale))^2)``, ``scale = median(r)``.

    ``residual`` is a per-view misfit such as ``1 - IoU``. Views fitting as well as the typical view
    keep a weight near 1; a view ``k`` times worse than the median gets about ``(c / k)^2``.
    ``floor`` keeps the scale positive once every view fits almost perfectly.
    """
    r = np.asarray(residual, dtype=np.float64)
    scale = max(float(np.median(r)), floor)
    return 1.0 / (1.0 + (r / (c * scale)) ** 2)
