"""The 3D view of ``autoalign label``, with viser: the cameras as frustums (with their photos), the
fused cloud ``recon`` made (``SCENE_DIR/cloud.ply``), every placed object at its pose, and a
transform gizmo to drag or turn the chosen one (the page then shows its new outlines).

viser is what 3D-vision tools use for this (meshes, frustums, point clouds, images and gizmos in
the browser, from Python, through its own websocket server); the page embeds it. It listens on
127.0.0.1 only. viser works in metres: everything is drawn at 1/1000 of the scene's millimetres.
"""

from __future__ import annotations

import contextlib
import io
import threading

import numpy as np
from numpy.typing import NDArray

from autoalign.cli.label_http import HOST, instance_rgb
from autoalign.label.session import LabelSession

MM_PER_UNIT = 1000.0
MAX_CLOUD_POINTS = 200_000
THUMB_WIDTH = 160


def _no_banner() -> contextlib.AbstractContextManager[object]:
    """Silence what viser prints on stdout as it starts and stops: a boxed URL of its own port (its
    ``verbose=False`` does not cover it), which people opened instead of the page's own URL printed below it."""
    return contextlib.redirect_stdout(io.StringIO())


class SceneViewer:
    """A viser server showing ``session``, kept up to date by a thread that follows its revisions."""

    def __init__(self, session: LabelSession) -> None:
        import viser

        self.session = session
        with _no_banner():
            self.server = viser.ViserServer(host=HOST, port=0, verbose=False)
        self.server.scene.set_up_direction("+z")
        self._shown: dict[int, tuple[int | None, int]] = {}  # instance -> (obj_id, pose_revision) drawn
        self._handles: dict[int, object] = {}
        self.frustums: dict[int, object] = {}  # image id -> its frustum
        self.cloud: object | None = None
        self._stop = threading.Event()
        self._add_cameras()
        self._add_cloud()
        self._add_origin()
        self._frame_view()
        options = [str(k) for k in session.instances]
        self.choice = self.server.gui.add_dropdown("instance to move", options, initial_value=options[0])
        self.gizmo = self.server.scene.add_transform_controls("/gizmo", scale=0.08, visible=False)
        self.choice.on_update(lambda _: self._chosen())
        self.gizmo.on_update(lambda event: self._dragged() if event.phase == "end" else None)  # on release
        self._thread = threading.Thread(target=self._follow, name="autoalign-3d", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}/"

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)  # it waits at most a second for the session
        with _no_banner():
            self.server.stop()

    # ------------------------------------------------------------------ what is drawn

    def _add_cameras(self) -> None:
        import viser.transforms as tf

        from autoalign.quality.overlay import photo_at

        s = self.session
        for im, cam in zip(s.image_ids, s.views):
            photo = photo_at(s.scene_dir, im, THUMB_WIDTH, max(1, round(THUMB_WIDTH * cam.height / cam.width)))
            self.frustums[im] = self.server.scene.add_camera_frustum(
                f"/cameras/{im}", fov=float(2 * np.arctan(cam.height / (2 * cam.K[1, 1]))),
                aspect=cam.width / cam.height, scale=0.03, thickness=0.0015, color=(90, 110, 140),
                image=None if photo is None else photo[:, :, ::-1].copy(),
                wxyz=tf.SO3.from_matrix(cam.R_w2c.T).wxyz, position=cam.centre / MM_PER_UNIT)

    def _add_cloud(self) -> None:
        path = self.session.scene_dir / "cloud.ply"
        if not path.is_file():
            return
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(path))
        pts = np.asarray(pcd.points)
        if len(pts) == 0:
            return
        keep = np.random.default_rng(0).choice(len(pts), min(len(pts), MAX_CLOUD_POINTS), replace=False)
        colours = (np.asarray(pcd.colors)[keep] * 255).astype(np.uint8) if pcd.has_colors() else (180, 180, 180)
        self.cloud = self.server.scene.add_point_cloud("/cloud", pts[keep] / MM_PER_UNIT, colours, point_size=0.002)

    def _frame_view(self) -> None:
        """Start the browser's camera above the ring of views, looking at where they look."""
        from autoalign.engine.seeding import closest_point_to_rays

        s = self.session
        centres = np.array([c.centre for c in s.views]) / MM_PER_UNIT
        target = closest_point_to_rays(centres, np.array([c.R_w2c[2] for c in s.views]))
        spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) or 0.5
        up = np.array([0.0, 0.0, 1.0])
        self.server.initial_camera.look_at = target
        self.server.initial_camera.position = target + up * spread + np.array([spread, -spread, 0.0])
        self.server.initial_camera.up = up

    def _add_origin(self) -> None:
        """A small sphere at the world origin, drawn like the objects: the browser prepares its
        shaders when the view opens rather than at the first placed object (seconds in software WebGL)."""
        import trimesh

        ball = trimesh.creation.icosphere(subdivisions=2, radius=4.0)
        self.server.scene.add_mesh_simple("/origin", ball.vertices / MM_PER_UNIT, ball.faces, color=(200, 200, 200))

    def _follow(self) -> None:
        revision = -1
        while not self._stop.is_set():
            revision = self.session.wait(revision, 1.0)
            try:
                self._update()
            except Exception:  # the viewer is closing; the page and the session go on
                if self._stop.is_set():
                    return
                raise

    def _update(self) -> None:
        import viser.transforms as tf

        focus = self.session.focus
        if focus is not None and str(focus) != self.choice.value:
            self.choice.value = str(focus)
            self._place_gizmo()
        for k, inst in list(self.session.instances.items()):
            key = (inst.obj_id, inst.pose_revision)
            if not inst.placed or self._shown.get(k) == key:
                continue
            if k not in self._handles or self._shown[k][0] != inst.obj_id:
                mesh = self.session.models.mesh(inst.obj_id)
                self._handles[k] = self.server.scene.add_mesh_simple(
                    f"/objects/{k}", mesh.vertices / MM_PER_UNIT, mesh.faces, color=instance_rgb(self.session, k))
            handle = self._handles[k]
            handle.wxyz = tf.SO3.from_matrix(inst.T_wm[:3, :3]).wxyz
            handle.position = inst.T_wm[:3, 3] / MM_PER_UNIT
            self._shown[k] = key
            if str(k) == self.choice.value:
                self._place_gizmo()

    def _chosen(self) -> None:
        """An instance chosen in the 3D view's panel: the gizmo goes to it, and it is the session's focus
        (else the next change would send the panel back to the page's selection)."""
        self.session.focus_on(int(self.choice.value))
        self._place_gizmo()

    def _place_gizmo(self) -> None:
        import viser.transforms as tf

        inst = self.session.instances[int(self.choice.value)]
        if not inst.placed:
            self.gizmo.visible = False
            return
        centre = inst.T_wm[:3, :3] @ self.session.models.mesh(inst.obj_id).centre + inst.T_wm[:3, 3]
        self.gizmo.wxyz = tf.SO3.from_matrix(inst.T_wm[:3, :3]).wxyz
        self.gizmo.position = centre / MM_PER_UNIT
        self.gizmo.visible = True

    def gizmo_pose(self, index: int) -> NDArray[np.float64]:
        """The world-from-model pose (mm) the gizmo now gives instance ``index``."""
        import viser.transforms as tf

        inst = self.session.instances[index]
        R = tf.SO3(np.asarray(self.gizmo.wxyz)).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.asarray(self.gizmo.position) * MM_PER_UNIT - R @ self.session.models.mesh(inst.obj_id).centre
        return T

    def _dragged(self) -> None:
        index = int(self.choice.value)
        if self.session.instances[index].placed:
            self.session.set_pose(index, self.gizmo_pose(index), source="3d")
