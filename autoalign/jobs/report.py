"""``refine.json``: the report of one refinement (:class:`RefineReport`, one object) or of a scene
(:class:`SceneReport`, every instance), built from the results as typed records; ``to_json()``
gives the file's content (plain JSON types: :func:`jsonable`).

In ``jobs``, beside :mod:`autoalign.jobs.refine_folder` which writes it, because it reads the results
of ``engine`` and ``scene``, which ``quality`` (the verdict and overlay) may not import. The command
line, the batch runner and Python users all build their reports here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign import __version__
from autoalign.engine.refine import RefineOptions, RefineResult
from autoalign.engine.uncertainty import BOUNDARY_BIAS_PX, SAME_VIEWPOINT_DEG, Uncertainty, axis_sigmas, weak_directions
from autoalign.geometry.camera import PIXEL_CONVENTION
from autoalign.geometry.se3 import rotation_angle_deg, transform_points
from autoalign.losses.term import ViewTermsRecord
from autoalign.quality.verdict import Verdict, low_weight_ids
from autoalign.scene.joint import JointRefinement

UNITS = "mm; poses are world-from-model, world = the frame of scene_camera.json"
OUTPUTS = {"scene_gt": "scene_gt.json", "refine": "refine.json", "overlay": "overlay.png"}
"""The files of a refinement, by their key in ``refine.json``'s ``outputs``."""
POOR_FIT_IOU = 0.7
"""A mean IoU after refinement below this is reported as a poor fit."""


def floats(a: Any) -> Any:
    """Nested lists of plain floats (NaN/inf as None) from an array-like."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        v = float(arr)
        return v if np.isfinite(v) else None
    return [floats(x) for x in arr]


def terms_record(terms: ViewTermsRecord | None) -> dict[str, Any] | None:
    """Each per-view evidence term per view of ``image_ids``: its loss (``mask_loss``, ``depth_loss``,
    ...), the view's robust weight, and, with more than one term, each one's share of the view's loss
    (``depth_share``, ...)."""
    if terms is None:
        return None
    out: dict[str, Any] = {f"{name}_loss": loss for name, loss in terms.losses.items()}
    out["weight"] = terms.weights
    if len(terms.losses) > 1:
        out.update({f"{name}_share": share for name, share in terms.shares().items()})
    return out


def jsonable(obj: Any) -> Any:
    """Plain JSON types from numpy scalars/arrays, dataclasses, tuples and paths (NaN as None)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return floats(obj) if obj.dtype.kind == "f" else obj.tolist()
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def pose_record(T: Any) -> dict[str, Any]:
    """A 4x4 pose as ``{"T_wm": 4x4, "R": 9 row-major, "t": 3 (mm)}``."""
    T = np.asarray(T, dtype=np.float64)
    return {"T_wm": floats(T), "R": floats(T[:3, :3].ravel()), "t": floats(T[:3, 3])}


def turn_rise_record(r: RefineResult) -> dict[str, Any]:
    """``turn_rise`` and its axis (:class:`~autoalign.engine.refine.RefineResult`), for refine.json."""
    axis = None if r.turn_rise_axis_m is None else [float(v) for v in r.turn_rise_axis_m]
    return {"turn_rise": r.turn_rise, "turn_rise_axis": axis}


def uncertainty_record(u: Uncertainty | None, free_axes_m: tuple[NDArray[np.float64], ...] = ()) -> dict[str, Any] | None:
    """The ``uncertainty`` entry of ``refine.json`` (see :mod:`autoalign.engine.uncertainty`); the turns
    about ``free_axes_m`` (the model's axes of continuous symmetry) are not listed as weakly observed."""
    if u is None:
        return None
    return {"sigma_mm": u.sigma_mm, "sigma_deg": u.sigma_deg, "axes": "along / about the model's x, y, z",
            "sigma_along_ray_mm": u.sigma_ray_mm, "sigma_across_ray_mm": u.sigma_across_mm,
            "median_view_direction": u.view_dir_m,
            "ray": "the median view's direction (camera to object centre) in the model's axes",
            "weakly_observed": weak_directions(u.covariance, free_axes_m), "covariance": u.covariance,
            "covariance_of": "twist (v mm, w rad) in the model's axes, about the model centre; jackknife over "
                             f"viewpoints (the views within {SAME_VIEWPOINT_DEG:g} deg of one direction left out "
                             "together, one Gauss-Newton step; a single viewpoint: the views' spread times their "
                             "number), scaled by views_spread_factor "
                             "where polishes with a fifth of the views left out moved farther, plus the prior on a "
                             f"shift of every mask's outline ({BOUNDARY_BIAS_PX:g} px, and with the photos "
                             "outline_disagreement_px on top: sqrt of the sum of squares), weakly observed turns "
                             "raised to the spread of their loss profile's minimum over resampled views",
            "covariance_components": {name: dict(zip(("sigma_mm", "sigma_deg"), axis_sigmas(part)))
                                      for name, part in u.components().items()},
            "covariance_components_are": "the covariance as a sum: the views' spread (times views_spread_factor, "
                                         "with the turn profiles), the outline prior, the photos' outline "
                                         "disagreement and a solved scale's share; sigmas of each alone",
            "views_spread_factor": u.spread_factor,
            "viewpoints": u.viewpoints,
            "outline_shift_per_px": u.bias_shift,
            "outline_disagreement_px": u.outline_disagreement_px,
            "outline_disagreement": "how far the masks' outlines lie outside the silhouettes at this pose, fitted "
                                    "with the photos too (px, median over the views whose mask is on the object; "
                                    "null: not measured)",
            "turn_profiles": [{"axis_m": f.axis_m, "sigma_deg": float(np.degrees(np.sqrt(f.variance)))}
                              for f in u.turn_floors],
            "naive_sigma_mm": u.naive_sigma_mm, "naive_sigma_deg": u.naive_sigma_deg}


def _id_list(ids: Any, limit: int = 20) -> str:
    """``1, 2, 3 ...``: at most ``limit`` ids."""
    ids = list(ids)
    return ", ".join(str(i) for i in ids[:limit]) + (" ..." if len(ids) > limit else "")


# ----------------------------------------------------------------------------------------------
# One object
# ----------------------------------------------------------------------------------------------

@dataclass
class Seed:
    """Where a refinement started: ``kind`` ``hull`` (searched), ``init`` (a coarse pose from
    ``init_file``, ``pose`` world-from-model) or ``click`` (``click``: image id and OpenCV pixel u, v)."""

    kind: str = "hull"
    init_file: str | None = None
    click: dict[str, float] | None = None
    pose: NDArray[np.float64] | None = None
    radius: tuple[float, float] | None = None  # the seed's stated uncertainty (mm, degrees)
    moved: tuple[float, float] | None = None  # how far the result ended from it (mm at the model's centre, degrees)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "init_file": self.init_file, "click": self.click,
                "pose": None if self.pose is None else pose_record(self.pose),
                "radius_mm_deg": self.radius, "moved_mm_deg": self.moved}


@dataclass
class RunnerUp:
    """The best clearly different pose (world from model), its distance from the winner: rotation
    (degrees) and translation of the model centre (mm)."""

    T_wm: NDArray[np.float64]
    loss: float
    mean_iou: float
    stage: str
    rotation_deg: float
    translation_mm: float

    @classmethod
    def of(cls, result: RefineResult, centre_m: NDArray[np.float64]) -> RunnerUp | None:
        """The runner-up of ``result`` (``None`` if there is none); ``centre_m``: the model centre (mm)."""
        if result.runner_up is None:
            return None
        Ru = np.asarray(result.runner_up.T_final, float)
        c = np.asarray(centre_m, float)[None]
        return cls(Ru, result.runner_up.loss, result.runner_up.mean_iou, result.runner_up.stage_name,
                   rotation_angle_deg(result.T_wm[:3, :3], Ru[:3, :3]),
                   float(np.linalg.norm(transform_points(result.T_wm, c) - transform_points(Ru, c))))

    def to_json(self) -> dict[str, Any]:
        return {"pose": pose_record(self.T_wm), "loss": self.loss, "mean_iou": self.mean_iou, "stage": self.stage,
                "rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm}


@dataclass
class RefineReport:
    """The report of one object's refinement in a scene folder (``autoalign refine --model``).

    ``T_cm_first``: the pose in the camera of image ``image_ids[0]`` (model to camera, mm);
    ``warnings``: those of the run before the report, then :meth:`notes`."""

    scene_dir: Path
    model: Path
    obj_id: int
    instance: int
    result: RefineResult
    verdict: Verdict
    seed: Seed
    image_ids: list[int]
    T_cm_first: NDArray[np.float64]
    runner_up: RunnerUp | None
    skipped: list[int]
    empty: list[int]
    image_scale: float
    options: RefineOptions
    timings: dict[str, float]
    warnings: list[str] = field(default_factory=list)

    @property
    def low_weight_ids(self) -> list[int]:
        return low_weight_ids(self.image_ids, self.result.weights, self.result.iou_after)

    def first_camera_pose(self) -> dict[str, Any]:
        return {"image_id": self.image_ids[0], "cam_R_m2c": floats(self.T_cm_first[:3, :3].ravel()),
                "cam_t_m2c": floats(self.T_cm_first[:3, 3])}

    def notes(self) -> list[str]:
        """What the person should look at (one line each): ambiguity, views set aside, a poor fit,
        missing masks."""
        r, notes = self.result, []
        iou_a = np.asarray(r.iou_after, float)
        if r.ambiguous and self.runner_up is not None:
            notes.append(f"ambiguous: another pose ({self.runner_up.rotation_deg:.1f} deg, "
                         f"{self.runner_up.translation_mm:.1f} mm away) fits almost as well (loss "
                         f"{self.runner_up.loss:.4g} vs {r.hypotheses[0].loss:.4g}); the object may be symmetric in "
                         "these views; check overlay.png and 'runner_up' in refine.json")
        low = self.low_weight_ids
        if low:
            iou_of = dict(zip(self.image_ids, iou_a))
            notes.append("views with low weight (their masks disagree with the others): image ids "
                         + ", ".join(f"{i} (IoU {iou_of[i]:.2f})" for i in low) + "; check those masks")
        if iou_a.mean() < POOR_FIT_IOU:
            notes.append(f"poor fit: mean IoU after refinement is only {iou_a.mean():.2f}; check the model's units "
                         "(mm), the starting pose and the masks (see overlay.png)")
        if self.empty:
            notes.append(f"{len(self.empty)} image(s) with an empty mask were treated as missing (not as 'object "
                         f"absent') and not used: ids {_id_list(self.empty)}; check the segmentation there")
        if self.skipped:
            notes.append(f"{len(self.skipped)} image(s) without a mask were skipped: ids {_id_list(self.skipped)}")
        return notes

    def to_json(self) -> dict[str, Any]:
        """The content of ``refine.json`` (plain JSON types)."""
        r = self.result
        iou_b, iou_a = np.asarray(r.iou_before, float), np.asarray(r.iou_after, float)
        return jsonable({
            "autoalign_version": __version__, "scene_dir": str(self.scene_dir), "model": str(self.model),
            "obj_id": self.obj_id, "instance": self.instance, "units": UNITS, "pixel_convention": PIXEL_CONVENTION,
            "pose": pose_record(r.T_wm), "pose_first_camera": self.first_camera_pose(),
            "pose_before": pose_record(r.T_init),
            "verdict": self.verdict.status, "reasons": self.verdict.reasons,
            "uncertainty": uncertainty_record(r.uncertainty), "seed": self.seed.to_json(),
            "seed_hold": None if r.seed_hold is None else r.seed_hold.to_json(),
            "image_ids": self.image_ids, "iou_before": iou_b, "iou_after": iou_a,
            "weights": np.asarray(r.weights, float),
            "mean_iou_before": float(iou_b.mean()), "mean_iou_after": float(iou_a.mean()),
            "min_iou_before": float(iou_b.min()), "min_iou_after": float(iou_a.min()),
            "low_weight_ids": self.low_weight_ids, "skipped": self.skipped, "empty_masks": self.empty,
            "image_scale": self.image_scale, "iterations": r.iterations, "renders": r.renders,
            "timings": self.timings,
            "hypotheses": [{"rank": k, "stage": h.stage_name, "loss": h.loss, "mean_iou": h.mean_iou,
                            "pose_init": pose_record(h.T_init), "pose": pose_record(h.T_final)}
                           for k, h in enumerate(r.hypotheses)],
            "ambiguous": bool(r.ambiguous), "turn_gap": r.turn_gap, **turn_rise_record(r),
            **{m.name: m.record() for m in r.measured}, "terms": terms_record(r.terms),
            "evidence": [e.record() for e in r.evidence()],
            "runner_up": None if self.runner_up is None else self.runner_up.to_json(),
            "options": self.options, "history": r.history, "outputs": dict(OUTPUTS),
            "warnings": self.warnings + self.notes(),
        })

    def summary(self, seconds: float, out: Path, paths: dict[str, Path]) -> dict[str, Any]:
        """What ``autoalign refine --json`` prints: the pose, the fit, the verdict, the output paths."""
        full = self.to_json()
        keys = ("pose", "pose_first_camera", "mean_iou_before", "mean_iou_after", "min_iou_after")
        return jsonable({**{k: full[k] for k in keys}, "time_s": seconds, "ambiguous": full["ambiguous"],
                         "verdict": self.verdict.status, "reasons": self.verdict.reasons,
                         "low_weight_ids": full["low_weight_ids"], "warnings": full["warnings"],
                         "out_dir": str(out.absolute()),
                         "outputs": {key: str(paths[name].absolute()) for key, name in OUTPUTS.items()}})


# ----------------------------------------------------------------------------------------------
# Every instance of a scene
# ----------------------------------------------------------------------------------------------

@dataclass
class InstanceReport:
    """One instance of a scene report: its result, verdict, model file and what it started from."""

    index: int
    obj_id: int
    position: int
    model: Path
    result: RefineResult
    verdict: Verdict
    seeded: bool
    empty: list[int]
    symmetric: bool
    seconds: float
    seed_move: tuple[float, float] | None = None  # how far it ended from its seed pose (mm at the centre, degrees)
    seed_radius: tuple[float, float] | None = None  # the seed's stated uncertainty (mm, degrees)
    free_axes_m: tuple[NDArray[np.float64], ...] = ()  # its model's axes of continuous symmetry (unit, model frame)

    def to_json(self) -> dict[str, Any]:
        res = self.result
        return {
            "instance": self.index, "obj_id": self.obj_id, "scene_gt_position": self.position,
            "model": str(self.model),
            "verdict": self.verdict.status, "reasons": self.verdict.reasons, "set_aside_ids": self.verdict.set_aside,
            "pose": pose_record(res.T_wm), "pose_before": pose_record(res.T_init),
            "uncertainty": uncertainty_record(res.uncertainty, self.free_axes_m),
            "seed": "init" if self.seeded else "hull", "moved_from_seed_mm_deg": self.seed_move,
            "seed_radius_mm_deg": self.seed_radius,
            "seed_hold": None if res.seed_hold is None else res.seed_hold.to_json(),
            "image_ids": [int(i) for i in res.image_ids], "iou_before": res.iou_before, "iou_after": res.iou_after,
            "weights": res.weights, "median_iou_after": float(np.median(res.iou_after)),
            "empty_masks": self.empty,
            "ambiguous": bool(res.ambiguous), "symmetric": self.symmetric, "turn_gap": res.turn_gap,
            **turn_rise_record(res),
            **{m.name: m.record() for m in res.measured}, "terms": terms_record(res.terms),
            "evidence": [e.record() for e in res.evidence()],
            "iterations": res.iterations, "renders": res.renders,
            "timings": {**res.timings, "instance": self.seconds},
        }


def joint_record(joint: JointRefinement) -> dict[str, Any]:
    """A joint stage (:class:`~autoalign.scene.joint.JointRefinement`): iterations, why it stopped, loss
    and median per-view misfit (1 - IoU) before and after."""
    return {"iterations": joint.iterations, "stop": joint.stop.value,
            "loss_before": joint.loss_before, "loss_after": joint.loss_after,
            "median_view_misfit_before": float(np.median(list(joint.view_misfit_before.values()))),
            "median_view_misfit_after": float(np.median(list(joint.view_misfit_after.values())))}


def cameras_record(attempt: JointRefinement, accepted: bool) -> dict[str, Any]:
    """The ``cameras`` entry: the camera corrections tried (:class:`~autoalign.scene.joint.JointRefinement`)
    and whether they were kept; per view the correction ``E`` (corrected ``T_cw = T_cw @ E``)."""
    joint = joint_record(attempt)
    return {"refined": accepted, "file": "scene_camera.json", "iterations": attempt.iterations,
            "loss_before": attempt.loss_before, "loss_after": attempt.loss_after,
            "median_view_misfit_before": joint["median_view_misfit_before"],
            "median_view_misfit_after": joint["median_view_misfit_after"],
            "per_view": {str(im): {"translation_mm": float(np.linalg.norm(E[:3, 3])),
                                   "rotation_deg": rotation_angle_deg(E[:3, :3], np.eye(3)),
                                   "T_correction": E,
                                   "misfit_before": attempt.view_misfit_before.get(im),
                                   "misfit_after": attempt.view_misfit_after.get(im)}
                         for im, E in attempt.corrections.items()}}


@dataclass
class ScaleReport:
    """A solved scene scale: mm per unit of the given cameras, its relative sigma, whether it
    settled, and the first guess from the masks (factor and spread)."""

    settled: bool
    mm_per_unit: float
    sigma_relative: float
    guess_mm_per_unit: float
    guess_spread: float

    def to_json(self) -> dict[str, Any]:
        return {"solved": True, "settled": self.settled, "mm_per_unit": self.mm_per_unit,
                "sigma_relative": self.sigma_relative, "guess_mm_per_unit": self.guess_mm_per_unit,
                "guess_spread": self.guess_spread, "file": "scene_camera.json"}


@dataclass
class SceneReport:
    """The report of a scene's refinement (``autoalign refine --models``): every instance, the joint
    stage, the solved scale and the camera corrections when there were any (``cameras_written``:
    ``scene_camera.json`` is among the outputs)."""

    scene_dir: Path
    models: Path
    image_scale: float
    instances_from: str
    unmodelled: list[int]
    instances: list[InstanceReport]
    options: RefineOptions
    timings: dict[str, float]
    warnings: list[str]
    joint: JointRefinement | None = None
    scale: ScaleReport | None = None
    cameras_written: bool = False
    cameras: dict[str, Any] | None = None
    image_ids: list[int] = field(default_factory=list)
    """The scene's views (image ids)."""

    @property
    def flagged(self) -> list[InstanceReport]:
        return [i for i in self.instances if i.verdict.status != "ok"]

    def to_json(self) -> dict[str, Any]:
        """The content of ``refine.json`` (plain JSON types)."""
        report: dict[str, Any] = {
            "autoalign_version": __version__, "scene_dir": str(self.scene_dir), "models": str(self.models),
            "units": UNITS, "pixel_convention": PIXEL_CONVENTION, "image_scale": self.image_scale,
            "instances_from": self.instances_from, "unmodelled_instances": self.unmodelled,
            "instances": [i.to_json() for i in self.instances], "options": self.options, "timings": self.timings,
            "outputs": {**OUTPUTS, **({"scene_camera": "scene_camera.json"} if self.cameras_written else {})},
            "warnings": list(self.warnings),
        }
        if self.joint is not None:
            report["joint"] = joint_record(self.joint)
        if self.scale is not None:
            report["scale"] = self.scale.to_json()
        if self.cameras is not None:
            report["cameras"] = self.cameras
        return jsonable(report)

    def summary(self, seconds: float, out: Path, warnings: list[str]) -> dict[str, Any]:
        """What ``autoalign refine --models --json`` prints: per instance its verdict and pose, and
        ``warnings`` (all of the run's, also those that came after the report)."""
        records = self.to_json()["instances"]
        keys = ("instance", "obj_id", "verdict", "reasons", "median_iou_after", "pose")
        return jsonable({"instances": [{k: rec[k] for k in keys} for rec in records], "time_s": seconds,
                         "out_dir": str(out.absolute()), "warnings": list(warnings)})
