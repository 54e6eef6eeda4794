"""The verdict's reasons stay short enough to read (issue 43, item 12): a weakly observed pose names
its largest turn and shift, and refine.json keeps every direction (``Uncertainty.weak``)."""

from __future__ import annotations

import numpy as np

from autoalign.engine.uncertainty import uncertainty_of
from autoalign.quality.verdict import judge


def test_a_weak_pose_names_its_largest_turn_and_shift_only() -> None:
    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    cov = np.zeros((6, 6))  # every direction weak, none along a model axis: six unit vectors to name
    cov[:3, :3] = Q @ np.diag([9.0, 4.0, 2.5]) @ Q.T
    cov[3:, 3:] = Q @ np.diag([np.radians(6.0), np.radians(3.0), np.radians(1.5)]) ** 2 @ Q.T
    u = uncertainty_of(cov, cov, np.eye(3))
    assert len(u.weak) == 6
    verdict = judge(np.full(10, 0.95), np.ones(10), list(range(10)), uncertainty=u)
    reason = next(r for r in verdict.reasons if r.startswith("weakly observed"))
    assert u.weak[0] in reason and next(w for w in u.weak if w.startswith("shift")) in reason
    assert "4 more in refine.json" in reason and len(reason) < 220, reason
