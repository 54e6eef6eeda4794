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

The histograms are learned from a few thousand pixels in ``sectors * bins^3`` bins, so they tell
apart even colours that both sides share (clear glass shows its background's) by chance. Where they
are fused with a mask, the posterior's log-odds are first weighted by :func:`colour_weight`: the
tempering under which they best predict pixels the histograms were not learned from (1 for colours
the object has of its own; near 0 where they differ by chance, so the term weights itself and cannot
drag the outline the mask draws). Without a mask the colours alone draw it (with the photo's edges),
as learned.

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
        edge_weight: where the masks are withheld, the photo's edges pull the outline too
            (:mod:`autoalign.losses.edge`) with this weight against the region targets; ``None``: not.
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
    edge_weight: float | None = 0.5

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
        key = codes if group is None else group * bins ** 3 + codes
        return ColourModel.learn_keys(key, inside, outside, bins, groups, min_px)

    @staticmethod
    def learn_keys(key: NDArray[np.int64], inside: NDArray[np.bool_], outside: NDArray[np.bool_], bins: int,
                   groups: int = 1, min_px: int = 0) -> "ColourModel":
        """:meth:`learn` from each pixel's ``key``, ``group * bins^3 + code`` (its bin in the flattened
        ``(groups, bins^3)`` histograms), for a caller that has the keys already."""
        return ColourModel.of_counts(*colour_counts(key, inside, outside, bins, groups, min_px), bins)

    @staticmethod
    def of_counts(fg: NDArray[np.float64], bg: NDArray[np.float64], bins: int) -> "ColourModel":
        """The models of pixel counts per bin ``(groups, bins^3)`` (:func:`colour_counts`), normalised
        in place: no fresh ``(groups, bins^3)`` arrays (the counts are the models' afterwards)."""
        fg /= np.maximum(fg.sum(1, keepdims=True), 1.0)
        bg /= np.maximum(bg.sum(1, keepdims=True), 1.0)
        return ColourModel(fg, bg, bins)

    def posterior(self, codes: NDArray[np.int64], group: NDArray[np.int64] | None = None) -> NDArray[np.float64]:
        """``P(object | colour)`` with equal priors, each pixel by its group's models; a colour
        neither model has seen gives 1/2 (each histogram gets half a count's worth spread over its bins)."""
        eps = 0.5 / self.bins ** 3
        g = 0 if group is None else group
        pf, pb = self.fg[g, codes] + eps, self.bg[g, codes] + eps
        return pf / (pf + pb)

    def posterior_of_keys(self, key: NDArray[np.int64]) -> NDArray[np.float64]:
        """:meth:`posterior` of the pixels with these keys (:meth:`learn_keys`): one flat look-up per
        histogram instead of a (group, code) pair of indices, the same numbers."""
        eps = 0.5 / self.bins ** 3
        pf, pb = np.take(self.fg, key), np.take(self.bg, key)  # flat look-ups
        pf += eps
        pb += eps
        pb += pf  # pf + pb, in place: a fresh array costs more (page faults) than the arithmetic
        pf /= pb
        return pf


def colour_counts(key: NDArray[np.int64], inside: NDArray[np.bool_], outside: NDArray[np.bool_], bins: int,
                  groups: int = 1, min_px: int = 0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pixel counts per bin ``(groups, bins^3)`` of the ``inside`` and ``outside`` pixels by their
    ``key`` (:meth:`ColourModel.learn_keys`); a group with fewer than ``min_px`` pixels inside or
    outside gets the counts of all."""
    n = bins ** 3
    fg = np.bincount(key[inside], minlength=groups * n).astype(np.float64).reshape(groups, n)
    bg = np.bincount(key[outside], minlength=groups * n).astype(np.float64).reshape(groups, n)
    weak = np.minimum(fg.sum(1), bg.sum(1)) < min_px
    fg[weak], bg[weak] = fg.sum(0), bg.sum(0)
    return fg, bg


def _code_bits(bins: int) -> int:
    """log2(bins), the bits of each channel a histogram bin keeps; an error unless ``bins`` is a power of two."""
    shift = 8 - int(round(np.log2(bins)))
    if 2 ** (8 - shift) != bins:
        raise ValueError(f"bins must be a power of two up to 256, not {bins}")
    return 8 - shift


def colour_codes(photo: NDArray[np.uint8], bins: int) -> NDArray[np.int64]:
    """The histogram bin of every pixel of an (H, W, 3) uint8 photo, (H, W)."""
    shift = 8 - _code_bits(bins)
    q = (photo >> shift).astype(np.int64)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


def _code_image(photo: NDArray[np.uint8], bins: int) -> NDArray[np.int32]:
    """:func:`colour_codes` as int32 (a code has at most 24 bits), each channel's bits shifted into
    place: a fraction of the int64 version's time on a box of the photo."""
    bits = _code_bits(bins)
    if not 0 <= bits <= 8:  # out of the uint8 range: the plain formula's numbers, whatever they are
        return colour_codes(photo, bins).astype(np.int32)
    shift = 8 - bits
    code = np.right_shift(photo[..., 0], shift, dtype=np.int32)
    code <<= 2 * bits
    channel = np.right_shift(photo[..., 1], shift, dtype=np.int32)
    channel <<= bits
    code |= channel
    code |= np.right_shift(photo[..., 2], shift, dtype=np.int32, out=channel)
    return code


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
    or below: the colours do not change there; NaN: nothing to compare), how well the colour models
    tell the object from its surroundings (:func:`colour_separation`), and the weight the target gave
    the colours' log-odds (:func:`colour_weight`; 1: as learned, as always without a mask)."""

    target: NDArray[np.float32]
    band_px: float
    agreement: float
    edge_contrast: float = float("nan")
    separation: float = float("nan")
    weight: float = 1.0


SECTOR_EDGE_RAD = 0.01
"""Pixels whose approximate angle (:func:`cv2.phase`, documented to about 0.3 degrees = 0.005 rad,
measured 1.6e-4 rad) is this close to a sector's edge get numpy's exact angle (:func:`_sector_of`)."""


def _sector_of(shape: tuple[int, int], centre: tuple[float, float], sectors: int) -> NDArray[np.int64]:
    """Each pixel's angular sector (0..sectors-1) about ``centre`` (row, column): the whole part of
    ``(arctan2(row - centre row, column - centre column) + pi) / (2 pi) * sectors``.

    ``np.arctan2`` costs about 20 ns a pixel; the far cheaper :func:`cv2.phase` decides the sector of
    every pixel farther than :data:`SECTOR_EDGE_RAD` from a sector's edge, and only the few nearer
    ones (about 2.5% with 8 sectors) are worked out with ``np.arctan2`` from the same float64
    offsets as the formula above, so every pixel's sector is the one that formula gives."""
    h, w = shape
    dy, dx = np.arange(h) - centre[0], np.arange(w) - centre[1]  # float64 offsets (px)
    # the reversed offset (-dx, -dy) points at arctan2(dy, dx) + pi, which cv2.phase gives in [0, 2 pi]
    back_x, back_y = np.empty(shape, np.float32), np.empty(shape, np.float32)
    back_x[:] = -dx.astype(np.float32)
    back_y[:] = -dy.astype(np.float32)[:, None]
    turns = cv2.phase(back_x, back_y)
    turns *= np.float32(sectors / (2 * np.pi))  # sectors from the angle -pi (to about 2e-4 rad)
    sector = np.floor(turns, out=back_x).astype(np.int64)
    off_edge = np.subtract(turns, np.rint(turns, out=back_y), out=back_y)  # to the nearest edge, in sectors
    at_edge = np.flatnonzero(np.abs(off_edge, out=off_edge) < SECTOR_EDGE_RAD * sectors / (2 * np.pi))
    iy, ix = np.divmod(at_edge, w)
    sector.ravel()[at_edge] = ((np.arctan2(dy[iy], dx[ix]) + np.pi) / (2 * np.pi) * sectors).astype(np.int64)
    return np.minimum(sector, sectors - 1, out=sector)


def _distances(region: NDArray[np.bool_]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Each pixel's distance (px, cv2's 3x3 L2 chamfer) to the nearest pixel outside ``region`` (0
    outside it) and to the nearest pixel of it (0 in it); beyond the array's edge is outside."""
    # a bool array's bytes are its 0 / 1 already: no copy
    region8 = region.view(np.uint8) if region.dtype == np.bool_ else region.astype(np.uint8)
    r8 = cv2.copyMakeBorder(region8, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    return (cv2.distanceTransform(r8, cv2.DIST_L2, 3)[1:-1, 1:-1],
            cv2.distanceTransform(1 - r8, cv2.DIST_L2, 3)[1:-1, 1:-1])


def _mask_image(mask: NDArray[np.float32] | None, shape: tuple[int, int]) -> NDArray[np.float32]:
    """The mask as 0 / 1 float32 (> 0.5: the object; ``None``: all 0), the target beyond the band."""
    if mask is None:
        return np.zeros(shape, np.float32)
    mask = np.asarray(mask)
    if mask.dtype == np.float32 and mask.ndim == 2:  # the usual case: cv2's threshold (> 0.5) is the cheaper
        return cv2.threshold(mask, 0.5, 1.0, cv2.THRESH_BINARY)[1]
    return (mask > 0.5).astype(np.float32)


def _centre(sil: NDArray[np.bool_]) -> tuple[float, float]:
    """The mean row and column of a non-empty silhouette's pixels, exactly as ``np.nonzero`` and
    ``mean`` give them (sums of whole numbers are exact in float64) without listing the pixels."""
    n = np.count_nonzero(sil)
    rows, cols = np.count_nonzero(sil, axis=1), np.count_nonzero(sil, axis=0)
    return (float(rows @ np.arange(len(rows))) / n, float(cols @ np.arange(len(cols))) / n)


def _fused(known: NDArray[np.bool_], post: NDArray[np.float64], trust: float, miss: float) -> NDArray[np.float64]:
    """``P(object)`` from the mask (``known``: it says object; ``trust``, ``miss``: ``P(object)`` where it
    says object, background) and the colour posterior ``post`` as independent evidence: their odds
    multiply. The same float64 operations as ``odds = p_mask / (1 - p_mask) * post / max(1 - post, 1e-6)``,
    ``odds / (1 + odds)``, the mask's odds worked out once per value and the rest in place."""
    odds = np.where(known, trust / (1.0 - trust), miss / (1.0 - miss))
    odds *= post
    scratch = np.subtract(1.0, post)
    odds /= np.maximum(scratch, 1e-6, out=scratch)
    odds /= np.add(odds, 1.0, out=scratch)
    return odds


def region_target(photo: NDArray[np.uint8], silhouette: NDArray[np.bool_], mask: NDArray[np.float32] | None = None,
                  exclude: NDArray[np.bool_] | None = None, options: RegionOptions = RegionOptions(),
                  separation: bool = False) -> RegionTarget:
    """The region target of one view (see the module doc). Only the box of the silhouette and its
    band is worked on: beyond it the target is the mask (or 0). The colour models' separation is
    measured only when asked (``separation``): the rounds need the target alone.

    Args:
        photo: (H, W, 3) uint8, the view's photo at the masks' resolution.
        silhouette: (H, W) the object's hard silhouette at the current pose.
        mask: the instance's mask there (> 0.5 = the object), or ``None``.
        exclude: pixels other modelled objects claim, or ``None``.
    """
    H, W = silhouette.shape
    sil_full = np.ascontiguousarray(silhouette, dtype=bool)
    target = _mask_image(mask, (H, W))
    x, y, w, h = cv2.boundingRect(sil_full.view(np.uint8))  # the silhouette's box (px)
    if w == 0:
        return RegionTarget(target, 0.0, float("nan"), float("nan"))
    band = options.band_px(sil_full)
    gap = options.gap * band
    r = int(np.ceil(band + gap)) + 1
    y0, y1, x0, x1 = max(y - r, 0), min(y + h + r, H), max(x - r, 0), min(x + w + r, W)
    box = (slice(y0, y1), slice(x0, x1))
    sil, known = sil_full[box], target[box] > 0.5
    # distances within the box: the band never reaches past it, and a silhouette cut by the box's
    # edge is the image's edge, where the distance inside is measured to the image's border too
    d_in, d_out = _distances(sil)
    near = d_out <= band + gap  # the silhouette and the band outside it
    excl = None if exclude is None else exclude[box]
    # every pixel the models learn from or judge is near: work on those alone (suffix _n), by sector
    sil_n, known_n, din_n = sil[near], known[near], d_in[near]
    inside_n = (sil_n & (din_n > gap) & (din_n <= band + gap)) | known_n
    outside_n = ~sil_n & (d_out[near] > gap) & ~known_n
    excl_n = None if excl is None else excl[near]
    if excl_n is not None:
        inside_n &= ~excl_n
        outside_n &= ~excl_n
    key = _sector_of(sil.shape, _centre(sil), options.sectors)  # each pixel's key: sector * bins^3 + code
    key *= options.bins ** 3
    key += _code_image(photo[box], options.bins)
    key_n = key[near]
    counts = colour_counts(key_n, inside_n, outside_n, options.bins, options.sectors, options.min_sector_px)
    # with a mask, the colours' log-odds weighted by what they predict (before the counts become the
    # models); without one they alone draw the outline (with the photo's edges), as learned
    weight = colour_weight(*counts, key_n, inside_n, outside_n) if mask is not None else 1.0
    post_n = ColourModel.of_counts(*counts, options.bins).posterior_of_keys(key_n)
    if excl_n is not None:
        post_n[excl_n] = 0.5
    post = np.full(sil.shape, 0.5)  # the box's posteriors, for the edge contrasts
    post[near] = post_n
    band_n = (din_n <= band + gap) | ~sil_n
    if excl_n is not None:
        band_n &= ~excl_n
    told, told_n = post, post_n  # what the colours tell, with their log-odds weighted
    if weight != 1.0:
        told_n = _tempered(post_n, weight)
        told = np.full(sil.shape, 0.5)
        told[near] = told_n
    fused_n = told_n
    if mask is not None:  # the mask and the colours as independent evidence: their odds multiply
        trust, miss = MASK_TRUST, MASK_MISS
        if edge_contrast(known, told, excl) >= EDGE_SUPPORTS:  # the colours change where the mask's outline is
            trust, miss = mask_rates(known_n[band_n], sil_n[band_n])
        fused_n = _fused(known_n, told_n, trust, miss)
    target[box][near] = fused_n
    # what the photo alone says of the pose: its colours' agreement with the silhouette, and their change across it
    agree = np.where(sil_n, post_n > 0.5, post_n < 0.5)[band_n & (post_n != 0.5)]
    return RegionTarget(target, band, float(agree.mean()) if agree.size else float("nan"),
                        edge_contrast(sil, post, excl, (d_in, d_out)),
                        colour_separation(key_n, inside_n, outside_n, options.bins, options.sectors,
                                          options.min_sector_px) if separation else float("nan"), weight)


MIN_SEPARATION_PX = 20
"""Pixels each side needs for :func:`colour_separation` to say something (fewer: NaN)."""


def colour_separation(key: NDArray[np.int64], inside: NDArray[np.bool_], outside: NDArray[np.bool_], bins: int,
                      groups: int = 1, min_px: int = 0) -> float:
    """How well the colour models learned from the ``inside`` and ``outside`` pixels (their keys,
    :meth:`ColourModel.learn_keys`, with its ``groups`` and ``min_px``) tell the two apart: the mean
    posterior of the inside pixels less that of the outside pixels, each pixel's posterior from models
    learned without it (leave-one-out: with a few thousand pixels in ``groups * bins^3`` bins, a model
    always recognises its own pixels). Near 0: the same colours on both sides (clear glass shows its
    background's); near 1: no colour shared. NaN with fewer than :data:`MIN_SEPARATION_PX` pixels a side."""
    if np.count_nonzero(inside) < MIN_SEPARATION_PX or np.count_nonzero(outside) < MIN_SEPARATION_PX:
        return float("nan")
    fg, bg = colour_counts(key, inside, outside, bins, groups, min_px)

    def mean_posterior(k: NDArray[np.int64], own_fg: bool) -> float:
        pf, pb = _held_out_likelihoods(fg, bg, k, own_fg)
        return float(np.mean(pf / (pf + pb)))

    return mean_posterior(key[inside], True) - mean_posterior(key[outside], False)


def _held_out_likelihoods(fg: NDArray[np.float64], bg: NDArray[np.float64], key: NDArray[np.int64],
                          own_fg: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``P(y | object)`` and ``P(y | surroundings)`` (each with :meth:`ColourModel.posterior`'s half count)
    of the pixels with ``key``, from the counts ``fg``, ``bg`` (:func:`colour_counts`) less each pixel's
    own (it is one of the object's, ``own_fg``, or of the surroundings')."""
    n = fg.shape[1]
    f, b = fg.ravel()[key], bg.ravel()[key]
    nf, nb = fg.sum(1)[key // n], bg.sum(1)[key // n]
    if own_fg:
        f, nf = f - 1.0, nf - 1.0
    else:
        b, nb = b - 1.0, nb - 1.0
    eps = 0.5 / n
    return f / np.maximum(nf, 1.0) + eps, b / np.maximum(nb, 1.0) + eps


WEIGHT_PX = 2000
"""Pixels of each side :func:`colour_weight` calibrates on at most (every k-th of them): the weight
is one number (against all the pixels, the 44 glass and LM-O instances' median weights moved by 0.004
typically, at most 0.02)."""
WEIGHT_BISECTIONS = 14
"""Halvings of [0, 1] that find :func:`colour_weight` (to 6e-5)."""


def colour_weight(fg: NDArray[np.float64], bg: NDArray[np.float64], key: NDArray[np.int64],
                  inside: NDArray[np.bool_], outside: NDArray[np.bool_]) -> float:
    """The weight ``w`` in [0, 1] of the colour models' log-odds that best predicts pixels they were not
    learned from: the maximum over ``w`` of the mean log-likelihood of the ``inside`` pixels' being the
    object and the ``outside`` pixels' not (each side's mean, as the posterior's equal priors), each
    pixel's log-odds from the models learned without it (``fg``, ``bg``: the counts the models are
    learned from, ``key``: each pixel's bin, :func:`colour_counts`). The tempering of a classifier's
    scores to calibrate them (Platt scaling without a bias), never above 1: models that tell the sides
    apart keep their posteriors (1), and colours both sides share, whose histograms still differ by
    chance, are drawn towards 1/2, where they pull nowhere (:func:`_tempered`). 1 with fewer than
    :data:`MIN_SEPARATION_PX` pixels a side."""
    sides = []
    for side, own_fg in ((inside, True), (outside, False)):
        at = np.flatnonzero(side)
        if len(at) < MIN_SEPARATION_PX:
            return 1.0
        pf, pb = _held_out_likelihoods(fg, bg, key[at[::-(-len(at) // WEIGHT_PX)]], own_fg)
        sides.append(np.log(pf / pb))
    l_in, l_out = sides

    def slope(w: float) -> float:  # d/dw of the mean log-likelihood; it falls as w grows (concave)
        return float(np.mean(l_in / (1.0 + np.exp(w * l_in))) - np.mean(l_out / (1.0 + np.exp(-w * l_out))))

    if slope(1.0) >= 0.0:
        return 1.0
    if slope(0.0) <= 0.0:
        return 0.0
    lo, hi = 0.0, 1.0
    for _ in range(WEIGHT_BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if slope(mid) > 0.0 else (lo, mid)
    return 0.5 * (lo + hi)


def _tempered(post: NDArray[np.float64], weight: float) -> NDArray[np.float64]:
    """Posteriors with their log-odds times ``weight``: ``p^w / (p^w + (1 - p)^w)``."""
    odds = np.power(post / np.maximum(1.0 - post, 1e-300), weight)
    return odds / (1.0 + odds)


def edge_contrast(region: NDArray[np.bool_], post: NDArray[np.float64], exclude: NDArray[np.bool_] | None = None,
                  distances: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None) -> float:
    """The mean colour posterior ``post`` in a ring just inside ``region``'s outline less that in the
    ring just outside it (:data:`EDGE_RING_PX`; ``exclude``: pixels left out; ``distances``: the
    distances inside and outside ``region`` where known). Near 1: the colours change from the object's
    to the surroundings' along the outline; near 0: they do not change there; NaN: nothing to compare."""
    d_in, d_out = _distances(region) if distances is None else distances
    lo, hi = EDGE_RING_PX
    ring_in, ring_out = region & (d_in > lo) & (d_in <= hi), ~region & (d_out > lo) & (d_out <= hi)
    if exclude is not None:
        ring_in, ring_out = ring_in & ~exclude, ring_out & ~exclude
    return float(post[ring_in].mean() - post[ring_out].mean()) if ring_in.any() and ring_out.any() else float("nan")
