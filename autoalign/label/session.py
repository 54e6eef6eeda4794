"""One labelling session of ``autoalign label``: every mask instance of a scene, the object and
pose a person gave it, autoalign's verdict on it, and what the person decided.

The page (:mod:`autoalign.cli.label_http`) and the 3D view (:mod:`autoalign.cli.label_3d`) only
call this: a click places and refines an object (:meth:`LabelSession.place`), a nudge or a drag
moves it (:meth:`~LabelSession.nudge`, :meth:`~LabelSession.set_pose`), "refine from here"
polishes it (:meth:`~LabelSession.refine_from_here`), and accept / reject / symmetric record the
decision. The state is saved to ``OUT_DIR/session.json`` atomically after every change and read
back when the server starts again, so that nothing accepted is lost.

Thread safety: several browser tabs, the 3D view and the refinement job call in from their own
threads. State changes happen under one lock (short); everything that renders or moves a pose
also holds the render lock for its whole read-compute-write, so two nudges from two tabs are
both applied, one after the other, and the renderer (drjit) is used by one thread at a time.

Units and frames: poses are world-from-model 4x4 in mm (the frame of ``scene_camera.json``);
pixel coordinates in and out are OpenCV's (the centre of the top-left pixel at 0, 0), in the
masks' resolution (the views' ``width`` x ``height``).
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign import __version__
from autoalign.engine.refine import RefineOptions, RefineResult, refine
from autoalign.engine.seeding import Click
from autoalign.engine.uncertainty import Uncertainty
from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera, uv_from_opencv
from autoalign.geometry.se3 import make_pose, so3_exp
from autoalign.io.atomic_files import write_bytes_atomic
from autoalign.io.bop import Scene, read_json_file, scene_gt_of
from autoalign.io.instances import (
    Instance,
    InstanceScenes,
    read_instance_scenes,
    read_instances,
)
from autoalign.io.models import ModelSet
from autoalign.quality.overlap import mask_iou
from autoalign.quality.verdict import Verdict, judge
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer
from autoalign.jobs.report import floats

Progress = Callable[[str, int, int], None]

DECISIONS = ("open", "accepted", "rejected")
"""What the person decided about an instance: nothing yet, its label is right, or it is not wanted."""
CONTOUR_EPS_PX = 0.5
"""Contours are simplified (Douglas-Peucker) to within this many pixels before they go to the page."""
WORST_VIEWS = 3
UNDO_STEPS = 50
SESSION_KIND = "autoalign label session"


@dataclass
class LabelledInstance:
    """One mask instance (``..._{index:06d}.png``) and what the session knows of it.

    Attributes:
        index: the instance's mask number.
        obj_id: the object the person chose for it (``None``: not placed yet).
        T_wm: world-from-model pose (4x4, mm), ``None`` until placed.
        decision: one of :data:`DECISIONS`.
        symmetric: the person marked the object symmetric (a turn about its axis is not an error).
        source: what set the pose last (``click``, ``refine``, ``nudge``, ``3d``).
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
    def from_record(d: dict[str, Any]) -> "LabelledInstance":
        T = d.get("T_wm")
        return LabelledInstance(
            int(d["index"]), None if d.get("obj_id") is None else int(d["obj_id"]),
            None if T is None else np.asarray(T, dtype=np.float64).reshape(4, 4), str(d.get("decision", "open")),
            bool(d.get("symmetric", False)), str(d.get("source", "")), d.get("verdict"), list(d.get("reasons", [])),
            d.get("sigma_mm"), d.get("sigma_deg"), list(d.get("weakly_observed", [])),
            {int(k): float(v) for k, v in (d.get("ious") or {}).items()}, int(d.get("pose_revision", 0)))


@dataclass
class JobState:
    """The one slow task the session runs at a time (placing, refining or exporting) and its progress."""

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
        return {"kind": self.kind, "instance": self.instance, "running": self.running, "stage": self.stage,
                "done": self.done, "total": self.total, "error": self.error, "seconds": self.seconds,
                "number": self.number}


def contour_polylines(mask: NDArray[np.bool_]) -> list[list[list[float]]]:
    """The outer contours of ``mask`` as polylines of OpenCV pixel coordinates (pixel centres at
    integers), simplified to within :data:`CONTOUR_EPS_PX`."""
    found, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in found:
        poly = cv2.approxPolyDP(c, CONTOUR_EPS_PX, True).reshape(-1, 2)
        out.append([[int(x), int(y)] for x, y in poly])
    return out


def nudged_pose(T_wm: NDArray[np.float64], centre_m: NDArray[np.float64], cam: Camera,
                move_mm: NDArray[np.float64], turn_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_wm`` moved by ``move_mm`` and turned by ``turn_deg`` (a rotation vector, degrees) about the
    object's centre, both given along the axes of ``cam`` (x right, y down, z forward)."""
    R_cw = cam.R_w2c.T
    c_w = T_wm[:3, :3] @ centre_m + T_wm[:3, 3]
    R = so3_exp(R_cw @ np.radians(turn_deg))
    return make_pose(R @ T_wm[:3, :3], R @ (T_wm[:3, 3] - c_w) + c_w + R_cw @ move_mm)


class LabelSession:
    """The state of ``autoalign label`` on one scene (see module doc).

    Args:
        scene_dir: a BOP scene folder with ``scene_camera.json`` and instance masks in ``mask_visib/``.
        models: the objects that can be chosen.
        out_dir: where ``session.json`` is kept and the export is written.
        instances_file: an instances file (``{"instances": {"0": 5}}``) whose objects are offered first.
    """

    def __init__(self, scene_dir: str | os.PathLike[str], models: ModelSet, out_dir: str | os.PathLike[str],
                 instances_file: str | os.PathLike[str] | None = None, options: RefineOptions | None = None) -> None:
        self.scene_dir, self.models, self.out_dir = Path(scene_dir), models, Path(out_dir)
        self.options = options or RefineOptions()
        self.found: InstanceScenes = read_instance_scenes(self.scene_dir, None)
        indices = [i.index for i in self.found.instances]
        if not indices:
            raise AutoalignError(f"{self.scene_dir / 'mask_visib'}: no non-empty instance mask; label a scene with "
                                 "masks (a segmenter's, or 'autoalign recon --propose')")
        self.suggested = self._suggested_objects(instances_file)
        self.object_ids = sorted(int(p.stem[4:]) for p in models.folder.glob("obj_*.ply") if p.stem[4:].isdigit())
        if not self.object_ids:
            raise AutoalignError(f"{models.folder}: no obj_XXXXXX.ply; pass a BOP models folder to --models")
        self.instances = {k: LabelledInstance(k) for k in indices}
        self.revision = 0
        self.focus: int | None = None  # the instance last selected on a page (the 3D view's gizmo goes to it)
        self.job = JobState()
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._render = threading.Lock()
        self._rasterizers: dict[int, SoftSilhouetteRasterizer] = {}
        self._contours: dict[int, tuple[int, dict[int, list[list[list[float]]]]]] = {}
        self._undo: dict[int, list[LabelledInstance]] = {}  # per instance, its states before its last moves
        self._load()

    # ------------------------------------------------------------------ reading and saving

    @property
    def session_path(self) -> Path:
        return self.out_dir / "session.json"

    @property
    def views(self) -> list[Camera]:
        return self.found.cameras

    @property
    def image_ids(self) -> list[int]:
        return self.found.image_ids

    def _suggested_objects(self, instances_file: Path | None) -> dict[int, int]:
        """instance -> obj_id from an instances file or the scene's own ``scene_gt.json`` (if any)."""
        if instances_file is None and not (self.scene_dir / "scene_gt.json").is_file():
            return {}
        return {i.index: i.obj_id for i in read_instances(self.scene_dir, instances_file)}

    def _load(self) -> None:
        path = self.session_path
        if not path.is_file():
            return
        fix = f"delete {path} to start a new session, or pass another --out"
        data = read_json_file(path, fix)
        if not isinstance(data, dict) or data.get("kind") != SESSION_KIND:
            raise AutoalignError(f"{path}: not an autoalign label session; {fix}")
        if Path(data.get("scene_dir", "")).resolve() != self.scene_dir.resolve():
            raise AutoalignError(f"{path}: belongs to the scene {data.get('scene_dir')}, not {self.scene_dir}; {fix}")
        try:
            for rec in data["instances"]:
                inst = LabelledInstance.from_record(rec)
                if inst.obj_id is not None and inst.obj_id not in self.object_ids:
                    raise AutoalignError(f"{path}: instance {inst.index} is object {inst.obj_id}, which has no model "
                                         f"in {self.models.folder}; pass the models the session was made with")
                if inst.index in self.instances and inst.decision in DECISIONS:
                    self.instances[inst.index] = inst
            self.revision = int(data.get("revision", 0))
        except (KeyError, TypeError, ValueError):
            raise AutoalignError(f"{path}: unreadable instance entries; {fix}") from None

    def _save(self) -> None:
        """Write ``session.json`` atomically (call with the state lock held)."""
        data = {"kind": SESSION_KIND, "autoalign_version": __version__, "scene_dir": str(self.scene_dir.absolute()),
                "models": str(self.models.folder.absolute()), "revision": self.revision,
                "units": "mm; T_wm is world-from-model, world = the frame of scene_camera.json",
                "instances": [i.record() for i in self.instances.values()]}
        self.out_dir.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(self.session_path, json.dumps(data, indent=1).encode())

    def _changed_now(self, save: bool = True) -> None:
        """Count a change, save it (state lock held) and wake everyone waiting in :meth:`wait`."""
        self.revision += 1
        if save:
            self._save()
        self._changed.notify_all()

    def wait(self, since: int, timeout_s: float) -> int:
        """Block until the revision differs from ``since`` or ``timeout_s`` passed; the revision.

        A ``since`` above the revision comes from a page that saw this session before the server
        restarted (progress counts revisions that are not saved): it is answered at once."""
        with self._changed:
            self._changed.wait_for(lambda: self.revision != since, timeout=timeout_s)
            return self.revision

    # ------------------------------------------------------------------ what the page shows

    def snapshot(self) -> dict[str, Any]:
        """Everything the page shows but the images and contours, as JSON."""
        with self._lock:
            return {"revision": self.revision, "scene_dir": str(self.scene_dir.absolute()),
                    "out_dir": str(self.out_dir.absolute()),
                    "objects": [{"obj_id": o, "diameter": self.models.info.get(o, {}).get("diameter")}
                                for o in self.object_ids],
                    "views": [{"image_id": im, "width": c.width, "height": c.height}
                              for im, c in zip(self.image_ids, self.views)],
                    "instances": [{**i.record(), "suggested_obj_id": self.suggested.get(i.index),
                                   "views": self.scene_of(i.index).image_ids}
                                  for i in self.instances.values()],
                    "focus": self.focus, "job": self.job.record()}

    def scene_of(self, index: int) -> Scene:
        """The views and masks of instance ``index`` (other masks' pixels ignored)."""
        return self.found.scenes[[i.index for i in self.found.instances].index(index)]

    def masks_in_view(self, image_id: int) -> dict[int, NDArray[np.bool_]]:
        """Every instance's mask in image ``image_id`` (at the views' resolution), by instance."""
        out = {}
        for inst, sc in zip(self.found.instances, self.found.scenes):
            if image_id in sc.image_ids:
                out[inst.index] = np.asarray(sc.masks[sc.image_ids.index(image_id)]) > 0.5
        return out

    def instance_at(self, image_id: int, u: float, v: float) -> int:
        """The instance whose mask covers OpenCV pixel ``(u, v)`` of image ``image_id`` (the smallest,
        where masks overlap). Raises :class:`AutoalignError` if none does."""
        if image_id not in self.image_ids:
            raise AutoalignError(f"image {image_id} is not a view of {self.scene_dir}")
        cam = self.views[self.image_ids.index(image_id)]
        col, row = int(round(u)), int(round(v))
        if not (0 <= col < cam.width and 0 <= row < cam.height):
            raise AutoalignError(f"pixel {u:.0f},{v:.0f} is outside the {cam.width}x{cam.height} image {image_id}")
        under = [(int(m.sum()), k) for k, m in self.masks_in_view(image_id).items() if m[row, col]]
        if not under:
            raise AutoalignError(f"no instance mask under pixel {col},{row} of image {image_id}; click inside a tinted "
                                 "region (autoalign aligns a model with a mask)")
        return min(under)[1]

    def contours(self, index: int) -> tuple[int, dict[int, list[list[list[float]]]]]:
        """``(pose_revision, {image_id: polylines})`` of instance ``index``'s silhouette in every view."""
        with self._lock:
            inst = self.instances[index]
            cached = self._contours.get(index)
            if not inst.placed:
                return inst.pose_revision, {}
            if cached is not None and cached[0] == inst.pose_revision:
                return cached
        with self._render:
            with self._lock:
                inst = self.instances[index]
                rev, T, obj = inst.pose_revision, inst.T_wm, inst.obj_id
            if not inst.placed:
                return rev, {}
            polys = self._outlines(self._silhouettes(obj, T))
        with self._lock:
            if self.instances[index].pose_revision == rev:
                self._contours[index] = (rev, polys)
        return rev, polys

    # ------------------------------------------------------------------ rendering (render lock held)

    def _rasterizer(self, obj_id: int) -> SoftSilhouetteRasterizer:
        if obj_id not in self._rasterizers:
            self._rasterizers[obj_id] = SoftSilhouetteRasterizer(self.models.mesh(obj_id))
        return self._rasterizers[obj_id]

    def _silhouettes(self, obj_id: int, T_wm: NDArray[np.float64]) -> dict[int, NDArray[np.bool_]]:
        """The object's ray-cast silhouette at ``T_wm`` in every view, by image id."""
        return dict(zip(self.image_ids, self._rasterizer(obj_id).hard_masks(T_wm, self.views)))

    @staticmethod
    def _outlines(silhouettes: dict[int, NDArray[np.bool_]]) -> dict[int, list[list[list[float]]]]:
        return {im: contour_polylines(m) for im, m in silhouettes.items() if m.any()}

    def _fit(self, index: int, silhouettes: dict[int, NDArray[np.bool_]]) -> dict[int, float]:
        """Per-view hard IoU of the silhouettes with instance ``index``'s masks (the pixels other masks
        claim left out, as :func:`~autoalign.engine.refine.hard_ious`), by image id."""
        scene = self.scene_of(index)
        return {im: mask_iou(silhouettes[im], np.asarray(t) > 0.5, scene.compared(k))
                for k, (im, t) in enumerate(zip(scene.image_ids, scene.masks))}

    def _store_pose(self, index: int, obj_id: int, T_wm: NDArray[np.float64], source: str,
                    judged: tuple[Verdict, Uncertainty | None] | None = None) -> None:
        """Set the pose (and, after a refinement, its verdict and uncertainty), render its contours, save."""
        T_wm = np.asarray(T_wm, dtype=np.float64)
        silhouettes = self._silhouettes(obj_id, T_wm)  # ray-cast once for the fit and the outlines
        ious, polys = self._fit(index, silhouettes), self._outlines(silhouettes)
        with self._lock:
            inst = self.instances[index]
            changes: dict[str, Any] = {"obj_id": obj_id, "T_wm": T_wm, "source": source, "ious": ious,
                                       "pose_revision": inst.pose_revision + 1}
            if judged is None:  # what the last refinement said no longer holds for this pose
                changes.update(verdict=None, reasons=["moved by hand since the last refinement: refine from here "
                                                      "to judge it"], sigma_mm=None, sigma_deg=None,
                               weakly_observed=[])
            else:
                verdict, u = judged
                changes.update(verdict=verdict.status, reasons=list(verdict.reasons),
                               sigma_mm=None if u is None else [float(x) for x in u.sigma_mm],
                               sigma_deg=None if u is None else [float(x) for x in u.sigma_deg],
                               weakly_observed=[] if u is None else list(u.weak))
            if source == "click":
                changes["decision"] = "open"
            if inst.placed:
                self._undo.setdefault(index, []).append(inst)
                del self._undo[index][:-UNDO_STEPS]
            self.instances[index] = replace(inst, **changes)
            self._contours[index] = (inst.pose_revision + 1, polys)
            self._changed_now()

    def undo(self, index: int) -> None:
        """Put instance ``index`` back where it was before its last move (with what autoalign said of
        it there); its decision stays. Kept for the last :data:`UNDO_STEPS` moves while the server runs."""
        with self._render:
            with self._lock:
                if not self._undo.get(index):
                    raise AutoalignError(f"instance {index}: nothing to undo")
                before = self._undo[index].pop()
                now = self._known(index)
                self.instances[index] = replace(before, decision=now.decision, symmetric=now.symmetric,
                                                pose_revision=now.pose_revision + 1)
                self._contours.pop(index, None)
                self._changed_now()

    def _judged(self, index: int, obj_id: int, result: RefineResult) -> tuple[Verdict, Uncertainty | None]:
        """The verdict on a refinement of instance ``index`` (as ``refine`` gives it) and its uncertainty."""
        from autoalign.scene.refine import verdict_of

        return verdict_of(result, self.scene_of(index).empty, self.models, obj_id), result.uncertainty

    # ------------------------------------------------------------------ what a person does

    def place(self, obj_id: int, image_id: int, u: float, v: float, progress: Progress | None = None) -> int:
        """Place ``obj_id`` on the instance clicked at OpenCV pixel ``(u, v)`` of ``image_id``: position
        from the click's ray and the other views' masks, orientation searched, then refined
        (:func:`~autoalign.engine.refine.refine`); returns the instance."""
        self._check_object(obj_id)
        index = self.instance_at(image_id, u, v)
        iu, iv = uv_from_opencv(np.array([u, v], dtype=np.float64))
        with self._render:
            result = refine(self.scene_of(index), self.models.mesh(obj_id), Click(image_id, float(iu), float(iv)),
                            self.options, progress=progress)
            self._store_pose(index, obj_id, result.T_wm, "click", self._judged(index, obj_id, result))
        return index

    def refine_from_here(self, index: int, progress: Progress | None = None) -> None:
        """Refine instance ``index`` from its current pose (after a nudge or a drag)."""
        with self._render:
            inst = self._placed(index)
            result = refine(self.scene_of(index), self.models.mesh(inst.obj_id), inst.T_wm.copy(), self.options,
                            progress=progress)
            self._store_pose(index, inst.obj_id, result.T_wm, "refine", self._judged(index, inst.obj_id, result))

    def refine_together(self, progress: Progress | None = None) -> None:
        """Refine every placed instance that is not rejected together, occlusion-aware
        (:func:`~autoalign.scene.joint.refine_jointly`: in each view a pixel belongs to the nearest
        of their surfaces, so the contour between two objects moves with both), and judge each."""
        from autoalign.scene.joint import refine_jointly

        with self._render:
            with self._lock:
                chosen = [i for i in self.instances.values() if i.placed and i.decision != "rejected"]
            if len(chosen) < 2:
                raise AutoalignError("refining together needs two or more placed instances that are not rejected; "
                                     "place more, or refine the one from where it is")
            scenes = [self.scene_of(i.index) for i in chosen]
            together = replace(self.found, instances=[Instance(i.index, i.obj_id) for i in chosen], scenes=scenes)
            joint = refine_jointly(together, [self.models.mesh(i.obj_id) for i in chosen], [i.T_wm for i in chosen],
                                   robust=self.options.robust, progress=progress)
            for k, (inst, scene) in enumerate(zip(chosen, scenes)):
                unc = joint.uncertainties[k]
                verdict = judge(joint.evaluation.hard_iou(k), joint.evaluation.weights[k], scene.image_ids,
                                scene.empty, False, self.models.symmetric(inst.obj_id), unc,
                                self.models.continuous_axes(inst.obj_id), None)
                self._store_pose(inst.index, inst.obj_id, joint.poses[k], "together", (verdict, unc))

    def nudge(self, index: int, image_id: int, move_mm: list[float], turn_deg: list[float]) -> None:
        """Move instance ``index`` by ``move_mm`` and turn it by ``turn_deg`` (rotation vector) about
        its centre, along the axes of camera ``image_id`` (x right, y down, z forward)."""
        move, turn = np.asarray(move_mm, dtype=np.float64), np.asarray(turn_deg, dtype=np.float64)
        if move.shape != (3,) or turn.shape != (3,) or not (np.isfinite(move).all() and np.isfinite(turn).all()):
            raise AutoalignError("a nudge is three finite numbers to move (mm) and three to turn (degrees)")
        if image_id not in self.image_ids:
            raise AutoalignError(f"image {image_id} is not a view of {self.scene_dir}")
        cam = self.views[self.image_ids.index(image_id)]
        with self._render:
            inst = self._placed(index)
            T = nudged_pose(inst.T_wm, self.models.mesh(inst.obj_id).centre, cam, move, turn)
            self._store_pose(index, inst.obj_id, T, "nudge")

    def set_pose(self, index: int, T_wm: NDArray[np.float64], source: str = "3d") -> None:
        """Put instance ``index`` at ``T_wm`` (4x4, mm), e.g. where it was dragged in the 3D view."""
        T = np.asarray(T_wm, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise AutoalignError("a pose is a finite 4x4 matrix")
        with self._render:
            inst = self._placed(index)
            self._store_pose(index, inst.obj_id, T, source)

    def decide(self, index: int, decision: str) -> None:
        """Record ``accepted``, ``rejected`` or ``open`` for instance ``index``."""
        if decision not in DECISIONS:
            raise AutoalignError(f"decision {decision!r}: one of {', '.join(DECISIONS)}")
        with self._lock:
            inst = self._placed(index) if decision == "accepted" else self._known(index)
            self.instances[index] = replace(inst, decision=decision)
            self._changed_now()

    def focus_on(self, index: int) -> None:
        """Note the instance a person selected on a page (not saved: it is where they look, not a label)."""
        with self._lock:
            self._known(index)
            if self.focus != index:
                self.focus = index
                self._changed_now(save=False)

    def mark_symmetric(self, index: int, symmetric: bool) -> None:
        with self._lock:
            self.instances[index] = replace(self._known(index), symmetric=bool(symmetric))
            self._changed_now()

    def _check_object(self, obj_id: int) -> None:
        if obj_id not in self.object_ids:
            raise AutoalignError(f"object {obj_id} has no model in {self.models.folder}; choose one of "
                                 f"{', '.join(map(str, self.object_ids))}")

    def _known(self, index: int) -> LabelledInstance:
        if index not in self.instances:
            raise AutoalignError(f"instance {index} has no mask in {self.scene_dir / 'mask_visib'}")
        return self.instances[index]

    def _placed(self, index: int) -> LabelledInstance:
        inst = self._known(index)
        if not inst.placed:
            raise AutoalignError(f"instance {index} has no object yet; choose an object and click it in a view")
        return inst

    # ------------------------------------------------------------------ the result

    def accepted_labels(self) -> dict[str, list[dict[str, Any]]]:
        """BOP ``scene_gt.json`` of the accepted instances, in every image (entry k = k-th accepted
        instance by mask number). Raises if nothing is accepted."""
        with self._lock:
            chosen = [(i.obj_id, i.T_wm) for i in self.instances.values() if i.decision == "accepted" and i.placed]
        if not chosen:
            raise AutoalignError("no instance is accepted yet; accept the labels to export first")
        return scene_gt_of(chosen, self.views, self.image_ids)

    def decisions(self) -> dict[str, Any]:
        """Every placed instance's record and the accepted ones' numbers (``labels.json`` of the export)."""
        with self._lock:
            return {"instances": [i.record() for i in self.instances.values() if i.placed],
                    "accepted": [i.index for i in self.instances.values() if i.decision == "accepted" and i.placed],
                    "labels": "scene_gt.json lists the accepted instances, in this order"}

    # ------------------------------------------------------------------ the slow job

    def start_job(self, kind: str, instance: int | None, work: Callable[[Progress], None]) -> bool:
        """Run ``work(progress)`` on a thread of its own unless a job is running (then ``False``).
        Its progress and its error, if any (one line), are in :attr:`job` for the page."""
        with self._lock:
            if self.job.running:
                return False
            self.job = JobState(kind, instance, True, "starting", 0, 0, None, time.perf_counter(), 0.0,
                                self.job.number + 1)
            self._changed_now(save=False)
        threading.Thread(target=self._run_job, args=(work,), name=f"autoalign-{kind}", daemon=True).start()
        return True

    def _progress(self, stage: str, done: int, total: int) -> None:
        with self._lock:
            self.job = replace(self.job, stage=stage, done=done, total=total,
                               seconds=time.perf_counter() - self.job.started)
            self._changed_now(save=False)

    def _run_job(self, work: Callable[[Progress], None]) -> None:
        error = None
        try:
            work(self._progress)
        except AutoalignError as exc:
            error = str(exc)
        except Exception as exc:  # a bug: the page says so instead of the job hanging forever
            error = f"internal error ({type(exc).__name__}: {exc}); please report it"
        with self._lock:
            self.job = replace(self.job, running=False, stage="failed" if error else "done", error=error,
                               seconds=time.perf_counter() - self.job.started)
            self._changed_now(save=False)
