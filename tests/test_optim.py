"""Levenberg-Marquardt's stopping rules at full resolution (step size and predicted decrease)."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.objective import Level, SilhouetteObjective
from autoalign.engine.solver import FTOL, STEP_RULES, LevenbergMarquardt, Stop, solve_pose
from autoalign.experiments.scenes.synthetic import make_scene
from autoalign.experiments.studies.protocol import ImageSetup, make_trial
from autoalign.experiments.studies.runner import get_model
from autoalign.geometry.se3 import apply_twist, rotation_angle_deg, transform_points
from autoalign.rasterizers.pyramid import AS_GIVEN, MeshPyramid


def _max_reprojection_px(T: np.ndarray, T_gt: np.ndarray, vertices_m: np.ndarray, scene) -> float:
    """Largest image distance (px) between a model vertex under ``T`` and under ``T_gt``, over all views."""
    a, b = transform_points(T, vertices_m), transform_points(T_gt, vertices_m)
    return max(float(np.linalg.norm(c.project(a) - c.project(b), axis=1).max()) for c in scene.cameras)


@pytest.mark.slow
def test_lm_stops_at_the_noise_floor_without_extra_renders() -> None:
    """At the true pose a step predicted to gain less than ``ftol`` of the objective is not tried:
    one render (the start's), no iteration.

    Without that rule (``ftol=0``) LM keeps rendering rejected sub-micrometre steps until the
    damping has shrunk them below the step tolerance; the pose does not get better for it.
    """
    entry = get_model("procedural44", 3)  # the mug, large in the image: full-resolution renders are costly
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, 3, 0, 40, 100.0, ImageSetup())
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    level = Level(1.0, 0.5, 15)
    renders, poses, stops = [], [], []
    for ftol in (1e-3, 0.0):
        obj = SilhouetteObjective(MeshPyramid(entry.mesh), scene, detail=AS_GIVEN)
        T, trace = solve_pose(obj, geo.T_gt, level, LevenbergMarquardt(ftol))
        assert trace.converged
        stops.append(trace.stop)
        renders.append((obj.renders, trace.iterations))
        poses.append(T)
    assert renders[0] == (1, 0), renders
    assert renders[1][0] >= 4, renders
    assert stops == [Stop.FTOL, Stop.SMALL_STEP], stops
    for T in poses:
        assert np.linalg.norm(T[:3, 3] - geo.T_gt[:3, 3]) < 0.01
        assert rotation_angle_deg(T[:3, :3], geo.T_gt[:3, :3]) < 0.01


@pytest.mark.slow
def test_lm_stops_after_an_accepted_step_that_gains_too_little() -> None:
    """At full resolution after the quarter-resolution level (as the engine runs them), LM stops once
    the next step is predicted to gain less than ``ftol`` of the objective: fewer accepted steps and
    fewer renders than going on until the steps are below the step tolerance (``ftol=0``), and a
    pose as good in the images: no model vertex within 1/20 px of where the true pose puts it.
    (In degrees the early stop leaves more: 0.021 here against 0.012, about a rotation the
    silhouettes barely see; the quarter-resolution start is 0.11 px off.)"""
    entry = get_model("procedural44", 11)
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, 11, 0, 40, 100.0, ImageSetup())
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    start = apply_twist(geo.T_gt, np.array([2.0, -2.0, 1.0, *np.radians([1.0, 1.5, -0.5])]),
                        transform_points(geo.T_gt, entry.mesh.centre[None])[0])
    obj = SilhouetteObjective(MeshPyramid(entry.mesh), scene, detail=AS_GIVEN)
    T_quarter, _ = solve_pose(obj, start, Level(0.25, 1.0, 40), LevenbergMarquardt(FTOL))
    runs = []
    for ftol in (1e-3, 0.0):
        before = obj.renders
        T, trace = solve_pose(obj, T_quarter, Level(1.0, 0.5, 15), LevenbergMarquardt(ftol))
        assert trace.converged
        runs.append((obj.renders - before, T, len(trace.values)))
    (r_on, T_on, n_on), (r_off, T_off, n_off) = runs
    assert n_on < n_off and r_on < r_off, runs
    for T in (T_on, T_off):
        assert _max_reprojection_px(T, geo.T_gt, entry.mesh.vertices, scene) < 0.05


def _mug_objective(twist: np.ndarray) -> tuple[SilhouetteObjective, np.ndarray]:
    """The mug in 12 views, its objective (the mesh as given at every level) and a start the
    twist ``(v mm, w rad)`` away from the truth, about the mesh centre."""
    entry = get_model("procedural44", 3)
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, 3, 0, 12, 100.0, ImageSetup())
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    start = apply_twist(geo.T_gt, twist, transform_points(geo.T_gt, entry.mesh.centre[None])[0])
    return SilhouetteObjective(MeshPyramid(entry.mesh), scene, detail=AS_GIVEN), start


def test_stops_are_named_budget_and_caller() -> None:
    """A far start with a one-iteration budget stops on the budget; a callback that says stop is
    named as the reason; neither counts as converged."""
    obj, start = _mug_objective(np.array([6.0, -4.0, 3.0, *np.radians([4.0, -3.0, 5.0])]))
    _, budget = solve_pose(obj, start, Level(0.25, 1.0, 1), LevenbergMarquardt(FTOL))
    _, caller = solve_pose(obj, start, Level(0.25, 1.0, 10), LevenbergMarquardt(FTOL), callback=lambda it, ev: True)
    assert (budget.stop, caller.stop) == (Stop.BUDGET, Stop.CALLER)
    assert not budget.converged and not caller.converged


def test_every_solver_ends_with_a_reason_and_the_final_evaluation() -> None:
    """LM, GN and Adam run in the one loop: each names why it stopped (a :class:`Stop` with a
    message) and hands back the evaluation at the pose it returns (Adam's included)."""
    obj, start = _mug_objective(np.array([3.0, -2.0, 1.0, *np.radians([2.0, -1.0, 1.0])]))
    level = Level(0.25, 1.0, 3)
    for name, rule in STEP_RULES.items():
        T, trace = solve_pose(obj, start, level, rule)
        assert isinstance(trace.stop, Stop) and trace.stop.message, name
        assert trace.final is not None and trace.start is not None, name
        assert np.isclose(trace.final.value, obj.evaluate(T, level, weights=trace.final.weights).value, rtol=1e-12), name
    assert all(s.message for s in Stop)


class _ToyParts:
    """What the toy problems of two unknowns, one per part, share: the value is the parts' sum."""

    def reweighted(self, point):
        return point

    def value(self, point) -> float:
        return float(point.sum())

    def retract(self, x, step):
        return x + step

    def reject(self, x) -> None:
        pass

    def small(self, step) -> bool:
        return False

    def parts(self, point):
        return [(slice(0, 1), float(point[0])), (slice(1, 2), float(point[1]))]


class _TwoParts(_ToyParts):
    """A toy least-squares problem of two independent unknowns: part 0 fixed at a large loss
    (``big``), part 1 ``sqrt(1 + (x - 3)^2) - 1``, a valley whose Gauss-Newton curvature (1, its
    value at the minimum) is too high far from it, so that each step gains a little (as a kettle's
    turn did in a joint solve). ``whole``: the problem is judged as one part."""

    def __init__(self, big: float, whole: bool) -> None:
        self.big, self.whole = big, whole

    def evaluate(self, x, weights_of=None):
        return np.array([self.big, np.sqrt(1.0 + (x[1] - 3.0) ** 2) - 1.0])

    def normal_equations(self, x, point):
        d = x[1] - 3.0
        return np.diag([1.0, 1.0]), np.array([0.0, d / np.sqrt(1.0 + d * d)])

    def parts(self, point):
        return [(slice(None), float(point.sum()))] if self.whole else super().parts(point)


def test_lm_judges_each_part_against_its_own_loss() -> None:
    """A part still descending stops the solve only once its own predicted gain is below ``ftol``
    of its own loss: judged against the whole (a large loss beside it) it stopped 3 away from its
    minimum, untried."""
    from autoalign.engine.solver import LevenbergMarquardt, minimise

    rule = LevenbergMarquardt(1e-3, max_step=None, floor_of_trace=False)
    whole = minimise(_TwoParts(1000.0, True), np.zeros(2), rule, 50)
    assert whole.trace.stop is Stop.FTOL and whole.trace.iterations == 0 and whole.x[1] == 0.0
    parts = minimise(_TwoParts(1000.0, False), np.zeros(2), rule, 50)
    assert parts.trace.stop is Stop.FTOL and abs(parts.x[1] - 3.0) < 0.1, parts.x


class _LinearParts(_ToyParts):
    """A linear least-squares toy ``r = J x - b`` of two unknowns, one per part: part 0's value is
    ``big`` (a loss it cannot shed, like an object's wrong masks), part 1's is ``0.5 |r|^2 + 0.5``
    (0.5 it cannot shed: a loss that reaches 0 never passes a relative test). ``moved`` records
    every step's part 0."""

    def __init__(self, J: np.ndarray, b: np.ndarray, big: float) -> None:
        self.J, self.b, self.big = J, b, big
        self.moved: list[float] = []

    def evaluate(self, x, weights_of=None):
        r = self.J @ x - self.b
        return np.array([self.big, 0.5 * float(r @ r) + 0.5])

    def normal_equations(self, x, point):
        return self.J.T @ self.J, self.J.T @ (self.J @ x - self.b)

    def retract(self, x, step):
        self.moved.append(float(step[0]))
        return x + step


def test_lm_holds_a_converged_part_while_another_moves() -> None:
    """Independent parts: part 0 is 0.001 from its minimum (a predicted gain far below ``ftol``
    of its value), part 1 is 3 away. Part 0 is never moved (in a joint solve: never rendered again)
    and part 1 reaches its minimum."""
    from autoalign.engine.solver import LevenbergMarquardt, minimise

    problem = _LinearParts(np.eye(2), np.array([0.001, 3.0]), big=1.0)
    sol = minimise(problem, np.zeros(2), LevenbergMarquardt(1e-3, max_step=None, floor_of_trace=False), 50)
    assert sol.trace.stop is Stop.FTOL and abs(sol.x[1] - 3.0) < 1e-2, sol.x
    assert problem.moved and all(m == 0.0 for m in problem.moved) and sol.x[0] == 0.0


def test_lm_moves_parts_that_share_a_valley_together() -> None:
    """Coupled parts: the fit needs ``x0 + x1 = 3`` and, weakly, ``x0 = x1``. Part 0's own share
    of the predicted gain is far below ``ftol`` of its large value, yet holding it leaves part 1
    nothing to gain at (0, 2.97): the solve moves both and reaches (1.5, 1.5) instead of spending
    its budget there."""
    from autoalign.engine.solver import LevenbergMarquardt, minimise

    problem = _LinearParts(np.array([[1.0, 1.0], [0.1, -0.1]]), np.array([3.0, 0.0]), big=1e4)
    sol = minimise(problem, np.zeros(2), LevenbergMarquardt(1e-3, max_step=None, floor_of_trace=False), 50)
    assert sol.trace.stop is Stop.FTOL and sol.trace.iterations < 10, sol.trace
    assert np.allclose(sol.x, [1.5, 1.5], atol=0.02), sol.x


class _NoiseFloor(_TwoParts):
    """Part 0 as in :class:`_TwoParts`; part 1's Gauss-Newton model promises a gain (gradient -0.1,
    curvature 1) that its value, ``0.1 + 0.01 |x_1|``, never gives: a loss at the noise floor of
    re-rendering, where every trial comes out worse."""

    def evaluate(self, x, weights_of=None):
        return np.array([self.big, 0.1 + 0.01 * abs(x[1])])

    def normal_equations(self, x, point):
        return np.diag([1.0, 1.0]), np.array([0.0, -0.1])


def test_lm_judges_a_part_whose_trial_failed_against_the_whole() -> None:
    """After a trial that came out worse, the step's predicted gain is judged against the whole
    value: the solve stops after that one trial instead of shrinking the step until the part's
    gain is below ``ftol`` of its own small value (ten more renders of the whole scene)."""
    from autoalign.engine.solver import LevenbergMarquardt, minimise

    sol = minimise(_NoiseFloor(1000.0, False), np.zeros(2), LevenbergMarquardt(1e-3, max_step=None,
                                                                                floor_of_trace=False), 50)
    assert sol.trace.stop is Stop.FTOL and sol.trace.tries == 1 and sol.x[1] == 0.0, sol.trace


def test_a_subset_objective_reuses_the_resampled_views() -> None:
    """``SilhouetteObjective.subset`` (the refits' leave-a-fifth-out objectives): the views at each
    scale already resampled are taken from the whole (nothing resampled again) and equal those a
    new objective on the same views makes, and it evaluates the same loss."""
    import autoalign.engine.objective as objective_module

    entry = get_model("procedural44", 3)
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, 3, 0, 10, 100.0, ImageSetup())
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    whole = SilhouetteObjective(MeshPyramid(entry.mesh), scene, detail=AS_GIVEN)
    whole.at_scale(0.25)
    idx = [0, 2, 3, 7, 9]
    resized = []
    real = objective_module.cv2.resize
    objective_module.cv2.resize = lambda *a, **kw: resized.append(1) or real(*a, **kw)
    try:
        sub = whole.subset(idx)
        got = sub.at_scale(0.25)
    finally:
        objective_module.cv2.resize = real
    assert not resized
    fresh = SilhouetteObjective(MeshPyramid(entry.mesh), scene.subset(idx), detail=AS_GIVEN)
    want = fresh.at_scale(0.25)
    assert all(np.array_equal(a, b) for a, b in zip(got.targets, want.targets)) and len(got.targets) == 5
    assert np.array_equal(got.totals, want.totals)
    assert [c.K.tolist() for c in got.cameras] == [c.K.tolist() for c in want.cameras]
    T = apply_twist(geo.T_gt, np.array([1.0, 0.0, 0.0, 0.0, 0.01, 0.0]),
                    transform_points(geo.T_gt, entry.mesh.centre[None])[0])
    level = Level(0.25, 0.5, 1)
    assert sub.evaluate(T, level).value == fresh.evaluate(T, level).value
