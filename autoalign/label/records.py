"""The records of a labelling session: one mask instance and what is known of it
(:class:`LabelledInstance`, as ``session.json`` and the page see it), the verdict a refinement gave
a pose (:class:`Judgement`), and the session's one slow job (:class:`JobState`).

Units and frames: poses are world-from-model 4x4 in mm (the frame of ``scene_camera.json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.engine.uncertainty import Uncertainty, weak_directions
from autoalign.errors import AutoalignError
from autoalign.jobs.report import floats
from autoalign.quality.verdict import Verdict

DECISIONS = ("open", "accepted", "rejected")
"""What the person decided about an instance: nothing yet, its label is right, or it is not wanted."""
WORST_VIEWS = 3
MOVED_BY_HAND = "moved by hand since the last refinement: refine from here to judge it"
SEARCHED = "search"
"""The source of a click's first pose, the orientation search's best, shown while it is refined (not saved)."""
REFINING = "refining"
"""The source of a pose refined so far (a click's, or a refinement's from where a person left it), shown
while the refinement ends and its uncertainty and verdict are worked out (not saved)."""
SHOWN_ONLY = (SEARCHED, REFINING)
"""Sources of the poses shown before a refinement's result: neither saved nor kept for undo."""
BEING_REFINED = "the orientation search's best pose, shown while it is refined and judged"
BEING_JUDGED = "refined so far, shown while the refinement ends and its uncertainty and verdict are worked out"
NEW_PLACEMENT = ("click", SEARCHED)
"""Sources that place an object anew: its decision starts over (a refined pose shown meanwhile keeps
the decision it finds: a click's is open already, a refinement from here keeps the person's)."""
MAX_POSITION_MM = 1e6
"""A pose farther than this (1 km) from the world's origin is refused: nothing a scene shows is there,
and a pose pushed there (a nudge of 1e308 mm) ends in inf and NaN."""
ROTATION_TOL = 1e-4
"""How far a pose's rotation may be from orthonormal (R Rᵀ = I, det R = 1), element-wise (the 3D view's
gizmo sends its turn as a quaternion of limited precision)."""


def pose_problem(T: Any) -> str | None:
    """What is wrong with ``T`` as a world-from-model pose (4x4 rigid, finite, mm, within
    :data:`MAX_POSITION_MM` of the origin), or ``None`` if nothing."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        return "not a 4x4 matrix of numbers"
    if T.shape != (4, 4):
        return f"of shape {T.shape}, not 4x4"
    if not np.isfinite(T).all():
        return "not finite (null, NaN or infinite entries)"
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: refused below, not warned about
        off = np.abs(R @ R.T - np.eye(3)).max()
    if not off <= ROTATION_TOL or np.linalg.det(R) < 0 or np.any(T[3] != [0, 0, 0, 1]):
        return "not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)"
    far = float(np.abs(T[:3, 3]).max())
    if far > MAX_POSITION_MM:
        return f"{far:.3g} mm from the origin along an axis (more than {MAX_POSITION_MM:g})"
    return None


def checked_pose(T: Any, refused: str) -> NDArray[np.float64]:
    """``T`` as a float 4x4 pose; raises :class:`AutoalignError` ``"{refused} that is {problem}"`` if
    :func:`pose_problem` finds one."""
    problem = pose_problem(T)
    if problem is not None:
        raise AutoalignError(f"{refused} that is {problem}")
    return np.asarray(T, dtype=np.float64)


@dataclass
class LabelledInstance:
    """One mask instance (``..._{index:06d}.png``) and what the session knows of it.

    Attributes:
        index: the instance's mask number.
        obj_id: the object the person chose for it (``None``: not placed yet).
        T_wm: world-from-model pose (4x4, mm), ``None`` until placed.
        decision: one of :data:`DECISIONS`.
        symmetric: the person marked the object symmetric (a turn about its axis is not an error).
        source: what set the pose last (``click``, ``refine``, ``nudge``, ``3d``, ``together``, or
            :data:`SEARCHED` while a click is refined).
        verdict: autoalign's ``ok`` / ``check`` / ``failed`` after a refinement, ``None`` once the
            pose was moved by hand since (``reasons`` says so).
        reasons: why the verdict is what it is.
        sigma_mm / sigma_deg: per model axis (x, y, z) from the last refinement, or ``None``.
        weakly_observed: the directions the last refinement could not pin down.
        ious: hard IoU of the silhouette at ``T_wm`` with the instance's mask, by image id.
        pose_revision: counts the pose's changes (the page fetches contours again when it moves).
    """

    index: int
    obj_id: int | None = None
    T_wm: NDArray[np.float64] | None = None
    decision: str = "open"
    symmetric: bool = False
    source: str = ""
    verdict: str | None = None
    reasons: list[str] = field(default_factory=list)
    sigma_mm: list[float] | None = None
    sigma_deg: list[float] | None = None
    weakly_observed: list[str] = field(default_factory=list)
    ious: dict[int, float] = field(default_factory=dict)
    pose_revision: int = 0

    @property
    def placed(self) -> bool:
        return self.T_wm is not None and self.obj_id is not None

    @property
    def worst_views(self) -> list[int]:
        """The image ids of the :data:`WORST_VIEWS` views whose mask the silhouette fits least."""
        return [im for im, _ in sorted(self.ious.items(), key=lambda kv: kv[1])[:WORST_VIEWS]]

    def record(self) -> dict[str, Any]:
        """The instance as JSON (``session.json`` and the page's state)."""
        return {"index": self.index, "obj_id": self.obj_id,
                "T_wm": None if self.T_wm is None else floats(self.T_wm),
                "decision": self.decision, "symmetric": self.symmetric, "source": self.source,
                "verdict": self.verdict, "reasons": list(self.reasons), "sigma_mm": self.sigma_mm,
                "sigma_deg": self.sigma_deg, "weakly_observed": list(self.weakly_observed),
                "ious": {str(k): float(v) for k, v in self.ious.items()},
                "median_iou": float(np.median(list(self.ious.values()))) if self.ious else None,
                "worst_views": self.worst_views, "pose_revision": self.pose_revision}

    @staticmethod
    def from_record(d: dict[str, Any]) -> LabelledInstance:
        """The instance of a :meth:`record` (raises ``KeyError``, ``TypeError`` or ``ValueError`` on a bad
        one: a pose that :func:`pose_problem` finds wrong, an object without a pose or a pose without
        an object, a non-finite IoU)."""
        T = d.get("T_wm")
        if (T is None) != (d.get("obj_id") is None):
            raise ValueError("T_wm is null" if T is None else "T_wm given without obj_id")
        if T is not None and (problem := pose_problem(T)) is not None:
            raise ValueError(f"T_wm is {problem}")
        if not all(isinstance(v, (int, float)) and 0.0 <= v <= 1.0 for v in (d.get("ious") or {}).values()):
            raise ValueError("ious are not numbers from 0 to 1")
        return LabelledInstance(
            int(d["index"]), None if d.get("obj_id") is None else int(d["obj_id"]),
            None if T is None else np.asarray(T, dtype=np.float64).reshape(4, 4), str(d.get("decision", "open")),
            bool(d.get("symmetric", False)), str(d.get("source", "")), d.get("verdict"), list(d.get("reasons", [])),
            d.get("sigma_mm"), d.get("sigma_deg"), list(d.get("weakly_observed", [])),
            {int(k): float(v) for k, v in (d.get("ious") or {}).items()}, int(d.get("pose_revision", 0)))


@dataclass(frozen=True)
class Judgement:
    """What a refinement said of the pose it gave: autoalign's verdict and the pose's uncertainty;
    ``free_axes_m``: the model's axes of continuous symmetry (unit, model frame), whose turns are no
    weakness."""

    verdict: Verdict
    uncertainty: Uncertainty | None
    free_axes_m: tuple[NDArray[np.float64], ...] = ()

    @property
    def weakly_observed(self) -> list[str]:
        """The weakly observed directions of the pose, the free turns left out (none without an uncertainty)."""
        u = self.uncertainty
        return [] if u is None else weak_directions(u.covariance, self.free_axes_m)


FAR_FROM_CLICK_PX = 20.0
"""A placement whose silhouette in the clicked view passes farther than this from the clicked pixel
is shown as far from the click (its verdict ``check``, with the distance): the search found a pose
elsewhere, on another object's mask or on a part the person did not mean."""


def click_distance_px(silhouette: NDArray[np.bool_], u: float, v: float) -> float:
    """Pixels from the OpenCV pixel ``(u, v)`` (centre of column u, row v) to the nearest pixel of
    ``silhouette`` (0 inside it; infinite when it is empty)."""
    if not silhouette.any():
        return float("inf")
    h, w = silhouette.shape
    col, row = int(np.clip(round(u), 0, w - 1)), int(np.clip(round(v), 0, h - 1))
    outside = (~silhouette).astype(np.uint8)
    return float(cv2.distanceTransform(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[row, col])


def far_from_click(judged: Judgement, silhouette: NDArray[np.bool_], image_id: int, u: float, v: float) -> Judgement:
    """``judged`` flagged ``check`` with the distance when the placement's silhouette in the clicked
    view (``image_id``) passes farther than :data:`FAR_FROM_CLICK_PX` from the click ``(u, v)``."""
    d = click_distance_px(silhouette, u, v)
    if d <= FAR_FROM_CLICK_PX:
        return judged
    where = "not in the clicked view" if not np.isfinite(d) else f"{d:.0f} px from the click"
    status = "failed" if judged.verdict.status == "failed" else "check"
    reason = (f"placed far from the click: its outline in image {image_id} is {where} (more than "
              f"{FAR_FROM_CLICK_PX:g} px); check that it is the object you clicked, or click it again nearer its middle")
    return replace(judged, verdict=replace(judged.verdict, status=status, reasons=judged.verdict.reasons + [reason]))


def moved(inst: LabelledInstance, obj_id: int, T_wm: NDArray[np.float64], source: str, ious: dict[int, float],
          judged: Judgement | None) -> LabelledInstance:
    """``inst`` as object ``obj_id`` at ``T_wm`` (4x4, mm), set by ``source``, fitting its masks by
    ``ious``; with ``judged`` (after a refinement) its verdict and uncertainty, else none (moved by
    hand, or one of :data:`SHOWN_ONLY`: not yet refined or judged). A click starts its decision over."""
    u = None if judged is None else judged.uncertainty
    unjudged = {SEARCHED: BEING_REFINED, REFINING: BEING_JUDGED}.get(source, MOVED_BY_HAND)
    return replace(
        inst, obj_id=obj_id, T_wm=T_wm, source=source, ious=ious, pose_revision=inst.pose_revision + 1,
        verdict=None if judged is None else judged.verdict.status,
        reasons=[unjudged] if judged is None else list(judged.verdict.reasons),
        sigma_mm=None if u is None else [float(x) for x in u.sigma_mm],
        sigma_deg=None if u is None else [float(x) for x in u.sigma_deg],
        weakly_observed=[] if judged is None else judged.weakly_observed,
        decision="open" if source in NEW_PLACEMENT else inst.decision)


@dataclass
class JobState:
    """The one slow task the session runs at a time (placing, refining or exporting) and its progress
    (``started`` and ``seconds``: ``time.perf_counter`` seconds)."""

    kind: str = ""
    instance: int | None = None
    running: bool = False
    stage: str = ""
    done: int = 0
    total: int = 0
    error: str | None = None
    started: float = 0.0
    seconds: float = 0.0
    number: int = 0

    def record(self) -> dict[str, Any]:
        """The job as JSON (the page's state)."""
        return {"kind": self.kind, "instance": self.instance, "running": self.running, "stage": self.stage,
                "done": self.done, "total": self.total, "error": self.error, "seconds": self.seconds,
                "number": self.number}
