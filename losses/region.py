"""The region term's evidence: per view, colour models of the object and of its surroundings, and
the pixel-wise posterior that a pixel shows the object (PWP3D, RBOT, SRT3D).

At a pose, the object's hard silhouette in a view splits a band around its outline into an inside
and an outside. A colour histogram of each (:class:`ColourModel`, RGB, ``bins`` per channel) gives
per pixel the likelihoods ``P(y | object)`` and ``P(y | surroundings)``, and with equal priors (the
two halves of the band are about the same size, as in RBOT) the posterior
``p(x) = P(y | object) / (P(y | object) + P(y | surroundings))``. That posterior image is the
region term's target (:func:`region_target`): the soft silhouette ``s(x)`` and its Jacobian meet it
in the same per-pixel residual ``s(x) - p(x)`` as a mask (:func:`~autoalign.losses.silhouette.l2`),
so the photo joins the Levenberg-Marquardt system like the mask term. A colour both models share
gives ``p = 1/2``, whose residual is the same for ``s = 0`` and ``s = 1``: it pulls nowhere.

With the histograms held fixed the target is a fixed image and the objective a function of the pose
alone, so the solver's steps are compared on one objective; the histograms are learned again from
the pose reached, as RBOT and PWP3D learn them again per frame (:mod:`autoalign.engine.photo_evidence`).

Where the instance has a mask, its pixels train the object's model, never the surroundings', and
mask and colour are two independent pieces of evidence for each pixel of the band: their odds
multiply (the mask's from how often real segmenter masks are right, :data:`MASK_TRUST` and
:data:`MASK_MISS`, or, where the colours confirm the mask's own outline (:data:`EDGE_SUPPORTS`),
from how well it fits the pose where it fits better: :func:`mask_rates`). A pixel the mask misses but whose colour is clearly the object's becomes the
object (the photo completes a mask that misses parts); one the mask claims against clearly
background colours becomes undecided (1/2, no pull); and the mask keeps the object's colour model
off a look-alike background. Pixels that other modelled objects claim (``exclude``) train neither
model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class RegionOptions:
    """The region (colour) term.

    Attributes:
        bins: histogram bins per colour channel (a power of two; RBOT uses 32 for whole frames,
            a band of a few thousand pixels fills 16^3 better).
        band: half-width of the band the models are learned in, as a fraction of the
            silhouette's equivalent diameter (``sqrt(4 area / pi)``), clipped to
            ``[min_band_px, max_band_px]`` pixels; also how far beyond the silhouette the
            posterior is the target (farther out the target is 0: background).
        rounds: at most this many times the models are learned again at the pose reached at the
            schedule's first level, before the last round goes through the whole schedule.
        tol_mm, tol_deg: rounds stop once one moves the pose less than this.
        gap: the models learn from the band less its first ``gap`` (fraction of the band's
            half-width) on either side of the outline, where a pose still off puts pixels on the
            wrong side; the models' colours then come from pixels the pose has right.
        round_ftol: the rounds' Levenberg-Marquardt ``ftol`` (:class:`~autoalign.engine.objective.Level`):
            pixels whose colour both models share keep the loss high, so a step's relative decrease
            is small, and with the masks' tolerance a round stopped after one or two steps.
        sectors: the band is split into this many angular sectors about the silhouette's centre,
            each with its own pair of models (RBOT's local models: a cluttered background differs
            around the object); one with fewer than ``min_sector_px`` pixels inside or outside
            uses the models of the whole band.
    """

    bins: int = 16
    band: float = 0.25
    min_band_px: float = 6.0
    max_band_px: float = 40.0
    rounds: int = 6
    tol_mm: float = 0.3
    tol_deg: float = 0.3
    gap: float = 0.5
    min_sector_px: int = 100
    round_ftol: float = 1e-6
    sectors: int = 8

    def band_px(self, silhouette: NDArray[np.bool_]) -> float:
        """The band's half-width (px) for a silhouette."""
        diameter = float(np.sqrt(4.0 * np.count_nonzero(silhouette) / np.pi))
        return float(np.clip(self.band * diameter, self.min_band_px, self.max_band_px))


@dataclass
class ColourModel:
    """Normalised colour histograms (``bins^3``) of the object (``fg``) and of its surroundings
    (``bg``), one pair per group of pixels (``(groups, bins^3)``: the band's angular sectors)."""

    fg: NDArray[np.float64]
    bg: NDArray[np.float64]
    bins: int

    @staticmethod
    def learn(codes: NDArray[np.int64], inside: NDArray[np.bool_], outside: NDArray[np.bool_], bins: int,
              group: NDArray[np.int64] | None = None, groups: int = 1, min_px: int = 0) -> "ColourModel":
        """Histograms of the colour ``codes`` (:func:`colour_codes`) of the ``inside`` and ``outside``
        pixels, per ``group`` (same shape as ``codes``, values ``0..groups-1``; ``None``: one group).
        A group with fewer than ``min_px`` pixels inside or outside gets the histograms of all."""
        n = bins ** 3
        key = codes if group is None else group * n + codes
        fg = np.bincount(key[inside], minlength=groups * n).astype(np.float64).reshape(groups, n)
        bg = np.bincount(key[outside], minlength=groups * n).astype(np.float64).reshape(groups, n)
        weak = np.minimum(fg.sum(1), bg.sum(1)) < min_px
        fg[weak], bg[weak] = fg.sum(0), bg.sum(0)
        return ColourModel(fg / np.maximum(fg.sum(1, keepdims=True), 1.0), bg / np.maximum(bg.sum(1, keepdims=True), 1.0),
                           bins)

    def posterior(self, codes: NDArray[np.int64], group: NDArray[np.int64] | None = None) -> NDArray[np.float64]:
        """``P(object | colour)`` with equal priors, each pixel by its group's models; a colour
        neither model has seen gives 1/2 (each histogram gets half a count's worth spread over its bins)."""
        eps = 0.5 / self.bins ** 3
        g = 0 if group is None else group
        pf, pb = self.fg[g, codes] + eps, self.bg[g, codes] + eps
        return pf / (pf + pb)


def colour_codes(photo: NDArray[np.uint8], bins: int) -> NDArray[np.int64]:
    """The histogram bin of every pixel of an (H, W, 3) uint8 photo, (H, W)."""
    shift = 8 - int(round(np.log2(bins)))
    if 2 ** (8 - shift) != bins:
        raise ValueError(f"bins must be a power of two up to 256, not {bins}")
    q = (photo >> shift).astype(np.int64)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


MASK_TRUST = 0.9
"""P(object | the mask says object): on the real LM-O SAM masks a median 9% of a mask lies off its
object (``experiments/results/sam_mask_rates.md``)."""
MASK_MISS = 0.2
"""P(object | the mask says background) near the outline: the SAM masks miss a median 17% of the
object's silhouette, in 39% of the views more than 30%; of the band's pixels a mask leaves out, about
a fifth are then the object."""
EDGE_RING_PX = (1.0, 4.0)
"""The rings either side of the outline whose posteriors give the edge contrast: from and to
this far from it (px; the first pixel is the photo's blurred edge)."""


EDGE_SUPPORTS = 0.35
"""Edge contrast (:func:`edge_contrast`) at or above which the photo's colours confirm an outline:
on the synthetic textured scenes 0.41-0.70 at the true poses, 0.33-0.50 at 2 mm / 2 deg off,
0.16-0.23 at 5 mm / 5 deg; on the real LM-O photos (Kinect v1) only 0.16-0.39 at the dataset's
labels. The verdict reads a pose's this way; a mask whose own outline the colours confirm is trusted
as far as it fits the pose (:func:`mask_rates`), one eroded by 4 px (the object's colours on both
sides of its outline) is held to the typical rates, and the colours complete it."""


def mask_rates(mask: NDArray[np.bool_], silhouette: NDArray[np.bool_]) -> tuple[float, float]:
    """A view's mask's ``P(object | mask says object)`` and ``P(object | mask says background)`` in
    the band (``mask`` and the pose's ``silhouette`` at its pixels), counted against the silhouette
    with Laplace's rule of succession, and never less reliable than segmenter masks typically are
    (:data:`MASK_TRUST`, :data:`MASK_MISS`). A mask that fits the pose is trusted as far as it fits:
    where the colours cannot tell object from surroundings (a blurred edge, a look-alike background)
    they then cannot move an outline the mask draws exactly; a mask that misses parts or strays
    is held to the typical rates, and the colours complete it."""
    said_object, said_background = silhouette[mask], silhouette[~mask]
    trust = (np.count_nonzero(said_object) + 1.0) / (said_object.size + 2.0)
    miss = (np.count_nonzero(said_background) + 1.0) / (said_background.size + 2.0)
    return max(trust, MASK_TRUST), min(miss, MASK_MISS)


@dataclass
class RegionTarget:
    """One view's region evidence: the ``target`` (H, W) float32 in [0, 1] (the posterior near the
    silhouette, fused with the mask; beyond the band the mask, or 0), the band's half-width (px), the share of the
    band's pixels whose posterior agrees with the pose's silhouette (> 1/2 inside, < 1/2 outside),
    and the edge contrast: the mean posterior in a ring just inside the outline (:data:`EDGE_RING_PX`)
    less that in the ring just outside it (near 1: the outline lies on the photo's object edge; near 0
    or below: the colours do not change there; NaN: nothing to compare)."""

    target: NDArray[np.float32]
    band_px: float
    agreement: float
    edge_contrast: float = float("nan")


def _sector_of(shape: tuple[int, int], centre: tuple[float, float], sectors: int) -> NDArray[np.int64]:
    """Each pixel's angular sector (0..sectors-1) about ``centre`` (row, column)."""
    yy, xx = np.ogrid[0:shape[0], 0:shape[1]]
    angle = np.arctan2(yy - centre[0], xx - centre[1])
    return np.minimum(((angle + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)


def region_target(photo: NDArray[np.uint8], silhouette: NDArray[np.bool_], mask: NDArray[np.float32] | None = None,
                  exclude: NDArray[np.bool_] | None = None, options: RegionOptions = RegionOptions()) -> RegionTarget:
    """The region target of one view (see the module doc). Only the box of the silhouette and its
    band is worked on: beyond it the target is the mask (or 0).

    Args:
        photo: (H, W, 3) uint8, the view's photo at the masks' resolution.
        silhouette: (H, W) the object's hard silhouette at the current pose.
        mask: the instance's mask there (> 0.5 = the object), or ``None``.
        exclude: pixels other modelled objects claim, or ``None``.
    """
    H, W = silhouette.shape
    sil_full = np.asarray(silhouette, dtype=bool)
    target = np.zeros((H, W), np.float32) if mask is None else (np.asarray(mask) > 0.5).astype(np.float32)
    rows, cols = np.flatnonzero(sil_full.any(1)), np.flatnonzero(sil_full.any(0))
    if len(rows) == 0:
        return RegionTarget(target, 0.0, float("nan"), float("nan"))
    band = options.band_px(sil_full)
    gap = options.gap * band
    r = int(np.ceil(band + gap)) + 1
    y0, y1, x0, x1 = max(rows[0] - r, 0), min(rows[-1] + r + 1, H), max(cols[0] - r, 0), min(cols[-1] + r + 1, W)
    box = (slice(y0, y1), slice(x0, x1))
    sil, known = sil_full[box], target[box] > 0.5
    ys, xs = np.nonzero(sil)
    # distances within the box: the band never reaches past it, and a silhouette cut by the box's
    # edge is the image's edge, where the distance inside is measured to the image's border too
    sil8 = np.pad(sil.astype(np.uint8), 1, constant_values=0)
    d_out = cv2.distanceTransform(1 - sil8, cv2.DIST_L2, 3)[1:-1, 1:-1]
    d_in = cv2.distanceTransform(sil8, cv2.DIST_L2, 3)[1:-1, 1:-1]
    near = d_out <= band + gap  # the silhouette and the band outside it
    inside = (sil & (d_in > gap) & (d_in <= band + gap)) | (known & near)
    outside = ~sil & (d_out > gap) & near & ~known
    excl = None if exclude is None else exclude[box]
    if excl is not None:
        inside &= ~excl
        outside &= ~excl
    # every pixel the models learn from or judge is near: work on those alone, by sector
    codes = colour_codes(photo[box][near], options.bins)
    sector = _sector_of(sil.shape, (float(ys.mean()), float(xs.mean())), options.sectors)[near]
    model = ColourModel.learn(codes, inside[near], outside[near], options.bins, sector, options.sectors,
                              options.min_sector_px)
    post = np.full(sil.shape, 0.5)
    post[near] = model.posterior(codes, sector)
    if excl is not None:
        post[excl] = 0.5
    band_pixels = near & ((d_in <= band + gap) | ~sil)
    if excl is not None:
        band_pixels &= ~excl
    fused = post
    if mask is not None:  # the mask and the colours as independent evidence: their odds multiply
        trust, miss = MASK_TRUST, MASK_MISS
        if edge_contrast(known, post, excl) >= EDGE_SUPPORTS:  # the colours change where the mask's outline is
            trust, miss = mask_rates(known[band_pixels], sil[band_pixels])
        p_mask = np.where(known, trust, miss)
        odds = p_mask / (1.0 - p_mask) * post / np.maximum(1.0 - post, 1e-6)
        fused = odds / (1.0 + odds)
    target[box] = np.where(near, fused, target[box])
    # what the photo alone says of the pose: its colours' agreement with the silhouette, and their change across it
    agree = np.where(sil, post > 0.5, post < 0.5)[band_pixels & (post != 0.5)]
    return RegionTarget(target, band, float(agree.mean()) if agree.size else float("nan"),
                        edge_contrast(sil, post, excl, (d_in, d_out)))


def edge_contrast(region: NDArray[np.bool_], post: NDArray[np.float64], exclude: NDArray[np.bool_] | None = None,
                  distances: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None) -> float:
    """The mean colour posterior ``post`` in a ring just inside ``region``'s outline less that in the
    ring just outside it (:data:`EDGE_RING_PX`; ``exclude``: pixels left out; ``distances``: the
    distances inside and outside ``region`` where known). Near 1: the colours change from the object's
    to the surroundings' along the outline; near 0: they do not change there; NaN: nothing to compare."""
    if distances is None:
        r8 = np.pad(region.astype(np.uint8), 1, constant_values=0)
        distances = (cv2.distanceTransform(r8, cv2.DIST_L2, 3)[1:-1, 1:-1],
                     cv2.distanceTransform(1 - r8, cv2.DIST_L2, 3)[1:-1, 1:-1])
    d_in, d_out = distances
    lo, hi = EDGE_RING_PX
    ring_in, ring_out = region & (d_in > lo) & (d_in <= hi), ~region & (d_out > lo) & (d_out <= hi)
    if exclude is not None:
        ring_in, ring_out = ring_in & ~exclude, ring_out & ~exclude
    return float(post[ring_in].mean() - post[ring_out].mean()) if ring_in.any() and ring_out.any() else float("nan")
