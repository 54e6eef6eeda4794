"""Multi-view silhouette losses in least-squares form, and robust per-view weights.

Every loss returns :class:`ViewTerms`: per view ``i`` the value ``loss_i = 0.5 * |rho_i|^2`` of a
residual vector ``rho_i``, its gradient ``J_i^T rho_i`` and the Gauss-Newton matrix ``J_i^T J_i``
with respect to the pose twist ``(v [mm], w [rad])``. Optimisers combine them with per-view
weights, so second-order and first-order methods see the same objective. Beside them, how masks
and silhouettes compare: IoU (``overlap``) and the offset of a mask's outline (``outline_offset``).

May import: ``autoalign.geometry``, ``autoalign.rasterizers``, ``autoalign.io``, ``autoalign.runtime``,
``autoalign.errors``.
"""

from autoalign.losses.robust import (
           cauchy_weights,
           implausible_views,
           robust_view_weights,
)
from autoalign.losses.silhouette import (
           LOSSES,
           ViewTerms,
           bce,
           dice,
           iou,
           l2,
           targets_in_crops,
)

__all__ = ["LOSSES", "ViewTerms", "bce", "dice", "iou", "l2", "targets_in_crops", "cauchy_weights", "implausible_views",
           "robust_view_weights"]
