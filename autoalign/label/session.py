"""One labelling session of ``autoalign label``: every mask instance of a scene, the object and
pose a person gave it, autoalign's verdict on it, and what the person decided.

The page (:mod:`autoalign.cli.label_http`) and the 3D view (:mod:`autoalign.cli.label_3d`) only
call this: a click places and refines an object (:meth:`LabelSession.place`), a nudge or a drag
moves it (:meth:`~LabelSession.nudge`, :meth:`~LabelSession.set_pose`), "refine from here"
polishes it (:meth:`~LabelSession.refine_from_here`), and accept / reject / symmetric record the
decision. The state is saved to ``OUT_DIR/session.json`` atomically after every change and read
back when the server starts again, so that nothing accepted is lost. The parts: the scene read
once (:mod:`~autoalign.label.scene`), the records (:mod:`~autoalign.label.records`), the state
under its lock (:mod:`~autoalign.label.state`), ``session.json`` (:mod:`~autoalign.label.session_file`),
undo (:mod:`~autoalign.label.undo`), silhouettes and outlines (:mod:`~autoalign.label.page_geometry`)
and the slow job's thread (:mod:`~autoalign.label.jobs`).

Thread safety: several browser tabs, the 3D view and the refinement job call in from their own
threads. State changes happen under one lock (short); everything that renders or moves a pose
also holds the render lock for its whole read-compute-write, so two nudges from two tabs are
both applied, one after the other, and the renderer (drjit) is used by one thread at a time.

Units and frames: poses are world-from-model 4x4 in mm (the frame of ``scene_camera.json``);
pixel coordinates in and out are OpenCV's (the centre of the top-left pixel at 0, 0), in the
masks' resolution (the views' ``width`` x ``height``).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.refine import PosePreview, RefineOptions, RefineResult, refine
from autoalign.engine.seeding import Click
from autoalign.errors import AutoalignError
from autoalign.geometry.camera import uv_from_opencv
from autoalign.io.bop import Scene, scene_gt_of
from autoalign.io.instances import Instance
from autoalign.io.models import ModelSet
from autoalign.label.fields import nudge_vectors
from autoalign.label.jobs import JobRunner, Progress
from autoalign.label.page_geometry import (
    Outlines,
    SilhouetteRenderer,
    fit,
    nudged_pose,
    outlines,
)
from autoalign.label.records import (
    DECISIONS,
    REFINING,
    SEARCHED,
    SHOWN_ONLY,
    JobState,
    Judgement,
    LabelledInstance,
    checked_pose,
    far_from_click,
    moved,
)
from autoalign.label.scene import SessionScene
from autoalign.label.session_file import SessionFile
from autoalign.label.state import SessionState
from autoalign.label.undo import UndoHistory

__all__ = ["LabelSession", "Progress"]  # Progress: for the server's jobs


def click_previews(store: Callable[[NDArray[np.float64], str], None]) -> PosePreview:
    """The engine's previews of a click (:data:`~autoalign.engine.refine.PosePreview`) given to ``store``
    with their source: the first is the orientation search's pose (:data:`SEARCHED`), the others
    refined poses before their uncertainty and verdict (:data:`REFINING`; where depth that sees through
    the object is set aside and the search runs again, its second search's pose is shown as one too)."""
    shown: list[str] = []

    def show(T_wm: NDArray[np.float64]) -> None:
        shown.append(SEARCHED if not shown else REFINING)
        store(T_wm, shown[-1])

    return show


@contextlib.contextmanager
def shown_until_judged(state: SessionState, contours: dict[int, Any], *indices: int) -> Iterator[None]:
    """The instances ``indices`` put back as saved (and their outlines in ``contours`` dropped) if the work
    within fails: the poses shown meanwhile (:data:`~autoalign.label.records.SHOWN_ONLY`) were no label."""
    try:
        yield
    except BaseException:
        for index in indices:
            if state.put_back(index):
                contours.pop(index, None)
        raise


def judged_refinement(result: RefineResult, scene: Scene, models: ModelSet, obj_id: int) -> Judgement:
    """The verdict on a refinement of object ``obj_id`` in ``scene`` (as ``refine`` gives it) and its uncertainty."""
    from autoalign.scene.refine import verdict_of

    return Judgement(verdict_of(result, scene.empty, models, obj_id), result.uncertainty, models.continuous_axes(obj_id))


class LabelSession(SessionScene):
    """The state of ``autoalign label`` on one scene (see module doc): the scene (the base class),
    its instances' state, saved to ``session.json``, with undo and one slow job at a time.

    Args:
        scene_dir: a BOP scene folder with ``scene_camera.json`` and instance masks in ``mask_visib/``.
        models: the objects that can be chosen.
        out_dir: where ``session.json`` is kept and the export is written.
        instances_file: an instances file (``{"instances": {"0": 5}}``) whose objects are offered first.
    """

    def __init__(self, scene_dir: str | os.PathLike[str], models: ModelSet, out_dir: str | os.PathLike[str],
                 instances_file: str | os.PathLike[str] | None = None, options: RefineOptions | None = None) -> None:
        super().__init__(scene_dir, models, instances_file)
        self.out_dir = Path(out_dir)
        self.options = options or RefineOptions()
        self.file = SessionFile(self.out_dir, self.scene_dir, models.folder)
        instances = {k: LabelledInstance(k) for k in self.indices}
        saved = self.file.read(self.object_ids)
        for inst in saved.instances if saved else []:
            if inst.index in instances and inst.decision in DECISIONS:
                instances[inst.index] = inst
        self.state = SessionState(instances, saved.revision if saved else 0, self.file.write)
        self.jobs = JobRunner(self.state)
        self._undo = UndoHistory()
        self._render = threading.Lock()
        self._renderer = SilhouetteRenderer(models, self.image_ids, self.views, self.options.detail)
        self._contours: dict[int, tuple[int, Outlines]] = {}  # instance -> (pose_revision, its outlines)

    @property
    def session_path(self) -> Path:
        return self.file.path

    @property
    def instances(self) -> dict[int, LabelledInstance]:
        return self.state.instances

    @property
    def revision(self) -> int:
        return self.state.revision

    @property
    def focus(self) -> int | None:
        return self.state.focus

    @property
    def job(self) -> JobState:
        return self.jobs.job

    def wait(self, since: int, timeout_s: float) -> int:
        """Block until the revision differs from ``since`` or ``timeout_s`` passed; the revision
        (:meth:`~autoalign.label.state.SessionState.wait`)."""
        return self.state.wait(since, timeout_s)

    def start_job(self, kind: str, instance: int | None, work: Callable[[Progress], None]) -> bool:
        """Run ``work(progress)`` on a thread of its own unless a job is running (then ``False``).
        Its progress and its error, if any (one line), are in :attr:`job` for the page."""
        return self.jobs.start(kind, instance, work)

    # ------------------------------------------------------------------ what the page shows

    def snapshot(self) -> dict[str, Any]:
        """Everything the page shows but the images and contours, as JSON."""
        with self.state.lock:
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

    def contours(self, index: int) -> tuple[int, Outlines]:
        """``(pose_revision, {image_id: polylines})`` of instance ``index``'s silhouette in every view."""
        with self.state.lock:
            inst = self.instances[index]
            cached = self._contours.get(index)
            if not inst.placed:
                return inst.pose_revision, {}
            if cached is not None and cached[0] == inst.pose_revision:
                return cached
        with self._render:
            with self.state.lock:
                inst = self.instances[index]
                rev, T, obj = inst.pose_revision, inst.T_wm, inst.obj_id
            if not inst.placed:
                return rev, {}
            polys = outlines(self._renderer.silhouettes(obj, T))
        with self.state.lock:
            if self.instances[index].pose_revision == rev:
                self._contours[index] = (rev, polys)
        return rev, polys

    # ------------------------------------------------------------------ moving a pose (render lock held)

    def _store_pose(self, index: int, obj_id: int, T_wm: NDArray[np.float64], source: str,
                    judged: Judgement | None = None, click: tuple[int, float, float] | None = None) -> None:
        """Set the pose (and its judgement; placed from a ``click``, image id and OpenCV u, v: far from it, flagged).
        Raises, changing nothing, if the pose is not a finite rigid transform near the scene
        (:func:`~autoalign.label.records.pose_problem`). A click's searched and refining poses
        (:data:`~autoalign.label.records.SHOWN_ONLY`) are shown but neither saved
        (:meth:`SessionState.put`) nor kept for undo: the judged pose replaces them."""
        T_wm = checked_pose(T_wm, f"instance {index}: refused a pose ({source})")
        silhouettes = self._renderer.silhouettes(obj_id, T_wm)  # ray-cast once for the fit and the outlines
        judged = judged if click is None or judged is None else far_from_click(judged, silhouettes[click[0]], *click)
        ious, polys = fit(self.scene_of(index), silhouettes), outlines(silhouettes)
        with self.state.lock:
            inst = self.instances[index]
            if inst.placed and inst.source not in SHOWN_ONLY:
                self._undo.push(inst)
            self._contours[index] = (inst.pose_revision + 1, polys)
            self.state.put(moved(inst, obj_id, T_wm, source, ious, judged), shown_only=source in SHOWN_ONLY)

    def _judged(self, index: int, obj_id: int, result: RefineResult) -> Judgement:
        """The verdict on a refinement of instance ``index`` (as ``refine`` gives it) and its uncertainty."""
        return judged_refinement(result, self.scene_of(index), self.models, obj_id)

    def undo(self, index: int) -> None:
        """Put instance ``index`` back where it was before its last move (with what autoalign said of
        it there); its decision stays. Kept for the last :data:`~autoalign.label.undo.UNDO_STEPS`
        moves while the server runs."""
        with self._render:
            with self.state.lock:
                before = self._undo.pop(index)
                now = self._known(index)
                self.instances[index] = replace(before, decision=now.decision, symmetric=now.symmetric,
                                                pose_revision=now.pose_revision + 1)
                self._contours.pop(index, None)
                self.state.changed()

    # ------------------------------------------------------------------ what a person does

    def place(self, obj_id: int, image_id: int, u: float, v: float, progress: Progress | None = None) -> int:
        """Place ``obj_id`` on the instance clicked at OpenCV pixel ``(u, v)`` of ``image_id``: position from
        the click's ray and the other views' masks, orientation searched, then refined (``engine.refine``,
        with the photos where the scene has them); returns the instance. The search's first pose is shown at
        once (:data:`~autoalign.label.records.SEARCHED`), each refined pose before its uncertainty and
        verdict (:data:`~autoalign.label.records.REFINING`), and the judged pose last. A click next to a
        mask that missed the part clicked means that mask's instance
        (:meth:`~autoalign.label.scene.SessionScene.click_target`)."""
        self.check_object(obj_id)
        index, *near = self.click_target(image_id, u, v)  # off a mask but next to one: seeded from its mask
        iu, iv = uv_from_opencv(np.array(near, dtype=np.float64))
        show = click_previews(lambda T_wm, source: self._store_pose(index, obj_id, T_wm, source))
        with self._render, shown_until_judged(self.state, self._contours, index):
            result = refine(self.scene_of(index), self.models.pyramid(obj_id),
                            Click(image_id, float(iu), float(iv)), self.options, progress=progress, preview=show)
            self._store_pose(index, obj_id, result.T_wm, "click", self._judged(index, obj_id, result),
                             (image_id, float(u), float(v)))  # the person's own click, for the distance
        return index

    def refine_from_here(self, index: int, progress: Progress | None = None) -> None:
        """Refine instance ``index`` from its current pose (after a nudge or a drag); the refined pose is
        shown before its uncertainty and verdict (:data:`~autoalign.label.records.REFINING`), then judged."""
        with self._render, shown_until_judged(self.state, self._contours, index):
            inst = self._placed(index)
            shown = lambda T_wm: self._store_pose(index, inst.obj_id, T_wm, REFINING)  # noqa: E731
            result = refine(self.scene_of(index), self.models.pyramid(inst.obj_id), inst.T_wm.copy(), self.options,
                            progress=progress, preview=shown)
            self._store_pose(index, inst.obj_id, result.T_wm, "refine", self._judged(index, inst.obj_id, result))

    def refine_together(self, progress: Progress | None = None) -> None:
        """Refine every placed instance that is not rejected together, as ``autoalign refine --models``
        does from ``--init`` poses where they are placed (:func:`~autoalign.scene.refine.refine_scene`:
        each alone from its pose, then all of them occlusion-aware, with the scene's depth and photos,
        each judged as the command judges it), so that the page and the command agree."""
        from autoalign.scene.refine import refine_scene

        with self._render:
            with self.state.lock:
                chosen = [i for i in self.instances.values() if i.placed and i.decision != "rejected"]
            if len(chosen) < 2:
                raise AutoalignError("refining together needs two or more placed instances that are not rejected; "
                                     "place more, or refine the one from where it is")
            together = replace(self.found, instances=[Instance(i.index, i.obj_id) for i in chosen],
                               scenes=[self.scene_of(i.index) for i in chosen])
            obj_of = {i.index: i.obj_id for i in chosen}
            shown = lambda k, T_wm: self._store_pose(k, obj_of[k], T_wm, REFINING)  # noqa: E731
            with shown_until_judged(self.state, self._contours, *obj_of):  # each alone pose shown as it comes
                refined = refine_scene(together, self.models, {i.index: i.T_wm.copy() for i in chosen}, self.options,
                                       progress=progress, preview=shown)
                for r in refined.results:
                    self._store_pose(r.instance.index, r.instance.obj_id, r.result.T_wm, "together",
                                     Judgement(r.verdict, r.result.uncertainty,
                                               self.models.continuous_axes(r.instance.obj_id)))

    def nudge(self, index: int, image_id: int, move_mm: list[float], turn_deg: list[float]) -> None:
        """Move instance ``index`` by ``move_mm`` and turn it by ``turn_deg`` (rotation vector) about
        its centre, along the axes of camera ``image_id`` (x right, y down, z forward)."""
        move, turn = nudge_vectors(move_mm, turn_deg)
        cam = self.view(image_id)
        with self._render:
            inst = self._placed(index)
            T = nudged_pose(inst.T_wm, self.models.mesh(inst.obj_id).centre, cam, move, turn)
            self._store_pose(index, inst.obj_id, T, "nudge")

    def set_pose(self, index: int, T_wm: NDArray[np.float64], source: str = "3d") -> None:
        """Put instance ``index`` at ``T_wm`` (4x4, mm), e.g. where it was dragged in the 3D view."""
        T = checked_pose(T_wm, f"instance {index}: refused a pose")
        with self._render:
            inst = self._placed(index)
            self._store_pose(index, inst.obj_id, T, source)

    def decide(self, index: int, decision: str) -> None:
        """Record ``accepted``, ``rejected`` or ``open`` for instance ``index``."""
        if decision not in DECISIONS:
            raise AutoalignError(f"decision {decision!r}: one of {', '.join(DECISIONS)}")
        with self.state.lock:
            inst = self._placed(index) if decision == "accepted" else self._known(index)
            self.instances[index] = replace(inst, decision=decision)
            self.state.changed()

    def focus_on(self, index: int) -> None:
        """Note the instance a person selected on a page (not saved: it is where they look, not a label)."""
        with self.state.lock:
            self._known(index)
            if self.state.focus != index:
                self.state.focus = index
                self.state.changed(save=False)

    def mark_symmetric(self, index: int, symmetric: bool) -> None:
        with self.state.lock:
            self.instances[index] = replace(self._known(index), symmetric=bool(symmetric))
            self.state.changed()

    def _known(self, index: int) -> LabelledInstance:
        self.check_instance(index)
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
        with self.state.lock:
            chosen = [(i.obj_id, i.T_wm) for i in self.instances.values() if i.decision == "accepted" and i.placed]
        if not chosen:
            raise AutoalignError("no instance is accepted yet; accept the labels to export first")
        return scene_gt_of(chosen, self.views, self.image_ids)
