"""Depth that sees through an object: glass, for a structured-light or time-of-flight sensor.

Where the instance's masks show the object and the object at a pose covers the pixel, an opaque
surface is measured on the object, within the sensor's noise. Through glass the sensor measures
what is behind it, or nothing (holes). A view *sees through* a sample when its measurement lies
behind the rendered surface by more than the occluder margin (:class:`~autoalign.losses.depth.DepthNoise`:
the larger of ``occluder_mm`` and 5 sigma) or is missing. Such depth is not evidence about the
object's surface: it must neither pull the pose nor fail it (:class:`SeeThrough` says so, with
the numbers).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.losses.depth import MAX_SAMPLES, MIN_SAMPLES_TO_JUDGE, DepthNoise
from autoalign.losses.term import Stance, TermEvidence
from autoalign.rasterizers.ray_casting import RayCaster

SEES_THROUGH = 0.5
"""Median share (over the views that can judge) of the object's samples inside its masks whose
depth lies behind its surface or is missing, at or above which the depth sees through the object.
Measured at the true poses: synthetic glass (the sensor seeing the table through it, holes in
blobs on it) 0.996-0.998, opaque objects beside it 0.04 (the sensor's 3% holes and its one pixel
of misregistration); the real YCB-Video frames' labels 0.02, 0.05 and 0.14 (the mug, its thin
handle); at the poses the masks give on ``see_through_depth``'s glass 0.98-1.00."""


@dataclass
class SeeThrough:
    """The measured depth of an object that it sees through (module doc): per view the share of the
    object's samples inside its masks measured behind its surface or missing (NaN: fewer than
    :data:`~autoalign.losses.depth.MIN_SAMPLES_TO_JUDGE` samples), at the pose it was measured at;
    ``declared``: the model is declared transparent (``materials.json``), whatever the share."""

    share: NDArray[np.float64]
    declared: bool = False
    name = "depth"

    @property
    def median_share(self) -> float | None:
        """The median share over the views that can judge (``None``: none can)."""
        s = self.share[np.isfinite(self.share)]
        return float(np.median(s)) if len(s) else None

    def sees_through(self) -> bool:
        """Whether the depth is to be read as seeing through the object: declared, or measured so."""
        m = self.median_share
        return self.declared or (m is not None and m >= SEES_THROUGH)

    def record(self) -> dict[str, Any]:
        """Whether the depth sees through the object, whether that was declared, and per view the share."""
        return {"sees_through": self.sees_through(), "declared": self.declared, "through_share": self.share}

    def evidence(self) -> TermEvidence:
        """No evidence about the object (:attr:`~autoalign.losses.term.Stance.NO_EVIDENCE`), with its
        reason: never a contradiction."""
        m = self.median_share
        numbers = "" if m is None else (f": a median {100 * m:.0f}% of its depth samples inside its masks lie "
                                        "behind its surface or are missing")
        how = "declared transparent in materials.json" if self.declared else "recognised as transparent to depth"
        return TermEvidence(self.name, Stance.NO_EVIDENCE, m if m is not None else float("nan"),
                            f"the measured depth sees through this object ({how}{numbers}); it is not used",
                            fails=False, sees_outline=False, reliability=self.share)


def see_through_shares(caster: RayCaster, mesh: Mesh, T_wm: NDArray[np.float64], cameras: list[Camera],
                       depths: list[NDArray[np.float32]], masks: list[NDArray[np.float32]],
                       noise: DepthNoise = DepthNoise(), max_samples: int = MAX_SAMPLES) -> NDArray[np.float64]:
    """Per view, the share of the pixels inside the instance's mask (> 0.5) that the mesh at ``T_wm``
    (world from model, mm) covers whose measured depth (mm along the optical axis, 0 = none) lies
    behind the rendered surface by more than the occluder margin or is missing (module doc); NaN
    where fewer than ``MIN_SAMPLES_TO_JUDGE`` such pixels are sampled (a grid of about ``max_samples``)."""
    out = np.full(len(cameras), np.nan)
    samples = []
    for mask in masks:
        rows, cols = np.nonzero(np.asarray(mask) > 0.5)
        step = max(1, int(np.ceil(len(rows) / max_samples)))
        samples.append((rows[::step], cols[::step]) if len(rows) >= MIN_SAMPLES_TO_JUDGE else (rows[:0], cols[:0]))
    rays = [cam.depth_rays(cols, rows).astype(np.float32) for cam, (rows, cols) in zip(cameras, samples)]  # unit z
    cast = caster.first_hits_from(T_wm, [c.centre for c in cameras], rays)  # t is depth
    for k, (measured, (rows, cols), hits) in enumerate(zip(depths, samples, cast)):
        if len(rows) == 0:
            continue
        z_r = hits.t.astype(np.float64)
        hit = np.isfinite(z_r)
        if hit.sum() < MIN_SAMPLES_TO_JUDGE:
            continue
        out[k] = float(np.mean(seen_through(measured[rows[hit], cols[hit]], z_r[hit], noise)))
    return out


def seen_through(z_measured: NDArray[np.floating], z_surface: NDArray[np.floating],
                 noise: DepthNoise = DepthNoise()) -> NDArray[np.bool_]:
    """Per sample, whether the measured depth (mm along the optical axis, 0 = none) is missing or lies
    behind the object's surface there (``z_surface``, mm) by more than the occluder margin (the
    larger of ``noise.occluder_mm`` and 5 sigma)."""
    z_m, z_r = np.asarray(z_measured, dtype=np.float64), np.asarray(z_surface, dtype=np.float64)
    return (z_m <= 0) | (z_m > z_r + np.maximum(noise.occluder_mm, 5.0 * noise.sigma(z_r)))


def through_share(z_measured: NDArray[np.floating], z_surface: NDArray[np.floating],
                  noise: DepthNoise = DepthNoise()) -> float:
    """The share of the samples whose depth is :func:`seen_through` (NaN below
    :data:`~autoalign.losses.depth.MIN_SAMPLES_TO_JUDGE` samples): one view's measure, as
    :func:`see_through_shares` makes it from rays and ``check`` from its rendering of a label."""
    if np.size(z_surface) < MIN_SAMPLES_TO_JUDGE:
        return float("nan")
    return float(np.mean(seen_through(z_measured, z_surface, noise)))
