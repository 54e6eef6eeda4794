"""How well the silhouettes pin a refined pose down: its 6x6 covariance, sigma per model axis,
and the directions the views barely see.

At the optimum of the weighted least-squares silhouette loss, with the Gauss-Newton matrix ``H``
(the sum over views of ``w_v J_v^T J_v / area_v``) and per-view gradients ``g_v = w_v J_v^T r_v``:

* ``naive``: ``H^-1 * 2 loss / (n - 6)``, the textbook residual-variance estimate, with ``n`` the
  pixels whose silhouette value depends on the pose (the band). It takes pixels as independent,
  but a mask's boundary error runs along the outline over many pixels, so it is far too small;
* ``sandwich``: ``H^-1 (V / (V - 1) sum_v g_v g_v^T) H^-1``, the cluster-robust estimate with one
  cluster per view: whatever the correlation of a view's pixels, the views' errors are taken as
  independent. It sees what the views disagree on (a mask tight in one view and loose in another,
  a camera off by a pixel), but not an error every view shares;
* ``jackknife`` (reported): the spread of the poses with each view left out (one Newton step each,
  :func:`jackknife`). The same as the sandwich to first order, but a view that alone fixes a
  direction (few views, one that sees a detail) counts for what leaving it out would do; on the
  real LM-O halves from ``--init`` it
  covered 60% of the axes within 3 sigma where the sandwich covered 54% (62% with the weak turns'
  profiles, ``experiments/results/split_half_real.md``);
* ``boundary bias`` (added to the views' spread; reported): a mask outline a few pixels too tight or too
  loose in *every* view moves the pose coherently, and no spread of the residuals shows it. With
  ``b_v`` the change of view ``v``'s gradient per pixel of outward boundary shift of its target,
  the pose moves by ``s = -H^-1 sum_v w_v b_v`` per pixel; a prior ``sigma_b`` (px) on that shared
  shift adds ``sigma_b^2 s s^T``. From one viewpoint ``s`` lies along the viewing ray: apparent
  size is all that fixes distance there, and a 4 px tight mask makes the object look several
  percent farther.
* ``outline disagreement`` (with the photos; reported): where the masks' outlines lie ``d`` px
  outside the silhouettes of a pose fitted with the photos' colours too, the two kinds of
  evidence disagree by ``d`` about where the outline is, and the pose lies between them; the
  shared shift's variance becomes ``sigma_b^2 + d^2`` (:func:`with_outline_disagreement`). On the
  real YCB-Video frames with masks eroded by 4 px (``experiments/results/few_viewpoints.md``)
  ``d`` is 3-5 px, and the mug, whose colour runs on into a red brick, ends 18 mm along the ray
  at 1.3 sigma (3.5 with the prior alone); on LM-O's SAM masks ``d`` is 0 to 1 px.

A weakly observed turn's variance is then raised to the spread its loss profile's minimum shows
over resampled views (:mod:`autoalign.engine.turn_profile`): a nearly symmetric object's roll is
not a parabola far from the pose.

The twist is ``(v [mm], w [rad])`` in the world frame about the object centre; sigmas are
reported about and along the model's own axes (its x, y, z), since those name what a person sees
(a bottle's roll is a turn about its model axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

WEAK_DEG = 1.0
"""A turn whose sigma exceeds this many degrees is named as weakly observed ..."""
WEAK_MM = 1.0
"""... and so is a shift whose sigma exceeds this many millimetres ..."""
WEAK_RATIO = 5.0
"""... or either whose sigma is this many times that of the best observed direction of its kind
(a flashlight's roll about its axis: 0.3-0.4 degrees against 0.03 about the other axes)."""
BOUNDARY_BIAS_PX = 1.2
"""The prior sigma (px, at the images' resolution) of a shift every mask's outline shares. Measured
on the real SAM masks of the LM-O dev scenes (``python -m autoalign.experiments.studies.sam_mask_rates``):
per view, the median distance of the mask's outline outside the labels' ray-cast silhouette (masks
on the object only, occlusion edges left out); per object, the median over its views is the shift
its masks share: RMS 1.2 px over 16 objects, from -3 to +1 px. (An earlier estimate from the masks'
areas, 0.8 px, counted only masks with IoU >= 0.8, which leaves out the tight masks of small
objects: a 3 px shift costs a 60 px wide ape 0.2 of IoU.) On the 200 synthetic instances of
``experiments/results/uncertainty_calibration.md`` (per-view outline errors of up to 2 px) the
prior's size was weighed at the sandwich: 0 / 1 / 1.5 / 2 px put 86% / 94% / 95% / 96% of the
per-axis errors within 3 sigma with medians |error| / sigma of 1.40 / 0.80 / 0.61 / 0.49 (a
Gaussian's: 99.7%, 0.67)."""
SAME_VIEWPOINT_DEG = 1.0
"""Views whose directions to the object differ by less than this see one outline: a 1 degree turn
of the view moves the outline of a 100 mm object seen from 600 mm with a 600 px focal length by
under a pixel, less than a mask's own error (:data:`BOUNDARY_BIAS_PX`). Their masks' errors are one
measurement, not independent ones (a segmenter errs alike on near-identical images), so the views'
spread counts such a group as one view (:func:`viewpoint_groups`); ten frames of a still RGB-D
camera are one viewpoint, not ten."""
MIN_VIEWPOINTS = 2
"""With fewer viewpoints than this the views' spread cannot be measured: their errors are one sample."""
SAME_AXIS = 0.95
"""Two unit axes whose dot product's magnitude is at least this name the same turn."""
_AXES = "xyz"


@dataclass(frozen=True)
class TurnFloor:
    """The least variance (rad^2) of the turn about the unit model-frame axis ``axis_m`` (through
    the object's centre): that of its loss profile's minimum over resampled views
    (:mod:`autoalign.engine.turn_profile`)."""

    axis_m: NDArray[np.float64]
    variance: float


@dataclass(frozen=True)
class CovarianceParts:
    """What a pose's covariance is made of, by name (model axes; twist ``(v [mm], w [rad])`` about
    the object's centre; see the module doc). :func:`compose` is the one function that sums them.

    Attributes:
        spread: (6, 6) the views' spread as measured (their jackknife over viewpoints).
        naive: (6, 6) the residual-variance estimate, for comparison (``None``: not measured).
        spread_factor: the spread is scaled by it where polishes with views left out moved the pose
            farther than its Newton steps (:mod:`autoalign.engine.refit_spread`).
        turn_floors: each weakly observed turn's least variance, from its loss profile
            (:mod:`autoalign.engine.turn_profile`).
        bias_shift: (6,) the twist the pose moves by per pixel of outward shift of every mask's outline.
        outline_px: the prior sigma of that shared shift (px).
        disagreement_px: with the photos, how far the masks' outlines lie outside the fitted
            silhouettes (px; :func:`with_outline_disagreement`); ``None``: not measured.
        scale: a solved scene scale's relative sigma and the label's distance from its cameras (mm);
            ``None``: the scale was given.
        view_dir_m: (3,) unit direction of the median view in the model's axes; ``None``: not known.
        viewpoints: the independent viewpoints the spread counts (:func:`viewpoint_groups`).
    """

    spread: NDArray[np.float64]
    naive: NDArray[np.float64] | None = None
    spread_factor: float = 1.0
    turn_floors: tuple[TurnFloor, ...] = ()
    bias_shift: NDArray[np.float64] = field(default_factory=lambda: np.zeros(6))
    outline_px: float = BOUNDARY_BIAS_PX
    disagreement_px: float | None = None
    scale: tuple[float, float] | None = None
    view_dir_m: NDArray[np.float64] | None = None
    viewpoints: int | None = None

    def stages(self) -> tuple[NDArray[np.float64], ...]:
        """The covariance as it is summed, each stage with one more part: the views' spread (scaled,
        its turns floored), plus the outline prior (the floors then raised in it too), plus the
        photos' disagreement, plus the scale's share along the ray."""
        views = self.spread_factor * self.spread
        shift = np.outer(self.bias_shift, self.bias_shift)
        prior = views + self.outline_px ** 2 * shift
        for f in self.turn_floors:
            e = np.r_[np.zeros(3), f.axis_m]
            for C in (views, prior):
                var = float(e @ C @ e)
                if f.variance > var:
                    C += (f.variance - var) * np.outer(e, e)
        disagreement = prior if self.disagreement_px is None else prior + self.disagreement_px ** 2 * shift
        full = disagreement
        if self.scale is not None and self.view_dir_m is not None and self.scale[0] > 0.0:
            full = disagreement.copy()
            full[:3, :3] += (self.scale[0] * self.scale[1]) ** 2 * np.outer(self.view_dir_m, self.view_dir_m)
        return views, prior, disagreement, full


@dataclass
class Uncertainty:
    """The covariance of a pose and what it says.

    Attributes:
        covariance: (6, 6) of the twist ``(v [mm], w [rad])`` in the model's axes, about its centre.
        sigma_mm: (3,) standard deviation of the position along the model's x, y, z (mm).
        sigma_deg: (3,) standard deviation of the orientation about the model's x, y, z (degrees).
        weak: the weakly observed directions, e.g. ``"turn about model z: 12.3 deg"``.
        weak_turn_axes: the unit model-frame axes of the turns the views' geometry barely fixes
            (from the views' spread alone, before the outline shift's prior), largest first, and
            those of ``turn_floors`` (the joint stage's pose keeps the floors its instance's
            profiles found alone, whose turns its own spread may see better).
        naive_sigma_mm / naive_sigma_deg: the same from the residual-variance estimate (for comparison).
        bias_shift: (6,) the twist (model axes, mm and rad) the pose moves by per pixel of outward
            shift of every mask's outline (see the module doc); zero where it was not measured.
        view_dir_m: (3,) unit viewing direction of the median view, in the model's axes (camera
            to object centre; the view closest to the mean direction); ``None``: not known.
        sigma_ray_mm: position sigma along ``view_dir_m`` (mm), where silhouettes are weakest.
        sigma_across_mm: the largest position sigma across it (mm).
        turn_floors: the weakly observed turns whose variance their loss profile raised (included
            in ``covariance``).
        spread_factor: the factor the views' spread was scaled by, where polishes with views left
            out moved the pose farther than its Newton steps (:mod:`autoalign.engine.refit_spread`;
            1: not scaled).
        outline_disagreement_px: how far the masks' outlines lie outside the silhouettes of a pose
            fitted with the photos too (:func:`with_outline_disagreement`); ``None``: not measured.
        spread: (6, 6) what the views show of the pose: their spread (scaled by ``spread_factor``)
            with the turns' profiles (``turn_floors``), without the outline-shift prior; the
            weakly observed turns are found in it. ``None``: ``covariance`` is all there is.
        viewpoints: how many independent viewpoints the views' spread counts
            (:func:`viewpoint_groups`); below :data:`MIN_VIEWPOINTS` the spread is a guess (the
            views counted as one, :func:`jackknife`). ``None``: not known.
    """

    covariance: NDArray[np.float64]
    sigma_mm: NDArray[np.float64]
    sigma_deg: NDArray[np.float64]
    weak: list[str] = field(default_factory=list)
    weak_turn_axes: list[NDArray[np.float64]] = field(default_factory=list)
    naive_sigma_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    naive_sigma_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    bias_shift: NDArray[np.float64] = field(default_factory=lambda: np.zeros(6))
    view_dir_m: NDArray[np.float64] | None = None
    sigma_ray_mm: float | None = None
    sigma_across_mm: float | None = None
    turn_floors: list[TurnFloor] = field(default_factory=list)
    spread_factor: float = 1.0
    outline_disagreement_px: float | None = None
    spread: NDArray[np.float64] | None = None
    viewpoints: int | None = None
    parts: CovarianceParts | None = None

    @property
    def views_spread(self) -> NDArray[np.float64]:
        """(6, 6) what the views show of the pose: :attr:`spread`, or :attr:`covariance` where
        there is no spread apart from it."""
        return self.covariance if self.spread is None else self.spread

    def weak_turns_not_free(self, free_axes_m: tuple[NDArray[np.float64], ...] = ()) -> list[NDArray[np.float64]]:
        """:attr:`weak_turn_axes` but those about an axis of continuous symmetry ``free_axes_m`` (model
        frame): a can's free spin is no weakness, and no profile or search can measure it."""
        free = [np.asarray(a, dtype=np.float64) / np.linalg.norm(a) for a in free_axes_m]
        return [a for a in self.weak_turn_axes if all(abs(float(a @ f)) < SAME_AXIS for f in free)]

    def components(self) -> dict[str, NDArray[np.float64]]:
        """:attr:`covariance` as the sum it is made of (6x6 each, model axes; :class:`CovarianceParts`):
        ``views`` (the views' spread, scaled by :attr:`spread_factor`, with the turn profiles'
        floors), ``outline_prior`` (:data:`BOUNDARY_BIAS_PX` on a shift every mask's outline
        shares), ``outline_disagreement`` (with the photos: the masks' offset from the fitted
        outlines, on the same shift) and ``scale`` (a solved scene scale along the ray)."""
        if self.parts is None:
            zero = np.zeros((6, 6))
            return {"views": self.covariance, "outline_prior": zero, "outline_disagreement": zero, "scale": zero}
        views, prior, disagreement, full = self.parts.stages()
        return {"views": views, "outline_prior": prior - views, "outline_disagreement": disagreement - prior,
                "scale": full - disagreement}

    def adding(self, **parts: Any) -> "Uncertainty":
        """This uncertainty with the named parts (:class:`CovarianceParts` fields) set, summed again."""
        base = self.parts if self.parts is not None else CovarianceParts(self.covariance, outline_px=0.0)
        return compose(replace(base, **parts))


def _into_model(R_wm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 6x6 map of a world-frame twist into the model's axes (``v_m = R^T v``, ``w_m = R^T w``)."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R_wm.T
    return A


def _to_model(cov_w: NDArray[np.float64], R_wm: NDArray[np.float64]) -> NDArray[np.float64]:
    """A world-frame twist covariance in the model's axes."""
    A = _into_model(R_wm)
    return A @ cov_w @ A.T


def axis_sigmas(cov: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sigmas of a 6x6 twist covariance along (mm) and about (degrees) its three axes (a negative
    diagonal, rounding, as zero)."""
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return d[:3], np.degrees(d[3:])


def turn_sigma_deg(cov_m: NDArray[np.float64], axis_m: NDArray[np.float64]) -> float:
    """The sigma (degrees) of the turn about the unit model-frame axis ``axis_m`` in the (6, 6)
    model-frame covariance ``cov_m`` (twist ``(v [mm], w [rad])``)."""
    a = np.asarray(axis_m, dtype=np.float64)
    return float(np.degrees(np.sqrt(max(float(a @ cov_m[3:, 3:] @ a), 0.0))))


def direction_name(u: NDArray[np.float64]) -> str:
    """A unit model-frame direction by its nearest model axis (``model z``) or its components."""
    k = int(np.argmax(np.abs(u)))
    if abs(u[k]) > 0.9:
        return f"model {_AXES[k]}"
    return "model (" + ", ".join(f"{x:+.2f}" for x in u * np.sign(u[k])) + ")"


def turns_not_free(free_axes_m: tuple[NDArray[np.float64], ...]) -> NDArray[np.float64]:
    """(3, k) orthonormal columns (model frame) spanning the turn axes at right angles to every one of
    ``free_axes_m`` (axes of continuous symmetry); k = 0 when every turn is free."""
    P = np.eye(3)
    for a in free_axes_m:
        a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
        P = P @ (np.eye(3) - np.outer(a, a))
    vals, vecs = np.linalg.eigh(P @ P.T)
    return vecs[:, vals > 0.5]


def _weak(cov_m: NDArray[np.float64], weak_mm: float = WEAK_MM, weak_deg: float = WEAK_DEG,
          ratio: float = WEAK_RATIO, free_axes_m: tuple[NDArray[np.float64], ...] = ()
          ) -> list[tuple[str, NDArray[np.float64]]]:
    """The principal directions of the position and orientation blocks whose sigma is large, in
    absolute terms or against the best observed direction of the block, largest first (turns
    first), each named and with its unit model-frame vector; turns about ``free_axes_m`` (axes of
    continuous symmetry: no view sees them, no label depends on them) left out."""
    out = []
    for block, unit, limit, what in ((slice(3, 6), np.degrees(1.0), weak_deg, "turn about"),
                                     (slice(0, 3), 1.0, weak_mm, "shift along")):
        B = turns_not_free(free_axes_m) if what == "turn about" else np.eye(3)
        if B.shape[1] == 0:  # every turn free (a sphere): none to name
            continue
        vals, vecs = np.linalg.eigh(B.T @ cov_m[block, block] @ B)
        vecs = B @ vecs
        best = float(np.sqrt(max(vals[0], 0.0))) * unit
        for lam, u in sorted(zip(vals, vecs.T), key=lambda x: -x[0]):
            s = float(np.sqrt(max(lam, 0.0))) * unit
            if s > limit or s > ratio * best:
                out.append((f"{what} {direction_name(u)}: {s:.2g} {'deg' if what == 'turn about' else 'mm'}", u))
    return out


def weak_directions(cov_m: NDArray[np.float64], free_axes_m: tuple[NDArray[np.float64], ...] = ()) -> list[str]:
    """:attr:`Uncertainty.weak` of the covariance ``cov_m`` (model frame), the turns about the
    model's axes of continuous symmetry ``free_axes_m`` left out (a can's free spin is no weakness)."""
    return [t for t, _ in _weak(cov_m, free_axes_m=free_axes_m)]


def _weak_turn_axes(spread_m: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The unit model-frame axes of the weakly observed turns of a views' spread (model frame)."""
    return [u for t, u in _weak(spread_m) if t.startswith("turn")]


def pose_uncertainty(H: NDArray[np.float64], view_grads: NDArray[np.float64], view_gn: NDArray[np.float64],
                     weights: NDArray[np.float64], value: float, n_band: int, R_wm: NDArray[np.float64],
                     bias_grads: NDArray[np.float64] | None = None, view_dirs_w: NDArray[np.float64] | None = None,
                     bias_px: float = BOUNDARY_BIAS_PX, spread_factor: float = 1.0,
                     groups: list[NDArray[np.int64]] | None = None) -> Uncertainty:
    """The uncertainty of a converged pose (see the module doc).

    Args:
        H: (6, 6) weighted Gauss-Newton matrix at the pose (world twist).
        view_grads: (V, 6) unweighted per-view gradients ``J_v^T r_v``.
        view_gn: (V, 6, 6) unweighted per-view Gauss-Newton matrices (the views' spread is their
            jackknife, :func:`jackknife`).
        weights: (V,) the view weights of ``H``.
        value: the weighted loss ``sum_v w_v loss_v``.
        n_band: pixels whose value depends on the pose.
        R_wm: the pose's rotation (world from model).
        bias_grads: (V, 6) unweighted per-view gradient change per pixel of outward shift of the
            target's outline (:func:`~autoalign.losses.silhouette.boundary_bias_grads`); ``None``: not measured.
        view_dirs_w: (V, 3) unit directions from each camera to the object centre (world).
        bias_px: the prior sigma of the shared outline shift (px).
        spread_factor: the views' spread is scaled by it (:mod:`autoalign.engine.refit_spread`).
        groups: the views of each viewpoint (:func:`viewpoint_groups` of ``view_dirs_w``, which it
            defaults to; ``None`` without directions: each view its own).
    """
    H_inv = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    w = np.asarray(weights, dtype=np.float64)[:, None]
    shift_w = np.zeros(6) if bias_grads is None else -H_inv @ (w * bias_grads).sum(axis=0)
    every = np.arange(6)
    g = view_grads * w
    if groups is None and view_dirs_w is not None:
        groups = viewpoint_groups(view_dirs_w)
    spread = jackknife(H_inv, [(every, wv * Hv) for wv, Hv in zip(w[:, 0], view_gn)], g, groups=groups)
    return uncertainty_of(spread, H_inv * (2.0 * value / max(n_band - 6, 1)), R_wm, shift_w,
                          median_view_direction(view_dirs_w, w[:, 0]), bias_px, spread_factor,
                          None if groups is None else viewpoints_seen(groups, g))


def median_view_direction(view_dirs_w: NDArray[np.float64] | None,
                          weights: NDArray[np.float64] | None = None) -> NDArray[np.float64] | None:
    """The unit direction (world) of the view closest to the (weighted) mean viewing direction."""
    if view_dirs_w is None or len(view_dirs_w) == 0:
        return None
    d = np.asarray(view_dirs_w, dtype=np.float64)
    w = np.ones(len(d)) if weights is None else np.asarray(weights, dtype=np.float64)
    mean = (w[:, None] * d).sum(axis=0)
    if np.linalg.norm(mean) < 1e-9:
        mean = d.sum(axis=0)
    return d[int(np.argmax(d @ mean))]


def viewpoint_groups(view_dirs_w: NDArray[np.float64],
                     same_deg: float = SAME_VIEWPOINT_DEG) -> list[NDArray[np.int64]]:
    """The views (unit directions ``view_dirs_w`` (V, 3) from each camera to the object) in groups
    that see it from one viewpoint: each group holds the views within ``same_deg`` of its first
    (in order), so that a slow sweep is cut into pieces rather than chained into one."""
    d = np.asarray(view_dirs_w, dtype=np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    free = np.ones(len(d), dtype=bool)
    cos = np.cos(np.radians(same_deg))
    groups: list[NDArray[np.int64]] = []
    for v in range(len(d)):
        if free[v]:
            members = np.flatnonzero(free & (d @ d[v] >= cos))
            free[members] = False
            groups.append(members.astype(np.int64))
    return groups


def viewpoints_seen(groups: list[NDArray[np.int64]], cluster_grads: NDArray[np.float64]) -> int:
    """How many of ``groups`` hold a view that counts (a non-zero gradient in ``cluster_grads`` (V, n))."""
    used = np.any(cluster_grads != 0.0, axis=1)
    return sum(bool(used[g].any()) for g in groups)


def jackknife(H_inv: NDArray[np.float64], cluster_H: list[tuple[NDArray[np.int64], NDArray[np.float64]]],
              cluster_grads: NDArray[np.float64],
              seen_from: Callable[[NDArray[np.int64], NDArray[np.float64]], NDArray[np.float64]] | None = None,
              groups: list[NDArray[np.int64]] | None = None) -> NDArray[np.float64]:
    """The delete-a-group jackknife covariance, each deletion one Newton step: without the views
    ``G`` of a group the optimum moves by ``d_G = (H - H_G)^-1 g_G``, and the covariance is
    ``(K - 1) / K sum_G (d_G - mean d)(d_G - mean d)^T`` over the ``K`` groups that count (a view
    with a non-zero gradient). ``H_inv`` (n, n) the inverse of the weighted Gauss-Newton matrix
    ``H``; per view, ``cluster_H`` its weighted part of ``H`` as the unknowns it touches (k,) and
    their block (k, k), and ``cluster_grads`` (V, n) its weighted gradient (zero outside those
    unknowns). ``(H - H_G)^-1`` comes from ``H^-1`` by the Woodbury identity, a k x k solve per group.
    ``groups``: the views of one viewpoint each (:func:`viewpoint_groups`); ``None``: a group per view.

    Unlike the sandwich (:func:`sandwich`: ``H^-1`` on both sides), a view that alone fixes a
    direction moves the pose far when left out: with few views, or one that dominates, the
    jackknife is the larger (the small-sample correction the sandwich lacks).

    With a single viewpoint there is nothing to leave out: the spread over the views is taken
    (which sees only what differs between near-identical images) times their number ``V``, the
    variance of ``V`` measurements whose errors are one (the design effect of a cluster of
    ``V`` fully correlated samples). The verdict does not trust it (:data:`MIN_VIEWPOINTS`).

    ``seen_from(G, d_G)``, if given, re-expresses group ``G``'s deletion step (its views' indices)
    before it counts (the joint solve's objects relative to the cameras that still see them)."""
    V = len(cluster_H)
    used = np.any(cluster_grads != 0.0, axis=1)
    if groups is None:
        groups = [np.array([v], dtype=np.int64) for v in range(V)]
    kept = [g[used[g]] for g in groups if used[g].any()]
    if len(kept) < 2:
        views = [np.array([v], dtype=np.int64) for v in np.flatnonzero(used)]
        if len(views) < 2:
            return sandwich(H_inv, cluster_grads)
        return len(views) * _delete_groups(H_inv, cluster_H, cluster_grads, views, seen_from)
    return _delete_groups(H_inv, cluster_H, cluster_grads, kept, seen_from)


def _delete_groups(H_inv: NDArray[np.float64], cluster_H: list[tuple[NDArray[np.int64], NDArray[np.float64]]],
                   cluster_grads: NDArray[np.float64], groups: list[NDArray[np.int64]],
                   seen_from: Callable[[NDArray[np.int64], NDArray[np.float64]], NDArray[np.float64]] | None,
                   ) -> NDArray[np.float64]:
    """:func:`jackknife` over ``groups`` (at least two, each of views that count)."""
    K = len(groups)
    d = np.zeros((K, H_inv.shape[0]))
    for row, members in enumerate(groups):
        idx, S = _merged_block([cluster_H[v] for v in members])
        d[row] = deletion_step(H_inv, idx, S, cluster_grads[members].sum(axis=0)[idx])
        if seen_from is not None:
            d[row] = seen_from(members, d[row])
    d -= d.mean(axis=0)
    return d.T @ d * ((K - 1) / K)


def _merged_block(blocks: list[tuple[NDArray[np.int64], NDArray[np.float64]]],
                  ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Views' parts of ``H`` (unknowns (k,), block (k, k)) summed over the union of their unknowns."""
    if len(blocks) == 1:
        return blocks[0]
    idx = np.unique(np.concatenate([i for i, _ in blocks])).astype(np.int64)
    S = np.zeros((len(idx), len(idx)))
    for i, B in blocks:
        at = np.searchsorted(idx, i)
        S[np.ix_(at, at)] += B
    return idx, S


def deletion_step(H_inv: NDArray[np.float64], idx: NDArray[np.int64], S: NDArray[np.float64],
                  g: NDArray[np.float64]) -> NDArray[np.float64]:
    """The Newton step ``(H - H_d)^-1 g_d`` (n,) of the optimum when a part of the data is deleted:
    its weighted part of ``H`` is the block ``S`` (k, k) over the unknowns ``idx`` (k,), its weighted
    gradient ``g`` (k,) there; ``(H - H_d)^-1`` from ``H_inv`` by the Woodbury identity (a k x k solve)."""
    A, B = H_inv[:, idx], H_inv[np.ix_(idx, idx)]
    inner = np.linalg.lstsq(np.eye(len(idx)) - B @ S, B @ g, rcond=1e-9)[0]
    return A @ (g + S @ inner)


def sandwich(H_inv: NDArray[np.float64], cluster_grads: NDArray[np.float64]) -> NDArray[np.float64]:
    """The cluster-robust covariance ``H^-1 (V / (V - 1) sum_v g_v g_v^T) H^-1`` from the weighted
    gradients ``g_v`` (V, n) of the clusters (views); clusters with a zero gradient do not count."""
    V = int(np.count_nonzero(np.any(cluster_grads != 0.0, axis=1)))
    meat = cluster_grads.T @ cluster_grads * (V / max(V - 1, 1))
    return H_inv @ meat @ H_inv


def _ray_sigmas(cov_m: NDArray[np.float64], d_m: NDArray[np.float64]) -> tuple[float, float]:
    """Position sigma along the unit model-frame direction ``d_m`` and the largest across it (mm)."""
    P = cov_m[:3, :3]
    along = float(np.sqrt(max(d_m @ P @ d_m, 0.0)))
    Q = np.eye(3) - np.outer(d_m, d_m)
    across = float(np.sqrt(max(np.linalg.eigvalsh(Q @ P @ Q).max(), 0.0)))
    return along, across


def compose(parts: CovarianceParts) -> Uncertainty:
    """The uncertainty its named ``parts`` make (:meth:`CovarianceParts.stages`): the covariance and
    what it says (sigmas per model axis, along and across the median view's ray, the weakly
    observed directions; the weakly observed turns are found in the views' spread alone, before the
    outline prior, which inflates every direction it moves and hides the ratio). The one function
    an :class:`Uncertainty` is built by."""
    views, _, _, cov = parts.stages()
    axes = _weak_turn_axes(parts.spread_factor * parts.spread)
    for f in parts.turn_floors:
        if all(abs(float(f.axis_m @ a)) < SAME_AXIS for a in axes):
            axes.append(f.axis_m)
    d_m = None if parts.view_dir_m is None else np.asarray(parts.view_dir_m, dtype=np.float64)
    along, across = _ray_sigmas(cov, d_m) if d_m is not None else (None, None)
    naive = axis_sigmas(parts.naive) if parts.naive is not None else (np.zeros(3), np.zeros(3))
    return Uncertainty(cov, *axis_sigmas(cov), [t for t, _ in _weak(cov)], axes, *naive, parts.bias_shift, d_m,
                       along, across, list(parts.turn_floors), float(parts.spread_factor), parts.disagreement_px,
                       views, parts.viewpoints, parts)


def uncertainty_of(cov_w: NDArray[np.float64], naive_w: NDArray[np.float64], R_wm: NDArray[np.float64],
                   bias_shift_w: NDArray[np.float64] | None = None, view_dir_w: NDArray[np.float64] | None = None,
                   bias_px: float = BOUNDARY_BIAS_PX, spread_factor: float = 1.0,
                   viewpoints: int | None = None) -> Uncertainty:
    """The uncertainty of the world-twist spread ``cov_w`` (6x6, about the object centre) in the
    model's axes (:func:`compose`), scaled by ``spread_factor``, with the prior on a shared outline
    shift (``bias_shift_w``: the world twist per px, ``bias_px``: its sigma); ``naive_w`` is the
    residual-variance estimate, for comparison; ``view_dir_w``: the median view's unit direction
    (world), for the sigmas along and across it."""
    shift = np.zeros(6) if bias_shift_w is None else _into_model(R_wm) @ np.asarray(bias_shift_w, dtype=np.float64)
    d_m = None if view_dir_w is None else R_wm.T @ np.asarray(view_dir_w, dtype=np.float64)
    if d_m is not None:
        d_m = d_m / np.linalg.norm(d_m)
    return compose(CovarianceParts(_to_model(cov_w, R_wm), _to_model(naive_w, R_wm), float(spread_factor),
                                   bias_shift=shift, outline_px=bias_px, view_dir_m=d_m, viewpoints=viewpoints))


def with_outline_disagreement(u: Uncertainty, offset_px: float) -> Uncertainty:
    """``u`` with the measured disagreement about where the outline lies added to the outline
    prior: ``offset_px`` is the shift the masks' outlines share outside the silhouettes of a pose
    fitted with the photos as well (:func:`~autoalign.losses.outline_offset.shared_outline_offset`).
    The masks and the colours then disagree by that much, and the pose lies somewhere between the
    two: which one is right, the fit cannot tell (a mask eroded by 4 px against a photo whose colour
    runs on into a neighbour of the same colour), so the shared shift's variance becomes
    ``BOUNDARY_BIAS_PX^2 + offset_px^2``. NaN (nothing to measure) leaves ``u`` as it is."""
    if not np.isfinite(offset_px):
        return u
    return u.adding(disagreement_px=float(offset_px))


def with_scale_sigma(u: Uncertainty, sigma_relative: float, distance_mm: float) -> Uncertainty:
    """``u`` with the solved scene scale's uncertainty (relative ``sigma_relative``) added as the
    label sees it: a scene grown by ``1 + s`` about any point moves every label in its camera's
    frame by ``s`` times its distance from the camera (``distance_mm``, the median view's), along
    the ray (``u.view_dir_m``); the instance's twist, taken relative to the grown scene, holds none of it."""
    if u.view_dir_m is None or sigma_relative <= 0.0:
        return u
    return u.adding(scale=(float(sigma_relative), float(distance_mm)))


def with_turn_floors(u: Uncertainty, floors: list[TurnFloor]) -> Uncertainty:
    """``u`` with the variance of each floor's turn raised to at least the floor's, along that turn
    alone, in its covariance and its spread (``u.turn_floors`` records them), and each floor's turn
    among the weakly observed ones."""
    if not floors:
        return u
    return u.adding(turn_floors=tuple(u.turn_floors) + tuple(floors))
