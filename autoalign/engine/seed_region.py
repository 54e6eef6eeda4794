"""A seed is evidence: the region of poses within a given seed's stated uncertainty.

A person who gives a coarse pose (``--init``) says the object is within some millimetres and
degrees of it (:data:`SEED_RADIUS`, ``--seed-radius``). When the masks pull the pose farther, the
engine also finds the best pose *inside* that region: :class:`SeedRegion` adds a penalty that is
zero inside and grows steeply outside (two residuals, the centre's distance and the turn's angle
beyond the radius, in units of the radius), so Levenberg-Marquardt stops at the region's best fit.
The far pose is returned only when it fits clearly better (:data:`CLEARLY_BETTER`); either way
the result is flagged (:mod:`autoalign.quality.verdict`).

Twists are ``(v [mm], w [rad])`` in the world frame about the object centre, as the engine's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.se3 import Symmetries, closest_symmetric_pose, so3_log, transform_points
from autoalign.losses.term import Fragments, PoseTerms, TermValues

SEED_RADIUS = (25.0, 30.0)
"""The stated uncertainty of a given seed pose (mm at the model's centre, degrees) unless the person
gives another (``refine --seed-radius``): a coarse pose as the studies give it (10 mm / 15 deg off)
with a margin. A pose 256 mm away (the real driller of issue 29, on masks that miss its handle) is
the masks pulling it elsewhere."""
CLEARLY_BETTER = 0.5
"""A pose beyond the seed's radius is returned only when its loss (mean weighted, full resolution)
is at most this fraction of the best pose inside the radius: half the misfit. Otherwise the pose
inside is returned, flagged with the distance to the far one and how much better it fits."""
STIFFNESS = 1e3
"""Per view, the penalty's weight: at 10% beyond the radius it costs 5 per view, where a view's whole
mask loss is at most 1 (area-normalised) and below 0.05 at a good fit."""


@dataclass(frozen=True)
class SeedRegion:
    """The poses within ``radius`` (mm at the centre, degrees) of ``T_seed`` (world from model),
    modulo the model's ``symmetries``; ``centre_m`` the model's centre (mm), ``weight`` the penalty's
    scale (``STIFFNESS`` x views)."""

    T_seed: NDArray[np.float64]
    centre_m: NDArray[np.float64]
    radius: tuple[float, float]
    weight: float
    symmetries: Symmetries = Symmetries()
    name = "seed"

    def residuals(self, fragments: Fragments) -> TermValues:
        """The region's penalty as an evidence term on the pose alone."""
        return TermValues(self.name, pose=self.term(fragments.T_wm))

    def term(self, T_wm: NDArray[np.float64]) -> PoseTerms:
        """The penalty at ``T_wm`` and its derivatives (zero inside the region), the move measured to
        the symmetric equivalent of ``T_wm`` nearest the seed (a free turn about an axis of
        continuous symmetry costs nothing; at that nearest equivalent the turn's derivative is the
        plain one's, the symmetry's angle being at its optimum)."""
        if self.symmetries:
            T_wm = closest_symmetric_pose(self.T_seed, T_wm, self.symmetries.discrete, self.symmetries.continuous)
        grad, gn, value = np.zeros(6), np.zeros((6, 6)), 0.0
        s = float(np.sqrt(self.weight))
        d = transform_points(T_wm, self.centre_m[None])[0] - transform_points(self.T_seed, self.centre_m[None])[0]
        dist = float(np.linalg.norm(d))
        if dist > self.radius[0]:
            e = s * (dist - self.radius[0]) / self.radius[0]
            J = np.zeros(6)
            J[:3] = s / self.radius[0] * d / dist  # the centre moves with v alone (twist about the centre)
            value, grad, gn = value + 0.5 * e * e, grad + J * e, gn + np.outer(J, J)
        w = so3_log(T_wm[:3, :3] @ self.T_seed[:3, :3].T)  # world-frame turn from the seed
        angle, limit = float(np.linalg.norm(w)), np.radians(self.radius[1])
        if angle > limit:
            e = s * (angle - limit) / limit
            J = np.zeros(6)
            J[3:] = s / limit * w / angle  # d angle / d w: the turn's own axis (exp(dw) R, small dw)
            value, grad, gn = value + 0.5 * e * e, grad + J * e, gn + np.outer(J, J)
        return PoseTerms(value, grad, gn)


@dataclass
class SeedHold:
    """What happened to a result that ended beyond its seed's radius.

    Attributes:
        far_T_wm: the pose the masks pulled it to (world from model, mm).
        far_move: that pose's distance from the seed (mm at the centre, degrees).
        far_loss / near_loss: mean weighted loss at full resolution of the far pose and of the best
            pose within the radius.
        kept_far: whether the far pose was returned (it fit clearly better); else the near one was.
    """

    far_T_wm: NDArray[np.float64]
    far_move: tuple[float, float]
    far_loss: float
    near_loss: float
    kept_far: bool

    def to_json(self) -> dict:
        return {"far_T_wm": self.far_T_wm.tolist(), "far_moved_from_seed_mm_deg": list(self.far_move),
                "far_loss": self.far_loss, "near_loss": self.near_loss,
                "returned": "far" if self.kept_far else "within the seed's radius",
                "rule": f"the far pose only when its loss is at most {CLEARLY_BETTER:g} x the near one's"}
