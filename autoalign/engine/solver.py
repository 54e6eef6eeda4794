"""Pose optimisers over the 6-D twist ``(v [mm], w [rad])`` about the object centre.

* :func:`levenberg_marquardt` — damped Gauss-Newton (second order), the default.
* :func:`gauss_newton` — undamped Gauss-Newton with step halving.
* :func:`adam` — the first-order reference.

Each runs one :class:`~autoalign.engine.objective.Level` of the coarse-to-fine schedule and stops when a step
moves the object by less than ``tol_mm`` and ``tol_deg`` (Levenberg-Marquardt also, before trying
it, when the next step's predicted decrease is below ``ftol`` of the objective).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Evaluation, Level, SilhouetteObjective
from autoalign.geometry.se3 import apply_twist, transform_points

TOL_MM = 0.01
TOL_DEG = 0.001
FTOL = 1e-3
COARSE_MM = 0.1
COARSE_DEG = 0.05


class Stop:
    """Why an optimiser stopped (``Trace.stop``)."""

    SMALL_STEP = "small step"  # the last step moved the object by less than the tolerances
    FTOL = "predicted gain below ftol"  # LM: the next step would gain less than ftol of the objective
    DAMPING_LIMIT = "damping limit"  # LM: no damping up to 1e8 gave a decrease
    NO_DECREASE = "no decrease"  # GN: twelve halvings of the step gave no decrease
    BUDGET = "iteration budget"  # the level's max_iters ran out
    CALLER = "stopped by caller"  # the callback returned True
    CONVERGED = (SMALL_STEP, FTOL, DAMPING_LIMIT, NO_DECREASE)


@dataclass
class Trace:
    """What an optimiser did: objective per accepted iteration, step sizes, renders, why it stopped."""

    values: list[float] = field(default_factory=list)
    step_mm: list[float] = field(default_factory=list)
    step_deg: list[float] = field(default_factory=list)
    poses: list[NDArray[np.float64]] = field(default_factory=list)
    iterations: int = 0
    stop: str = Stop.BUDGET
    final: Evaluation | None = None  # the objective at the returned pose (LM and GN)
    start: Evaluation | None = None  # the objective at the starting pose (LM and GN)

    @property
    def converged(self) -> bool:
        """Stopped because nothing worth a step was left at this level (not by budget or caller)."""
        return self.stop in Stop.CONVERGED


Callback = Callable[[int, Evaluation], "bool | None"]
"""``callback(iteration, evaluation)`` after each accepted iteration; returning ``True`` stops the
optimiser there (the trace is then not ``converged``)."""


def _centre(objective: SilhouetteObjective, T: NDArray[np.float64]) -> NDArray[np.float64]:
    return transform_points(T, objective.centre_m[None])[0]


def level_tolerance(level: Level, tol_mm: float, tol_deg: float) -> tuple[float, float]:
    """Stopping tolerances at ``level``: the given ones at full resolution, looser when coarser.

    A coarse level only has to bring the pose within reach of the next one: it stops once a
    step moves the object by less than ``COARSE_MM / scale`` and ``COARSE_DEG / scale``
    (0.4 mm and 0.2 degrees at quarter resolution).
    """
    if level.scale >= 1.0:
        return tol_mm, tol_deg
    return max(tol_mm, COARSE_MM / level.scale), max(tol_deg, COARSE_DEG / level.scale)


def _small(step: NDArray[np.float64], tol_mm: float, tol_deg: float) -> bool:
    return bool(np.linalg.norm(step[:3]) < tol_mm and np.degrees(np.linalg.norm(step[3:])) < tol_deg)


def _record(trace: Trace, ev: Evaluation, T: NDArray[np.float64], step: NDArray[np.float64]) -> None:
    trace.values.append(ev.value)
    trace.step_mm.append(float(np.linalg.norm(step[:3])))
    trace.step_deg.append(float(np.degrees(np.linalg.norm(step[3:]))))
    trace.poses.append(T.copy())


Search = Callable[[NDArray[np.float64], Evaluation, float, float],
                  "tuple[NDArray[np.float64], Evaluation, NDArray[np.float64]] | str"]


def _descend(objective: SilhouetteObjective, T: NDArray[np.float64], level: Level, search: Search,
             tol_mm: float, tol_deg: float, callback: Callback | None) -> tuple[NDArray[np.float64], Trace]:
    """The outer loop shared by the second-order methods.

    ``search(T, ev, tol_mm, tol_deg)`` returns ``(T_new, ev_new, step)`` for a step that does
    not increase the objective (with the view weights of ``ev``), or the :class:`Stop` reason
    when there is none worth trying. Robust weights are then re-computed from the new fit (IRLS) without a new render.
    An iteration is one call that tried at least one step (rendered).
    """
    trace = Trace()
    tol_mm, tol_deg = level_tolerance(level, tol_mm, tol_deg)
    ev = trace.start = objective.evaluate(T, level)
    for it in range(level.max_iters):
        renders = objective.renders
        found = search(T, ev, tol_mm, tol_deg)
        if objective.renders > renders:  # an iteration tries at least one step
            trace.iterations = it + 1
        if isinstance(found, str):  # no descent worth a step left at this resolution
            trace.stop = found
            break
        T, ev_new, step = found
        ev = objective.reweighted(ev_new)
        _record(trace, ev, T, step)
        if callback and callback(it, ev):
            trace.stop = Stop.CALLER
            break
        if _small(step, tol_mm, tol_deg):
            trace.stop = Stop.SMALL_STEP
            break
    trace.final = ev
    return T, trace


def levenberg_marquardt(objective: SilhouetteObjective, T: NDArray[np.float64], level: Level,
                        lam: float = 1e-3, tol_mm: float = TOL_MM, tol_deg: float = TOL_DEG,
                        callback: Callback | None = None, damping_growth: float = 4.0,
                        max_step_mm: float = 30.0, max_step_deg: float = 20.0,
                        ftol: float = FTOL) -> tuple[NDArray[np.float64], Trace]:
    """Levenberg-Marquardt on the weighted Gauss-Newton system ``(H + lam diag(H)) step = -g``.

    A rejected step raises the damping ``lam`` by ``damping_growth``, an accepted one lowers it
    three-fold. Steps are clipped to ``max_step_mm`` / ``max_step_deg`` (a trust region for far starts).

    Besides the step-size test it stops, without trying it (nothing is rendered), at a step whose
    decrease predicted by the Gauss-Newton model is below ``ftol`` of the objective (MINPACK's
    ``ftol`` test; ``ftol / scale`` below full resolution, where the next level goes on, unless
    the level sets its own ``Level.ftol``). The
    objective's own noise (outlines discretised in pixels) is then larger than what the model can
    still gain: without this rule LM kept rendering sub-micrometre steps at full resolution, each
    gaining 1e-5 of the objective, without a better pose. What it leaves is a few hundredths of
    a pixel in the images, mostly in directions the silhouettes barely see (a flashlight's small
    button turning it about its axis by a few tenths of a degree).
    """
    state = {"lam": lam}
    f_tol = level.ftol if level.ftol is not None else ftol / min(level.scale, 1.0)

    def search(T: NDArray[np.float64], ev: Evaluation, tol_mm: float, tol_deg: float):
        H, g = ev.gn, ev.grad
        D = np.diag(np.maximum(np.diag(H), 1e-12 * max(np.trace(H), 1e-30)))
        while state["lam"] <= 1e8:
            try:
                step = -np.linalg.solve(H + state["lam"] * D, g)
            except np.linalg.LinAlgError:
                step = np.zeros(6)
            step = _clip_step(step, max_step_mm, max_step_deg)
            predicted = -(g @ step + 0.5 * step @ H @ step)
            if predicted < f_tol * ev.value:
                return Stop.FTOL
            if _small(step, tol_mm, tol_deg):
                return Stop.SMALL_STEP
            T_new = apply_twist(T, step, _centre(objective, T))
            ev_new = objective.evaluate(T_new, level, weights=ev.weights)
            if ev_new.value <= ev.value:
                state["lam"] = max(state["lam"] / 3.0, 1e-7)
                return T_new, ev_new, step
            state["lam"] *= damping_growth
        return Stop.DAMPING_LIMIT

    return _descend(objective, T, level, search, tol_mm, tol_deg, callback)


def gauss_newton(objective: SilhouetteObjective, T: NDArray[np.float64], level: Level,
                 tol_mm: float = TOL_MM, tol_deg: float = TOL_DEG,
                 callback: Callback | None = None) -> tuple[NDArray[np.float64], Trace]:
    """Gauss-Newton steps ``H step = -g`` with step halving (up to 12 times) until the objective decreases."""

    def search(T: NDArray[np.float64], ev: Evaluation, tol_mm: float, tol_deg: float):
        step = _clip_step(-np.linalg.lstsq(ev.gn, ev.grad, rcond=1e-10)[0], 30.0, 20.0)
        for _ in range(12):
            T_new = apply_twist(T, step, _centre(objective, T))
            ev_new = objective.evaluate(T_new, level, weights=ev.weights)
            if ev_new.value <= ev.value:
                return T_new, ev_new, step
            step = step / 2.0
        return Stop.NO_DECREASE

    return _descend(objective, T, level, search, tol_mm, tol_deg, callback)


def adam(objective: SilhouetteObjective, T: NDArray[np.float64], level: Level,
         lr_mm: float = 1.0, lr_deg: float = 1.0, betas: tuple[float, float] = (0.9, 0.999),
         decay: float = 0.97, tol_mm: float = TOL_MM, tol_deg: float = TOL_DEG,
         callback: Callback | None = None) -> tuple[NDArray[np.float64], Trace]:
    """Adam on the twist with per-block learning rates (mm and degrees per step), decayed geometrically."""
    trace = Trace()
    tol_mm, tol_deg = level_tolerance(level, tol_mm, tol_deg)
    m = np.zeros(6)
    v = np.zeros(6)
    lr = np.array([lr_mm] * 3 + [np.radians(lr_deg)] * 3)
    for it in range(level.max_iters):
        ev = objective.evaluate(T, level)
        if it == 0:
            trace.start = ev
        g = ev.grad
        m = betas[0] * m + (1 - betas[0]) * g
        v = betas[1] * v + (1 - betas[1]) * g * g
        mh = m / (1 - betas[0] ** (it + 1))
        vh = v / (1 - betas[1] ** (it + 1))
        step = -lr * (decay ** it) * mh / (np.sqrt(vh) + 1e-12)
        T = apply_twist(T, step, _centre(objective, T))
        trace.iterations = it + 1
        _record(trace, ev, T, step)
        if callback and callback(it, ev):
            trace.stop = Stop.CALLER
            break
        if _small(step, tol_mm, tol_deg):
            trace.stop = Stop.SMALL_STEP
            break
    return T, trace


def _clip_step(step: NDArray[np.float64], max_mm: float, max_deg: float) -> NDArray[np.float64]:
    step = step.copy()
    n_t = np.linalg.norm(step[:3])
    if n_t > max_mm:
        step[:3] *= max_mm / n_t
    n_r = np.degrees(np.linalg.norm(step[3:]))
    if n_r > max_deg:
        step[3:] *= max_deg / n_r
    return step


OPTIMIZERS = {"lm": levenberg_marquardt, "gn": gauss_newton, "adam": adam}
