"""Resting contact: an object standing on the table touches its plane.

Masks fix a pose worst along the viewing rays, and glass, whose depth is no evidence, has nothing
else to fix it there; an object that rests on the table has its lowest point on the table's plane,
which fixes that direction from one viewpoint. :class:`RestingContact` is that statement as an
evidence term on the pose alone: one residual, the object's height above the plane (mm; below it:
negative) in units of :data:`CONTACT_SIGMA_MM`, the lowest point a soft minimum over the model's
hull vertices (their heights' mean under softmax weights of temperature :data:`SOFT_MIN_MM`: a flat
base's many lowest vertices give exactly their height), so that the residual is smooth as the
object tilts from one rim point to the next. An object at rest also stands on one of its stable
faces (:attr:`~autoalign.geometry.mesh.Mesh.resting_downs`, trimesh's stable poses): three more
residuals, the nearest stable face's downward direction less the plane's downward normal, in units
of :data:`TILT_SIGMA_DEG` (masks seen from one side trade a tilt against a slide along the rays,
and a lowest point on the plane alone lets an object stand on one rim point).

Twists are ``(v [mm], w [rad])`` in the world frame about the object centre, as the engine's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.se3 import hat3
from autoalign.losses.term import Fragments, PoseTerms, Stance, TermEvidence, TermValues

CONTACT_SIGMA_MM = 1.0
"""How far a resting object's lowest point may lie from the plane (mm, one sigma): a scanned mesh's
base and a table's flatness, each about a millimetre."""
CONTACT_STIFFNESS = 1.0
"""Per view, the term's weight: a resting object 1 mm off the plane costs 0.5 per view, where a
view's whole mask loss is at most 1, and a bottle's masks eroded by 3 px and seen from one side
slid it 26 mm along the rays for 0.03 of loss per view. Along the plane's normal the contact
outweighs the masks; across it, it says nothing."""
CONTACT_IOU_DROP = 0.1
"""A contact is set aside when the masks fit the pose on the plane worse than this in median IoU.
Measured (``tests/test_contact.py``, ``glass_photos``): 40 standing glass instances held to the
table, at most 0.003; a bottle seen from one side with masks eroded by 3 px, 0.055 (the masks slid
it 26 mm along the rays); a box standing on another, 0.80; 16 objects lying in no stable pose forced
onto a stable face, 0.02-0.69."""
CONTACT_MAX_LEAN_DEG = 10.0
"""A contact is also set aside when, at the pose the other evidence gives, the object leans more
than this from every one of its stable faces: no object at rest does, so it leans on something
(measured in ``glass_photos``: 40 standing glass instances 0.1-7.9 deg; 16 objects lying in no
stable pose 14-79 deg, four of them losing less than 0.1 of IoU when forced onto a face)."""
OFFERED_GAP_MM = 5.0
"""An object not declared resting but offered the table (its depth is seen through: glass) is taken
as resting on it only when, at the pose the other evidence gives, its lowest point lies within this
of the plane (mm, either side) and it stands within :data:`CONTACT_MAX_LEAN_DEG` of a stable face:
the evidence agrees that it stands there, and the contact fixes what the masks fix worst. Sunk
deeper than this below that plane, which its own depth measures through it, it contradicts the
depth: no object stands inside the table (an upside-down or slid glass whose masks fit it)."""
TILT_SIGMA_DEG = 2.0
"""How far a resting object may lean from its stable face (degrees, one sigma): a scanned base
that is not quite flat, a table not quite level."""
SOFT_MIN_MM = 0.5
"""The soft minimum's temperature (mm): vertices more than a few of these above the lowest count
for nothing."""


@dataclass(frozen=True)
class TablePlane:
    """The plane objects rest on (world frame, mm): its unit ``normal`` pointing to the side the
    objects stand on, and a ``point`` on it."""

    normal: NDArray[np.float64]
    point: NDArray[np.float64]

    @staticmethod
    def of(normal: Any, point: Any) -> "TablePlane":
        """A plane through ``point`` with ``normal`` (any length but zero)."""
        n = np.asarray(normal, dtype=np.float64)
        return TablePlane(n / np.linalg.norm(n), np.asarray(point, dtype=np.float64))

    def heights(self, X_w: NDArray[np.float64]) -> NDArray[np.float64]:
        """Signed heights (mm) of world points (N, 3) above the plane."""
        return (np.asarray(X_w, dtype=np.float64) - self.point) @ self.normal

    def record(self) -> dict[str, list[float]]:
        return {"normal": self.normal.tolist(), "point_mm": self.point.tolist()}


@dataclass(frozen=True)
class RestingContact:
    """The object with hull ``vertices_m`` (model frame, mm) rests on ``plane``, on one of its stable
    faces ``downs_m`` (unit downward directions, model frame; none: any tilt); ``centre_m`` the point
    its twists turn about, ``weight`` the term's scale (:data:`CONTACT_STIFFNESS` x views)."""

    plane: TablePlane
    vertices_m: NDArray[np.float64]
    centre_m: NDArray[np.float64]
    weight: float
    downs_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    name = "contact"

    def residuals(self, fragments: Fragments) -> TermValues:
        """The contact as an evidence term on the pose alone."""
        return TermValues(self.name, pose=self.term(fragments.T_wm))

    def _lowest(self, T_wm: NDArray[np.float64]) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        """The soft-minimum height (mm), its derivatives by each vertex's height, and the vertices (world)."""
        X = self.vertices_m @ T_wm[:3, :3].T + T_wm[:3, 3]
        h = self.plane.heights(X)
        p = np.exp(-(h - h.min()) / SOFT_MIN_MM)
        p /= p.sum()
        low = float(p @ h)
        return low, p * (1.0 - (h - low) / SOFT_MIN_MM), X

    def gap_mm(self, T_wm: NDArray[np.float64]) -> float:
        """The object's lowest point above the plane at ``T_wm`` (mm; negative: below it), the
        soft minimum the term uses."""
        return self._lowest(np.asarray(T_wm, dtype=np.float64))[0]

    def tilt_deg(self, T_wm: NDArray[np.float64]) -> float:
        """The angle (degrees) between the nearest stable face's downward direction at ``T_wm`` and
        the plane's downward normal (NaN without stable faces)."""
        if len(self.downs_m) == 0:
            return float("nan")
        down = self._down(np.asarray(T_wm, dtype=np.float64))
        return float(np.degrees(np.arccos(np.clip(-down @ self.plane.normal, -1.0, 1.0))))

    def _down(self, T_wm: NDArray[np.float64]) -> NDArray[np.float64]:
        """The stable face's downward direction (world) nearest the plane's downward normal."""
        downs = self.downs_m @ T_wm[:3, :3].T
        return downs[int(np.argmax(-downs @ self.plane.normal))]

    def term(self, T_wm: NDArray[np.float64]) -> PoseTerms:
        """``0.5 * weight * |r|^2`` and its derivatives with respect to the twist, ``r`` the gap over
        its sigma and the tilt residual over its. A vertex at ``X`` moves by ``v + w x (X - c)``, so
        its height by ``n . v + w . ((X - c) x n)``; a direction ``d`` turns by ``w x d``."""
        T_wm = np.asarray(T_wm, dtype=np.float64)
        gap, dgap, X = self._lowest(T_wm)
        c = T_wm[:3, :3] @ self.centre_m + T_wm[:3, 3]
        n = self.plane.normal
        s = np.sqrt(self.weight)
        J = [np.concatenate([dgap.sum() * n, dgap @ np.cross(X - c, n)]) * (s / CONTACT_SIGMA_MM)]
        r = [s * gap / CONTACT_SIGMA_MM]
        if len(self.downs_m):
            d = self._down(T_wm)
            k = s / np.radians(TILT_SIGMA_DEG)
            r += list(k * (d + n))
            J += list(np.hstack([np.zeros((3, 3)), -k * hat3(d)]))
        Jm, e = np.array(J), np.array(r)
        return PoseTerms(0.5 * float(e @ e), Jm.T @ e, Jm.T @ Jm)


@dataclass
class Contact:
    """What the resting contact did to a result: the plane, the lowest point's height above it
    (mm) and the lean from the nearest stable face (degrees) at the pose the other evidence gave
    and at the result, the masks' median IoU at both, and whether the contact was kept: it is not
    when the masks fit the pose on the plane clearly worse (median IoU lower by more than
    :data:`CONTACT_IOU_DROP`), which says that the object stands on something else, or when at the
    masks' pose it leans more than :data:`CONTACT_MAX_LEAN_DEG` from every stable face. ``declared``:
    by ``--resting``; else offered to glass (:data:`OFFERED_GAP_MM`), and not kept when sunk in the
    table (:attr:`in_table`). ``stood_up_deg``: stood on another stable face instead
    (:mod:`autoalign.engine.stand_up`: sunk, or where the orientation was searched, the standing the
    masks fit best), the turn that took (degrees, modulo the symmetries); ``None`` otherwise.
    ``nearest``: sunk from a given pose with the masks withheld, stood on its nearest stable face."""

    plane: TablePlane
    gap_before_mm: float
    gap_after_mm: float
    tilt_before_deg: float
    tilt_after_deg: float
    iou_before: float
    iou_after: float
    declared: bool = True
    stood_up_deg: float | None = None
    nearest: bool = False
    name = "contact"

    @property
    def fits_worse(self) -> bool:
        """On the plane the masks fit clearly worse."""
        return self.iou_after < self.iou_before - CONTACT_IOU_DROP

    @property
    def leans(self) -> bool:
        """At the masks' pose it leans beyond any stable face (False without stable faces)."""
        return bool(self.tilt_before_deg > CONTACT_MAX_LEAN_DEG) and self.stood_up_deg is None

    @property
    def in_table(self) -> bool:
        """Offered, at the masks' pose sunk below the plane by more than :data:`OFFERED_GAP_MM`, and
        not stood up on a face where the masks fit as well."""
        return (not self.declared and self.gap_before_mm < -OFFERED_GAP_MM
                and (self.stood_up_deg is None or self.fits_worse))

    @property
    def kept(self) -> bool:
        return not (self.fits_worse or self.leans or self.in_table)

    def record(self) -> dict[str, Any]:
        return {"plane": self.plane.record(), "gap_before_mm": self.gap_before_mm, "gap_after_mm": self.gap_after_mm,
                "tilt_before_deg": self.tilt_before_deg, "tilt_after_deg": self.tilt_after_deg,
                "median_iou_before": self.iou_before, "median_iou_on_plane": self.iou_after, "kept": self.kept,
                "declared": self.declared, "stood_up_deg": self.stood_up_deg, "stood_on_nearest_face": self.nearest,
                "rule": ("" if self.declared else
                         f"offered (the depth sees through it) when its lowest point lies within {OFFERED_GAP_MM:g} mm "
                         "of the plane the depth shows; sunk deeper below it, the depth contradicts the pose, "
                         "and where the orientation was searched it is stood on its stable faces instead (from a "
                         "given pose with the masks withheld, on its nearest); ")
                        + f"kept unless the masks fit the pose on the plane worse by more than {CONTACT_IOU_DROP:g} "
                        f"in median IoU, or it leans more than {CONTACT_MAX_LEAN_DEG:g} deg from every stable face "
                        "at the masks' pose"}

    def evidence(self) -> TermEvidence:
        """A kept contact supports the pose along the plane's normal; one set aside is said, never
        held against the pose (the object may stand on another)."""
        if self.kept and self.stood_up_deg is not None and self.gap_before_mm >= -OFFERED_GAP_MM:
            return TermEvidence(self.name, Stance.NEUTRAL, 1.0,
                                f"stood on another face: the masks cannot tell its standings apart well, and on the "
                                f"table they fit it best turned {self.stood_up_deg:.0f} deg from the searched "
                                f"orientation (median IoU {self.iou_after:.2f} against {self.iou_before:.2f}); check "
                                "which way up it stands in overlay.png")
        if self.kept and self.stood_up_deg is not None:
            how = ("leaning or sunk), so it was stood on its nearest stable face" if self.nearest else
                   f"upside down or on its side), so it was turned {self.stood_up_deg:.0f} deg onto the stable "
                   "face the masks fit best")
            return TermEvidence(self.name, Stance.NEUTRAL, 1.0,
                                f"stood up on the table its depth shows: where the masks put it, its lowest point lay "
                                f"{-self.gap_before_mm:.1f} mm inside that table ({how} "
                                f"(median IoU {self.iou_after:.2f} against {self.iou_before:.2f})")
        if self.kept:
            why = "" if self.declared else " (its depth sees through it, and it stands on the plane the depth shows)"
            return TermEvidence(self.name, Stance.NEUTRAL, 1.0,
                                f"rests on the table{why}: its lowest point {self.gap_before_mm:+.1f} mm from the plane "
                                f"and {self.tilt_before_deg:.1f} deg from standing at the masks' pose, "
                                f"{self.gap_after_mm:+.1f} mm and {self.tilt_after_deg:.1f} deg at the result")
        if self.in_table:
            tried = ("" if self.stood_up_deg is None else
                     f" (stood on its {'nearest' if self.nearest else 'best'} stable face the masks fit worse: "
                     f"median IoU {self.iou_after:.2f} against {self.iou_before:.2f})")
            return TermEvidence(self.name, Stance.CONTRADICTS, 0.0,
                                f"its lowest point lies {-self.gap_before_mm:.1f} mm below the table its depth shows "
                                "through it: nothing stands inside the table, so the pose is wrong (upside down, or "
                                f"slid along the rays) unless the table has a hollow there{tried}; look at it in "
                                "overlay.png")
        why = (f"it leans {self.tilt_before_deg:.0f} deg from every face it could rest on" if self.leans else
               f"on the plane the masks fit worse (median IoU {self.iou_after:.2f} against {self.iou_before:.2f})")
        return TermEvidence(self.name, Stance.NO_EVIDENCE, 0.0,
                            f"{'declared resting' if self.declared else 'offered the table'}, but not resting on the "
                            f"table: {why}; its lowest point is {self.gap_before_mm:+.1f} mm from the plane")
