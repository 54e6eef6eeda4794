"""The depth term: the object's rendered depth against a sensor's measured depth, per view.

For each sampled pixel inside the object's rendered silhouette with a measurement, the residual is
point to plane, as in KinectFusion and ICG's depth modality (projective association: the measured
point is the one on the same pixel's ray; point to plane converges from farther than point to
point): ``r = n . (X - X_meas)`` (mm), with ``X`` the rendered surface point and ``n`` its normal
(world frame). Its noise is a structured-light / time-of-flight sensor's, ``sigma_z`` growing with
the square of the distance (:class:`DepthNoise`).

Robust to what a capture has: pixels without a measurement (0) are not used; a measurement much
nearer than the rendered surface is an unmodelled occluder that hides the object there, not a
residual; the rest pass through a Cauchy loss (scale :data:`CAUCHY_C` sigmas), so holes, edges and
one or two pixels of colour-depth misregistration weigh little.

The per-view terms are means over the view's used pixels, in units of the noise, with their
gradients and Gauss-Newton matrices with respect to the pose twist ``(v mm, w rad)`` about a
centre (:func:`~autoalign.geometry.se3.apply_twist`): a surface point moves by ``v + w x (X - c)``,
so ``dr/dxi = [n, (X - c) x n]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera, uv_from_opencv
from autoalign.geometry.mesh import Mesh
from autoalign.losses.silhouette import ViewTerms
from autoalign.losses.term import Fragments, LevelViews, Stance, TermEvidence, TermValues
from autoalign.rasterizers.ray_casting import RayCaster

CAUCHY_C = 2.5
"""Residuals are down-weighted beyond this many sigmas (Cauchy: weight ``1 / (1 + (r / c sigma)^2)``)."""
INLIER_SIGMAS = 3.0
"""A residual within this many sigmas agrees with the measurement (:attr:`DepthTerms.inliers`)."""
SUPPORTS = 0.8
"""Median share (over the views) of the object's depth samples within ``INLIER_SIGMAS`` sigma of the
measurement at or above which the depth supports the pose. On the real YCB-Video frames the
dataset's labels give 0.97-1.0 and the same poses moved 5 mm along the ray 0.83-0.96, 10 mm 0.02-0.14."""
CONTRADICTS = 0.5
"""Below this median share the measured depth contradicts the pose, and fails it whatever the masks say."""
MIN_SAMPLES_TO_JUDGE = 50
"""A view with fewer depth samples on the object says nothing about it."""
MAX_SAMPLES = 4000
"""At most about this many pixels of a view are cast: the term's cost stays small next to the mask's."""
SAMPLES_MIN = 250
"""Below full resolution the term samples fewer pixels (in proportion to the level's scale), but at least these."""
PART_SHARE = 0.02
"""A piece of the surface (:attr:`~autoalign.geometry.mesh.Mesh.parts`) with at least this share of
the object's depth samples that is off in most of the views that see it is a part of the pose that
the depth contradicts (:meth:`DepthTerms.part_off`), however well the rest agrees ..."""
PART_SAMPLES = 10
"""... a view sees a piece when at least this many of its samples fall on it; the piece is off there
when most of them lie beyond ``INLIER_SIGMAS`` sigma. At the 45 right results of the 16 opaque and
metal instances of the path-traced glass scenes (three conditions), no piece was off in more than
10% of its views, and at the real YCB-Video frames' labels in none; at two ladles placed 47-59 mm
and 71-94 deg off with their bowls on the right one (91% and 80% of all samples agreeing), their
handles were off in 63% and 100%."""
PART_MIN_VIEWS = 3
"""A piece seen in fewer views than this says nothing."""


@dataclass(frozen=True)
class DepthNoise:
    """Depth noise of a Kinect-class sensor: ``sigma_z = max(floor_mm, k z^2)`` (z in m).

    Attributes:
        k_mm_per_m2: 1.5 mm at 0.6 m and 5 mm at 1.2 m give 4.2 and 3.5; the larger is kept.
        floor_mm: the least sigma (quantisation, and the mesh's own error).
        occluder_mm: a measurement nearer than the rendered surface by more than this and 5 sigma
            is an unmodelled occluder in front of the object.
    """

    k_mm_per_m2: float = 4.2
    floor_mm: float = 1.0
    occluder_mm: float = 20.0

    def sigma(self, z_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Sigma (mm) of a measurement at depth ``z_mm``."""
        return np.maximum(self.floor_mm, self.k_mm_per_m2 * (np.asarray(z_mm, dtype=np.float64) / 1000.0) ** 2)


@dataclass(frozen=True)
class PartOff:
    """A piece of the surface (``part``, :attr:`~autoalign.geometry.mesh.Mesh.parts`) holding ``share``
    of the object's depth samples, off (most of its samples beyond :data:`INLIER_SIGMAS` sigma) in
    ``views_off`` of the ``views_seen`` views that see it."""

    part: int
    share: float
    views_off: int
    views_seen: int


@dataclass
class DepthTerms:
    """Per-view depth terms of ``N`` views: ``loss`` (N,), ``grad`` (N, 6), ``gn`` (N, 6, 6) (means
    over the used pixels, in noise units), ``used`` (N,) pixels used, ``hidden`` (N,) pixels where an
    unmodelled occluder is in front of the object, ``rms_mm`` (N,) the used residuals' RMS (NaN: none),
    ``inliers`` (N,) the share of the used residuals within :data:`INLIER_SIGMAS` sigma (NaN: none);
    ``occluders``: per view the sampled pixels (rows, cols, full resolution) found hidden, and the
    sampling ``stride`` (px) per view; ``part_used`` and ``part_inliers`` (N, P): per view the used
    samples on each piece of the surface (:attr:`~autoalign.geometry.mesh.Mesh.parts`) and how many
    of them are within :data:`INLIER_SIGMAS` sigma."""

    loss: NDArray[np.float64]
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]
    used: NDArray[np.int64]
    hidden: NDArray[np.int64]
    rms_mm: NDArray[np.float64]
    inliers: NDArray[np.float64]
    occluders: list[tuple[NDArray[np.int64], NDArray[np.int64]]]
    stride: NDArray[np.int64]
    part_used: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 0), np.int64))
    part_inliers: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 0), np.int64))
    name = "depth"

    def record(self) -> dict[str, Any]:
        """Per view: pixels used, pixels where an unmodelled occluder is in front, the residuals' RMS
        (mm) and the term's loss (noise units)."""
        part = self.part_off()
        off = None if part is None else {"share": part.share, "views_off": part.views_off, "views_seen": part.views_seen}
        return {"used_px": self.used, "hidden_px": self.hidden, "rms_mm": self.rms_mm, "loss": self.loss,
                "part_off": off}

    def evidence(self) -> TermEvidence | None:
        """What the depth says of the pose (:class:`~autoalign.losses.term.TermEvidence`): the median over
        the views with at least ``MIN_SAMPLES_TO_JUDGE`` samples of the share within ``INLIER_SIGMAS``
        sigma; ``None`` without such views."""
        judged = self.used >= MIN_SAMPLES_TO_JUDGE
        if not judged.any():
            return None
        agree = float(np.median(self.inliers[judged]))
        within = f"a median {agree:.0%} of the object's depth samples within {INLIER_SIGMAS:g} sigma"
        part = self.part_off()
        fails = True
        if agree < CONTRADICTS:
            stance, reason = Stance.CONTRADICTS, f"the measured depth disagrees: {within} (< {CONTRADICTS:.0%})"
        elif part is not None:  # the rest may agree, but a piece of the object is where the depth says it is not
            stance, fails = Stance.CONTRADICTS, False
            reason = (f"the measured depth disagrees with a part of the object ({part.share:.0%} of its depth samples), "
                      f"off in {part.views_off} of the {part.views_seen} views that see it, though {within}: "
                      "look at its outline against the photo in overlay.png")
        elif agree >= SUPPORTS:
            stance, reason = Stance.SUPPORTS, f"the measured depth agrees: {within}"
        else:
            stance, reason = Stance.NEUTRAL, f"the measured depth neither confirms nor contradicts the pose: {within}"
        return TermEvidence("depth", stance, agree, reason, fails=fails,
                            reliability=np.where(judged, self.inliers, np.nan))

    def part_off(self) -> "PartOff | None":
        """The piece of the surface the depth contradicts (:data:`PART_SHARE`; the one off in the
        largest share of the views that see it), or ``None``."""
        if self.part_used.size == 0 or self.part_used.sum() == 0:
            return None
        share = self.part_used.sum(axis=0) / self.part_used.sum()
        seen = self.part_used >= PART_SAMPLES
        off = seen & (2 * self.part_inliers < self.part_used)
        n_seen, n_off = seen.sum(axis=0), off.sum(axis=0)
        bad = np.flatnonzero((share >= PART_SHARE) & (n_seen >= PART_MIN_VIEWS) & (2 * n_off > n_seen))
        if not len(bad):
            return None
        p = int(bad[np.argmax(n_off[bad] / n_seen[bad])])
        return PartOff(p, float(share[p]), int(n_off[p]), int(n_seen[p]))

    def hidden_mask(self, k: int, shape: tuple[int, int], scale: float) -> NDArray[np.bool_]:
        """View ``k``'s pixels, at ``scale`` of the full resolution (``shape`` (h, w) there), that
        its occluders hide: each hidden sample stands for its ``stride``-wide cell."""
        h, w = shape
        rows, cols = self.occluders[k]
        hidden = np.zeros((h, w), dtype=bool)
        if len(rows) == 0:
            return hidden
        half = self.stride[k] / 2.0
        # each cell's edges in continuous coordinates, at the level's resolution, clipped to the image
        y0 = np.clip(np.floor(uv_from_opencv(rows - half) * scale).astype(np.int64), 0, h)
        y1 = np.clip(np.ceil(uv_from_opencv(rows + half) * scale).astype(np.int64), 0, h)
        x0 = np.clip(np.floor(uv_from_opencv(cols - half) * scale).astype(np.int64), 0, w)
        x1 = np.clip(np.ceil(uv_from_opencv(cols + half) * scale).astype(np.int64), 0, w)
        keep = (y1 > y0) & (x1 > x0)
        if not keep.any():
            return hidden
        # the cells painted at once, on their box (beyond it nothing is painted): a 2D difference image
        top, left = int(y0[keep].min()), int(x0[keep].min())
        y0, y1, x0, x1 = y0[keep] - top, y1[keep] - top, x0[keep] - left, x1[keep] - left
        bh, bw = int(y1.max()), int(x1.max())
        corners = np.zeros((bh + 1, bw + 1), dtype=np.int64)
        np.add.at(corners, (y0, x0), 1)
        np.add.at(corners, (y0, x1), -1)
        np.add.at(corners, (y1, x0), -1)
        np.add.at(corners, (y1, x1), 1)
        hidden[top:top + bh, left:left + bw] = np.cumsum(np.cumsum(corners, axis=0), axis=1)[:bh, :bw] > 0
        return hidden


def sample_pixels(camera: Camera, mesh: Mesh, T_wm: NDArray[np.float64], measured: NDArray[np.float32],
                  max_samples: int = MAX_SAMPLES) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """Rows and columns of the pixels with a measurement inside the box of the mesh's projection
    at ``T_wm`` (a regular grid thinned to at most about ``max_samples``), and the grid's stride (px)."""
    H, W = measured.shape
    X_w = mesh.hull @ T_wm[:3, :3].T + T_wm[:3, 3]
    if np.any(camera.to_camera(X_w)[:, 2] <= 1e-6):
        x0, y0, x1, y1 = 0, 0, W, H  # the object reaches behind the camera: the whole image
    else:
        uv = camera.project(X_w)
        x0, y0 = max(int(np.floor(uv[:, 0].min())), 0), max(int(np.floor(uv[:, 1].min())), 0)
        x1, y1 = min(int(np.ceil(uv[:, 0].max())), W), min(int(np.ceil(uv[:, 1].max())), H)
    if x0 >= x1 or y0 >= y1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 1
    stride = max(1, int(np.ceil(np.sqrt((x1 - x0) * (y1 - y0) / max_samples))))
    rows, cols = np.mgrid[y0:y1:stride, x0:x1:stride]
    rows, cols = rows.ravel(), cols.ravel()
    keep = measured[rows, cols] > 0
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64), stride


def depth_terms(caster: RayCaster, mesh: Mesh, T_wm: NDArray[np.float64], cameras: list[Camera],
                depths: list[NDArray[np.float32]], centre_w: NDArray[np.float64],
                noise: DepthNoise = DepthNoise(), max_samples: int = MAX_SAMPLES,
                masks: list[NDArray[np.float32]] | None = None) -> DepthTerms:
    """The depth terms of the mesh at ``T_wm`` (world from model, mm) against ``depths`` (one (H, W)
    image per camera, mm along the optical axis, 0 = no measurement), twists about ``centre_w``.

    With the instance's visible ``masks`` (same size, > 0.5 = the object) a pixel inside its mask is
    never an occluder: it is the object, however far the pose still is (a start 20 mm too far
    would otherwise see its own surface as something in front of it)."""
    n = len(cameras)
    none = np.zeros(0, np.int64)
    parts = mesh.parts
    n_parts = int(parts.max()) + 1 if len(parts) else 0
    out = DepthTerms(np.zeros(n), np.zeros((n, 6)), np.zeros((n, 6, 6)), np.zeros(n, np.int64),
                     np.zeros(n, np.int64), np.full(n, np.nan), np.full(n, np.nan), [(none, none)] * n,
                     np.ones(n, np.int64), np.zeros((n, n_parts), np.int64), np.zeros((n, n_parts), np.int64))
    normals_m = mesh.face_normals
    samples = [sample_pixels(cam, mesh, T_wm, measured, max_samples) for cam, measured in zip(cameras, depths)]
    rays = [cam.depth_rays(cols, rows) for cam, (rows, cols, _) in zip(cameras, samples)]  # unit z: t is depth
    cast = caster.first_hits_from(T_wm, [c.centre for c in cameras], [d.astype(np.float32) for d in rays])
    for k, (cam, measured, (rows, cols, stride), d_w, hits) in enumerate(zip(cameras, depths, samples, rays, cast)):
        out.stride[k] = stride
        if len(rows) == 0:
            continue
        z_r = hits.t.astype(np.float64)
        z_m = measured[rows, cols].astype(np.float64)
        hit = np.isfinite(z_r)
        sigma = noise.sigma(z_m)
        occluded = hit & (z_m < z_r - np.maximum(noise.occluder_mm, 5.0 * sigma))
        if masks is not None:
            occluded &= ~(masks[k][rows, cols] > 0.5)
        use = hit & ~occluded
        out.hidden[k] = int(occluded.sum())
        out.occluders[k] = (rows[occluded], cols[occluded])
        if not use.any():
            continue
        d, z_r, z_m, sigma = d_w[use], z_r[use], z_m[use], sigma[use]
        n_w = normals_m[hits.prim[use]] @ T_wm[:3, :3].T
        n_w *= -np.sign(np.einsum("ij,ij->i", n_w, d))[:, None]  # facing the camera
        X = cam.centre + z_r[:, None] * d
        r = (z_r - z_m) * np.einsum("ij,ij->i", n_w, d)  # n . (X - X_meas), mm
        J = np.concatenate([n_w, np.cross(X - centre_w, n_w)], 1)
        u = r / (CAUCHY_C * sigma)
        w = 1.0 / (1.0 + u * u)  # Cauchy IRLS weight
        m = len(r)
        out.loss[k] = float(np.sum(0.5 * CAUCHY_C ** 2 * np.log1p(u * u))) / m
        a = w / sigma ** 2
        out.grad[k] = (a * r) @ J / m
        out.gn[k] = (J * a[:, None]).T @ J / m
        out.used[k] = m
        out.rms_mm[k] = float(np.sqrt(np.mean(r * r)))
        inlier = np.abs(r) < INLIER_SIGMAS * sigma
        out.inliers[k] = float(np.mean(inlier))
        on = parts[hits.prim[use]]
        out.part_used[k] = np.bincount(on, minlength=n_parts)
        out.part_inliers[k] = np.bincount(on[inlier], minlength=n_parts)
    return out


class DepthTerm:
    """The depth term (module doc) as an evidence term: the level's views' measured depth against the
    mesh at the fragments' pose, cast at the level's detail; the pixels it finds hidden by an
    unmodelled occluder are off for the terms after it (the masks do not see the object there)."""

    name = "depth"

    def __init__(self, noise: DepthNoise) -> None:
        self.noise = noise

    def residuals(self, fragments: Fragments) -> TermValues:
        f = fragments
        d = self.measure(f.rasterizer.caster, f.rasterizer.mesh, f.T_wm, f.centre_w, f.views, f.scale)
        hidden = None
        if d.hidden.any():
            hidden = [d.hidden_mask(k, (c.height, c.width), f.scale) for k, c in enumerate(f.views.cameras)]
        return TermValues(self.name, ViewTerms(d.loss, d.grad, d.gn), hidden=hidden, measured=d)

    def measure(self, caster: RayCaster, mesh: Mesh, T_wm: NDArray[np.float64], centre_w: NDArray[np.float64],
                views: LevelViews, scale: float) -> DepthTerms:
        """The depth terms of a mesh at ``T_wm`` in ``views`` (with measured depth) at a level of
        ``scale``, without the hidden pixels' images (the joint stage reads the terms alone)."""
        if views.depths is None:
            raise ValueError("the views have no measured depth")
        return depth_terms(caster, mesh, T_wm, views.full_cameras, views.depths, centre_w, self.noise,
                           max(SAMPLES_MIN, int(MAX_SAMPLES * scale)), views.full_targets)
