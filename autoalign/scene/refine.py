"""Refine every instance of a multi-object scene, each with a verdict, in two stages.

1. **Alone.** Each instance from its seed (or its masks' visual hull) through the engine's search
   and polish, against its own masks, its views' pixels that other instances' masks claim being
   ignored (:mod:`autoalign.io.instances`): where another object hides it, or another mask strayed
   onto it, its silhouette costs nothing. On a synthetic five-object scene with mutual occlusion
   this took the errors from 0.26-6.9 mm to 0.02-0.09 mm (README, "Several objects").
2. **Together.** All poses (and, if asked, a correction of every camera) from there on the
   occlusion-aware loss (:mod:`autoalign.scene.occlusion`, :mod:`autoalign.scene.joint`): what a
   modelled object hides is predicted, not only what another mask claims, so an instance whose
   occluder's masks are missing is not pulled, and the contour between two objects holds both.

Cameras known only up to scale (``solve_scale``) come in scaled by a first guess
(:mod:`autoalign.scene.scale`); the joint stage solves the scale with the poses, and while it moves
the scale by more than :data:`SCALE_SETTLED` the scene is rescaled and both stages run again from
there (the instances seeded with their joint poses), at most :data:`SCALE_ROUNDS` times. The joint
stage converges from a scale 30-40% off when the orientations are right, but the alone stage fits
each instance in cameras of the wrong scale, so a round first re-guesses the scale from the
orientations it found (:data:`SCALE_REGUESS`), until a joint stage has solved it from instances
whose alone stage ended ``ok``: the guess is a few percent off where the joint stage is a fraction
of a percent, and re-guessed after it, it undid the joint stage's scale in every round (3 of 6
3- and 4-object scenes never settled, the guess 3.3-4.2% above the truth; one object started 10%
off, whose alone stage ended ``failed``, still needs the guess: its joint stage drifts from it).
Only the instances whose alone stage ended ``ok`` decide the scale, in the joint stage and in that
guess (all, if none did): a mask that misses parts of its object asks for a larger scene, one on
another object for anything. On the real LM-O scene
``lmo_im0115_0389`` (the driller's SAM masks miss its dark handle, the egg box's and glue's are
mostly another object's), with the scene's own metric cameras taken as unscaled, the guesses from
all four instances kept the rounds from settling, at 5.2% too large; from the ``ok`` ones (the cat)
the scale settles 1.4% too large.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import turn_scores
from autoalign.engine.photo_evidence import PhotoEvidence
from autoalign.engine.refine import RefineOptions, RefineResult, refine
from autoalign.engine.see_through import measured_see_through
from autoalign.engine.seed_region import SEED_RADIUS
from autoalign.engine.solver import GaussNewton, LevenbergMarquardt, StepRule
from autoalign.engine.uncertainty import Uncertainty, with_outline_disagreement, with_scale_sigma
from autoalign.geometry.se3 import pose_change, symmetric_pose_change, transform_points
from autoalign.errors import AutoalignError
from autoalign.io.instances import Instance, InstanceScenes
from autoalign.io.models import ModelSet
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.contact import Contact, RestingContact
from autoalign.losses.region import RegionOptions
from autoalign.losses.region_term import RegionTerm
from autoalign.losses.see_through import SeeThrough
from autoalign.losses.outline_offset import shared_outline_offset
from autoalign.losses.overlap import view_ious
from autoalign.quality.verdict import LARGE_SIGMA_MM, PoseEvidence, Verdict, judge
from autoalign.rasterizers.pyramid import MeshPyramid
from autoalign.runtime.parallel import side_by_side
from autoalign.scene.cameras import corrections_accepted
from autoalign.scene.joint import JointRefinement, refine_jointly
from autoalign.scene.photos import others_left_out, region_terms
from autoalign.scene.scale import grown_pose, rescaled, scale_from_masks, scaled_cameras

Progress = Callable[[str, int, int], None]
InstancePreview = Callable[[int, NDArray[np.float64]], None]
"""``preview(index, T_wm)``: instance ``index``'s pose as its alone stage refines it (world-from-model,
4x4, mm), before its uncertainty and verdict (:data:`~autoalign.engine.refine.PosePreview`), in the
scene's cameras as they stand in that stage."""

SCALE_SETTLED = 0.005
"""A joint stage that moves the scene's scale by less than this fraction ends the rounds: at the
start of a round the alone stage fits each instance with the cameras at the round's scale."""
SCALE_ROUNDS = 4
SCALE_REGUESS = 0.02
"""After an alone stage, a first guess of the scale from the orientations it found
(:func:`~autoalign.scene.scale.scale_from_masks`) that differs by more than this fraction rescales
the scene and starts the round again, before the joint stage solves the scale exactly."""


@dataclass
class InstanceResult:
    """One instance's refined pose (``result.T_wm``, world from model, mm), its verdict and time (s)."""

    instance: Instance
    result: RefineResult
    verdict: Verdict
    seconds: float


def verdict_of(result: RefineResult, empty: tuple[int, ...], models: ModelSet, obj_id: int,
               seed: NDArray[np.float64] | None = None, seed_radius: tuple[float, float] = SEED_RADIUS) -> Verdict:
    """The verdict on an instance's result, with its model's symmetries and, given its seed pose,
    how far it ended from it (:func:`~autoalign.quality.verdict.judge`)."""
    seed_move = None if seed is None else symmetric_pose_change(seed, result.T_wm, models.mesh(obj_id).centre,
                                                                *models.symmetries(obj_id))
    return judge(PoseEvidence.of(result, empty, models.symmetric(obj_id), models.continuous_axes(obj_id), seed_move,
                                 seed_radius))


def refine_instances(found: InstanceScenes, models: ModelSet, seeds: dict[int, NDArray[np.float64]],
                     options: RefineOptions | None = None, progress: Progress | None = None,
                     seed_radius: tuple[float, float] = SEED_RADIUS, judge_seeds: bool = True,
                     preview: InstancePreview | None = None) -> list[InstanceResult]:
    """Refine every instance of ``found`` from its seed (``seeds[index]``: 4x4 world-from-model, mm;
    an instance without one is searched from the visual hull of its masks), each showing its poses to
    ``preview`` on the way."""
    n = len(found.instances)
    # the engine holds a result within the seed's radius unless it fits clearly better outside
    options = replace(options or RefineOptions(), seed_radius=seed_radius if judge_seeds else None)
    for inst in found.instances:  # each model made once, before the instances share it
        models.pyramid(inst.obj_id)
    shown_lock = threading.Lock()  # the instances run side by side: one progress line or preview at a time

    def one(k: int) -> InstanceResult:
        inst, scene = found.instances[k], found.scenes[k]
        t0 = time.perf_counter()
        label = f"obj {inst.obj_id} (instance {inst.index}, {k + 1}/{n})"

        def step(stage: str, done: int, total: int) -> None:
            if progress is not None:
                with shown_lock:
                    progress(f"{label}: {stage}", done, total)

        def shown(T_wm: NDArray[np.float64]) -> None:
            with shown_lock:
                preview(inst.index, T_wm)

        result = refine(scene, models.pyramid(inst.obj_id), seeds.get(inst.index), options, progress=step,
                        preview=None if preview is None else shown)
        seed = seeds.get(inst.index) if judge_seeds else None
        return InstanceResult(inst, result, verdict_of(result, scene.empty, models, inst.obj_id, seed, seed_radius),
                              time.perf_counter() - t0)

    return side_by_side(one, range(n))


@dataclass
class SceneRefinement:
    """What :func:`refine_scene` found: every instance's result (after the joint stage), the joint
    stage itself, the joint stage with camera corrections if they were asked for (``joint`` when
    they were kept), the scenes with the instances' own masks (through the cameras used at the end),
    and with ``solve_scale`` the factor by which the given cameras' translations were scaled, its relative sigma, and
    whether it settled (if not, every instance is at least ``check``)."""

    results: list[InstanceResult]
    joint: JointRefinement | None
    with_cameras: JointRefinement | None
    found: InstanceScenes
    scale: float = 1.0
    scale_sigma: float = 0.0
    scale_settled: bool = True

    @property
    def cameras_accepted(self) -> bool:
        return self.with_cameras is not None and self.with_cameras is self.joint


def _within(change: tuple[float, float], region: RegionOptions) -> bool:
    """Whether a pose change (mm, degrees) is below the photo rounds' tolerance."""
    return change[0] < region.tol_mm and change[1] < region.tol_deg


def _after_joint(alone: list[InstanceResult], joint: JointRefinement, given: InstanceScenes, found: InstanceScenes,
                 pyramids: list[MeshPyramid], models: ModelSet, opts: RefineOptions,
                 photo_alone: list[PhotoEvidence | None], regions: list[RegionTerm | None]) -> list[RefineResult]:
    """Each instance's result at the joint stage's pose: its per-view fit, uncertainty, weak turns
    and depth there; with photos, their evidence there (``photo_alone``, at the alone poses, where
    the joint stage moved an instance less than the photo rounds' tolerance) and the IoUs with its
    own masks (``given``: the instances as the joint stage saw them; ``found``: the same through its
    cameras, compared with their ``regions``' targets where they have one)."""
    photo = list(photo_alone)
    region = opts.region
    moved = [k for k, r in enumerate(alone) if photo[k] is not None and region is not None
             and not _within(pose_change(r.result.T_wm, joint.poses[k], pyramids[k].mesh.centre), region)]
    if moved and region is not None:  # the photo's evidence again at those joint poses, the others as left out before
        _, again = region_terms(given.through(found.camera_by_id), models, joint.poses, opts, region)
        for k in moved:
            photo[k] = again[k]
    compared = [ComparedViews.of(sc) if term is None else term.targets_in(sc)
                for sc, term in zip(found.scenes, regions)]
    after = []
    for k, r in enumerate(alone):
        alone_unc = r.result.uncertainty
        unc = joint.uncertainties[k] if alone_unc is None else joint.uncertainties[k].adding(
            spread_factor=alone_unc.spread_factor, bias_shift=alone_unc.bias_shift, view_dir_m=alone_unc.view_dir_m,
            turn_floors=tuple(alone_unc.turn_floors))
        gap = None
        weak = unc.weak_turns_not_free(pyramids[k].symmetries.axes)
        if weak and opts.disambiguation.weak_turns:  # the joint system's weak turns, tried at its pose
            own, scores, _ = turn_scores(pyramids[k].with_faces(opts.detail.coarse), compared[k],
                                         joint.poses[k], weak, pyramids[k].mesh.centre,
                                         opts.disambiguation.weak_turns)
            gap = own - float(scores.max())
        by_terms = joint.evaluation.measured(k)  # its own terms' records beside the masks (the depth's)
        seen = r.result.measurement(SeeThrough)
        if seen is not None:  # the depth sees through it: the joint stage did not use it either
            by_terms += (measured_see_through(compared[k], pyramids[k], joint.poses[k], opts, seen.declared),)
        had_photo = r.result.measurement(PhotoEvidence)
        iou = joint.evaluation.hard_iou(k)
        own_scene = given.scenes[k]
        if photo[k] is not None and own_scene.has_masks:  # with its own masks
            own = ComparedViews.of(replace(own_scene, cameras=found.scenes[k].cameras))
            silhouettes = pyramids[k].fine(opts.detail).hard_masks(joint.poses[k], own.cameras)
            iou = view_ious(silhouettes, own)
            unc = with_outline_disagreement(unc, shared_outline_offset(silhouettes, own))
        if joint.scale_sigma > 0.0:  # the labels follow the solved scale along their rays
            centre_w = transform_points(joint.poses[k], pyramids[k].mesh.centre[None])[0]
            distance = float(np.median([np.linalg.norm(centre_w - c.centre) for c in found.scenes[k].cameras]))
            unc = with_scale_sigma(unc, joint.scale_sigma, distance)
        # the alone turn rise weighed its depth against cameras of the unsolved scale: then it says nothing
        rise = (r.result.turn_rise, r.result.turn_rise_axis_m) if joint.scale_sigma == 0.0 else (None, None)
        evidence = (had_photo if photo[k] is None or had_photo is None
                    else replace(photo[k], rounds=had_photo.rounds, side=had_photo.side))
        contact = r.result.measurement(Contact)
        if contact is not None and contact.kept:  # held to the plane in the joint stage too: its gap there
            mesh = pyramids[k].mesh
            on = RestingContact(contact.plane, mesh.hull, mesh.centre, 1.0, mesh.resting_downs)
            contact = replace(contact, gap_after_mm=on.gap_mm(joint.poses[k]), tilt_after_deg=on.tilt_deg(joint.poses[k]))
        measured = by_terms + tuple(m for m in (evidence, contact) if m is not None)
        after.append(replace(r.result, T_wm=joint.poses[k], iou_after=iou, weights=joint.evaluation.weights[k],
                             uncertainty=unc, turn_gap=gap, turn_rise=rise[0], turn_rise_axis_m=rise[1],
                             terms=joint.evaluation.record(k), measured=measured))
    return after


def without_see_through_depth(found: InstanceScenes, alone: list[InstanceResult]) -> InstanceScenes:
    """``found`` without the measured depth of the instances it sees through (their results alone
    say so: :mod:`autoalign.engine.see_through`), for the joint stage."""
    see_through = [r.result.measurement(SeeThrough) is not None for r in alone]
    if not any(see_through):
        return found
    return replace(found, scenes=[replace(sc, depths=None) if st else sc for sc, st in zip(found.scenes, see_through)])


def _flagged(r: InstanceResult, reason: str) -> InstanceResult:
    """The instance at least ``check``, with ``reason`` added."""
    return replace(r, verdict=replace(r.verdict, status="failed" if r.verdict.status == "failed" else "check",
                                      reasons=r.verdict.reasons + [reason]))


def _moved_by_votes(u: Uncertainty | None, votes_sigma: float) -> float:
    """How far (mm, sigma) the objects' disagreement on the scene's scale (its relative sigma
    ``votes_sigma``) moves a label of uncertainty ``u`` along its rays (inf: not known)."""
    if u is None or u.parts is None or u.parts.scale is None:
        return float("inf")
    return votes_sigma * u.parts.scale[1]


def _flagged_by_scale(results: list[InstanceResult], joint: JointRefinement, rounds: int,
                      settled: bool) -> list[InstanceResult]:
    """``results`` with what the solved scene scale says of them: the objects' disagreement on it, where
    it exceeds the views' spread, on the labels it moves along their rays by more than the position sigma
    that leaves a label in doubt (:data:`~autoalign.quality.verdict.LARGE_SIGMA_MM`); a scale that did not
    settle in ``rounds``, on every label (each one's depth in its camera follows it). Models that all fit
    their masks still disagree by a few parts in 10^4 (their outlines' pixels): 0.01-0.07% on the 3- and
    4-object scenes of ``bench_scene``, which moves a label 700 mm away by at most 0.5 mm."""
    if joint.scale_votes_sigma ** 2 > joint.scale_sigma ** 2 / 2:  # more than the views' spread
        pct = 100 * joint.scale_votes_sigma
        moved = [_moved_by_votes(r.result.uncertainty, joint.scale_votes_sigma) for r in results]
        results = [_flagged(r, f"the objects disagree on the scene's scale: it moves by {pct:.2g}% (sigma) as "
                               f"each one's say is left out, this label by {mm:.2g} mm along its rays; check the "
                               "models' sizes and units") if mm > LARGE_SIGMA_MM else r
                   for r, mm in zip(results, moved)]
    if not settled:
        reason = f"the scene's scale did not settle in {rounds} rounds: the objects' masks and their fit disagree on it"
        results = [_flagged(r, reason) for r in results]
    return results


def joint_rule(opts: RefineOptions) -> StepRule | None:
    """The joint stage's step rule for ``opts.optimizer`` (``None``: its Levenberg-Marquardt). The
    joint stage solves the instances' L2 mask residuals together (the occlusion-aware objective):
    a loss or an optimiser it cannot honour is an error, not a stage silently run otherwise."""
    fix = "leave it out, or refine one object at a time with --model"
    if opts.loss != "l2":
        raise AutoalignError(f"--loss {opts.loss}: the objects of --models are refined together with the l2 loss "
                             f"only (their residuals are solved jointly); {fix}")
    if not isinstance(opts.optimizer, (LevenbergMarquardt, GaussNewton)):
        raise AutoalignError(f"--optimizer {opts.optimizer.name}: the objects of --models are refined together by "
                             f"least squares (lm or gn) only; {fix}")
    return GaussNewton(max_step=None) if isinstance(opts.optimizer, GaussNewton) else None


def refine_scene(found: InstanceScenes, models: ModelSet, seeds: dict[int, NDArray[np.float64]],
                 options: RefineOptions | None = None, refine_cameras: bool = False, solve_scale: bool = False,
                 progress: Progress | None = None, seed_radius: tuple[float, float] = SEED_RADIUS,
                 preview: InstancePreview | None = None) -> SceneRefinement:
    """Every instance alone (seed, search, polish: :func:`refine_instances`), then all of them
    together, occlusion-aware (:func:`~autoalign.scene.joint.refine_jointly`), with a correction
    of every camera if ``refine_cameras``. Corrections that explain too little of the misfit to be
    trusted (:func:`~autoalign.scene.cameras.corrections_accepted`) are dropped with the poses
    solved along with them, and the joint stage runs again without them. Each instance's pose,
    per-view fit, uncertainty and verdict are then those of the joint stage. A single instance
    without camera refinement has nothing to be solved with: its own result is kept.

    With ``solve_scale`` the cameras' translations are taken to be in an unknown unit, already
    scaled by a first guess (:func:`~autoalign.scene.scale.scale_from_masks`); the scale is solved
    with the poses (see module doc). Each instance's alone poses go to ``preview`` as they come."""
    opts = options or RefineOptions()
    rule = joint_rule(opts) if len(found.instances) > 1 or refine_cameras or solve_scale else None
    given_seeds = dict(seeds)  # a result farther than seed_radius from its seed is flagged (not with a scale to solve)
    scale, scale_sigma, settled = 1.0, 0.0, not solve_scale
    solved = False  # whether a joint stage has solved the scale from instances that fit alone
    rounds = SCALE_ROUNDS if solve_scale else 1
    for round_ in range(rounds):
        alone = refine_instances(found, models, seeds, opts, progress, seed_radius, not solve_scale, preview)
        if len(alone) == 1 and not refine_cameras and not solve_scale:
            return SceneRefinement(alone, None, None, found)
        fits = [r.verdict.status == "ok" for r in alone]
        scale_from = fits if any(fits) else None  # the instances whose masks decide the scale (all if none fit)
        if solve_scale and not solved and round_ < rounds - 1:  # the scale again, from the orientations found
            rotations = {r.instance.index: r.result.T_wm[:3, :3] for r in alone}
            guess = scale_from_masks(found, models, rotations, scale_from)
            if abs(guess.factor - 1.0) > SCALE_REGUESS:
                found, scale = rescaled(found, guess.factor), scale * guess.factor
                seeds = {r.instance.index: grown_pose(r.result.T_wm, models.mesh(r.instance.obj_id).centre, guess.factor)
                         for r in alone}
                continue
        pyramids, start = [models.pyramid(r.instance.obj_id) for r in alone], [r.result.T_wm for r in alone]
        holds = [r.result.holds for r in alone]  # the terms on the pose that held each alone, kept jointly
        t0 = time.perf_counter()
        photo_alone: list[PhotoEvidence | None] = [None] * len(alone)
        regions: list[RegionTerm | None] = [None] * len(alone)
        given = found  # the instances as read; with photos, their region terms at the alone poses, the others left out
        if opts.region is not None and any(sc.photos is not None for sc in found.scenes):
            found = given = others_left_out(found, models, {r.instance.index: r.result.T_wm for r in alone})
            regions, photo_alone = region_terms(given, models, start, opts, opts.region)
        opaque = without_see_through_depth(found, alone)
        edges = opts.region.edge_weight if opts.region is not None else None  # on the instances without masks
        attempt = (refine_jointly(opaque, pyramids, start, with_cameras=True, detail=opts.detail, robust=opts.robust,
                                  with_scale=solve_scale, depth=opts.depth, edges=edges, scale_from=scale_from,
                                  progress=progress, rule=rule, holds=holds, regions=regions)
                   if refine_cameras else None)
        if attempt is not None and corrections_accepted(attempt.view_misfit_before, attempt.view_misfit_after):
            joint = attempt
        else:
            joint = refine_jointly(opaque, pyramids, start, detail=opts.detail, robust=opts.robust, with_scale=solve_scale,
                                   depth=opts.depth, edges=edges, scale_from=scale_from, progress=progress, rule=rule,
                                   holds=holds, regions=regions)
        if solve_scale:
            found = found.through({**scaled_cameras(found.camera_by_id, joint.scale), **joint.cameras})
            scale, scale_sigma, solved = scale * joint.scale, joint.scale_sigma, any(fits)
            seeds = {r.instance.index: T for r, T in zip(alone, joint.poses)}  # already grown with the scene
            if abs(joint.scale - 1.0) < SCALE_SETTLED:
                settled = True
                break
        elif joint is attempt:
            found = found.through(joint.cameras)
    after = _after_joint(alone, joint, given, found, pyramids, models, opts, photo_alone, regions)
    seconds = (time.perf_counter() - t0) / max(len(alone), 1)
    results = [InstanceResult(r.instance, replace(res, timings={**res.timings, "joint": seconds}),
                              verdict_of(res, found.scenes[k].empty, models, r.instance.obj_id,
                                         None if solve_scale else given_seeds.get(r.instance.index), seed_radius),
                              r.seconds + seconds)
               for k, (r, res) in enumerate(zip(alone, after))]
    if solve_scale:
        results = _flagged_by_scale(results, joint, rounds, settled)
    # the instances' own masks through the final cameras
    return SceneRefinement(results, joint, attempt, given.through(found.camera_by_id), scale, scale_sigma, settled)

