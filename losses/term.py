"""Evidence terms: everything a pose is compared with, in one shape.

One render of the object at a pose (:class:`Fragments`) feeds every term, as a rasterizer's
fragments feed any of PyTorch3D's shaders. A term (:class:`Term`) reads the fragments, never the
scene folder, and gives its residuals in least-squares form, as ICG's modalities give their
gradient and Hessian to one optimiser: per view (:class:`~autoalign.losses.silhouette.ViewTerms`,
weighed by the views' robust weights) or on the pose alone (:class:`PoseTerms`), with what it
measured. :func:`evaluate_terms` runs them and :func:`sum_terms` is the one place they are summed.

A term may find pixels that something no model holds hides from the camera (the depth term's
unmodelled occluders, :attr:`TermValues.hidden`): the terms after it see the fragments without them.
A term may hold state learned at a pose (the region term's colour models,
:meth:`~autoalign.losses.region_term.RegionTerm.learned_at`), fixed while a pose is descended on it
and learned again at the pose reached between rounds (:mod:`autoalign.engine.photo_evidence`).
Twists are ``(v [mm], w [rad])`` in the world frame about ``Fragments.centre_w``.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.losses.silhouette import ViewTerms, targets_in_crops
from autoalign.rasterizers.soft_silhouette import Silhouettes, SoftSilhouetteRasterizer


@dataclass(frozen=True)
class LevelViews:
    """The views of one resolution level: cameras, area-resampled targets in [0, 1], per-view
    target sums, and the pixels not compared (``None``: all are), all at that resolution; and the
    same views' full-resolution cameras, targets, measured depth (mm, 0 = none; ``None``: no depth) and
    photos (BGR uint8; ``None``: none read by a term)."""

    cameras: list[Camera]
    targets: list[NDArray[np.float32]]
    totals: NDArray[np.float64]
    ignore: list[NDArray[np.bool_]] | None
    full_cameras: list[Camera]
    full_targets: list[NDArray[np.float32]]
    depths: list[NDArray[np.float32]] | None = None
    photos: list[NDArray[np.uint8]] | None = None

    @functools.cached_property
    def hard_totals(self) -> NDArray[np.int64]:
        """Per view, the target's pixels above a half (a hard mask's area), counted once."""
        return np.array([np.count_nonzero(t > 0.5) for t in self.targets], dtype=np.int64)


@dataclass(frozen=True)
class Fragments:
    """One render of one object at one pose and one resolution level: what every term reads.

    Attributes:
        T_wm: world-from-model pose (4x4, mm).
        centre_w: the point twists turn about (world frame, mm).
        scale: the level's resolution relative to the input.
        views: the level's views (:class:`LevelViews`).
        silhouettes: the soft silhouettes in those views, the pixels not compared already off.
        rasterizer: what rendered them, at the level's detail (its mesh and ray caster).
    """

    T_wm: NDArray[np.float64]
    centre_w: NDArray[np.float64]
    scale: float
    views: LevelViews
    silhouettes: Silhouettes
    rasterizer: SoftSilhouetteRasterizer

    def hiding(self, hidden: list[NDArray[np.bool_]]) -> "Fragments":
        """These fragments with the pixels ``hidden`` (one image per view, at the level's resolution) off."""
        return replace(self, silhouettes=self.silhouettes.without(targets_in_crops(hidden, self.silhouettes) > 0.5))


@dataclass(frozen=True)
class PoseTerms:
    """A term on the pose alone: ``value`` (0.5 * its squared residuals), ``grad`` (6,) and ``gn`` (6, 6)
    with respect to the twist."""

    value: float
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]


@dataclass(frozen=True)
class TermValues:
    """What one term gave at one render.

    Attributes:
        name: the term's name (``mask``, ``depth``, ``seed``), as reports write it.
        views: its per-view values (``iou`` is ``None`` for a term that measures no overlap), or ``None``.
        pose: its value on the pose alone, or ``None``.
        hidden: per view, the pixels (level resolution) it found hidden by something unmodelled.
        measured: the term's own record of what it measured (e.g. :class:`~autoalign.losses.depth.DepthTerms`).
    """

    name: str
    views: ViewTerms | None = None
    pose: PoseTerms | None = None
    hidden: list[NDArray[np.bool_]] | None = None
    measured: Measured | None = None


class Stance(enum.Enum):
    """What a kind of evidence says of a pose, on its own."""

    SUPPORTS = "supports"  # it agrees: masks that cover the silhouette loosely are no reason to check
    NEUTRAL = "neutral"  # it neither confirms nor contradicts the pose
    CONTRADICTS = "contradicts"  # it disagrees: the pose fails (a measurement) or is to be checked (an appearance)
    NO_EVIDENCE = "no evidence"  # it measured nothing about this object (depth through glass): said, never held against it


@dataclass(frozen=True)
class TermEvidence:
    """What one kind of evidence saw at the result, in the terms the verdict and the report read
    (:func:`~autoalign.quality.verdict.judge`): no rule in the verdict names a kind.

    Attributes:
        name: the term's name (``depth``, ``photo``).
        stance: what it says of the pose (:class:`Stance`).
        agreement: its median measure of agreement over the views that measured it (the depth: the
            share of samples within its noise; the photo: the edge contrast across the outline).
        reason: the stance in words, as a verdict's reason gives it.
        fails: whether its contradiction fails the pose (a measurement that disagrees) rather than
            asks for a look (an appearance that may deceive).
        sees_outline: it sees the object's outline itself (the photo): masks that do not match a pose
            it does not contradict ask for a look, not a failure.
        reliability: per view its own measure of agreement (NaN: it measured nothing there).
    """

    name: str
    stance: Stance
    agreement: float
    reason: str
    fails: bool = False
    sees_outline: bool = False
    reliability: NDArray[np.float64] | None = None

    def record(self) -> dict[str, Any]:
        """As ``refine.json`` writes it."""
        return {"term": self.name, "stance": self.stance.value, "agreement": self.agreement, "reason": self.reason}


class Measured(Protocol):
    """What one kind of evidence measured at a result: its ``name`` (the key ``refine.json`` writes
    its record under), its stance on the pose, and its record."""

    name: str

    def evidence(self) -> TermEvidence | None:
        """Its stance on the pose (``None``: it measured too little to have one)."""
        ...

    def record(self) -> dict[str, Any]:
        """Per view what it measured, as ``refine.json`` writes it."""
        ...


class Term(Protocol):
    """One kind of evidence: its ``name`` and its residuals at one render."""

    name: str

    def residuals(self, fragments: Fragments) -> TermValues:
        """The term at the fragments' pose: values, gradients and Gauss-Newton blocks."""
        ...


class PoseTerm(Protocol):
    """A term on the pose alone, which needs no render: its value and derivatives at a pose (the
    joint stage holds instances with these)."""

    name: str

    def term(self, T_wm: NDArray[np.float64]) -> PoseTerms:
        """The term at world-from-model ``T_wm`` (4x4, mm)."""
        ...


def evaluate_terms(terms: tuple[Term, ...], fragments: Fragments) -> tuple[Fragments, tuple[TermValues, ...]]:
    """Every term at one render, in order; the fragments the last term saw (hidden pixels off) and the values."""
    values = []
    for term in terms:
        v = term.residuals(fragments)
        if v.hidden is not None:
            fragments = fragments.hiding(v.hidden)
        values.append(v)
    return fragments, tuple(values)


def sum_terms(values: tuple[TermValues, ...]) -> tuple[ViewTerms, PoseTerms | None]:
    """The terms summed: per view (the IoU is the overlap term's), and on the pose."""
    per_view = [v.views for v in values if v.views is not None]
    if not per_view:
        raise ValueError("no term compares the views")
    loss, grad, gn = per_view[0].loss, per_view[0].grad, per_view[0].gn
    for t in per_view[1:]:
        loss, grad, gn = loss + t.loss, grad + t.grad, gn + t.gn
    iou = next((t.iou for t in per_view if t.iou is not None), None)
    if iou is None:
        raise ValueError("no term measures the overlap the view weights read")
    on_pose = [v.pose for v in values if v.pose is not None]
    pose = None
    for p in on_pose:
        pose = p if pose is None else PoseTerms(pose.value + p.value, pose.grad + p.grad, pose.gn + p.gn)
    return ViewTerms(loss, grad, gn, iou), pose


@dataclass
class ViewTermsRecord:
    """Each per-view term's loss at one pose, by name (views in order), with the views' robust weights."""

    losses: dict[str, NDArray[np.float64]]
    weights: NDArray[np.float64]

    def shares(self) -> dict[str, NDArray[np.float64]]:
        """Each term's share of its view's loss (0-1; 0 where the view's loss is 0)."""
        total = sum(self.losses.values())
        return {name: np.where(total > 0, loss / np.maximum(total, 1e-300), 0.0) for name, loss in self.losses.items()}

    @classmethod
    def of(cls, values: tuple[TermValues, ...], weights: NDArray[np.float64]) -> "ViewTermsRecord":
        return cls({v.name: v.views.loss for v in values if v.views is not None}, weights)
