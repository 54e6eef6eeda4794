"""The photo as evidence: refinement on region targets learned again from the pose reached.

Each round renders the object's hard silhouettes at the current pose, learns each view's colour
models in a band around them and makes the view's target from the pixel-wise posteriors, fused
with the instance's mask where it has one (:func:`~autoalign.losses.region.region_target`); the
pose is then descended on those targets by the mask engine (:func:`~autoalign.engine.refine.polish`,
depth included) at the schedule's first level; once a round moves the pose less than the options'
tolerance (or after ``rounds``), a last round on targets learned at the pose reached runs the rest
of the schedule with the disambiguation and the report (:func:`~autoalign.engine.refine.refine`).
The histograms stay fixed within a round, so the solver compares its steps on one objective;
learning them again between rounds is the alternation PWP3D and RBOT use per frame. Without a given
pose, where the masks alone fit loosely and find another pose almost as good, the rounds also start
from the half turns of theirs, and the photos choose (:func:`best_side`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, TypeVar

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import flips
from autoalign.engine.objective import SilhouetteObjective
from autoalign.engine.options import RefineOptions
from autoalign.engine.schedule import polish
from autoalign.engine.seeding import Click
from autoalign.engine.uncertainty import with_outline_disagreement
from autoalign.errors import AutoalignError
from autoalign.geometry.se3 import pose_change
from autoalign.io.bop import Scene
from autoalign.losses.region import EDGE_SUPPORTS, RegionOptions, region_target
from autoalign.losses.term import Stance, TermEvidence
from autoalign.losses.outline_offset import shared_outline_offset
from autoalign.losses.overlap import LOOSE_FIT_IOU, view_ious
from autoalign.rasterizers.pyramid import MeshPyramid

SUPPORTS = EDGE_SUPPORTS
"""Median edge contrast (over the views) at or above which the photo supports the pose
(:class:`~autoalign.losses.region.RegionTarget`; measured: :data:`~autoalign.losses.region.EDGE_SUPPORTS`):
on the real LM-O photos the photo rarely supports a pose and the masks decide."""
CONTRADICTS = 0.1
"""Below this median edge contrast the photo contradicts the pose (its colours do not change across
the outline): synthetic 0.07-0.13 at 10 mm / 10 deg off; real LM-O never below 0.16 at the
dataset's labels (no false alarm measured), but 0.10-0.24 at 10 mm off (most such poses not caught
by the photo: the masks and the depth must)."""

R = TypeVar("R")
"""The engine's result (:class:`~autoalign.engine.refine.RefineResult`): the engine calls this module."""


@dataclass(frozen=True)
class SideChoice:
    """Without a given pose, which side the photos chose (:func:`best_side`): the photo objective
    (:func:`photo_value`) after the rounds from the masks' pose and after each of its half turns'
    screening rounds, the half turns' axes (unit, model frame), and the one chosen (``None``: the
    masks' pose)."""

    masks_value: float
    turn_values: tuple[float, ...]
    axes_m: tuple[tuple[float, float, float], ...]
    chosen: int | None

    def record(self) -> dict[str, Any]:
        """As ``refine.json`` writes it under the photo's record."""
        return {"masks_pose_value": self.masks_value, "half_turn_values": list(self.turn_values),
                "half_turn_axes_model": [list(a) for a in self.axes_m],
                "chosen": "the masks' pose" if self.chosen is None else
                "half turn about model axis ({:+.3f}, {:+.3f}, {:+.3f})".format(*self.axes_m[self.chosen])}


@dataclass
class PhotoEvidence:
    """The region term at the result: per view the band's half-width (px), the share of the band's
    pixels whose colour posterior agrees with the silhouette and the edge contrast across the
    outline (:class:`~autoalign.losses.region.RegionTarget`; NaN: nothing to compare), the
    rounds the colour models were learned in, and whether the instance had masks (``--masks none``:
    the photo's colour regions stand in for them, in the IoUs too); without a given pose, the side it
    chose where it was asked to (:class:`SideChoice`); per view how well its colour models tell the
    object from its surroundings (:func:`~autoalign.losses.region.colour_separation`; ``None``: not measured)."""

    band_px: NDArray[np.float64]
    agreement: NDArray[np.float64]
    edge_contrast: NDArray[np.float64]
    rounds: int
    masks_given: bool = True
    side: SideChoice | None = None
    separation: NDArray[np.float64] | None = None
    name = "photo"

    def record(self) -> dict[str, Any]:
        """Per view: the band's half-width (px), the share of the band's pixels whose colour posterior
        agrees with the silhouette, the edge contrast across the outline, the colour models' separation;
        the rounds, and the side chosen."""
        out = {"band_px": self.band_px, "agreement": self.agreement, "edge_contrast": self.edge_contrast,
               "rounds": self.rounds, "masks_given": self.masks_given}
        if self.separation is not None:
            out["separation"] = self.separation
        if self.side is not None:
            out["side"] = self.side.record()
        return out

    def evidence(self) -> TermEvidence | None:
        """What the photo says of the pose (:class:`~autoalign.losses.term.TermEvidence`): the median
        edge contrast over the views that measured one; ``None`` without such views. A contradiction
        asks for a look, never fails the pose alone: an appearance may deceive."""
        c = np.asarray(self.edge_contrast, dtype=np.float64)
        if not np.isfinite(c).any():
            return None
        contrast = float(np.median(c[np.isfinite(c)]))
        if contrast >= SUPPORTS:
            stance, reason = Stance.SUPPORTS, ("the photo's colours change across the outline (median edge "
                                               f"contrast {contrast:.2f})")
        elif contrast < CONTRADICTS:
            stance, reason = Stance.CONTRADICTS, ("the photo disagrees: its colours barely change across the outline "
                                                  f"(median edge contrast {contrast:.2f} < {CONTRADICTS})")
        else:
            stance, reason = Stance.NEUTRAL, ("the photo neither confirms nor contradicts the pose (median edge "
                                              f"contrast {contrast:.2f})")
        return TermEvidence("photo", stance, contrast, reason, sees_outline=True, reliability=c)


def photo_targets(scene: Scene, silhouettes: list[NDArray[np.bool_]], options: RegionOptions,
                  measure: bool = False) -> tuple[Scene, PhotoEvidence]:
    """``scene`` with each view's region target as its mask (see :mod:`autoalign.losses.region`),
    the views' photos dropped (they are used) unless it has no masks (the edge term reads them then:
    :mod:`autoalign.losses.edge`), and the per-view evidence (with the colour models' separation
    when ``measure``: the evidence reported, not the rounds')."""
    if scene.photos is None:
        raise ValueError("the scene has no photos")
    has_mask = scene.has_masks
    per_view = [region_target(view.photo, sil, view.mask if has_mask else None, view.ignore, options, measure)
                for view, sil in zip(scene.views, silhouettes)]
    return (replace(scene, masks=[rt.target for rt in per_view], photos=None if has_mask else scene.photos),
            PhotoEvidence(np.array([rt.band_px for rt in per_view]), np.array([rt.agreement for rt in per_view]),
                          np.array([rt.edge_contrast for rt in per_view]), 0, has_mask,
                          separation=np.array([rt.separation for rt in per_view]) if measure else None))


SCREEN_ROUNDS = 2
"""Photo rounds that screen each half turn of the masks' pose without a given pose (:func:`best_side`;
one was too few: two of three turned objects were lost)."""


@dataclass(frozen=True)
class Rounds:
    """Where the photo rounds from one start led: the pose, the rounds, iterations and renders spent,
    whether the last round moved the pose less than the tolerance, and the side chosen (:func:`best_side`)."""

    T_wm: NDArray[np.float64]
    rounds: int
    iterations: int
    renders: int
    settled: bool = False
    side: SideChoice | None = None


def photo_rounds(scene: Scene, pyramid: MeshPyramid, T_wm: NDArray[np.float64], options: RefineOptions,
                 region: RegionOptions, progress: Callable[[str, int, int], None] | None = None,
                 max_rounds: int | None = None, stage: str = "photo round") -> Rounds:
    """The rounds of the module doc from ``T_wm``: colour models learned at the pose reached, the pose
    descended on their targets at the schedule's first level by the masks' engine (``options``), until a
    round moves it less than ``region``'s tolerance (or after ``max_rounds``, by default the region's
    ``rounds``); ``progress`` is told each round as ``stage`` and its number."""
    rast = pyramid.fine(options.detail)
    first_level = (replace(options.schedule[0], ftol=region.round_ftol),)
    T, iterations, renders, rounds, settled = T_wm, 0, 0, 0, False
    for r in range(region.rounds if max_rounds is None else max_rounds):
        targets, _ = photo_targets(scene, rast.hard_masks(T, scene.cameras), region)
        if not targets.has_masks:
            break
        T_new, its, n = polish(targets, pyramid, T, first_level, options, progress, f"{stage} {r + 1}")
        iterations, renders, rounds = iterations + its, renders + n, rounds + 1
        mm, deg = pose_change(T, T_new, pyramid.mesh.centre)
        T = T_new
        if mm < region.tol_mm and deg < region.tol_deg:
            settled = True
            break
    return Rounds(T, rounds, iterations, renders, settled)


def photo_value(scene: Scene, pyramid: MeshPyramid, T_wm: NDArray[np.float64], options: RefineOptions,
                region: RegionOptions) -> tuple[float, int]:
    """The objective at ``T_wm`` and the schedule's first level on the region targets learned at that
    pose (NaN: the object is in no view), which is comparable between poses: each is judged by the
    colours its own outline separates; and the renders it took."""
    targets, _ = photo_targets(scene, pyramid.fine(options.detail).hard_masks(T_wm, scene.cameras), region)
    if not targets.has_masks:
        return float("nan"), 0
    obj = SilhouetteObjective(pyramid, targets.without_empty_masks(), options.loss, options.robust, options.detail,
                              options.depth, options.edges)
    return obj.evaluate(T_wm, options.schedule[0], with_derivatives=False).value, obj.renders


def best_side(scene: Scene, pyramid: MeshPyramid, T_masks: NDArray[np.float64], options: RefineOptions,
              region: RegionOptions, progress: Callable[[str, int, int], None] | None = None) -> Rounds:
    """Without a given pose: the rounds from the masks' pose, and from a half turn of it about one of
    the mesh's principal axes where that fits its own colour targets better by more than the ranking's
    ambiguity tolerance (:func:`photo_value`); with the iterations and renders of all of them. The half
    turns are screened by ``SCREEN_ROUNDS`` rounds each, and the rounds of one that wins go on from
    there. Masks that miss much of an object fit it turned over about as well, while its colours
    separate along the whole outline only the right way up (a blob cut in half ended 178 deg off on
    the masks' pose)."""
    tol = options.ranking.ambiguity_tol
    best = photo_rounds(scene, pyramid, T_masks, options, region, progress)
    value, n = photo_value(scene, pyramid, best.T_wm, options, region)
    iterations, renders, masks_value, turn_values, chosen = best.iterations, best.renders + n, value, [], None
    axes = pyramid.mesh.principal_axes
    for k, T_flip in enumerate(flips(T_masks, axes, pyramid.mesh.centre)):
        other = photo_rounds(scene, pyramid, T_flip, options, region, progress, max_rounds=SCREEN_ROUNDS,
                             stage=f"half turn {k + 1} of {len(axes)}: photo round")
        other_value, n = photo_value(scene, pyramid, other.T_wm, options, region)
        iterations, renders = iterations + other.iterations, renders + other.renders + n
        turn_values.append(other_value)
        if np.isfinite(other_value) and (not np.isfinite(value) or other_value < value * (1.0 - tol)):
            best, value, chosen = other, other_value, k
    if chosen is not None and not best.settled:  # a half turn won before its rounds settled: they go on
        more = photo_rounds(scene, pyramid, best.T_wm, options, region, progress,
                            max_rounds=region.rounds - SCREEN_ROUNDS, stage=f"half turn {chosen + 1}: photo round")
        iterations, renders = iterations + more.iterations, renders + more.renders
        best = replace(more, rounds=best.rounds + more.rounds)
    side = SideChoice(masks_value, tuple(turn_values), tuple(tuple(float(x) for x in a) for a in axes), chosen)
    return replace(best, iterations=iterations, renders=renders, side=side)


def refine_with_photos(scene: Scene, pyramid: MeshPyramid, seed: NDArray[np.float64] | Click | None,
                       options: RefineOptions, refine: Callable[..., R],
                       progress: Callable[[str, int, int], None] | None = None) -> R:
    """Refine with the photos of ``scene`` as evidence (module doc); ``refine`` is the mask engine.

    A seed without a pose (a click, or none) is first placed from the masks alone; where they fit that
    pose loosely (median IoU below :data:`~autoalign.losses.overlap.LOOSE_FIT_IOU`) and find a clearly
    different pose that fits almost as well (``ambiguous``), the rounds run from it and from its half
    turns (:func:`best_side`). With no mask either, there is nothing to place it from and an error says
    what to give."""

    region = options.region
    assert region is not None
    has_mask = scene.has_masks
    # the edge term joins where the targets keep the photos, which they do without masks (photo_targets)
    masks_only = replace(options, region=None, edges=region.edge_weight, masks_withheld=not has_mask)
    rast = pyramid.fine(options.detail)
    if seed is None or isinstance(seed, Click):
        if not has_mask:
            raise AutoalignError("without masks the photos refine a coarse pose: give --init (a coarse scene_gt.json)")
        placed = refine(replace(scene, photos=None), pyramid, seed, masks_only, progress, pose_only=True)
        T_seed, placing = placed.T_wm, (placed.iterations, placed.renders)  # the path starts there
        # masks that miss much of it and find another pose nearly as good: the photos choose its side
        choose_side = placed.ambiguous and np.median(placed.iou_after) < LOOSE_FIT_IOU
    else:
        T_seed, choose_side, placing = np.asarray(seed, dtype=np.float64), False, (0, 0)
    run = (best_side if choose_side else photo_rounds)(scene, pyramid, T_seed, masks_only, region, progress)
    T, rounds, iterations, renders = run.T_wm, run.rounds, run.iterations + placing[0], run.renders + placing[1]
    targets, evidence = photo_targets(scene, rast.hard_masks(T, scene.cameras), region, measure=True)
    if not targets.has_masks:
        raise AutoalignError("the object is in no view at the given pose: check the --init pose and its obj_id")
    # the rounds converged at the first level: the last one goes on from the second (if the schedule has one)
    last = replace(masks_only, schedule=options.schedule[1:]) if rounds and len(options.schedule) > 1 else masks_only
    if seed is None or isinstance(seed, Click):  # no pose was given: nothing to hold the result near
        result = refine(targets, pyramid, T, replace(last, seed_radius=None), progress)
    else:  # held near the person's seed, not near the rounds' last pose
        result = refine(targets, pyramid, T, last, progress, anchor=T_seed)
    keep = [k for k, t in enumerate(targets.masks) if np.any(t > 0.5)]  # the views refine used
    evidence = PhotoEvidence(evidence.band_px[keep], evidence.agreement[keep], evidence.edge_contrast[keep], rounds + 1,
                             has_mask, run.side, None if evidence.separation is None else evidence.separation[keep])
    # the IoUs the report and the verdict read are with the instance's own masks where it has them
    compared = scene.subset(keep) if has_mask else targets.subset(keep)
    iou_after, unc = result.iou_after, result.uncertainty
    if has_mask:
        silhouettes = rast.hard_masks(result.T_wm, compared.cameras)
        iou_after = view_ious(silhouettes, compared)
        if unc is not None:  # the masks against the colours: how far apart they put the outline
            unc = with_outline_disagreement(unc, shared_outline_offset(silhouettes, compared))
    return replace(result, T_init=T_seed, iou_before=view_ious(rast.hard_masks(T_seed, compared.cameras), compared),
                   iou_after=iou_after, uncertainty=unc,
                   iterations=result.iterations + iterations, renders=result.renders + renders,
                   measured=result.measured + (evidence,))
