"""The verdict on one refined pose: ``ok``, ``check`` or ``failed``, with the reasons, so that a
person only needs to look at the flagged ones.

The rules read the fit itself, never a ground truth: the IoU of the silhouette with the masks
(median over the views, since real segmenter masks fail in some views), how many views the
robust weights set aside, whether another pose fits as well, how many views had no mask, how
large the pose's sigmas are, and what each other kind of evidence says of the pose on its own
(:class:`~autoalign.losses.term.TermEvidence`, which each kind states in its own module: the
measured depth in :mod:`autoalign.losses.depth`, the photo in :mod:`autoalign.engine.photo_evidence`).
Evidence that supports the pose keeps masks that cover it loosely (median IoU 0.5-0.75) from flagging
it, not masks that miss most of it (those ask for a look). Evidence that
contradicts it fails it when it is a measurement (the depth: whatever the masks say), and asks for
a look when it is an appearance (the photo's colours not changing across the outline). Evidence
that sees the outline itself and neither confirms nor contradicts the pose turns masks that
disagree into `check`, not `failed` (masks are the weakest evidence: on the real LM-O scenes the
glue's SAM masks lie mostly on other objects, IoU 0.17 with a label 2.8% of its diameter from the
dataset's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.photo_evidence import PhotoEvidence
from autoalign.engine.refine import RefineResult
from autoalign.engine.seed_region import SEED_RADIUS, SeedHold
from autoalign.engine.uncertainty import (MIN_VIEWPOINTS, SAME_VIEWPOINT_DEG, Uncertainty, direction_name,
                                         turn_sigma_deg, turns_not_free, weak_directions)
from autoalign.losses.overlap import LOOSE_FIT_IOU
from autoalign.losses.term import Stance, TermEvidence

FAILED_IOU = 0.5
"""Median IoU below this: the silhouette does not match the masks; the pose is taken as wrong."""
CHECK_IOU = LOOSE_FIT_IOU
"""Median IoU below this: a loose fit, to be looked at (:data:`~autoalign.losses.overlap.LOOSE_FIT_IOU`)."""
LOW_WEIGHT = 0.3
"""A view whose robust weight (mean 1) ends below this, with an IoU under ``LOW_WEIGHT_MAX_IOU``,
is counted as set aside: its mask disagrees with the others."""
LOW_WEIGHT_MAX_IOU = 0.95
SET_ASIDE_FRACTION = 0.5
"""More than this fraction of views set aside (or without a mask): the pose rests on fewer views
than disagree with it. Real segmenter masks fail in many views (42% of SAM's on the real LM-O
scenes): at 0.3, 36 of the 50 synthetic instances that replay those failures were flagged for it
alone, each within 0.12 mm / 0.3 deg of the truth (``experiments/studies/sam_failures.py``)."""
MIN_VIEWS = 3
"""Fewer views with a mask than this cannot fix a 6-DoF pose from silhouettes."""
LARGE_SIGMA_MM = 2.0
"""A position sigma above this (mm, along any direction) leaves the label in doubt ..."""
LARGE_SIGMA_DEG = 2.0
"""... and so does an orientation sigma above this (degrees, about any direction that is not an
axis of continuous symmetry of the model)."""
NEAR_SYMMETRY_GAP = 0.02
"""A weakly observed turn names the object nearly symmetric (a reason to check) unless turning the
pose about it clearly worsens the fit: by this much mean hard IoU at 1/4 resolution ..."""
NEAR_SYMMETRY_DEG = 1.0
"""... and its sigma in the views' spread (with its profile; the shared-outline prior left out) is
below this (degrees): a turn the views see so weakly that the descent can stop
several degrees off in it, in a small dip of the loss that the turns of 30-180 degrees do not test
(a pen, 9 deg off in roll with a sigma of 1.0 deg, ``ok`` before this rule). On the SAM-like synthetic
scenes with systematic mask errors (``experiments/results/uncertainty_calibration.md``) it flags
the instances given there, false alarms and misses counted."""
NEAR_TURN_RISE = 0.1
"""The object is also named nearly symmetric when turning the pose by 10-20 degrees about an axis it
is nearly round about raises the whole objective (the masks, and the photos and the depth where the
scene has them) by less than this share (``turn_rise``; measured whenever the depth's noise model is
set, as by default, with measured depth or without; not with ``--depth off``): none of them then
fixes that turn, whatever its sigma says (a YCB-Video tuna can seen from one side ended 8.8 deg off
about its axis, sigma 0.33 deg, ``ok``). Measured on the one-viewpoint RGB-D scenes of
``photo_evidence`` (72 instances of procedural and YCB-Video models): undeclared near-symmetric
objects -0.031 to 0.055 (the tuna can, a tomato soup can, a flashlight), every other undeclared one
nearly round about an axis (an oil can, a mug, brackets) 0.15 or more; the rest are round about no
axis, and not measured."""
SAME_FIT = 1.05
"""A pose kept within the seed's radius whose loss is within this factor of the far one's fits as
well (a symmetric object's equivalent turn, say): the masks do not pull it away, no reason is given."""
AGREEING_WEIGHT = 0.5
"""A view whose robust weight is at least this agrees with the pose: its mask is not one the fit sets aside."""
AGREEING_SHARE = 0.3
"""When the masks' median IoU fails the pose, but at least this share of the views (and at least
``MIN_VIEWS``) agree with it and fit it well (median IoU >= ``CHECK_IOU``), the masks that disagree
are taken as partial or on another object, not as evidence against the pose: `check`, not `failed`.
Real segmenters miss parts or take the wrong object in 32% of LM-O's views (sam_mask_rates.md).
A loose median (below ``CHECK_IOU``) is no reason to check when most views (at least
``1 - SET_ASIDE_FRACTION`` of them) agree and fit the pose well: the median then counts the masks
the fit sets aside, which are reasons of their own."""


def low_weight_ids(image_ids: list[int], weights: NDArray[np.float64], iou_after: NDArray[np.float64]) -> list[int]:
    """The image ids of the views set aside by the robust weights: weight below ``LOW_WEIGHT`` and
    IoU after refinement below ``LOW_WEIGHT_MAX_IOU`` (their masks disagree with the others)."""
    return [int(i) for i, w, a in zip(image_ids, np.asarray(weights, dtype=np.float64),
                                      np.asarray(iou_after, dtype=np.float64))
            if w < LOW_WEIGHT and a < LOW_WEIGHT_MAX_IOU]


@dataclass
class Verdict:
    """``status`` is ``ok``, ``check`` or ``failed``; ``reasons`` say why (for ``ok``, what was
    noticed without putting the pose in doubt);
    ``set_aside`` lists the image ids whose masks disagreed (low weight) or were empty."""

    status: str
    reasons: list[str] = field(default_factory=list)
    set_aside: list[int] = field(default_factory=list)


def largest_sigmas(uncertainty: Uncertainty, free_axes_m: tuple[NDArray[np.float64], ...] = ()) -> tuple[float, float]:
    """The largest position sigma (mm) and orientation sigma (degrees) over all directions, the
    turns about ``free_axes_m`` (unit, model frame: axes of continuous symmetry) left out."""
    C = uncertainty.covariance
    B = turns_not_free(free_axes_m)
    s_mm = float(np.sqrt(max(np.linalg.eigvalsh(C[:3, :3]).max(), 0.0)))
    s_rad = float(np.sqrt(max(np.linalg.eigvalsh(B.T @ C[3:, 3:] @ B).max(), 0.0))) if B.shape[1] else 0.0
    return s_mm, float(np.degrees(s_rad))


def flat_turn(turn_rise: float | None, symmetric: bool) -> bool:
    """Whether a turn of 10-20 degrees barely changes the whole fit (``turn_rise`` below
    :data:`NEAR_TURN_RISE`) of a model whose symmetries are not declared (declared ones explain it)."""
    return not symmetric and turn_rise is not None and turn_rise < NEAR_TURN_RISE


def nearly_symmetric(uncertainty: Uncertainty, free_axes_m: tuple[NDArray[np.float64], ...] = (),
                     turn_gap: float | None = None, symmetric: bool = False, turn_rise: float | None = None) -> bool:
    """Whether a turn that is not about an axis of continuous symmetry is weakly observed, and
    either its sigma is at least ``NEAR_SYMMETRY_DEG`` or turning the pose about such an axis
    (``turn_gap``, :class:`~autoalign.engine.refine.RefineResult`) does not clearly worsen the fit,
    or was not tried. For a model with declared symmetries (``symmetric``) the turn gap says
    nothing: one of its turns may be a symmetry (a hexagonal bar's 60 degrees about its axis).
    The sigma is what the views show (:attr:`~autoalign.engine.uncertainty.Uncertainty.spread`,
    where the weak turns are found), without the prior on a shared outline shift: that prior
    counts in the verdict's large-sigma rule, but it says nothing of a dip in the loss along the
    turn that the descent may stop in. A flat ``turn_rise`` (below
    :data:`NEAR_TURN_RISE`) names it nearly symmetric too, unless its symmetries are declared."""
    if flat_turn(turn_rise, symmetric):
        return True
    weak = uncertainty.weak_turns_not_free(free_axes_m)
    if not weak:
        return False
    loose = any(turn_sigma_deg(uncertainty.views_spread, a) >= NEAR_SYMMETRY_DEG for a in weak)
    return loose or (not symmetric and (turn_gap is None or turn_gap < NEAR_SYMMETRY_GAP))


@dataclass
class _Fit:
    """What the masks' IoU and the other evidence say of the pose together (:func:`_fit_against_the_evidence`):
    the reasons, whether it failed, whether loose masks are explained, and whether evidence that
    cannot fail it alone contradicts it (a look)."""

    reasons: list[str]
    failed: bool
    supported: bool
    look: bool


@dataclass(frozen=True)
class AgreeingViews:
    """The views whose masks agree with the pose (robust weight >= ``AGREEING_WEIGHT``).

    Attributes:
        count: how many.
        total: all the views with a mask.
        median_iou: their median hard IoU; ``None``: there are none.
    """

    count: int = 0
    total: int = 0
    median_iou: float | None = None

    def fit_well(self, share: float) -> bool:
        """Whether they are at least ``MIN_VIEWS`` and ``share`` of all, and fit the pose well
        (median IoU >= ``CHECK_IOU``)."""
        return (self.median_iou is not None and self.count >= MIN_VIEWS and self.count >= share * self.total
                and self.median_iou >= CHECK_IOU)


def agreeing_views(iou: NDArray[np.float64], weights: NDArray[np.float64]) -> AgreeingViews:
    """The views (per-view hard IoU ``iou`` and robust ``weights``) whose masks agree with the pose."""
    iou = np.asarray(iou, dtype=np.float64)
    agree = np.asarray(weights, dtype=np.float64) >= AGREEING_WEIGHT
    return AgreeingViews(int(agree.sum()), len(iou), float(np.median(iou[agree])) if agree.any() else None)


def _fit_against_the_evidence(med: float, terms: tuple[TermEvidence, ...],
                              agreeing: AgreeingViews = AgreeingViews()) -> _Fit:
    """The fit's reasons: the median mask IoU ``med`` read against what each other kind of evidence
    says (``terms``, in the order they were measured) and the views whose masks agree (module doc)."""
    contradicting = [t for t in terms if t.stance is Stance.CONTRADICTS]
    reasons = [t.reason for t in contradicting]
    failed = any(t.fails for t in contradicting)
    look = any(not t.fails for t in contradicting)
    support = next((t for t in terms if t.stance is Stance.SUPPORTS), None)
    undecided = next((t for t in terms if t.stance is Stance.NEUTRAL and t.sees_outline), None)
    supported = support is not None
    if support is not None and med < FAILED_IOU:
        # support explains loose masks, not masks that miss most of the silhouette: depth agreeing
        # with a pose pushed into the table, colours changing across a wrong outline
        reasons.append(f"silhouettes do not match the masks (median IoU {med:.2f} < {FAILED_IOU}), though "
                       f"{support.reason}: look at the outline against the photo in overlay.png")
        look = True
    elif support is not None and med < CHECK_IOU:
        reasons.append(f"the masks cover the silhouette loosely (median IoU {med:.2f}), but {support.reason}")
    elif med < FAILED_IOU and undecided is not None:
        # the masks are the weakest evidence: against an outline seen otherwise that does not contradict it, a look
        reasons.append(f"silhouettes do not match the masks (median IoU {med:.2f} < {FAILED_IOU}), and "
                       f"{undecided.reason}")
    elif med < FAILED_IOU and agreeing.fit_well(AGREEING_SHARE):
        # partial masks or masks on another object in most views: the rest still fit the pose well
        reasons.append(f"most masks disagree with the pose (median IoU {med:.2f}), but {agreeing.count} of "
                       f"{agreeing.total} views fit it well (median IoU {agreeing.median_iou:.2f}): look at the "
                       "down-weighted views; their masks may cover part of the object or another one")
    elif med < FAILED_IOU:
        reasons.append(f"silhouettes do not match the masks: median IoU {med:.2f} < {FAILED_IOU}; the pose is "
                       "wrong or the masks are: seed it closer (--init or a click) or mend the masks")
        failed = True
    elif med < CHECK_IOU and agreeing.fit_well(1.0 - SET_ASIDE_FRACTION):
        # the median counts the masks the fit sets aside: the views whose masks agree decide the fit
        reasons.append(f"the masks cover the silhouette loosely (median IoU {med:.2f}), but the {agreeing.count} of "
                       f"{agreeing.total} views whose masks agree with the pose fit it well "
                       f"(median IoU {agreeing.median_iou:.2f})")
        supported = True
    elif med < CHECK_IOU:
        reasons.append(f"loose fit: median IoU {med:.2f} < {CHECK_IOU}; compare the outline with the photo in "
                       "overlay.png: a right pose means loose masks, a wrong one a seed to give again")
    return _Fit(reasons, failed, supported, look)


def _seed_reasons(seed_move: tuple[float, float] | None, seed_radius: tuple[float, float],
                  seed_hold: SeedHold | None) -> tuple[list[str], bool]:
    """What a given seed says of the pose: the reasons, and whether they put it in doubt."""
    if seed_move is not None and (seed_move[0] > seed_radius[0] or seed_move[1] > seed_radius[1]):
        better = (f"; it fits {seed_hold.near_loss / max(seed_hold.far_loss, 1e-12):.1f}x better than the best pose "
                  "within it" if seed_hold is not None and seed_hold.kept_far else "")
        return [f"ended {seed_move[0]:.0f} mm / {seed_move[1]:.0f} deg from the given seed, beyond its stated "
                f"uncertainty ({seed_radius[0]:g} mm / {seed_radius[1]:g} deg){better}: check whether the seed "
                "or the result is right (--seed-radius states another)"], True
    if seed_hold is not None and not seed_hold.kept_far and seed_hold.near_loss > SAME_FIT * seed_hold.far_loss:
        return [f"the masks pull the pose to one {seed_hold.far_move[0]:.0f} mm / {seed_hold.far_move[1]:.0f} deg "
                f"from the given seed, beyond its stated uncertainty ({seed_radius[0]:g} mm / {seed_radius[1]:g} deg), "
                f"that fits only {seed_hold.near_loss / max(seed_hold.far_loss, 1e-12):.2f}x better: kept the best "
                "pose within it; check the masks, or state a wider --seed-radius"], True
    return [], False


def _largest_weak(weak: list[str]) -> str:
    """The largest weakly observed turn and shift of ``weak`` (largest first, turns first: see
    :attr:`~autoalign.engine.uncertainty.Uncertainty.weak`), and how many more ``refine.json``
    lists: a reason that named every direction ran to 400-600 characters of unit vectors."""
    shown = [w for w in weak if w.startswith("turn")][:1] + [w for w in weak if w.startswith("shift")][:1]
    more = len(weak) - len(shown)
    return "; ".join(shown) + (f"; {more} more in refine.json" if more else "")


def _sigma_reasons(uncertainty: Uncertainty, free_axes_m: tuple[NDArray[np.float64], ...],
                   turn_gap: float | None, symmetric: bool, turn_rise: tuple[float | None, NDArray[np.float64] | None]
                   = (None, None)) -> list[str]:
    """Why the pose is not well determined (views from one viewpoint, large sigmas, or a nearly
    symmetric object); none if it is."""
    if uncertainty.viewpoints is not None and uncertainty.viewpoints < MIN_VIEWPOINTS:
        # ten frames of a still camera agree with each other whatever the pose's error: on the
        # YCB-Video frames, poses 2-7 deg off had sigmas of 0.2-0.9 deg and were called ok
        return [f"one viewpoint: its views see it from within {SAME_VIEWPOINT_DEG:g} deg of one direction, so their "
                "agreement cannot show how far off it may be; add views from another side"]
    s_mm, s_deg = largest_sigmas(uncertainty, free_axes_m)
    if s_mm > LARGE_SIGMA_MM or s_deg > LARGE_SIGMA_DEG:
        return [f"weakly observed: sigma up to {s_mm:.2g} mm / {s_deg:.2g} deg"
                + (f" ({_largest_weak(weak)})" if (weak := weak_directions(uncertainty.covariance, free_axes_m)) else "")
                + ": views from other directions or measured depth would fix it"]
    rise, rise_axis = turn_rise
    if nearly_symmetric(uncertainty, free_axes_m, turn_gap, symmetric, rise):
        # the turn the views barely see is where a nearly symmetric object goes wrong: by several
        # degrees in 1 of 50 SAM-like synthetic instances, with a sigma far smaller
        flat = flat_turn(rise, symmetric) and rise_axis is not None
        axes = [rise_axis] if flat else list(uncertainty.weak_turn_axes)
        turns = "; ".join(f"the turn about {direction_name(a)} ({turn_sigma_deg(uncertainty.covariance, a):.2g} deg)"
                          for a in axes)
        if flat:
            turns += f" (turned 10-20 deg about it, the whole fit changes by {100 * rise:+.1f}%)"
        return [f"nearly symmetric: {turns} is weakly observed; check that the object's distinguishing "
                "detail (a handle, a label, a notch) sits where the photo shows it"]
    return []


@dataclass(frozen=True)
class PoseEvidence:
    """What the verdict weighs for one refined pose (:func:`judge`).

    Attributes:
        iou_after: (N,) hard IoU per used view.
        weights: (N,) final robust weights (mean 1).
        image_ids: the N views' image ids.
        empty_ids: image ids whose mask was empty (treated as missing).
        ambiguous: another, clearly different pose fits almost as well.
        symmetric: the model has declared symmetries, which explain such a runner-up and a small
            ``turn_gap`` (neither is then a reason to check).
        uncertainty: the pose's covariance (:mod:`autoalign.engine.uncertainty`); large sigmas, or a
            single viewpoint, are a reason.
        free_axes_m: the model's axes of continuous symmetry, about which any turn is as good.
        turn_gap: how much better the pose fits than its turns about weakly observed axes (see
            :func:`nearly_symmetric`).
        turn_rise, turn_rise_axis_m: with depth, how much the whole fit rises when the pose is turned
            10-20 degrees about that axis, one the mesh is nearly round about (unit, model frame;
            :data:`NEAR_TURN_RISE`).
        terms: what each other kind of evidence says of the pose, in the order they were measured
            (:class:`~autoalign.losses.term.TermEvidence`: the depth, the photo).
        seed_move: how far the pose ended from a given seed pose (mm at the model's centre, degrees;
            :func:`~autoalign.geometry.se3.pose_change`); beyond ``seed_radius`` it is a reason to check.
        seed_hold: the masks pulled the pose beyond the seed's radius
            (:class:`~autoalign.engine.seed_region.SeedHold`): a reason to check either way.
        masks_given: False when the instance had no masks (``--masks none``): the IoUs and the
            views' weights are then against the photo's colour regions, and the reasons say so.
    """

    iou_after: NDArray[np.float64]
    weights: NDArray[np.float64]
    image_ids: list[int]
    empty_ids: tuple[int, ...] = ()
    ambiguous: bool = False
    symmetric: bool = False
    uncertainty: Uncertainty | None = None
    free_axes_m: tuple[NDArray[np.float64], ...] = ()
    turn_gap: float | None = None
    turn_rise: float | None = None
    turn_rise_axis_m: NDArray[np.float64] | None = None
    terms: tuple[TermEvidence, ...] = ()
    seed_move: tuple[float, float] | None = None
    seed_radius: tuple[float, float] = SEED_RADIUS
    seed_hold: SeedHold | None = None
    masks_given: bool = True

    @classmethod
    def of(cls, result: RefineResult, empty_ids: tuple[int, ...] = (), symmetric: bool = False,
           free_axes_m: tuple[NDArray[np.float64], ...] = (), seed_move: tuple[float, float] | None = None,
           seed_radius: tuple[float, float] = SEED_RADIUS) -> PoseEvidence:
        """The evidence a refinement's ``result`` carries, with what only its caller knows: the
        scene's empty masks, the model's symmetries and how far the pose ended from a given seed."""
        return cls(result.iou_after, result.weights, list(result.image_ids), tuple(empty_ids),
                   bool(result.ambiguous), symmetric, result.uncertainty, free_axes_m, result.turn_gap,
                   result.turn_rise, result.turn_rise_axis_m, result.evidence(), seed_move, seed_radius,
                   result.seed_hold, (photo := result.measurement(PhotoEvidence)) is None or photo.masks_given)


NO_MASKS_SAID = ("no masks were given (--masks none): where these reasons speak of masks they mean the photo's "
                 "colour regions, the pixels whose colours are more the object's than its surroundings'")


def judge(e: PoseEvidence) -> Verdict:
    """The verdict on one pose from its evidence ``e`` (see the module doc and :class:`PoseEvidence`)."""
    iou = np.asarray(e.iou_after, dtype=np.float64)
    w = np.asarray(e.weights, dtype=np.float64)
    reasons: list[str] = []
    low = low_weight_ids(e.image_ids, w, iou)
    n_all = len(iou) + len(e.empty_ids)
    failed = False
    if len(iou) < MIN_VIEWS:
        reasons.append(f"only {len(iou)} view(s) with a mask (at least {MIN_VIEWS} needed): add masks or views")
        failed = True
    med = float(np.median(iou)) if len(iou) else 0.0
    fit = _fit_against_the_evidence(med, e.terms, agreeing_views(iou, w))
    reasons += fit.reasons + [t.reason for t in e.terms if t.stance is Stance.NO_EVIDENCE]
    failed = failed or fit.failed
    if low:
        reasons.append(f"{len(low)} view(s) down-weighted, their masks disagree with the others: image ids "
                       + ", ".join(map(str, low[:12])) + (" ..." if len(low) > 12 else ""))
    if e.empty_ids:
        reasons.append(f"{len(e.empty_ids)} view(s) with an empty mask treated as missing: image ids "
                       + ", ".join(map(str, list(e.empty_ids)[:12])) + (" ..." if len(e.empty_ids) > 12 else ""))
    set_aside = sorted(set(low) | set(int(i) for i in e.empty_ids))
    too_many = n_all > 0 and len(set_aside) > SET_ASIDE_FRACTION * n_all
    ambiguous = e.ambiguous and not e.symmetric
    if ambiguous:
        reasons.append("ambiguous: a clearly different pose fits almost as well (refine.json's runner_up); "
                       "look for the detail that tells them apart, or seed it with --init or a click")
    seed_reasons, far = _seed_reasons(e.seed_move, e.seed_radius, e.seed_hold)
    sigma_reasons = ([] if e.uncertainty is None
                     else _sigma_reasons(e.uncertainty, e.free_axes_m, e.turn_gap, e.symmetric,
                                         (e.turn_rise, e.turn_rise_axis_m)))
    reasons += seed_reasons + sigma_reasons
    if failed:
        status = "failed"
    elif (med < CHECK_IOU and not fit.supported) or too_many or ambiguous or sigma_reasons or fit.look or far:
        status = "check"
        if too_many:
            reasons.append(f"{len(set_aside)} of {n_all} views set aside (more than {SET_ASIDE_FRACTION:.0%})")
    else:
        status = "ok"
    if not e.masks_given and any("mask" in r for r in reasons):
        reasons.append(NO_MASKS_SAID)
    return Verdict(status, reasons, set_aside)
