"""One least-squares loop, :func:`minimise`, with the step rules it can take (in the spirit of
optimistix: a solver is a step rule with its own state; the loop, stopping and bookkeeping are shared).

* :class:`LevenbergMarquardt` — damped Gauss-Newton (second order), the default; its damping is its state.
* :class:`GaussNewton` — undamped Gauss-Newton with step halving.
* :class:`Adam` — the first-order reference.

A :class:`Problem` says how to evaluate an iterate, its normal equations and how a step moves it:
:class:`PoseProblem` is one object's twist ``(v [mm], w [rad])`` about its centre at one
:class:`~autoalign.engine.objective.Level` of the coarse-to-fine schedule; the joint multi-object
solve (:mod:`autoalign.scene.joint`) is another. Every solve ends with a :class:`Stop` reason
and the evaluation at the returned iterate (``Trace.final``).

For one object a solve stops when a step moves the object by less than ``tol_mm`` and ``tol_deg``
(Levenberg-Marquardt also, before trying it, when the next step's predicted decrease is below
``ftol`` of the objective).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from typing import Callable, Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Evaluation, Level, SilhouetteObjective
from autoalign.geometry.se3 import apply_twist, transform_points

TOL_MM = 0.01
TOL_DEG = 0.001
FTOL = 1e-3
COARSE_MM = 0.1
COARSE_DEG = 0.05

X = TypeVar("X")  # an iterate (a pose, or every pose and camera of a scene)
P = TypeVar("P")  # the evaluation of an iterate


class Stop(enum.Enum):
    """Why a solve stopped (``Trace.stop``); the value is the short name written in reports."""

    SMALL_STEP = "small step"
    FTOL = "predicted gain below ftol"
    DAMPING_LIMIT = "damping limit"
    NO_DECREASE = "no decrease"
    BUDGET = "iteration budget"
    CALLER = "stopped by caller"

    @property
    def message(self) -> str:
        """One sentence saying what happened."""
        return _MESSAGES[self]

    @property
    def converged(self) -> bool:
        """Nothing worth a step was left (not stopped by the budget or the caller)."""
        return self not in (Stop.BUDGET, Stop.CALLER)


_MESSAGES = {
    Stop.SMALL_STEP: "the last step moved the object by less than the tolerances",
    Stop.FTOL: "the next step was predicted to gain less than ftol of the objective",
    Stop.DAMPING_LIMIT: "Levenberg-Marquardt: no damping up to 1e8 gave a decrease",
    Stop.NO_DECREASE: "Gauss-Newton: twelve halvings of the step gave no decrease",
    Stop.BUDGET: "the iteration budget ran out",
    Stop.CALLER: "the callback asked to stop",
}


class Problem(Protocol[X, P]):
    """What :func:`minimise` needs of a least-squares problem over iterates ``X`` evaluated as ``P``."""

    def evaluate(self, x: X, weights_of: P | None = None) -> P:
        """The objective at ``x``, with the (IRLS) weights of ``weights_of`` if given, else its own."""

    def reweighted(self, point: P) -> P:
        """The same evaluation with weights re-computed from its own fit (no new render)."""

    def value(self, point: P) -> float:
        """The objective's value (what a step must not increase)."""

    def normal_equations(self, x: X, point: P) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The Gauss-Newton matrix ``H`` and the gradient ``g`` at ``x``."""

    def retract(self, x: X, step: NDArray[np.float64]) -> X:
        """``x`` moved by ``step``."""

    def reject(self, x: X) -> None:
        """Undo what evaluating a rejected trial changed; ``x`` is the iterate kept."""

    def small(self, step: NDArray[np.float64]) -> bool:
        """Whether ``step`` is below the tolerances (the solve has converged)."""

    def parts(self, point: P) -> list[tuple[slice, float]]:
        """The unknowns of each part whose convergence is judged on its own (``ftol`` of its own
        value), with that value: the whole problem, or each object of a joint solve."""


@dataclass
class Move(Generic[X, P]):
    """A step taken: the new iterate, its evaluation, the step, and the evaluation the iteration
    reports (the new one, except for Adam: the one its step came from)."""

    x: X
    point: P
    step: NDArray[np.float64]
    reported: P


@dataclass
class Outcome(Generic[X, P]):
    """What a step rule did in one iteration: a :class:`Move` or the :class:`Stop` reason, and how
    many trial iterates it evaluated."""

    tries: int
    move: Move[X, P] | None = None
    stop: Stop | None = None


class StepRule(Protocol):
    """A solver: ``init()`` its state, ``step(...)`` one iteration of it; ``at(level)`` the same rule
    for a problem at a resolution level (its tolerances there); ``name`` as ``--optimizer`` gives it."""

    name: str

    def init(self) -> object: ...

    def at(self, level: Level) -> "StepRule": ...

    def step(self, problem: Problem, x: object, point: object, state: object) -> Outcome: ...


@dataclass
class Trace(Generic[X, P]):
    """What a solve did: objective and iterate per accepted iteration, iterations, why it stopped."""

    values: list[float] = field(default_factory=list)
    iterates: list[X] = field(default_factory=list)
    iterations: int = 0  # iterations that evaluated at least one trial iterate
    tries: int = 0  # trial iterates evaluated
    stop: Stop = Stop.BUDGET
    start: P | None = None  # the objective at the starting iterate
    final: P | None = None  # the objective at the returned iterate

    @property
    def converged(self) -> bool:
        """Stopped because nothing worth a step was left (not by budget or caller)."""
        return self.stop.converged


@dataclass
class Solution(Generic[X, P]):
    """The iterate a solve returned and its :class:`Trace` (stop reason, start and final evaluation)."""

    x: X
    trace: Trace[X, P]

    @property
    def stop(self) -> Stop:
        return self.trace.stop


Callback = Callable[[int, Evaluation], "bool | None"]
"""``callback(iteration, evaluation)`` after each accepted iteration; returning ``True`` stops the
solve there (the trace is then not ``converged``)."""


def minimise(problem: Problem[X, P], x0: X, rule: StepRule, max_iters: int,
             callback: Callable[[int, P], bool | None] | None = None) -> Solution[X, P]:
    """Take ``rule``'s steps on ``problem`` from ``x0`` for at most ``max_iters`` iterations.

    Robust weights are re-computed from each accepted fit (IRLS) without a new render. It stops
    when the rule finds no step worth taking, after a step ``problem.small`` calls converged, when
    ``callback`` returns True, or when the budget runs out.
    """
    point = problem.evaluate(x0)
    trace: Trace[X, P] = Trace(start=point)
    state = rule.init()
    x = x0
    for it in range(max_iters):
        out = rule.step(problem, x, point, state)
        trace.tries += out.tries
        if out.tries:
            trace.iterations = it + 1
        if out.move is None:
            trace.stop = out.stop or Stop.BUDGET
            break
        x, point = out.move.x, out.move.point
        trace.values.append(problem.value(out.move.reported))
        trace.iterates.append(x)
        if callback and callback(it, out.move.reported):
            trace.stop = Stop.CALLER
            break
        if problem.small(out.move.step):
            trace.stop = Stop.SMALL_STEP
            break
    trace.final = point
    return Solution(x, trace)


def clip_step(step: NDArray[np.float64], max_mm: float, max_deg: float) -> NDArray[np.float64]:
    """``step`` (a twist, mm and rad) shortened to at most ``max_mm`` and ``max_deg`` (a trust region for far starts)."""
    step = step.copy()
    n_t = np.linalg.norm(step[:3])
    if n_t > max_mm:
        step[:3] *= max_mm / n_t
    n_r = np.degrees(np.linalg.norm(step[3:]))
    if n_r > max_deg:
        step[3:] *= max_deg / n_r
    return step


@dataclass
class Damping:
    """Levenberg-Marquardt's state: the damping ``lam``, kept from one iteration to the next."""

    lam: float


@dataclass(frozen=True)
class LevenbergMarquardt:
    """Levenberg-Marquardt on the weighted Gauss-Newton system ``(H + lam D) step = -g``, ``D = diag(H)``.

    A rejected step raises ``lam`` by ``growth``, an accepted one lowers it three-fold. Steps are
    clipped to ``max_step`` (mm, degrees; None: not clipped). It stops, without trying it (nothing
    is rendered), at a step whose decrease predicted by the Gauss-Newton model is below ``ftol`` of
    the objective (MINPACK's ``ftol`` test) in every part of the problem (``problem.parts``: in a
    joint solve each object's share of the decrease against its own loss, so that one object's
    slow valley is not judged against the whole scene's loss; after a trial that came out worse,
    the step's gain is judged against the whole value, as a loss at its noise floor gives no
    gain that its model predicts), or that ``problem.small`` calls converged. Until then the
    parts whose predicted gain is below ``ftol`` of their own are held where they are and the
    step solves for the others alone, when holding them loses no more of the predicted decrease
    than ``ftol`` of their values together and of the others' (else they share a valley with the
    others, as an object's distance and the scene's scale do, and all move): an object that has
    converged is not moved (nor, in a joint solve, rendered again) while another one follows its
    valley; it moves again when a later iterate predicts it a gain. ``D``'s entries are at least
    ``floor`` (times ``trace(H)`` if ``floor_of_trace``).
    """

    ftol: float
    lam: float = 1e-3
    growth: float = 4.0
    max_step: tuple[float, float] | None = (30.0, 20.0)
    floor: float = 1e-12
    floor_of_trace: bool = True
    name: str = field(default="lm", init=False)

    def init(self) -> Damping:
        return Damping(self.lam)

    def at(self, level: Level) -> "LevenbergMarquardt":
        """This rule with ``ftol`` at ``level`` (:func:`level_ftol`): below full resolution the loss's
        own noise grows, and so does what a step must gain to be tried."""
        return replace(self, ftol=level_ftol(level, self.ftol))

    def step(self, problem: Problem[X, P], x: X, point: P, state: Damping) -> Outcome[X, P]:
        H, g = problem.normal_equations(x, point)
        value = problem.value(point)
        parts = problem.parts(point)
        floor = self.floor * max(np.trace(H), 1e-30) if self.floor_of_trace else self.floor
        D = np.diag(np.maximum(np.diag(H), floor))
        tries = 0
        while state.lam <= 1e8:
            step = self._damped_step(H, D, g, state.lam, np.arange(len(g)))
            predicted = -(g * step + 0.5 * step * (H @ step))  # per unknown; their sum is the model's decrease
            done = [predicted[part].sum() <= self.ftol * v for part, v in parts]
            if all(done) or (tries and predicted.sum() <= self.ftol * value):
                return Outcome(tries, stop=Stop.FTOL)
            if any(done):
                step = self._with_held(H, D, g, state.lam, step, float(predicted.sum()), parts, done)
            if problem.small(step):
                return Outcome(tries, stop=Stop.SMALL_STEP)
            x_new = problem.retract(x, step)
            trial = problem.evaluate(x_new, point)
            tries += 1
            if problem.value(trial) <= value:
                state.lam = max(state.lam / 3.0, 1e-7)
                new = problem.reweighted(trial)
                return Outcome(tries, Move(x_new, new, step, new))
            problem.reject(x)
            state.lam *= self.growth
        return Outcome(tries, stop=Stop.DAMPING_LIMIT)

    def _with_held(self, H: NDArray[np.float64], D: NDArray[np.float64], g: NDArray[np.float64], lam: float,
                   step: NDArray[np.float64], decrease: float, parts: list[tuple[slice, float]],
                   held: list[bool]) -> NDArray[np.float64]:
        """The step with the ``held`` parts held, if that loses at most ``ftol`` of ``step``'s predicted
        ``decrease``, measured against the held parts' values and against the others'; else ``step``."""
        free = np.ones(len(g), dtype=bool)
        for (part, _), h in zip(parts, held):
            free[part] = not h
        reduced = self._damped_step(H, D, g, lam, np.flatnonzero(free))
        lost = decrease + (g @ reduced + 0.5 * reduced @ (H @ reduced))
        values = [sum(v for (_, v), h in zip(parts, held) if h == side) for side in (True, False)]
        return reduced if lost <= self.ftol * min(values) else step

    def _damped_step(self, H: NDArray[np.float64], D: NDArray[np.float64], g: NDArray[np.float64], lam: float,
                     free: NDArray[np.int_]) -> NDArray[np.float64]:
        """The damped Gauss-Newton step of the unknowns ``free`` with the others held (0), clipped."""
        step = np.zeros_like(g)
        try:
            step[free] = -np.linalg.solve((H + lam * D)[np.ix_(free, free)], g[free])
        except np.linalg.LinAlgError:
            pass
        return step if self.max_step is None else clip_step(step, *self.max_step)


@dataclass(frozen=True)
class GaussNewton:
    """Gauss-Newton steps ``H step = -g`` (least squares, clipped to ``max_step`` mm and degrees; None:
    not clipped) with step halving (up to ``halvings`` times) until the objective does not increase."""

    max_step: tuple[float, float] | None = (30.0, 20.0)
    halvings: int = 12
    name: str = field(default="gn", init=False)

    def init(self) -> None:
        return None

    def at(self, level: Level) -> "GaussNewton":
        return self

    def step(self, problem: Problem[X, P], x: X, point: P, state: None) -> Outcome[X, P]:
        H, g = problem.normal_equations(x, point)
        step = -np.linalg.lstsq(H, g, rcond=1e-10)[0]
        if self.max_step is not None:
            step = clip_step(step, *self.max_step)
        for k in range(self.halvings):
            x_new = problem.retract(x, step)
            trial = problem.evaluate(x_new, point)
            if problem.value(trial) <= problem.value(point):
                new = problem.reweighted(trial)
                return Outcome(k + 1, Move(x_new, new, step, new))
            problem.reject(x)
            step = step / 2.0
        return Outcome(self.halvings, stop=Stop.NO_DECREASE)


@dataclass
class Moments:
    """Adam's state: the first and second moments of the gradient and the steps taken."""

    m: NDArray[np.float64]
    v: NDArray[np.float64]
    taken: int = 0


@dataclass(frozen=True)
class Adam:
    """Adam on the twist with per-block learning rates (mm and degrees per step), decayed geometrically.
    Every step is taken; the iteration reports the evaluation its step came from."""

    lr_mm: float = 1.0
    lr_deg: float = 1.0
    betas: tuple[float, float] = (0.9, 0.999)
    decay: float = 0.97
    name: str = field(default="adam", init=False)

    def init(self) -> Moments:
        return Moments(np.zeros(6), np.zeros(6))

    def at(self, level: Level) -> "Adam":
        return self

    def step(self, problem: Problem[X, P], x: X, point: P, state: Moments) -> Outcome[X, P]:
        g = problem.normal_equations(x, point)[1]
        b1, b2 = self.betas
        it = state.taken
        state.m = b1 * state.m + (1 - b1) * g
        state.v = b2 * state.v + (1 - b2) * g * g
        mh = state.m / (1 - b1 ** (it + 1))
        vh = state.v / (1 - b2 ** (it + 1))
        lr = np.array([self.lr_mm] * 3 + [np.radians(self.lr_deg)] * 3)
        step = -lr * (self.decay ** it) * mh / (np.sqrt(vh) + 1e-12)
        state.taken += 1
        x_new = problem.retract(x, step)
        return Outcome(1, Move(x_new, problem.evaluate(x_new), step, point))


def level_tolerance(level: Level, tol_mm: float, tol_deg: float) -> tuple[float, float]:
    """Stopping tolerances at ``level``: the given ones at full resolution, looser when coarser.

    A coarse level only has to bring the pose within reach of the next one: it stops once a
    step moves the object by less than ``COARSE_MM / scale`` and ``COARSE_DEG / scale``
    (0.4 mm and 0.2 degrees at quarter resolution).
    """
    if level.scale >= 1.0:
        return tol_mm, tol_deg
    return max(tol_mm, COARSE_MM / level.scale), max(tol_deg, COARSE_DEG / level.scale)


def level_ftol(level: Level, ftol: float = FTOL) -> float:
    """``ftol`` at ``level``: ``Level.ftol`` if it sets one, else ``ftol / scale`` below full resolution
    (where the next level goes on)."""
    return level.ftol if level.ftol is not None else ftol / min(level.scale, 1.0)


@dataclass
class PoseProblem:
    """One object's pose (4x4 world from model, mm) at ``level``; steps are twists about its centre."""

    objective: SilhouetteObjective
    level: Level
    tol_mm: float = TOL_MM
    tol_deg: float = TOL_DEG

    def __post_init__(self) -> None:
        self.tol_mm, self.tol_deg = level_tolerance(self.level, self.tol_mm, self.tol_deg)

    def evaluate(self, T: NDArray[np.float64], weights_of: Evaluation | None = None) -> Evaluation:
        return self.objective.evaluate(T, self.level, weights=None if weights_of is None else weights_of.weights)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        return self.objective.reweighted(ev)

    def value(self, ev: Evaluation) -> float:
        return ev.value

    def normal_equations(self, T: NDArray[np.float64], ev: Evaluation) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return ev.gn, ev.grad

    def retract(self, T: NDArray[np.float64], step: NDArray[np.float64]) -> NDArray[np.float64]:
        return apply_twist(T, step, transform_points(T, self.objective.centre_m[None])[0])

    def reject(self, T: NDArray[np.float64]) -> None:
        pass

    def small(self, step: NDArray[np.float64]) -> bool:
        return bool(np.linalg.norm(step[:3]) < self.tol_mm and np.degrees(np.linalg.norm(step[3:])) < self.tol_deg)

    def parts(self, ev: Evaluation) -> list[tuple[slice, float]]:
        return [(slice(None), ev.value)]


def solve_pose(objective: SilhouetteObjective, T: NDArray[np.float64], level: Level, rule: StepRule,
               callback: Callback | None = None, tol_mm: float = TOL_MM,
               tol_deg: float = TOL_DEG) -> tuple[NDArray[np.float64], Trace]:
    """One object's pose (world from model, mm) descended at ``level`` by ``rule`` (:meth:`StepRule.at`
    the level), for at most ``level.max_iters`` iterations; ``callback(iteration, evaluation)``
    returning True stops it.

    With :class:`LevenbergMarquardt` it stops, besides the step-size test, without trying it, at a
    step whose predicted decrease is below ``ftol`` of the objective (at ``level`` as
    :func:`level_ftol` says). The objective's own noise (outlines discretised in pixels) is then
    larger than what the model can still gain: without this rule LM kept rendering sub-micrometre
    steps at full resolution, each gaining 1e-5 of the objective, without a better pose. What it
    leaves is a few hundredths of a pixel in the images, mostly in directions the silhouettes barely
    see (a flashlight's small button turning it about its axis by a few tenths of a degree).
    """
    sol = minimise(PoseProblem(objective, level, tol_mm, tol_deg), T, rule.at(level), level.max_iters, callback)
    return sol.x, sol.trace


STEP_RULES: dict[str, StepRule] = {"lm": LevenbergMarquardt(FTOL), "gn": GaussNewton(), "adam": Adam()}
"""The step rules by the name ``--optimizer`` gives, with their default settings."""
