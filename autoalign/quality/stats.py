"""Means of pixel distances with 95% percentile-bootstrap intervals, over values or over groups (views)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

N_BOOTSTRAP = 1000
"""Bootstrap resamples for the 95% confidence intervals."""

def bootstrap_mean_ci(values: NDArray[np.float64], rng: np.random.Generator,
                      n_boot: int = N_BOOTSTRAP) -> tuple[float, float] | None:
    """95% percentile bootstrap interval of the mean of ``values`` (None below 2 values)."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < 2:
        return None
    idx = rng.integers(0, values.size, size=(n_boot, values.size))
    means = values[idx].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def bootstrap_pooled_ci(groups: Sequence[NDArray[np.float64]], rng: np.random.Generator,
                        n_boot: int = N_BOOTSTRAP) -> tuple[float, float] | None:
    """95% bootstrap interval of the pooled mean of several groups (views), resampling whole
    groups; with a single non-empty group it resamples that group's values instead."""
    groups = [np.asarray(g, dtype=np.float64) for g in groups if len(g) > 0]
    if not groups:
        return None
    if len(groups) == 1:
        return bootstrap_mean_ci(groups[0], rng, n_boot)
    sums = np.array([g.sum() for g in groups])
    counts = np.array([g.size for g in groups], dtype=np.float64)
    idx = rng.integers(0, len(groups), size=(n_boot, len(groups)))
    means = sums[idx].sum(axis=1) / counts[idx].sum(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def pooled_mean_ci(groups: Sequence[NDArray[np.float64]], rng: np.random.Generator
                   ) -> tuple[float | None, tuple[float, float] | None]:
    """The mean of all values of ``groups`` (views) pooled, and its :func:`bootstrap_pooled_ci`;
    ``(None, None)`` without groups."""
    if not groups:
        return None, None
    return float(np.concatenate(groups).mean()), bootstrap_pooled_ci(groups, rng)
