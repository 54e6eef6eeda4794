"""The settings of :func:`~autoalign.engine.refine.refine`, grouped by concern (:class:`RefineOptions`).

A module of its own so that the stages that take them (:mod:`autoalign.engine.schedule`,
:mod:`autoalign.engine.photo_evidence`) need not import the engine that strings them together.
"""

from __future__ import annotations

from dataclasses import dataclass

from autoalign.engine.objective import Level
from autoalign.engine.seed_region import SEED_RADIUS
from autoalign.engine.solver import FTOL, STEP_RULES, StepRule
from autoalign.losses.contact import TablePlane
from autoalign.losses.depth import DepthNoise
from autoalign.losses.region import RegionOptions
from autoalign.rasterizers.pyramid import MeshDetail

DEFAULT_SCHEDULE: tuple[Level, ...] = (Level(0.25, 1.0, 40), Level(1.0, 0.5, 30))

@dataclass(frozen=True)
class SearchOptions:
    """The orientation search, when the seed gives no orientation (a click or the visual hull).

    Attributes:
        n_rotations: orientations of the rotation grid scored at the seed's centre.
        n_starts: best-scoring ones that start the search (16: on masks that miss parts or cover
            another object the 1/8-resolution score ranks orientations coarsely; with 8, the real
            LM-O driller's right basin was reached from none of them, and on synthetic SAM-like
            masks 4 of 30 objects ended wrong, 2 'ok'; with 16, 2, both flagged).
        climb_deg: before that, each climbs to the best of itself and its turns by +- these angles
            (degrees) about the model axes, by hard IoU (:func:`~autoalign.engine.hypotheses.climb_poses`).
        level: the cheap level every start is refined at (its ``ftol`` the full-resolution one: a
            hypothesis still far off descends slowly, 1-2% per step, and with ``ftol / scale`` the
            search lost the true orientation in 5 of 264 simulated trials with eroded or shifted masks).
        n_mid: best distinct ones of those refined at the schedule's first level.
        n_final: best distinct ones of those polished through the rest of the schedule (3: on the
            real LM-O watering can the right basin came third at the first level, behind two half turns).
        abandon: a hypothesis is given up when after two iterations its loss is above this multiple
            of the best loss found in the same stage (replayed on logged searches of the 44
            simulated models, giving up at 3x would not have lost the answer in any; 4x leaves a margin).
        flips: after ``level``, also refine the best hypothesis turned half a turn about each
            principal axis of the mesh (with 8 starts the search settled on such a flip of thin or
            flat objects in 2 of 44 simulated trials; with 16, in none of 88: a safety net).
    """

    n_rotations: int = 384
    n_starts: int = 16
    climb_deg: tuple[float, ...] = (10.0, 5.0)
    level: Level = Level(0.125, 1.0, 10, max_views=20, ftol=FTOL)
    n_mid: int = 3
    n_final: int = 3
    abandon: float = 4.0
    flips: bool = True


@dataclass(frozen=True)
class RankingOptions:
    """Which hypotheses go on to the next level, which are polished, and when two are ambiguous.

    Attributes:
        competitive: a distinct hypothesis goes on to the next level only if its loss there is
            within this factor of the best one's.
        polish_margin: at the last level a finalist other than the best is polished only when its
            estimated loss is below the best's by more than this fraction (see :func:`~autoalign.engine.refine._polish`);
            ``-inf`` polishes every one.
        ambiguity_tol: a runner-up within this relative loss of the winner (and at another pose)
            means ambiguous; so does one within ``competitive`` whose mean IoU is higher.
    """

    competitive: float = 1.5
    polish_margin: float = 0.0
    ambiguity_tol: float = 0.05


@dataclass(frozen=True)
class DisambiguationOptions:
    """Poses the polish cannot tell apart from the best by descent (:func:`~autoalign.engine.refine._disambiguate`).

    Attributes:
        orbits: when the runner-up reached the last level within ``competitive`` of the best (a
            loss estimated from one render there can be off by 10%) and is a 1/n turn (n = 3..12)
            away, try the other poses of that turn's orbit (see :func:`~autoalign.engine.hypotheses.orbit`)
            and polish the one whose full-resolution hard IoU beats the winner's by ``margin``.
        weak_turns: from a given pose, the result turned by these angles (degrees) about each weakly
            observed axis (:mod:`autoalign.engine.uncertainty`) is scored by hard IoU at 1/4
            resolution, and the best turn, if it beats the result by ``margin``, is polished too: a
            nearly symmetric object can settle where its distinguishing detail is out of sight. ``()``: off.
        near_turns: the result turned by these angles (degrees) about each of the mesh's principal
            axes is scored by hard IoU at 1/4 resolution, and the best turn, if it beats the result
            by ``near_margin``, is polished too: descent cannot leave a local minimum one of these turns
            away. On the synthetic calibration scenes (``uncertainty_calibration``) a plain gear ended
            half a tooth (17.5 deg) off with sigmas of 0.15 deg and was ``ok``; its 20 deg turn
            scored 0.85 against its 0.79 (the truth 0.88), while the 14 right poses beside it scored
            their best turn 0.007-0.11 below themselves. 12 renders at 1/4 resolution: about 0.06 s.
            The best turn the other way about the same axis is polished too when it also beats the
            result by ``near_margin`` (half a tooth off, a keyed gear's key is on one side, which 1/4
            resolution cannot see), and ``orbits`` then compares the two at full resolution. ``()``: off.
        near_margin: mean hard IoU by which a near turn must beat the best to be polished: a pipe
            or a rod turned about its axis of symmetry (the same pose) scored up to 0.0007 above
            itself, the half-tooth gear's turn 0.063.
        margin: mean hard IoU by which an orbit pose or a turn must beat the best to be polished.
    """

    orbits: bool = True
    weak_turns: tuple[float, ...] = (30.0, 60.0, 90.0, 120.0, 150.0, 180.0, -150.0, -120.0, -90.0, -60.0, -30.0)
    near_turns: tuple[float, ...] = (10.0, 20.0, -10.0, -20.0)
    margin: float = 0.001
    near_margin: float = 0.01


@dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`~autoalign.engine.refine.refine`, grouped by concern.

    Attributes:
        loss: ``l2`` (default: per-pixel residuals give Gauss-Newton a full-rank model and it
            converged in 3-4x fewer iterations than ``iou``/``dice``; see the results), ``bce``, ``iou``, ``dice``.
        optimizer: the step rule (:class:`~autoalign.engine.solver.StepRule`):
            :class:`~autoalign.engine.solver.LevenbergMarquardt` (default),
            :class:`~autoalign.engine.solver.GaussNewton` or :class:`~autoalign.engine.solver.Adam`
            (:data:`~autoalign.engine.solver.STEP_RULES` by their ``--optimizer`` names).
        robust: Cauchy re-weighting of views by their misfit.
        schedule: coarse-to-fine levels (scale, sigma in px, iterations) a pose is polished through.
        search: the orientation search (:class:`SearchOptions`).
        ranking: which hypotheses go on (:class:`RankingOptions`).
        disambiguation: orbits and weak turns (:class:`DisambiguationOptions`).
        detail: how many triangles the mesh is drawn with at each resolution
            (:class:`~autoalign.rasterizers.pyramid.MeshDetail`).
        depth: the depth sensor's noise model; the depth term (:mod:`autoalign.losses.depth`) joins
            the mask term in every view when the scene has measured depth
            (:func:`~autoalign.io.bop.with_depth`); ``None``: masks only.
        region: the region (colour) term (:mod:`autoalign.losses.region`), used when the scene
            carries its photos (:func:`~autoalign.io.photos.with_photos`); ``None``: photos ignored.
        seed_radius: the stated uncertainty of a given seed pose (mm at the model's centre,
            degrees): a result farther from it is returned only when it fits clearly better than the
            best pose within it (:mod:`autoalign.engine.seed_region`); ``None``: the seed is only a start.
        resting: the table plane the object is declared to rest on (:mod:`autoalign.losses.contact`):
            the result is polished again with its lowest point held to the plane, unless the masks
            then fit clearly worse (it stands on something else); ``None``: no contact declared.
        offer_table: without ``resting``, an object whose measured depth is seen through (glass:
            :mod:`autoalign.engine.see_through`) is offered the table plane that depth shows: it rests
            on it when the other evidence puts it there (:data:`~autoalign.losses.contact.OFFERED_GAP_MM`).
        table_offered: the plane offered (set by :mod:`autoalign.engine.see_through` for the runs
            without the depth; ``None``: none).
        edges: the weight of the photo's edges under the outline (:mod:`autoalign.losses.edge`), set by
            the photo rounds (``RegionOptions.edge_weight``); the term joins where the scene carries its
            photos, as the photo rounds' targets do only where the masks are withheld; ``None``: not used.
        masks_withheld: set by the photo rounds when the scene has no masks (the photos alone place the
            object): a given pose sunk in the offered table is then stood on its nearest stable face
            (:func:`~autoalign.engine.refine._resting`), as nothing but the colour regions hold it there.
    """

    loss: str = "l2"
    optimizer: StepRule = STEP_RULES["lm"]
    robust: bool = True
    schedule: tuple[Level, ...] = DEFAULT_SCHEDULE
    search: SearchOptions = SearchOptions()
    ranking: RankingOptions = RankingOptions()
    disambiguation: DisambiguationOptions = DisambiguationOptions()
    detail: MeshDetail = MeshDetail()
    depth: DepthNoise | None = DepthNoise()
    region: RegionOptions | None = RegionOptions()
    seed_radius: tuple[float, float] | None = SEED_RADIUS
    resting: TablePlane | None = None
    offer_table: bool = True
    table_offered: TablePlane | None = None
    edges: float | None = None
    masks_withheld: bool = False
