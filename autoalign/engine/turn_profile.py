"""A weakly observed turn's sigma from the loss along it, not from its curvature alone.

A nearly symmetric object (a pen, a bottle) fixes its roll through a small detail: the loss along
the roll is shallow and, beyond a few degrees, often not a parabola at all (a plateau, a second dip
where the detail lines up with a mask's error), and the few views that see the detail decide it.
The covariance only sees the curvature at the pose, so a pen can end 10 degrees off in roll with a
sigma of 2. So each weakly observed turn's loss is profiled: the pose turned by :data:`PROFILE_DEG`
(both ways, nothing else moved, the views' weights kept; twelve renders at half the images'
resolution, :data:`PROFILE_SCALE`), each view's loss kept.
Then the views are resampled (:data:`DRAWS` bootstrap draws of as many views, with replacement,
seeded; the views of one viewpoint drawn as one, :func:`~autoalign.engine.uncertainty.viewpoint_groups`)
and the turn that minimises each draw's summed profile is found (a parabola through the
lowest sample and its neighbours); the spread (standard deviation) of those turns is the turn's
sigma as the views' disagreement gives it, far from the pose too: where a few views decide it and
disagree, the draws' minima jump between dips; where those views agree, they stay put. The
covariance's variance of that turn is raised to it when it is larger, along that turn alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import turns
from autoalign.engine.objective import SilhouetteObjective
from autoalign.engine.options import Level
from autoalign.engine.uncertainty import TurnFloor, Uncertainty, with_turn_floors

PROFILE_SCALE = 0.5
"""The resolution of the profile's renders (of the images'). A coarser loss is a noisier one: on the
synthetic calibration scenes, the spread from renders at 1/4 resolution was about twice that at
full (a travel mug's roll 1.1 deg against 0.4, a gear's tilt 1.3 against 0.7); at 1/2 it is within
25% of full (0.5, 0.8) at a quarter of the cost."""

DRAWS = 500
"""Bootstrap draws of the views per turn: the spread's own sampling error is about 3%."""

PROFILE_DEG = (0.75, 1.5, 3.0, 6.0, 12.0, 24.0)
"""The turns (degrees, each both ways) the loss is evaluated at: doubling from the weak-turn limit's
sigma (:data:`~autoalign.engine.uncertainty.WEAK_DEG` = 1 deg; a parabola through three samples
finds a minimum between them to a fraction of their spacing) to where another
solution, not a sigma, begins (the weak-turn search, :func:`~autoalign.engine.hypotheses.turn_scores`,
tries 30 deg and beyond)."""


def profile_minimum(angles_deg: NDArray[np.float64], totals: NDArray[np.float64]) -> float:
    """The turn (degrees) that minimises a profile sampled at ``angles_deg`` (increasing): the
    lowest sample, moved to the vertex of the parabola through it and its neighbours (kept
    between them)."""
    k = int(np.argmin(totals))
    if k == 0 or k == len(angles_deg) - 1:
        return float(angles_deg[k])
    x, y = angles_deg[k - 1:k + 2], totals[k - 1:k + 2]
    a, b, _ = np.polyfit(x - x[1], y, 2)
    if a <= 0.0:
        return float(x[1])
    return float(np.clip(x[1] - b / (2.0 * a), x[0], x[2]))


def bootstrap_minima(angles_deg: NDArray[np.float64], view_losses: NDArray[np.float64],
                     draws: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """(draws,) the minimising turn (:func:`profile_minimum`) of the summed profile of each bootstrap
    draw of views; ``view_losses`` (V, K) each view's weighted loss at ``angles_deg`` (K,)."""
    V = len(view_losses)
    counts = rng.multinomial(V, np.full(V, 1.0 / V), size=draws).astype(np.float64)
    return np.array([profile_minimum(angles_deg, t) for t in counts @ view_losses])


def with_turn_profiles(obj: SilhouetteObjective, T_wm: NDArray[np.float64], u: Uncertainty,
                       weights: NDArray[np.float64], sigma_px: float,
                       groups: list[NDArray[np.int64]] | None = None) -> Uncertainty:
    """``u`` with the variance of each weakly observed turn (:attr:`Uncertainty.weak_turn_axes`)
    raised to its profile's (see the module doc), the loss evaluated at :data:`PROFILE_SCALE` with
    the silhouettes' blur ``sigma_px`` and the views' ``weights`` (the pose's). ``groups``: the views
    of one viewpoint each (:func:`~autoalign.engine.uncertainty.viewpoint_groups`), resampled as one;
    ``None``: each view its own. A turn about an axis of the model's continuous symmetry is not
    profiled: its loss is flat by the model's shape, and no view can say where it lies."""
    weak = u.weak_turns_not_free(obj.pyramid.symmetries.axes)
    if not weak:
        return u
    level = Level(PROFILE_SCALE, sigma_px, 0)
    side = np.asarray(PROFILE_DEG, dtype=np.float64)
    angles = np.r_[-side[::-1], 0.0, side]
    own = weights * obj.evaluate(T_wm, level, weights=weights, with_derivatives=False).terms.loss
    rng = np.random.default_rng(0)
    floors = []
    for axis_m in weak:
        a_m = np.asarray(axis_m, dtype=np.float64) / np.linalg.norm(axis_m)
        poses = turns(T_wm, a_m, obj.centre_m, tuple(angles[angles != 0.0]))
        turned = [weights * obj.evaluate(T, level, weights=weights, with_derivatives=False).terms.loss for T in poses]
        losses = np.stack(turned[:len(side)] + [own] + turned[len(side):], axis=1)  # (V, K) in angle order
        if groups is not None:
            losses = np.stack([losses[g].sum(axis=0) for g in groups])
        minima = bootstrap_minima(angles, losses, DRAWS, rng)
        floors.append(TurnFloor(a_m, float(np.radians(np.std(minima))) ** 2))
    return with_turn_floors(u, floors)
