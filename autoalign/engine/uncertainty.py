"""How well the silhouettes pin a refined pose down: its 6x6 covariance, sigma per model axis,
and the directions the views barely see.

At the optimum of the weighted least-squares silhouette loss, with the Gauss-Newton matrix ``H``
(the sum over views of ``w_v J_v^T J_v / area_v``) and per-view gradients ``g_v = w_v J_v^T r_v``:

* ``naive``: ``H^-1 * 2 loss / (n - 6)``, the textbook residual-variance estimate, with ``n`` the
  pixels whose silhouette value depends on the pose (the band). It takes pixels as independent,
  but a mask's boundary error runs along the outline over many pixels, so it is far too small;
* ``sandwich`` (reported): ``H^-1 (V / (V - 1) sum_v g_v g_v^T) H^-1``, the cluster-robust
  estimate with one cluster per view: whatever the correlation of a view's pixels, the views'
  errors are taken as independent. On synthetic scenes with noisy mask outlines it covers the
  true error as a Gaussian would (README, "Uncertainty"; ``tests/test_uncertainty.py``).

The twist is ``(v [mm], w [rad])`` in the world frame about the object centre; sigmas are
reported about and along the model's own axes (its x, y, z), since those name what a person sees
(a bottle's roll is a turn about its model axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

WEAK_DEG = 1.0
"""A turn whose sigma exceeds this many degrees is named as weakly observed ..."""
WEAK_MM = 1.0
"""... and so is a shift whose sigma exceeds this many millimetres ..."""
WEAK_RATIO = 5.0
"""... or either whose sigma is this many times that of the best observed direction of its kind
(a flashlight's roll about its axis: 0.3-0.4 degrees against 0.03 about the other axes)."""
_AXES = "xyz"


@dataclass
class Uncertainty:
    """The covariance of a pose and what it says.

    Attributes:
        covariance: (6, 6) of the twist ``(v [mm], w [rad])`` in the model's axes, about its centre.
        sigma_mm: (3,) standard deviation of the position along the model's x, y, z (mm).
        sigma_deg: (3,) standard deviation of the orientation about the model's x, y, z (degrees).
        weak: the weakly observed directions, e.g. ``"turn about model z: 12.3 deg"``.
        weak_turn_axes: the unit model-frame axes of the weakly observed turns, in that order.
        naive_sigma_mm / naive_sigma_deg: the same from the residual-variance estimate (for comparison).
    """

    covariance: NDArray[np.float64]
    sigma_mm: NDArray[np.float64]
    sigma_deg: NDArray[np.float64]
    weak: list[str] = field(default_factory=list)
    weak_turn_axes: list[NDArray[np.float64]] = field(default_factory=list)
    naive_sigma_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    naive_sigma_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))


def _to_model(cov_w: NDArray[np.float64], R_wm: NDArray[np.float64]) -> NDArray[np.float64]:
    """A world-frame twist covariance in the model's axes (``v_m = R^T v``, ``w_m = R^T w``)."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R_wm.T
    return A @ cov_w @ A.T


def _sigmas(cov: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return d[:3], np.degrees(d[3:])


def _direction_name(u: NDArray[np.float64]) -> str:
    """A unit model-frame direction by its nearest model axis (``model z``) or its components."""
    k = int(np.argmax(np.abs(u)))
    if abs(u[k]) > 0.9:
        return f"model {_AXES[k]}"
    return "model (" + ", ".join(f"{x:+.2f}" for x in u * np.sign(u[k])) + ")"


def _weak(cov_m: NDArray[np.float64], weak_mm: float = WEAK_MM, weak_deg: float = WEAK_DEG,
          ratio: float = WEAK_RATIO) -> list[tuple[str, NDArray[np.float64]]]:
    """The principal directions of the position and orientation blocks whose sigma is large, in
    absolute terms or against the best observed direction of the block, largest first (turns
    first), each named and with its unit model-frame vector."""
    out = []
    for block, unit, limit, what in ((slice(3, 6), np.degrees(1.0), weak_deg, "turn about"),
                                     (slice(0, 3), 1.0, weak_mm, "shift along")):
        vals, vecs = np.linalg.eigh(cov_m[block, block])
        best = float(np.sqrt(max(vals[0], 0.0))) * unit
        for lam, u in sorted(zip(vals, vecs.T), key=lambda x: -x[0]):
            s = float(np.sqrt(max(lam, 0.0))) * unit
            if s > limit or s > ratio * best:
                out.append((f"{what} {_direction_name(u)}: {s:.2g} {'deg' if what == 'turn about' else 'mm'}", u))
    return out


def pose_uncertainty(H: NDArray[np.float64], view_grads: NDArray[np.float64], weights: NDArray[np.float64],
                     value: float, n_band: int, R_wm: NDArray[np.float64]) -> Uncertainty:
    """The uncertainty of a converged pose (see the module doc).

    Args:
        H: (6, 6) weighted Gauss-Newton matrix at the pose (world twist).
        view_grads: (V, 6) unweighted per-view gradients ``J_v^T r_v``.
        weights: (V,) the view weights of ``H``.
        value: the weighted loss ``sum_v w_v loss_v``.
        n_band: pixels whose value depends on the pose.
        R_wm: the pose's rotation (world from model).
    """
    H_inv = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    g = view_grads * np.asarray(weights, dtype=np.float64)[:, None]
    return uncertainty_of(sandwich(H_inv, g), H_inv * (2.0 * value / max(n_band - 6, 1)), R_wm)


def sandwich(H_inv: NDArray[np.float64], cluster_grads: NDArray[np.float64]) -> NDArray[np.float64]:
    """The cluster-robust covariance ``H^-1 (V / (V - 1) sum_v g_v g_v^T) H^-1`` from the weighted
    gradients ``g_v`` (V, n) of the clusters (views); clusters with a zero gradient do not count."""
    V = int(np.count_nonzero(np.any(cluster_grads != 0.0, axis=1)))
    meat = cluster_grads.T @ cluster_grads * (V / max(V - 1, 1))
    return H_inv @ meat @ H_inv


def uncertainty_of(cov_w: NDArray[np.float64], naive_w: NDArray[np.float64], R_wm: NDArray[np.float64]) -> Uncertainty:
    """What the world-twist covariance ``cov_w`` (6x6, about the object centre) says, in the
    model's axes; ``naive_w`` is the residual-variance estimate, for comparison."""
    cov = _to_model(cov_w, R_wm)
    s_mm, s_deg = _sigmas(cov)
    n_mm, n_deg = _sigmas(_to_model(naive_w, R_wm))
    weak = _weak(cov)
    return Uncertainty(cov, s_mm, s_deg, [t for t, _ in weak], [u for t, u in weak if t.startswith("turn")], n_mm, n_deg)
