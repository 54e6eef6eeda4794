"""The photo as evidence: the rounds that learn the region term again at the pose reached.

Each round renders the object's hard silhouettes at the current pose and learns the region term
there (:class:`~autoalign.losses.region_term.RegionTerm`: each view's colour models in a band around
the silhouette, their posteriors fused with the instance's mask where it has one); the pose is then
descended with it in the mask term's place (:func:`~autoalign.engine.schedule.polish`, depth included)
at the schedule's first level. The term's state stays fixed within a round, so the solver compares
its steps on one objective; learning it again between rounds is the alternation PWP3D and RBOT use
per frame. Once a round moves the pose less than the options' tolerance (or after ``rounds``), the
engine runs the rest of the schedule, the disambiguation and the report with the term learned at the
pose reached (:func:`~autoalign.engine.refine.refine`), and :func:`photo_result` reports it. Without
a given pose, where the masks alone fit loosely and find another pose almost as good, the rounds
also start from the half turns of theirs, and the photos choose (:func:`best_side`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence, TypeVar

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import flips
from autoalign.engine.options import RefineOptions
from autoalign.engine.schedule import compared_objective, polish
from autoalign.engine.uncertainty import with_outline_disagreement
from autoalign.geometry.se3 import pose_change
from autoalign.io.bop import Scene
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.region import EDGE_SUPPORTS, RegionOptions, RegionTarget
from autoalign.losses.region_term import RegionTerm
from autoalign.losses.term import Stance, TermEvidence
from autoalign.losses.outline_offset import shared_outline_offset
from autoalign.losses.overlap import view_ious
from autoalign.rasterizers.pyramid import MeshDetail, MeshPyramid

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
    object from its surroundings (:func:`~autoalign.losses.region.colour_separation`; ``None``: not measured),
    and the weight its target gave their log-odds (:func:`~autoalign.losses.region.colour_weight`)."""

    band_px: NDArray[np.float64]
    agreement: NDArray[np.float64]
    edge_contrast: NDArray[np.float64]
    rounds: int
    masks_given: bool = True
    side: SideChoice | None = None
    separation: NDArray[np.float64] | None = None
    colour_weight: NDArray[np.float64] | None = None
    name = "photo"

    def record(self) -> dict[str, Any]:
        """Per view: the band's half-width (px), the share of the band's pixels whose colour posterior
        agrees with the silhouette, the edge contrast across the outline, the colour models' separation
        and the weight of their log-odds; the rounds, and the side chosen."""
        out = {"band_px": self.band_px, "agreement": self.agreement, "edge_contrast": self.edge_contrast,
               "rounds": self.rounds, "masks_given": self.masks_given}
        if self.separation is not None:
            out["separation"] = self.separation
        if self.colour_weight is not None:
            out["colour_weight"] = self.colour_weight
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


    @classmethod
    def of(cls, learned: Sequence[RegionTarget], rounds: int, masks_given: bool,
           side: SideChoice | None = None) -> "PhotoEvidence":
        """The evidence of the region targets ``learned`` (one per view, their separation measured)."""
        return cls(np.array([rt.band_px for rt in learned]), np.array([rt.agreement for rt in learned]),
                   np.array([rt.edge_contrast for rt in learned]), rounds, masks_given, side,
                   np.array([rt.separation for rt in learned]), np.array([rt.weight for rt in learned]))


def region_term_at(scene: Scene, pyramid: MeshPyramid, T_wm: NDArray[np.float64], options: RefineOptions,
                   region: RegionOptions, measure: bool = False) -> RegionTerm:
    """The region term of ``scene``'s views learned around the object's hard silhouettes at ``T_wm``
    (with ``options``' loss, and the colour models' separation when ``measure``)."""
    silhouettes = pyramid.fine(options.detail).hard_masks(T_wm, scene.cameras)
    return RegionTerm.learned_at(scene, silhouettes, region, options.loss, measure)


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
    first_level = (replace(options.schedule[0], ftol=region.round_ftol),)
    T, iterations, renders, rounds, settled = T_wm, 0, 0, 0, False
    for r in range(region.rounds if max_rounds is None else max_rounds):
        term = region_term_at(scene, pyramid, T, options, region)
        if not term.covered():
            break
        T_new, its, n = polish(scene, pyramid, T, first_level, options, progress, f"{stage} {r + 1}", term)
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
    term = region_term_at(scene, pyramid, T_wm, options, region)
    if not term.covered():
        return float("nan"), 0
    obj = compared_objective(pyramid, scene, options, term)
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


def photo_result(result: R, scene: Scene, pyramid: MeshPyramid, term: RegionTerm, T_seed: NDArray[np.float64],
                 run: Rounds, detail: MeshDetail) -> R:
    """The engine's ``result`` on ``term`` (learned on ``scene``'s views at the rounds' last pose, ``run``,
    from ``T_seed``) as a photo run reports it: with the photo's evidence (:class:`PhotoEvidence`) on the views
    it refined with, the IoUs with the instance's own masks where it has them (else with the targets) and
    the masks' disagreement with the colours on where the outline lies in its uncertainty."""
    keep = term.covered()  # the views refine used
    used = term.subset(keep)
    evidence = PhotoEvidence.of(used.learned, run.rounds + 1, term.masks_given, run.side)
    compared = ComparedViews.of(scene.subset(keep)) if term.masks_given else used.targets_in(scene.subset(keep))
    rast = pyramid.fine(detail)
    iou_after, unc = result.iou_after, result.uncertainty
    if term.masks_given:
        silhouettes = rast.hard_masks(result.T_wm, compared.cameras)
        iou_after = view_ious(silhouettes, compared)
        if unc is not None:  # the masks against the colours: how far apart they put the outline
            unc = with_outline_disagreement(unc, shared_outline_offset(silhouettes, compared))
    return replace(result, T_init=T_seed, iou_before=view_ious(rast.hard_masks(T_seed, compared.cameras), compared),
                   iou_after=iou_after, uncertainty=unc, iterations=result.iterations + run.iterations,
                   renders=result.renders + run.renders, measured=result.measured + (evidence,))
