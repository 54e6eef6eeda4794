"""The refinement engine, in stages: seed -> search -> polish -> disambiguate -> report.

``refine(scene, mesh, seed)`` is the Python API behind ``autoalign refine``.
"""

from __future__ import annotations

import enum
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, TypeVar

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import (
    best_poses,
    climb_poses,
    flips,
    orbit,
    poses_at,
    score_poses,
    turn_scores,
    turns,
)
from autoalign.engine.objective import Evaluation, Level, SilhouetteObjective
from autoalign.engine.options import (  # noqa: F401 - the engine's settings, importable from here too
    DEFAULT_SCHEDULE,
    DisambiguationOptions,
    RankingOptions,
    RefineOptions,
    SearchOptions,
)
from autoalign.engine.photo_evidence import best_side, photo_result, photo_rounds, region_term_at
from autoalign.engine.refit_spread import refit_ratio, spread_factor
from autoalign.engine.schedule import (  # noqa: F401 - polish: one pose, no search
    Progress, compared_objective, polish, run_schedule)
from autoalign.engine.see_through import in_doubt, measured_see_through, offering_table, seen_through_at_seed
from autoalign.engine.seed_region import CLEARLY_BETTER, STIFFNESS, SeedHold, SeedRegion
from autoalign.engine.seeding import Click, click_centre, hull_centre, rotation_grid
from autoalign.engine.solver import StepRule, Trace
from autoalign.engine.stand_up import best_standings, nearest_standing
from autoalign.engine.turn_profile import with_turn_profiles
from autoalign.engine.uncertainty import Uncertainty, pose_uncertainty, viewpoint_groups
from autoalign.errors import AutoalignError
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import pose_change, symmetric_pose_change, transform_points
from autoalign.io.bop import Scene
from autoalign.losses import targets_in_crops
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.silhouette import boundary_bias_grads
from autoalign.losses.contact import (CONTACT_MAX_LEAN_DEG, CONTACT_STIFFNESS, OFFERED_GAP_MM, Contact, RestingContact,
                                      TablePlane)
from autoalign.losses.term import Measured, PoseTerm, TermEvidence, ViewTermsRecord
from autoalign.losses.overlap import LOOSE_FIT_IOU, iou_from_counts, view_ious
from autoalign.losses.region_term import RegionTerm
from autoalign.losses.see_through import SeeThrough
from autoalign.rasterizers.pyramid import MeshPyramid
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

Seed = NDArray[np.float64] | Click | None
M = TypeVar("M")


class Stage(enum.Enum):
    """Where a hypothesis got to (:attr:`Hypothesis.stage`; ``refine.json`` writes :attr:`Hypothesis.stage_name`)."""

    START = "start"  # a start, not yet run
    FLIP = "flip"  # a half turn of the best start, not yet run
    SEARCH = "search"  # left in the orientation funnel, at its step Hypothesis.step (0, 1)
    DROPPED = "level"  # left behind after the polish level of scale Hypothesis.step
    ORBIT = "orbit"  # a turn of the runner-up's orbit, not yet polished
    WEAK_TURN = "weak turn"  # a turn about a weakly observed axis, not yet polished
    NEAR_TURN = "near turn"  # a small turn about a principal axis (out of a local minimum), not yet polished
    FINAL = "final"  # polished through the last level


@dataclass(eq=False)
class Hypothesis:
    """One start tried: its initial pose, its final pose, loss and mean IoU.

    ``loss`` is the mean weighted loss at the last level it reached; for a finalist not polished at
    the last level (``estimated``, see :func:`_polish`) it is its loss there scaled by the polishing
    gain of the best. An estimated loss never outranks a measured one. ``path`` holds the levels
    it went through from ``T_init``, in order; a flip or orbit candidate continues its parent's.
    """

    T_init: NDArray[np.float64]
    T_final: NDArray[np.float64]
    loss: float
    mean_iou: float
    stage: Stage
    path: tuple[tuple[Level, Trace], ...] = ()
    estimated: bool = False
    step: float | None = None

    @property
    def stage_name(self) -> str:
        """The stage as reports write it: ``search0``, ``level 0.5``, ``final``, ..."""
        if self.stage is Stage.SEARCH:
            return f"search{int(self.step)}"
        if self.stage is Stage.DROPPED:
            return f"level {self.step:g}"
        return self.stage.value

    def rank(self) -> tuple[bool, float]:
        """Sort key, best first: measured losses before estimated ones, then by loss."""
        return self.estimated, self.loss


@dataclass(frozen=True)
class TurnTests:
    """How the disambiguated pose fits against its turns: ``gap``, the mean hard IoU at 1/4
    resolution by which it beats its turns of 30-180 degrees about its weakly observed axes
    (``None``: none tried); ``rise``, with measured depth, the smallest relative rise of the whole
    objective from it to its turns of 10-20 degrees about an axis the mesh is nearly round about,
    ``rise_axis_m`` (unit, model frame; ``None``: no depth, or no such axis)."""

    gap: float | None = None
    rise: float | None = None
    rise_axis_m: NDArray[np.float64] | None = None


@dataclass
class Finalist:
    """A hypothesis polished through the last level, with its final view weights."""

    hypothesis: Hypothesis
    weights: NDArray[np.float64]


@dataclass
class Standing:
    """Every hypothesis ranked best first, the best one at a clearly different pose, and whether it
    fits almost as well as the best (``ambiguous``)."""

    ranked: list[Hypothesis]
    runner_up: Hypothesis | None
    ambiguous: bool


@dataclass
class RefineResult:
    """What :func:`refine` found.

    Attributes:
        T_wm: world-from-model pose (4x4, mm).
        T_init: the starting pose of the winning hypothesis (a scored, polished orientation, or the seed).
        iou_before / iou_after: per-view hard-mask IoU at full resolution
            (:func:`~autoalign.losses.overlap.view_ious`; with measured depth, ``iou_after`` also
            leaves out the pixels the depth shows hidden behind an unmodelled occluder).
        iterations: optimiser iterations of the winner from its start, every level it went through
            (the hypothesis search's included; with photos, the masks' placement and the photo rounds too).
        renders: soft renders used in total (with photos, the masks' placement's too).
        timings: seconds per stage.
        hypotheses: every start tried, best first.
        ambiguous: a clearly different pose fits almost as well (symmetric or ambiguous object).
        runner_up: the best hypothesis at a different pose, if any.
        weights: final per-view robust weights (low = the mask disagrees with the rest).
        history: objective and pose per accepted iteration of the winner, per level it went through.
        uncertainty: covariance and sigmas of the pose (:mod:`autoalign.engine.uncertainty`).
        turn_gap: from a given pose with weakly observed turns, how much better (mean hard IoU at
            1/4 resolution) the result fits than the best of its turns about those axes (30-180
            degrees; negative: a turn fit better and was refined); ``None`` when none were tried.
            Near 0 the object is nearly symmetric about such an axis.
        turn_rise: with measured depth, the smallest relative rise of the whole objective from the
            disambiguated pose to its turns of 10-20 degrees about an axis the mesh is nearly round
            about (:attr:`~autoalign.geometry.mesh.Mesh.round_axes`; negative: a turn fits better); near
            0 the evidence does not fix that turn (a nearly symmetric can seen from one side), about
            ``turn_rise_axis_m`` (unit, model frame). ``None``: no depth, no such axis (any turn
            changes the shape), or the pose held near its seed.
        terms: each evidence term's loss per view at the result, with the view weights
            (:class:`~autoalign.losses.term.ViewTermsRecord`).
        measured: what each kind of evidence beside the masks measured at the result, in the order it
            was measured (:class:`~autoalign.losses.term.Measured`): the depth term's
            (:class:`~autoalign.losses.depth.DepthTerms`), the photo's
            (:class:`~autoalign.engine.photo_evidence.PhotoEvidence`). With photos the terms compare
            the silhouettes with the region targets (the photo's posteriors fused with the mask);
            the IoUs are with the instance's masks, or with the targets where it has none.
        seed_hold: where the masks pulled the pose beyond a given seed's radius, the far pose and
            which was returned (:class:`~autoalign.engine.seed_region.SeedHold`); ``None`` otherwise.
        holds: the terms on the pose alone that hold the result (:class:`~autoalign.losses.term.PoseTerm`):
            the seed's region where the result is the best pose within it, the resting contact kept;
            the joint stage of several objects keeps them.
    """

    T_wm: NDArray[np.float64]
    T_init: NDArray[np.float64]
    iou_before: NDArray[np.float64]
    iou_after: NDArray[np.float64]
    iterations: int
    renders: int
    timings: dict[str, float]
    hypotheses: list[Hypothesis]
    ambiguous: bool
    runner_up: Hypothesis | None
    weights: NDArray[np.float64]
    history: list[dict[str, Any]] = field(default_factory=list)
    image_ids: list[int] = field(default_factory=list)
    uncertainty: Uncertainty | None = None
    turn_gap: float | None = None
    turn_rise: float | None = None
    turn_rise_axis_m: NDArray[np.float64] | None = None
    terms: ViewTermsRecord | None = None
    measured: tuple[Measured, ...] = ()
    seed_hold: SeedHold | None = None
    holds: tuple[PoseTerm, ...] = ()

    def evidence(self) -> tuple[TermEvidence, ...]:
        """What each kind of evidence beside the masks says of the pose, in the order it was measured
        (:class:`~autoalign.losses.term.TermEvidence`; a kind that measured too little is left out)."""
        said = (m.evidence() for m in self.measured)
        return tuple(e for e in said if e is not None)

    def measurement(self, kind: type[M]) -> M | None:
        """What the evidence of ``kind`` (e.g. :class:`~autoalign.losses.depth.DepthTerms`) measured, if it did."""
        return next((m for m in self.measured if isinstance(m, kind)), None)

    def with_cost_of(self, other: "RefineResult") -> "RefineResult":
        """This result with the renders and timings of the ``other`` run, made and set aside, added."""
        return replace(self, renders=self.renders + other.renders,
                       timings={k: other.timings.get(k, 0.0) + v for k, v in self.timings.items()})


def _final_loss(obj: SilhouetteObjective, T: NDArray[np.float64], level: Level,
                trace: Trace | None = None) -> tuple[float, float, NDArray[np.float64]]:
    """Mean weighted loss, mean soft IoU and view weights at ``T`` (reusing the optimiser's last evaluation)."""
    ev = trace.final if trace is not None and trace.final is not None else obj.evaluate(T, level, with_derivatives=False)
    return ev.value / len(ev.weights), float(np.mean(ev.terms.iou)), ev.weights


def _hard_ious_of(ev: Evaluation, views: ComparedViews) -> NDArray[np.float64]:
    """:func:`~autoalign.losses.overlap.view_ious` from the hard masks of a full-resolution
    evaluation, without casting them again (the ignored pixels are already off the evaluation's
    silhouettes and never on the instance's own target)."""
    sil = ev.silhouettes
    tg = [m > 0.5 for m in views.targets]
    t_crop = targets_in_crops(tg, sil) > 0.5
    vp = sil.view_of_pixel()
    inter = np.bincount(vp, weights=sil.hard & t_crop, minlength=sil.n_views)
    area = np.bincount(vp, weights=sil.hard, minlength=sil.n_views)
    return iou_from_counts(inter, area, [float(t.sum()) for t in tg])


def hard_ious(rast: SoftSilhouetteRasterizer, views: ComparedViews, T_wm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-view IoU of the ray-cast silhouette at ``T_wm`` with the views' targets, full resolution
    (the ignored pixels left out)."""
    return view_ious(rast.hard_masks(T_wm, views.cameras), views)


ALIKE_TURNS_DEG = np.r_[np.arange(5.0, 180.0, 5.0), -np.arange(5.0, 180.0, 5.0)]
"""The turns (degrees, one way then the other) about an axis the object is nearly round about
scanned for one that looks alike (:func:`_alike_turns`): at 1/4 resolution in one kernel, 0.05 s for
40 views. A gear's teeth 30 degrees apart score within 0.002 of the pose itself there, and 0.04-0.10
below it between them."""
ALIKE_SCORE_SCALE = 0.5
"""The resolution (of the images') at which the turns that look alike are scored against the pose
(:func:`_with_alike_turn`). A keyed gear a tooth off, its 11 other teeth scored in 40 views: the
right turn +0.0068 in mean hard IoU at full resolution, +0.0034 at 1/2 (0.04 s against 0.20), every
other turn below the pose at both."""
SAME_BASIN_SIZE = 0.1
SAME_BASIN_DEG = 10.0
"""In the search funnel, hypotheses closer than this fraction of the object's diameter and this many
degrees count as one: at 1/8 resolution a pixel spans 10-15 mm, and the search's ends in one basin
differ by a few millimetres and degrees. With the answer's own 2 mm / 5 degrees there, three copies of
a half-turned ape (154-157 degrees from the truth, 0.3% apart in loss) filled the places of the
first level and the right basin, 3% worse at 1/8 resolution, went no further."""


def _differs(A: NDArray[np.float64], B: NDArray[np.float64], centre_m: NDArray[np.float64],
             mm: float = 2.0, deg: float = 5.0) -> bool:
    d_mm, d_deg = pose_change(A, B, centre_m)
    return d_mm > mm or d_deg > deg


def _search(obj: SilhouetteObjective, starts: list[NDArray[np.float64]], mesh: Mesh, opts: RefineOptions,
            progress: Progress | None) -> tuple[list[Hypothesis], list[Hypothesis]]:
    """The orientation funnel: every start at ``opts.search.level`` (plus the best one's half
    turns), the best ``n_mid`` distinct at the schedule's first level, of which the best
    ``n_final`` distinct and competitive ones are returned as finalists (best first), with all the
    others. A hypothesis is given up once, after two iterations, its loss is ``opts.search.abandon``
    times the best of its stage so far."""
    levels = opts.schedule
    others: list[Hypothesis] = []
    pool = [Hypothesis(T, T, float("nan"), float("nan"), Stage.START) for T in starts]
    funnel = [(opts.search.level, opts.search.n_mid), (levels[0], opts.search.n_final)]
    for stage, (level, keep) in enumerate(funnel):
        done: list[Hypothesis] = []

        def run(todo: list[Hypothesis]) -> None:
            for j, h in enumerate(todo):
                bar = opts.search.abandon * min((d.loss for d in done), default=np.inf)
                Tc, tr = run_schedule(obj, h.T_final, (level,), opts.optimizer,
                                       give_up=lambda it, ev, bar=bar: it >= 1 and ev.value / len(ev.weights) > bar)
                loss, miou, _ = _final_loss(obj, Tc, level, tr[-1])
                done.append(Hypothesis(h.T_init, Tc, loss, miou, Stage.SEARCH, h.path + ((level, tr[-1]),), step=stage))
                if progress is not None:
                    progress(f"hypotheses {stage + 1}/{len(funnel)}", j + 1, len(todo))

        run(pool)
        if stage == 0 and opts.search.flips:  # the half turns of the best one compete too, from its path
            best = min(done, key=lambda h: h.loss)
            run([Hypothesis(best.T_init, T, float("nan"), float("nan"), Stage.FLIP, best.path)
                 for T in flips(best.T_final, mesh.principal_axes, mesh.centre)])
        done.sort(key=lambda h: h.loss)
        pool = []
        for h in done:  # keep distinct poses only
            if len(pool) < keep and all(_differs(h.T_final, f.T_final, mesh.centre, SAME_BASIN_SIZE * mesh.diameter,
                                                 SAME_BASIN_DEG) for f in pool):
                pool.append(h)
        others.extend(h for h in done if h not in pool)
    # A distinct runner-up goes on only while it is competitive: a clearly worse pose need not be polished.
    finalists = [h for h in pool if _competitive(h.loss, pool[0].loss, opts)]
    return finalists, others + [h for h in pool if h not in finalists]


def _competitive(loss: float, best_loss: float, opts: RefineOptions) -> bool:
    """Whether a hypothesis' loss is within ``opts.ranking.competitive`` of the best's, so that it goes on
    (the 1e-4 keeps near-zero losses of exact masks comparable)."""
    return loss <= best_loss * opts.ranking.competitive + 1e-4


def _polish(obj: SilhouetteObjective, finalists: list[Hypothesis], levels: tuple[Level, ...], opts: RefineOptions,
            progress: Progress | None, label: str = "refine"
            ) -> tuple[list["Finalist"], list[Hypothesis]]:
    """Take the finalists (best first) through ``levels`` together.

    After each level below the last, one no longer within ``opts.ranking.competitive`` of the best stops
    there (it can be neither the answer nor ambiguous with it). At the last level only the best is
    polished: another is rendered once and its loss scaled by the best's polishing gain (from the
    same level before, the same gain); it is polished too only if that estimate is below the best's
    loss (by ``opts.ranking.polish_margin``). On a symmetric object the runner-up is an equivalent pose,
    and polishing it bought nothing; on the real LM-O can a half-turned pose was polished first and
    the right one, estimated 1.8% lower, was left unpolished behind it when only a 5% lower estimate
    was polished.

    Returns the finalists (best first, :attr:`Stage.FINAL`) and the ones that stopped early.
    """
    alive, dropped = list(finalists), []
    scored: list[Finalist] = []
    gain = 1.0
    for li, lv in enumerate(levels):
        at_last = li == len(levels) - 1
        scored = []
        for k, h in enumerate(alive):
            if at_last and k > 0:
                ev = obj.evaluate(h.T_final, lv, with_derivatives=False)
                estimate = ev.value / len(ev.weights) * gain
                if estimate >= scored[0].hypothesis.loss * (1.0 - opts.ranking.polish_margin):
                    scored.append(Finalist(Hypothesis(h.T_init, h.T_final, estimate, float(np.mean(ev.terms.iou)),
                                                      Stage.FINAL, h.path, estimated=True), ev.weights))
                    continue
            name = label if len(alive) == 1 else f"{label} {k + 1}/{len(alive)}"
            T, tr = run_schedule(obj, h.T_final, (lv,), opts.optimizer, progress, f"{name} (level {li + 1}/{len(levels)})")
            loss, miou, weights = _final_loss(obj, T, lv, tr[-1])
            scored.append(Finalist(Hypothesis(h.T_init, T, loss, miou, Stage.FINAL, h.path + ((lv, tr[-1]),)), weights))
            start = tr[-1].start
            if k == 0 and start is not None:  # the best's polishing gain at this level
                gain = loss / max(start.value / len(start.weights), 1e-12)
        scored.sort(key=lambda f: f.hypothesis.rank())  # an estimate ranks last: had it been clearly better, it was polished
        if not at_last:
            best_loss = scored[0].hypothesis.loss
            dropped.extend(replace(f.hypothesis, stage=Stage.DROPPED, step=lv.scale) for f in scored
                           if not _competitive(f.hypothesis.loss, best_loss, opts))
            scored = [f for f in scored if _competitive(f.hypothesis.loss, best_loss, opts)]
        alive = [f.hypothesis for f in scored]
    return scored, dropped


def _final_state(obj: SilhouetteObjective, best: Hypothesis, weights: NDArray[np.float64],
                 levels: tuple[Level, ...], rule: StepRule,
                 with_uncertainty: bool = True) -> tuple[Evaluation, Uncertainty | None]:
    """The full-resolution evaluation at the best pose (the optimiser's last one when it has it)
    and the pose's uncertainty from it (``None`` when not ``with_uncertainty``)."""
    last_level, last_trace = best.path[-1] if best.path else (None, None)
    if last_trace is not None and last_trace.final is not None and last_level.scale == 1.0 and last_level.max_views is None:
        ev = last_trace.final
    else:
        ev = obj.evaluate(best.T_final, Level(1.0, levels[-1].sigma, 0), weights=weights)
    return ev, final_uncertainty(obj, ev, best.T_final, levels[-1], rule) if with_uncertainty else None


def final_uncertainty(obj: SilhouetteObjective, ev: Evaluation, T_wm: NDArray[np.float64],
                      last: Level, rule: StepRule) -> Uncertainty:
    """The pose's uncertainty from a full-resolution evaluation ``ev`` at it: the views' spread
    scaled where polishes with views left out move the pose farther than its Newton steps
    (:mod:`autoalign.engine.refit_spread`, with the step ``rule`` and the schedule's ``last`` level),
    with the prior on a shared shift of the masks' outlines (:mod:`autoalign.engine.uncertainty`)
    and each weakly observed turn's variance from its loss profile
    (:mod:`autoalign.engine.turn_profile`; ``last``'s blur)."""
    views = obj.at_scale(1.0)
    centre_w = transform_points(T_wm, obj.centre_m[None])[0]
    dirs = np.array([centre_w - c.centre for c in views.cameras])
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    bias = boundary_bias_grads(ev.silhouettes, views.targets, views.totals)
    factor = spread_factor(refit_ratio(obj, T_wm, ev, last, rule))
    groups = viewpoint_groups(dirs)
    u = pose_uncertainty(ev.gn, ev.terms.grad, ev.terms.gn, ev.weights, ev.value, len(ev.silhouettes.band),
                         T_wm[:3, :3], bias, dirs, spread_factor=factor, groups=groups)
    return with_turn_profiles(obj, T_wm, u, ev.weights, last.sigma, groups)


PosePreview = Callable[[NDArray[np.float64]], None]
"""``preview(T_wm)``: a pose worth showing before the result is ready (world-from-model, 4x4, mm), for
showing something at once (the label page's click): the orientation search's first answer, before any
descent, and the refined pose before its uncertainty and verdict are worked out (the stages after them,
a seed's hold, a resting contact, a weak turn, may still move it)."""


def _seed(views: ComparedViews, pyramid: MeshPyramid, seed: Seed, opts: RefineOptions,
          progress: Progress | None, preview: PosePreview | None = None) -> list[NDArray[np.float64]]:
    """Stage 1: the starting poses: the seed itself, or the best-scoring orientations of a rotation
    grid placed at the click's or the visual hull's centre, each climbed to the best of its small
    turns. The best-scoring one goes to ``preview``."""
    if seed is not None and not isinstance(seed, Click):
        return [np.asarray(seed, dtype=np.float64)]
    mesh, search = pyramid.mesh, pyramid.with_faces(opts.detail.search)
    scene = views.scene  # no region term without a given pose: the targets are the masks
    centre = click_centre(scene, seed, mesh.diameter) if isinstance(seed, Click) else hull_centre(scene, mesh.diameter)
    poses = poses_at(rotation_grid(opts.search.n_rotations), centre, mesh.centre)
    if progress is not None:
        progress("scoring orientations", 0, 1)
    top = best_poses(search, views, poses, opts.search.n_starts, anchor=centre)
    if preview is not None:
        preview(top[0].copy())
    starts = list(climb_poses(search, views, top, opts.search.climb_deg, anchor=centre))
    if progress is not None:
        progress("scoring orientations", 1, 1)
    return starts


def _rank(final: list[Finalist], others: list[Hypothesis], centre_m: NDArray[np.float64],
          opts: RefineOptions) -> Standing:
    """The standing of the finalists (best first) and every other hypothesis tried."""
    ranked = [f.hypothesis for f in final] + sorted(others, key=lambda h: h.loss)
    runner = next((h for h in ranked[1:] if _differs(h.T_final, ranked[0].T_final, centre_m)), None)
    # ambiguous: the runner-up's loss is almost the best's, or competitive while its IoU is higher
    # (the robust loss and the IoU disagree on which fits: masks that fail in some views)
    ambiguous = bool(runner is not None and runner.stage is Stage.FINAL
                     and (runner.loss <= ranked[0].loss * (1.0 + opts.ranking.ambiguity_tol) + 1e-4
                          or (_competitive(runner.loss, ranked[0].loss, opts)
                              and runner.mean_iou >= ranked[0].mean_iou)))
    return Standing(ranked, runner, ambiguous)


def _with_candidate(obj: SilhouetteObjective, final: list[Finalist], parent: Hypothesis, T: NDArray[np.float64],
                    stage: Stage, level: Level, opts: RefineOptions, progress: Progress | None) -> list[Finalist]:
    """``final`` with the pose ``T`` (reached from ``parent``'s path by a known turn) polished at
    ``level`` added, best first."""
    polished, _ = _polish(obj, [Hypothesis(parent.T_init, T, float("nan"), float("nan"), stage, parent.path)],
                          (level,), opts, progress, f"refine {stage.value}")
    return sorted(final + polished, key=lambda f: f.hypothesis.rank())


def _with_best_turn(obj: SilhouetteObjective, views: ComparedViews, final: list[Finalist], parent: Hypothesis,
                    axes_m: list[NDArray[np.float64]], angles_deg: tuple[float, ...], margin: float, stage: Stage,
                    opts: RefineOptions, progress: Progress | None, both_ways: bool = False
                    ) -> tuple[list[Finalist], float]:
    """``parent``'s turns about ``axes_m`` by ``angles_deg`` scored by hard IoU at 1/4 resolution
    (:func:`~autoalign.engine.hypotheses.turn_scores`); the best, if it beats ``parent`` by more than
    ``margin``, polished at the last level and added to ``final`` (best first). With ``both_ways``
    the best turn the other way about the same axis is polished too when it also beats ``parent``
    by ``margin``: a pose between two near-equal minima (a keyed gear half a tooth off) has one on
    each side, and 1/4 resolution cannot tell which holds the key. Returns the finalists and how
    much better ``parent`` scored than its best turn (negative: the turn was better)."""
    own, scores, cands = turn_scores(obj.pyramid.with_faces(opts.detail.coarse), views, parent.T_final,
                                     axes_m, obj.centre_m, angles_deg)
    k = int(np.argmax(scores))
    picked = [k] if scores[k] > own + margin else []
    if picked and both_ways:
        n = len(angles_deg)  # the turns are by axis, then by angle
        axis, sign = k // n, np.sign(angles_deg[k % n])
        other = [axis * n + j for j in range(n) if np.sign(angles_deg[j]) == -sign]
        j = max(other, key=lambda j: scores[j], default=None)
        if j is not None and scores[j] > own + margin:
            picked.append(j)
    for j in picked:
        final = _with_candidate(obj, final, parent, cands[j], stage, opts.schedule[-1], opts, progress)
    return final, own - float(scores[k])


def _turn_rise(obj: SilhouetteObjective, T_wm: NDArray[np.float64], axes_m: NDArray[np.float64],
               angles_deg: tuple[float, ...], level: Level) -> tuple[float, NDArray[np.float64]]:
    """How much the whole objective (every term: the masks, the depth where measured) rises at
    ``level`` when the pose ``T_wm`` is turned by ``angles_deg`` about each of ``axes_m`` (rows, unit,
    model frame): over the axes, the smallest relative rise to the best of that axis's turns
    (negative: a turn fits better), and that axis. The masks' hard IoU, which the near turns use, is
    blind to a turn about a near-symmetry axis; this says whether any evidence sees it."""
    own = obj.evaluate(T_wm, level, with_derivatives=False).value
    values = np.array([[obj.evaluate(T, level, with_derivatives=False).value
                        for T in turns(T_wm, a, obj.centre_m, angles_deg)] for a in axes_m])
    a = int(np.argmin(values.min(axis=1)))
    return float(values[a].min() / own - 1.0), np.asarray(axes_m[a], dtype=np.float64)


def _with_orbit(obj: SilhouetteObjective, views: ComparedViews, final: list[Finalist], standing: Standing,
                centre_m: NDArray[np.float64], others: list[Hypothesis], opts: RefineOptions,
                progress: Progress | None) -> tuple[list[Finalist], Standing]:
    """When the runner-up is competitive and a 1/n turn from the best, the rest of that turn's
    orbit scored by full-resolution hard IoU, and the best of it, if it beats the best by
    ``opts.disambiguation.margin``, polished and added (see :func:`_disambiguate`)."""
    runner = standing.runner_up
    if not (opts.disambiguation.orbits and runner is not None and runner.stage is Stage.FINAL
            and _competitive(runner.loss, standing.ranked[0].loss, opts)):
        return final, standing
    best = standing.ranked[0]
    cands = orbit(best.T_final, runner.T_final)
    if not len(cands):
        return final, standing
    fine = obj.pyramid.fine(opts.detail)
    ious = np.array([float(np.mean(hard_ious(fine, views, T))) for T in cands])
    if ious.max() <= float(np.mean(hard_ious(fine, views, best.T_final))) + opts.disambiguation.margin:
        return final, standing
    final = _with_candidate(obj, final, best, cands[int(np.argmax(ious))], Stage.ORBIT, opts.schedule[-1], opts,
                            progress)
    return final, _rank(final, others, centre_m, opts)


def _alike_turns(rast: SoftSilhouetteRasterizer, views: ComparedViews, T_wm: NDArray[np.float64], mesh: Mesh,
                 opts: RefineOptions) -> NDArray[np.float64]:
    """Poses (K, 4, 4) that ``T_wm`` turned about an axis it is nearly round about (:attr:`Mesh.round_axes
    <autoalign.geometry.mesh.Mesh.round_axes>`) looks alike at: the smallest turn of :data:`ALIKE_TURNS_DEG`,
    either way, whose hard IoU score at 1/4 resolution comes back within ``near_margin`` of its own after
    a smaller one fell short of it by more (a gear one tooth on), with the rest of that turn's orbit
    (:func:`~autoalign.engine.hypotheses.orbit`). An object round all the way (a can) looks alike at every
    turn and gives none."""
    out = []
    margin = opts.disambiguation.near_margin
    for axis in mesh.round_axes:
        own, scores, cands = turn_scores(rast, views, T_wm, [axis], mesh.centre, tuple(ALIKE_TURNS_DEG))
        n = len(ALIKE_TURNS_DEG) // 2
        for k in np.argsort(np.abs(ALIKE_TURNS_DEG), kind="stable"):
            way = slice(0, n) if ALIKE_TURNS_DEG[k] > 0 else slice(n, 2 * n)
            on_the_way = scores[way][: k % n]
            if scores[k] > own - margin and len(on_the_way) and on_the_way.min() < own - margin:
                out += [cands[k][None], orbit(T_wm, cands[k])]
                break
    return np.concatenate(out) if out else np.zeros((0, 4, 4))


def _with_alike_turn(obj: SilhouetteObjective, views: ComparedViews, final: list[Finalist], standing: Standing,
                     mesh: Mesh, others: list[Hypothesis], opts: RefineOptions, progress: Progress | None
                     ) -> tuple[list[Finalist], Standing]:
    """The best's turns that look alike (:func:`_alike_turns`) scored by hard IoU at
    :data:`ALIKE_SCORE_SCALE`, and the best of them, if it beats the best by
    ``opts.disambiguation.margin``, polished and added: descent from a seed half a tooth off can end a
    tooth off, and the turn that shows a gear's key is not among the small ones tried
    (:class:`~autoalign.engine.options.DisambiguationOptions`)."""
    if not opts.disambiguation.orbits or not len(mesh.round_axes):
        return final, standing
    best = standing.ranked[0]
    cands = _alike_turns(obj.pyramid.with_faces(opts.detail.coarse), views, best.T_final, mesh, opts)
    if not len(cands):
        return final, standing
    scores, _ = score_poses(obj.pyramid.at(ALIKE_SCORE_SCALE, opts.detail), views,
                            np.concatenate([best.T_final[None], cands]), scale=ALIKE_SCORE_SCALE,
                            max_views=len(views), trim=0.0, recentre=False)
    k = int(np.argmax(scores[1:]))
    if scores[1 + k] <= scores[0] + opts.disambiguation.margin:
        return final, standing
    final = _with_candidate(obj, final, best, cands[k], Stage.ORBIT, opts.schedule[-1], opts, progress)
    return final, _rank(final, others, mesh.centre, opts)


def _disambiguate(obj: SilhouetteObjective, views: ComparedViews, mesh: Mesh, final: list[Finalist],
                  others: list[Hypothesis], given_pose: bool, opts: RefineOptions, progress: Progress | None,
                  pose_only: bool = False, preview: PosePreview | None = None
                  ) -> tuple[list[Finalist], Standing, Evaluation, Uncertainty | None, TurnTests]:
    """Stage 4: poses the polish cannot tell apart from the best by descent.

    * **Orbits.** When the runner-up is competitive and a 1/n turn away, the rest of that turn's
      orbit is scored by full-resolution hard IoU (a gear whose key only shows at full
      resolution) and a clearly better one is polished.
    * **Near turns.** The best's small turns about the mesh's principal axes are scored at 1/4
      resolution and a clearly better one is polished: a local minimum a few tens of degrees from
      the right one (a plain gear half a tooth off) that descent cannot leave. So is the best turn
      the other way about the same axis, if also clearly better, and the orbits are tried again on
      the two (a keyed gear's key, on one side, barely shows at 1/4 resolution).
    * **Weak turns.** From a given pose, the best's turns about its weakly observed axes are
      scored at 1/4 resolution and a clearly better one is polished; how much worse the best
      turn fits is returned (``turn_gap``; ``None`` when none were tried).
    * **Turn rise.** How much the whole objective (depth included where measured) rises when the
      result is turned 10-20 degrees about the axes it is nearly round about (:attr:`Mesh.round_axes
      <autoalign.geometry.mesh.Mesh.round_axes>`; :func:`_turn_rise`; ``turn_rise``): a
      measurement for the verdict only, nothing is refined from it (refined, it took a scene whose
      cameras were 10% off in scale, so its depth disagreed, to a turn the masks did not support).

    Returns the finalists, their standing, the full-resolution evaluation and the uncertainty of
    the best (``None`` for ``pose_only`` without a given pose: then nothing reads it), and its turn tests.
    The best pose goes to ``preview`` before its uncertainty is worked out.
    """
    levels = opts.schedule
    final, standing = _with_orbit(obj, views, final, _rank(final, others, mesh.centre, opts), mesh.centre, others,
                                  opts, progress)
    if opts.disambiguation.near_turns:
        before = len(final)
        final, _ = _with_best_turn(obj, views, final, standing.ranked[0], list(mesh.principal_axes),
                                   opts.disambiguation.near_turns, opts.disambiguation.near_margin, Stage.NEAR_TURN,
                                   opts, progress, both_ways=True)
        standing = _rank(final, others, mesh.centre, opts)
        if len(final) > before:  # the near turns' minima may be a 1/n turn apart (a keyed gear's teeth)
            final, standing = _with_orbit(obj, views, final, standing, mesh.centre, others, opts, progress)
    final, standing = _with_alike_turn(obj, views, final, standing, mesh, others, opts, progress)
    best = final[0]
    if preview is not None:  # the pose first, its uncertainty (a sizeable part of the time) when ready
        preview(best.hypothesis.T_final.copy())
    ev, uncertainty = _final_state(obj, best.hypothesis, best.weights, levels, opts.optimizer,
                                   with_uncertainty=given_pose or not pose_only)
    turn_gap = None
    weak = [] if uncertainty is None else uncertainty.weak_turns_not_free(obj.pyramid.symmetries.axes)
    if given_pose and opts.disambiguation.weak_turns and weak:
        final, turn_gap = _with_best_turn(obj, views, final, best.hypothesis, weak,
                                          opts.disambiguation.weak_turns, opts.disambiguation.margin, Stage.WEAK_TURN,
                                          opts, progress)
        if turn_gap < -opts.disambiguation.margin:
            standing = _rank(final, others, mesh.centre, opts)
            if final[0] is not best:
                ev, uncertainty = _final_state(obj, final[0].hypothesis, final[0].weights, levels, opts.optimizer)
    # obj.depth is the sensor's noise model (set by default, measured depth or not; None with --depth off)
    if obj.depth is None or not opts.disambiguation.near_turns or not len(mesh.round_axes):
        return final, standing, ev, uncertainty, TurnTests(turn_gap)
    rise = _turn_rise(obj, final[0].hypothesis.T_final, mesh.round_axes, opts.disambiguation.near_turns, levels[-1])
    return final, standing, ev, uncertainty, TurnTests(turn_gap, *rise)


def _seed_region(obj: SilhouetteObjective, anchor: NDArray[np.float64], opts: RefineOptions) -> SeedRegion:
    """The region of poses within ``opts.seed_radius`` of the given pose ``anchor``, as a term on the pose."""
    return SeedRegion(anchor, obj.centre_m, opts.seed_radius, STIFFNESS * len(obj.compared), obj.pyramid.symmetries)


def _contact(obj: SilhouetteObjective, plane: TablePlane) -> RestingContact:
    """The object resting on ``plane`` on one of its stable faces, as a term on the pose."""
    mesh = obj.pyramid.mesh
    return RestingContact(plane, mesh.hull, obj.centre_m, CONTACT_STIFFNESS * len(obj.compared), mesh.resting_downs)


def _held_near_seed(obj: SilhouetteObjective, anchor: NDArray[np.float64], best: Finalist, ev: Evaluation,
                    opts: RefineOptions, progress: Progress | None
                    ) -> tuple[Finalist, Evaluation, Uncertainty | None, SeedHold | None]:
    """Stage 4b, a seed is evidence: when ``best`` ended beyond ``opts.seed_radius`` of the given
    pose ``anchor``, the best pose within it (the schedule from ``anchor`` with the region's
    penalty, :mod:`autoalign.engine.seed_region`; with depth, also from where the other terms alone
    lead), returned instead unless ``best`` fits clearly better (its full-resolution evaluation
    ``ev``). The move is measured modulo the model's symmetries (``obj.pyramid.symmetries``): a
    free turn about an axis of continuous symmetry is no move. Returns the finalist kept, its
    evaluation, its uncertainty (``None``: unchanged) and the hold (``None``: within the radius)."""
    h = best.hypothesis
    syms = obj.pyramid.symmetries
    move = symmetric_pose_change(anchor, h.T_final, obj.centre_m, syms.discrete, syms.continuous)
    if opts.seed_radius is None or (move[0] <= opts.seed_radius[0] and move[1] <= opts.seed_radius[1]):
        return best, ev, None, None
    held = obj.with_pose_term(_seed_region(obj, anchor, opts))
    full = Level(1.0, opts.schedule[-1].sigma, 0)
    candidates = []
    # the whole schedule, which the far pose's pull may take to the region's edge, and the last level alone
    for levels in (opts.schedule, opts.schedule[-1:]):
        T, traces = run_schedule(held, anchor, levels, opts.optimizer, progress, "within the seed's radius")
        candidates.append((T, traces, levels))
    no_depth = held.without_depth()
    if no_depth is not None:  # depth's pull (a metal highlight, a thin part's few samples) can lead a descent
        # astray from the seed: also from where the masks and photos alone lead, polished with the depth
        T, _ = run_schedule(no_depth, anchor, opts.schedule, opts.optimizer, progress, "within the seed's radius")
        T, traces = run_schedule(held, T, opts.schedule[-1:], opts.optimizer, progress, "within the seed's radius")
        candidates.append((T, traces, opts.schedule[-1:]))
    evs = [obj.evaluate(T, full) for T, _, _ in candidates]
    k = int(np.argmin([e.value for e in evs]))
    (T_near, traces, levels), ev_near = candidates[k], evs[k]
    near_loss, far_loss = ev_near.value / len(ev_near.weights), ev.value / len(ev.weights)
    hold = SeedHold(h.T_final, move, far_loss, near_loss, far_loss <= CLEARLY_BETTER * near_loss)
    if hold.kept_far:
        return best, ev, None, hold
    near = Hypothesis(anchor, T_near, near_loss, float(np.mean(ev_near.terms.iou)), Stage.FINAL,
                      tuple(zip(levels, traces)))
    uncertainty = final_uncertainty(obj, ev_near, T_near, opts.schedule[-1], opts.optimizer)
    return Finalist(near, ev_near.weights), ev_near, uncertainty, hold


def _held_on(obj: SilhouetteObjective, term: RestingContact, starts: list[NDArray[np.float64]], opts: RefineOptions,
             progress: Progress | None) -> tuple[NDArray[np.float64], list[Trace], Evaluation]:
    """The best of ``starts`` polished through the schedule with the contact ``term`` held (by the
    held value: the other evidence's at full resolution plus the contact's): its pose, its traces
    and its full-resolution evaluation without the contact (one render)."""
    held = obj.with_pose_term(term)
    full = Level(1.0, opts.schedule[-1].sigma, 0)
    runs = [run_schedule(held, T, opts.schedule, opts.optimizer, progress, "resting on the table") for T in starts]
    evs = [obj.evaluate(T, full) for T, _ in runs]
    k = int(np.argmin([e.value + term.term(T).value for e, (T, _) in zip(evs, runs)]))
    return runs[k][0], runs[k][1], evs[k]


def _resting(obj: SilhouetteObjective, best: Finalist, ev: Evaluation, plane: TablePlane, declared: bool,
             may_turn: bool, opts: RefineOptions, progress: Progress | None
             ) -> tuple[Finalist, Evaluation, Contact] | None:
    """Stage 4c, a resting contact (:mod:`autoalign.losses.contact`), ``declared`` or offered (then only
    when ``best``'s lowest point lies within :data:`~autoalign.losses.contact.OFFERED_GAP_MM` of the
    plane and it leans within :data:`~autoalign.losses.contact.CONTACT_MAX_LEAN_DEG` of a stable face;
    ``None`` otherwise, nothing run): ``best`` polished
    again through the schedule with its lowest point held to ``plane``, from its own
    pose and from its start (the start's orientation may be the nearer one: masks seen from one side
    turn a pose they also slide along the rays), the better held fit, and what the contact did. It
    is kept unless the masks fit that pose clearly worse (median IoU at full resolution lower by
    more than :data:`~autoalign.losses.contact.CONTACT_IOU_DROP` than ``ev``'s) or ``best`` leans
    beyond any stable face (:attr:`~autoalign.losses.contact.Contact.kept`): then the object stands
    on something else, and ``best`` stays.

    Where the orientation was searched (``may_turn``: no pose given), the poses standing it on its
    stable faces (:mod:`autoalign.engine.stand_up`: an upside-down glass) compete too, the best yaw of
    each of the two best faces polished on the plane. Offered, and sunk deeper than that below the plane, ``best`` contradicts
    the depth: there only the standings are tried, and the better kept unless the masks fit it clearly
    worse; from a given pose the contradiction is recorded and nothing run
    (:attr:`~autoalign.losses.contact.Contact.in_table`), unless the masks are withheld
    (``opts.masks_withheld``: the photos alone place it, and clear glass leaves a seed's tilt, sunk in
    the table): then ``best`` and its start are each stood on their nearest stable face
    (:func:`~autoalign.engine.stand_up.nearest_standing`) and polished on the plane, on the same rule."""
    h = best.hypothesis
    term = _contact(obj, plane)
    gap, tilt = term.gap_mm(h.T_final), term.tilt_deg(h.T_final)
    iou = float(np.median(ev.terms.iou))
    sunk = not declared and gap < -OFFERED_GAP_MM
    nearest = sunk and not may_turn and opts.masks_withheld
    if sunk:  # in the table its depth shows: stood on its faces where the orientation is the search's,
        # from a given pose without masks on the face nearest its own orientation and its start's
        if may_turn:
            starts = list(best_standings(obj.pyramid.with_faces(opts.detail.coarse), obj.compared, h.T_final, term))
        elif nearest:
            starts = [T for T in (nearest_standing(h.T_final, term), nearest_standing(h.T_init, term)) if T is not None]
        else:
            starts = []
        if not starts:
            return best, ev, Contact(plane, gap, gap, tilt, tilt, iou, iou, declared)
    elif not declared and not (gap <= OFFERED_GAP_MM and tilt <= CONTACT_MAX_LEAN_DEG):
        return None  # the evidence does not put it on the table
    else:  # where the search chose the orientation, its other standings compete on the plane too: masks
        # that cannot tell a glass's base from its rim leave the search's pick upside down as often as not
        starts = [h.T_final, h.T_init] + (list(best_standings(obj.pyramid.with_faces(opts.detail.coarse), obj.compared,
                                                              h.T_final, term)) if may_turn else [])
    T_on, traces, ev_on = _held_on(obj, term, starts, opts, progress)
    syms = obj.pyramid.symmetries
    turned = symmetric_pose_change(h.T_final, T_on, obj.centre_m, syms.discrete, syms.continuous)[1]
    turned = turned if sunk or (may_turn and turned > CONTACT_MAX_LEAN_DEG) else None
    contact = Contact(plane, gap, term.gap_mm(T_on), tilt, term.tilt_deg(T_on), iou, float(np.median(ev_on.terms.iou)),
                      declared, turned, nearest=nearest)
    on = Hypothesis(h.T_init, T_on, ev_on.value / len(ev_on.weights), float(np.mean(ev_on.terms.iou)), Stage.FINAL,
                    tuple(zip(opts.schedule, traces)))
    return Finalist(on, ev_on.weights), ev_on, contact


POSE_FIX = "give a 4x4 world-from-model pose: a rotation (det +1, no scale) and a translation in mm, last row 0 0 0 1"
SEED_FIX = POSE_FIX.replace("give a 4x4", "give None (search from the masks), an autoalign.Click, or a 4x4")


def checked_pose(T: Any, name: str, fix: str = POSE_FIX) -> NDArray[np.float64]:
    """``T`` as a 4x4 rigid pose (a rotation a few decimals off re-orthonormalised); an error naming
    ``name`` and ending with ``fix`` otherwise."""
    try:
        A = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise AutoalignError(f"{name}={str(T)[:40]!r} is not a pose; {fix}") from None
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        raise AutoalignError(f"{name}: an array of shape {A.shape} is not a finite 4x4 pose; {fix}")
    R = A[:3, :3]
    if (np.abs(A[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3
            or np.linalg.det(R) < 0):
        raise AutoalignError(f"{name}: its upper 3x3 is not a rotation (det {np.linalg.det(R):.3g}; a scaled or "
                             f"mirrored pose?) or its last row is not 0 0 0 1; {fix}")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-9:  # a pose as files store it, a few decimals off
        U, _, Vt = np.linalg.svd(R)
        A[:3, :3] = U @ Vt
    return A


def checked_seed(seed: Any) -> Seed:
    """``seed`` as :func:`refine` takes it: ``None``, a :class:`Click`, or a 4x4 pose (:func:`checked_pose`)."""
    return seed if seed is None or isinstance(seed, Click) else checked_pose(seed, "seed", SEED_FIX)


def checked_inputs(scene: Any, mesh: Any, seed: Any, anchor: Any) -> tuple[Seed, NDArray[np.float64] | None]:
    """:func:`refine`'s ``seed`` and ``anchor`` as it takes them (:func:`checked_seed`); an error, saying
    how to make them, unless ``scene`` is a :class:`Scene` and ``mesh`` a mesh or its pyramid."""
    if not isinstance(scene, Scene):
        raise AutoalignError(f"scene: a {type(scene).__name__} is not a Scene; read the folder with "
                             "autoalign.read_scene(folder) (or autoalign.read_evidence) and pass that")
    if not isinstance(mesh, (Mesh, MeshPyramid)):
        raise AutoalignError(f"mesh: a {type(mesh).__name__} is not a Mesh; load it with autoalign.load_mesh(path)")
    return checked_seed(seed), None if anchor is None else checked_pose(anchor, "anchor")


def refine(scene: Scene, mesh: Mesh | MeshPyramid, seed: Seed = None, options: RefineOptions | None = None,
           progress: Progress | None = None, anchor: NDArray[np.float64] | None = None,
           preview: PosePreview | None = None) -> RefineResult:
    """Find the world-from-model pose of ``mesh`` whose silhouettes match the masks of ``scene``.

    The stages: seed (:func:`_seed`) -> search (:func:`_search`, when there are several starts)
    -> polish (:func:`_polish`) -> disambiguate (:func:`_disambiguate`) -> report.

    Args:
        scene: calibrated views with target masks (mm, BOP world frame). Views whose mask is
            empty are left out (:meth:`Scene.without_empty_masks`; ``RefineResult.image_ids`` lists the used ones).
            With its photos (:attr:`Scene.photos`) they are evidence too, and the masks may be empty
            (:mod:`autoalign.engine.photo_evidence`; a seed pose is needed then). Its measured depth
            is evidence too, unless it sees through the object (glass: :mod:`autoalign.engine.see_through`).
        mesh: the object model (mm), or its :class:`~autoalign.rasterizers.pyramid.MeshPyramid` (e.g.
            :meth:`ModelSet.pyramid <autoalign.io.models.ModelSet.pyramid>`) to share its rasterizers with other calls
            and give the model's symmetries (the seed's hold measures moves modulo them).
        seed: a coarse world-from-model pose (4x4), a :class:`Click`, or ``None`` (visual hull).
            Without a pose the orientation is searched with ``options.n_rotations`` hypotheses.
        options: see :class:`RefineOptions`.
        progress: called as ``progress(stage, done, total)`` while it works.
        anchor: the pose ``options.seed_radius`` is measured from (default: a seed pose).
        preview: called with the poses to show before the result is ready (:data:`PosePreview`):
            the best-scoring orientation of the search's grid at the seed's centre when a search
            starts (a click or no seed), before any descent; then each refinement's pose before its
            uncertainty is worked out (with photos, the masks' pose and then the photos'). Depth that
            sees through the object, set aside, runs them again. The result is unchanged by it.
    """
    seed, anchor = checked_inputs(scene, mesh, seed, anchor)
    opts = options or RefineOptions()
    pyramid = mesh if isinstance(mesh, MeshPyramid) else MeshPyramid(mesh)
    if scene.depths is not None and opts.depth is not None:
        return _refine_minding_see_through(scene, pyramid, seed, opts, progress, anchor, preview)
    return _refine_evidence(scene, pyramid, seed, opts, progress, anchor, preview)


def _refine_minding_see_through(scene: Scene, pyramid: MeshPyramid, seed: Seed, opts: RefineOptions,
                                progress: Progress | None, anchor: NDArray[np.float64] | None,
                                preview: PosePreview | None) -> RefineResult:
    """:func:`_refine_evidence` on ``scene``, which has measured depth, minding depth that sees
    through the object (the rules of :mod:`autoalign.engine.see_through`)."""

    def without_depth(told: Progress | None) -> tuple[RefineResult, SeeThrough]:
        """The run without the depth, the table it shows offered, and what the depth says at its pose."""
        alt = _refine_evidence(replace(scene, depths=None), pyramid, seed, offering_table(scene, opts), told, anchor,
                               preview)
        seen = measured_see_through(ComparedViews.of(scene), pyramid, alt.T_wm, opts, declared=pyramid.transparent)
        return replace(alt, measured=(seen,) + alt.measured), seen

    if pyramid.transparent:
        return without_depth(progress)[0]
    if seen_through_at_seed(scene, pyramid, seed, opts):
        # without the depth first, with it only if that result is not seen through: one run for glass
        alt, seen = without_depth(progress)
        return alt if seen.sees_through() else \
            _refine_evidence(scene, pyramid, seed, opts, progress, anchor, preview).with_cost_of(alt)
    result = _refine_evidence(scene, pyramid, seed, opts, progress, anchor, preview)
    if pyramid.material == "opaque" or not in_doubt(result):
        return result

    def told(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(f"without the depth: {stage}", done, total)

    alt, seen = without_depth(told)
    return alt.with_cost_of(result) if seen.sees_through() else result


def _refine_evidence(scene: Scene, pyramid: MeshPyramid, seed: Seed, opts: RefineOptions,
                     progress: Progress | None = None, anchor: NDArray[np.float64] | None = None,
                     preview: PosePreview | None = None, pose_only: bool = False,
                     region: RegionTerm | None = None) -> RefineResult:
    """:func:`refine` on its evidence as given: with the photos (:func:`_refine_with_photos`), else
    the masks (and the depth) alone, or the ``region`` term learned on the scene's views in the mask
    term's place. ``pose_only``: the caller reads only ``T_wm`` (the photos' start from the masks), so
    without a given pose the uncertainty, which would change nothing of it, is not computed."""
    if region is None and scene.photos is not None and opts.region is not None:
        return _refine_with_photos(scene, pyramid, seed, opts, progress, anchor, preview)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    obj = compared_objective(pyramid, scene, opts, region)
    views = obj.compared  # those whose target shows the object
    if len(views) == 0:
        raise AutoalignError("every mask of the scene is empty; there is nothing to align the object with")
    timings["setup"] = time.perf_counter() - t_start
    t0 = time.perf_counter()
    given_pose = seed is not None and not isinstance(seed, Click)
    mesh = pyramid.mesh
    levels = opts.schedule
    starts = _seed(views, pyramid, seed, opts, progress, preview)
    timings["seed"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if len(starts) > 1:
        finalists, others = _search(obj, starts, mesh, opts, progress)
        rest = levels[1:] or levels  # a one-level schedule polishes the search's result at that level
    else:
        finalists, others = [Hypothesis(starts[0], starts[0], float("nan"), float("nan"), Stage.START)], []
        rest = levels
    timings["hypotheses"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    final, dropped = _polish(obj, finalists, rest, opts, progress)
    final, standing, final_ev, uncertainty, turn = _disambiguate(obj, views, mesh, final, others + dropped,
                                                                 given_pose, opts, progress, pose_only, preview)
    timings["refine"] = time.perf_counter() - t0
    hold, holds = None, []
    if given_pose or anchor is not None:
        t0 = time.perf_counter()
        given = np.asarray(seed if anchor is None else anchor)
        kept, final_ev, held_unc, hold = _held_near_seed(obj, given, final[0], final_ev, opts, progress)
        if held_unc is not None:  # the pose within the radius: the far pose's turn gap says nothing of it
            final, uncertainty, turn = [kept] + final, held_unc, TurnTests()
        if hold is not None and not hold.kept_far:
            holds.append(_seed_region(obj, given, opts))
        timings["seed"] += time.perf_counter() - t0
    contact = None
    plane = opts.resting if opts.resting is not None else opts.table_offered
    if plane is not None:
        t0 = time.perf_counter()
        rested_as = _resting(obj, final[0], final_ev, plane, opts.resting is not None,
                             not given_pose and anchor is None, opts, progress)
        if rested_as is not None:
            rested, rested_ev, contact = rested_as
            if contact.kept:
                final, final_ev = [rested] + final, rested_ev
                holds.append(_contact(obj, plane))
                if uncertainty is not None:
                    uncertainty = final_uncertainty(obj, final_ev, rested.hypothesis.T_final, opts.schedule[-1],
                                                    opts.optimizer)
        timings["contact"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    best = final[0].hypothesis
    iou_before = hard_ious(obj.pyramid.fine(opts.detail), views, best.T_init)
    iou_after = _hard_ious_of(final_ev, views)
    timings["report"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    history = [{"scale": lv.scale, "sigma": lv.sigma, "values": tr.values, "poses": tr.iterates, "iterations": tr.iterations,
                "converged": tr.converged, "stop": tr.stop.value} for lv, tr in best.path]
    return RefineResult(
        T_wm=best.T_final, T_init=best.T_init, iou_before=iou_before, iou_after=iou_after,
        iterations=sum(tr.iterations for _, tr in best.path), renders=obj.renders, timings=timings,
        hypotheses=standing.ranked, ambiguous=standing.ambiguous, runner_up=standing.runner_up,
        weights=final[0].weights, history=history, image_ids=list(views.image_ids), uncertainty=uncertainty,
        turn_gap=turn.gap, turn_rise=turn.rise, turn_rise_axis_m=turn.rise_axis_m, terms=final_ev.record(),
        measured=final_ev.measured + ((contact,) if contact else ()),
        seed_hold=hold, holds=tuple(holds))


def _refine_with_photos(scene: Scene, pyramid: MeshPyramid, seed: Seed, opts: RefineOptions, progress: Progress | None,
                        anchor: NDArray[np.float64] | None, preview: PosePreview | None) -> RefineResult:
    """:func:`refine` with the photos of ``scene`` as evidence: the rounds of
    :mod:`autoalign.engine.photo_evidence`, then the rest of the schedule, the disambiguation and the
    report with the region term learned at the pose they reached, held near ``anchor`` or else a seed
    pose (not near the rounds' last pose).

    A seed without a pose (a click, or none) is first placed from the masks alone; where they fit that
    pose loosely (median IoU below :data:`~autoalign.losses.overlap.LOOSE_FIT_IOU`) and find a clearly
    different pose that fits almost as well (``ambiguous``), the rounds run from it and from its half
    turns (:func:`~autoalign.engine.photo_evidence.best_side`). With no mask either, there is nothing to
    place it from and an error says what to give."""
    region = opts.region
    assert region is not None
    has_mask = scene.has_masks
    # the edge term joins where the region term keeps the photos, which it does without masks
    masks_only = replace(opts, region=None, edges=region.edge_weight, masks_withheld=not has_mask)
    pose_given = seed is not None and not isinstance(seed, Click)
    if not pose_given:
        if not has_mask:
            raise AutoalignError("without masks the photos refine a coarse pose: give --init (a coarse scene_gt.json)")
        placed = _refine_evidence(replace(scene, photos=None), pyramid, seed, masks_only, progress, preview=preview,
                                  pose_only=True)
        T_seed = placed.T_wm  # the path starts there
        # masks that miss much of it and find another pose nearly as good: the photos choose its side
        choose_side = placed.ambiguous and np.median(placed.iou_after) < LOOSE_FIT_IOU
    else:
        T_seed, choose_side = np.asarray(seed, dtype=np.float64), False
    run = (best_side if choose_side else photo_rounds)(scene, pyramid, T_seed, masks_only, region, progress)
    if not pose_given:
        run = replace(run, iterations=run.iterations + placed.iterations, renders=run.renders + placed.renders)
    term = region_term_at(scene, pyramid, run.T_wm, masks_only, region, measure=True)
    if not term.covered():
        raise AutoalignError("the object is in no view at the given pose: check the --init pose and its obj_id")
    # the rounds converged at the first level: the last one goes on from the second (if the schedule has one)
    last = replace(masks_only, schedule=opts.schedule[1:]) if run.rounds and len(opts.schedule) > 1 else masks_only
    held_near = anchor if anchor is not None else T_seed if pose_given else None
    if held_near is None:  # no pose was given: nothing to hold the result near
        last = replace(last, seed_radius=None)
    result = _refine_evidence(scene, pyramid, run.T_wm, last, progress, held_near, preview, region=term)
    return photo_result(result, scene, pyramid, term, T_seed, run, opts.detail)
