"""A weakly observed turn's sigma from the loss along it, not from its curvature alone.

A nearly symmetric object (a pen, a bottle) fixes its roll through a small detail: the loss along
the roll is shallow and, beyond a few degrees, often not a parabola at all (a plateau, a second dip
where the detail lines up with a mask's error), and the few views that see the detail decide it.
The covariance only sees the curvature at the pose, so a pen can end 10 degrees off in roll with a
sigma of 2. So each weakly observed turn's loss is profiled: the pose turned by :data:`PROFILE_DEG`
(both ways, nothing else moved, the views' weights kept; twelve renders at half the images'
resolution, :data:`PROFILE_SCALE`), each view's loss kept.
Then the views are resampled (:data:`DRAWS` bootstrap draws of as many views, with replacement,
seeded) and the turn that minimises each draw's summed profile is found (a parabola through the
lowest sample and its neighbours); the spread (standard deviation) of those turns is the turn's
sigma as the views' disagreement gives it, far from the pose too: where a few views decide it and
disagree, the draws' minima jump between dips; where those views agree, they stay put. The
covariance's variance of that turn is raised to it when it is larger, along that turn alone.

Resampling views sees what they disagree on, not what every mask shares. The covariance's prior on
a shift every mask's outline shares (:data:`~autoalign.engine.uncertainty.BOUNDARY_BIAS_PX`) is
linear, taken at the pose; along a shallow turn a small tilt of the profile moves its minimum far,
so the profile carries that prior itself: each view's loss is also taken (the same renders)
against its mask with the outline moved out and in by one and two of the prior's sigmas (by the
Euclidean distance to it, :func:`~autoalign.losses.silhouette.moved_outline`), and each draw adds
one shift, drawn from the prior and shared by its views (the loss interpolated between those
shifts). The spread of
those draws' minima is the turn's floor in the reported covariance; the views' own spread, without
the shared shift, its floor in the views' spread (:attr:`~autoalign.engine.uncertainty.Uncertainty.spread`,
what the nearly-symmetric rule reads). Measured in ``docs/results.md``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import turns
from autoalign.engine.objective import SilhouetteObjective
from autoalign.engine.options import Level
from autoalign.engine.uncertainty import BOUNDARY_BIAS_PX, TurnFloor, Uncertainty, with_turn_floors

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


def view_draws(views: int, draws: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """(draws, views) how often each view is drawn in each bootstrap draw of as many views, with replacement."""
    return rng.multinomial(views, np.full(views, 1.0 / views), size=draws).astype(np.float64)


def draw_minima(angles_deg: NDArray[np.float64], totals: NDArray[np.float64]) -> NDArray[np.float64]:
    """(D,) the minimising turn (:func:`profile_minimum`) of each of the summed profiles ``totals``
    (D, K) sampled at ``angles_deg`` (K,)."""
    return np.array([profile_minimum(angles_deg, t) for t in totals])


def bootstrap_minima(angles_deg: NDArray[np.float64], view_losses: NDArray[np.float64],
                     draws: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """(draws,) the minimising turn (:func:`profile_minimum`) of the summed profile of each bootstrap
    draw of views; ``view_losses`` (V, K) each view's weighted loss at ``angles_deg`` (K,)."""
    return draw_minima(angles_deg, view_draws(len(view_losses), draws, rng) @ view_losses)


SHIFT_STEPS = (-2.0, -1.0, 0.0, 1.0, 2.0)
"""The shared outline shifts (in the prior's sigmas) each view's loss is taken at along a profile;
a draw's shift between them is interpolated, beyond them extrapolated, linearly."""


def shared_shift_minima(angles_deg: NDArray[np.float64], shifted: NDArray[np.float64],
                        shifts_px: NDArray[np.float64], sigma_px: float, counts: NDArray[np.float64],
                        rng: np.random.Generator) -> NDArray[np.float64]:
    """(D,) the minimising turn of each draw of views (``counts`` (D, V), :func:`view_draws`) with
    one outline shift every view shares, drawn from N(0, ``sigma_px``^2): ``shifted`` (S, V, K) each
    view's weighted loss at ``angles_deg`` (K,) with the outlines moved by each of ``shifts_px`` (S,
    increasing), between which the loss is taken as linear in the shift."""
    per_draw = np.einsum("dv,svk->sdk", counts, shifted)  # (S, D, K) each draw's summed profile per shift
    b = rng.normal(0.0, sigma_px, len(counts))
    seg = np.clip(np.searchsorted(shifts_px, b) - 1, 0, len(shifts_px) - 2)
    w = ((b - shifts_px[seg]) / (shifts_px[seg + 1] - shifts_px[seg]))[:, None]
    d = np.arange(len(counts))
    return draw_minima(angles_deg, (1.0 - w) * per_draw[seg, d] + w * per_draw[seg + 1, d])


def with_turn_profiles(obj: SilhouetteObjective, T_wm: NDArray[np.float64], u: Uncertainty,
                       weights: NDArray[np.float64], sigma_px: float) -> Uncertainty:
    """``u`` with the variance of each weakly observed turn (:attr:`Uncertainty.weak_turn_axes`)
    raised to its profile's (see the module doc), the loss evaluated at :data:`PROFILE_SCALE` with
    the silhouettes' blur ``sigma_px`` and the views' ``weights`` (the pose's)."""
    if not u.weak_turn_axes:
        return u
    level = Level(PROFILE_SCALE, sigma_px, 0)
    shifts = BOUNDARY_BIAS_PX * np.asarray(SHIFT_STEPS)  # px of the full-resolution masks
    moved = [None if b == 0.0 else obj.with_moved_outlines(level, float(b)) for b in shifts]
    side = np.asarray(PROFILE_DEG, dtype=np.float64)
    angles = np.r_[-side[::-1], 0.0, side]

    def losses(T: NDArray[np.float64]) -> NDArray[np.float64]:
        """(S, V) each view's weighted loss at ``T`` against the masks with each shared shift."""
        ev = obj.evaluate(T, level, weights=weights, with_derivatives=False)
        return weights * np.stack([ev.terms.loss if v is None else obj.loss_against(ev, v) for v in moved])

    own = losses(T_wm)
    rng, shift_rng = np.random.default_rng(0), np.random.default_rng(1)
    floors = []
    for axis_m in u.weak_turn_axes:
        a_m = np.asarray(axis_m, dtype=np.float64) / np.linalg.norm(axis_m)
        turned = [losses(T) for T in turns(T_wm, a_m, obj.centre_m, tuple(angles[angles != 0.0]))]
        shifted = np.stack(turned[:len(side)] + [own] + turned[len(side):], axis=2)  # (S, V, K) in angle order
        counts = view_draws(len(weights), DRAWS, rng)
        alone = draw_minima(angles, counts @ shifted[SHIFT_STEPS.index(0.0)])
        shared = shared_shift_minima(angles, shifted, shifts, BOUNDARY_BIAS_PX, counts, shift_rng)
        floors.append(TurnFloor(a_m, float(np.radians(np.std(alone))) ** 2, float(np.radians(np.std(shared))) ** 2))
    return with_turn_floors(u, floors)
