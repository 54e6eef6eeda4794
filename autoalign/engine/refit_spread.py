"""How far the views really move the pose: the jackknife's Newton steps checked against refits.

The views' spread (:func:`~autoalign.engine.uncertainty.jackknife`) takes one Newton step per view
left out, with the other views' robust weights held. On real masks that can be far too narrow: on
the real LM-O ape (15 views, SAM masks of IoU 0.3-0.8) a polish with one view left out moved the
pose 6-16 times farther than its Newton step (with the weights recomputed, as every polish does,
the pose slides where the masks disagree), and the two halves of its views ended 5.4 mm apart with
sigmas of 0.2-0.5 mm. Without the robust weights the steps and the polishes agreed to within 1.5x.

So the views are split into :data:`GROUPS` interleaved groups; the pose is polished at
:data:`REFIT_SCALE` of the images' resolution with every view, then from there with each group left
out, each polish run to its move (:data:`REFIT_FTOL`); each move is set against the Newton step of
the same deletion, both measured by the weighted Gauss-Newton matrix ``H`` (the information they
carry). Where the polishes moved farther, the
ratio of the summed squares is the factor the views' spread (a variance) is scaled by
(:attr:`~autoalign.engine.uncertainty.Uncertainty.spread_factor`); never below 1, since a polish
that stops within its tolerance moves by nothing.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Evaluation, Level, SilhouetteObjective
from autoalign.engine.schedule import run_schedule
from autoalign.engine.solver import StepRule
from autoalign.engine.uncertainty import deletion_step
from autoalign.geometry.se3 import so3_log

GROUPS = 5
"""Interleaved groups of views left out in turn: five polishes (each without a fifth of the views).
A scene with fewer than two views per group is not checked."""
REFIT_SCALE = 0.25
"""The polishes' resolution (of the images'). On the LM-O ape's halves the ratio at 1/2 was 19-55
against 73-150 at full resolution; both put the halves' disagreement within 3 combined sigmas on
5-6 of its 6 axes (1-2 before). With the polishes run to their move (:data:`REFIT_FTOL`), 1/4
gave factors like 1/2's on the LM-O halves of ``lmo_im0115_0389`` (4-130 against 1.3-50) at 0.6 of
its cost."""
REFIT_FTOL = 1e-4
"""The polishes' ``ftol`` (:class:`~autoalign.engine.objective.Level`). A refit measures a move, and
with a fifth of the views left out the optimum moves by a step whose predicted gain is a small
fraction of the loss: at the level's own ``ftol`` (2e-3 at 1/2 resolution) Levenberg-Marquardt
stopped before its first or second step, and the factor stayed 1 for 5 of the 8 halves of
``lmo_im0115_0389`` (a glue half whose SAM masks are on another object in 78% of its views among
them, 0.25 mm along the ray against halves 5.3 mm apart)."""
REFIT_ITERS = 6
"""At most this many iterations per polish (the cost's bound)."""


def _move(T_from: NDArray[np.float64], T_to: NDArray[np.float64], centre_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The world twist ``(v [mm], w [rad])`` about the object's centre from ``T_from`` to ``T_to``
    (the frame of the Gauss-Newton matrix)."""
    c0 = T_from[:3, :3] @ centre_m + T_from[:3, 3]
    c1 = T_to[:3, :3] @ centre_m + T_to[:3, 3]
    return np.r_[c1 - c0, so3_log(T_to[:3, :3] @ T_from[:3, :3].T)]


def refit_ratio(obj: SilhouetteObjective, T_wm: NDArray[np.float64], ev: Evaluation, last: Level,
                rule: StepRule) -> float | None:
    """``sum_g a_g^T H a_g / sum_g l_g^T H l_g`` over the groups ``g`` (module doc): ``a_g`` the
    polish's move with group ``g`` left out, ``l_g`` its Newton step ``(H - H_g)^-1 g_g``
    (:func:`~autoalign.engine.uncertainty.deletion_step`, as the jackknife's) from the
    full-resolution evaluation ``ev`` at ``T_wm`` (its weights held); the polishes at
    :data:`REFIT_SCALE` with ``last``'s blur and iterations. ``None`` with too few views."""
    n = len(obj.compared)
    if n < 2 * GROUPS:
        return None
    level = replace(last, scale=REFIT_SCALE, max_views=None, ftol=REFIT_FTOL, max_iters=REFIT_ITERS)
    T0, _ = run_schedule(obj, T_wm, (level,), rule)
    w = ev.weights
    H = ev.gn
    H_inv = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    every = np.arange(6)
    actual = linear = 0.0
    for g in range(GROUPS):
        out = np.arange(n) % GROUPS == g
        sub = obj.subset(np.flatnonzero(~out))
        Tg, _ = run_schedule(sub, T0, (level,), rule)
        a = _move(T0, Tg, obj.centre_m)
        step = deletion_step(H_inv, every, np.einsum("v,vij->ij", w[out], ev.terms.gn[out]),
                             (w[out, None] * ev.terms.grad[out]).sum(axis=0))
        actual += float(a @ H @ a)
        linear += float(step @ H @ step)
    return actual / linear if linear > 0.0 else None


def spread_factor(ratio: float | None) -> float:
    """The factor the views' spread is scaled by: the refits' ratio where it is above 1, else 1."""
    return 1.0 if ratio is None else max(1.0, float(ratio))
