"""Synthetic hand-held RGB-D streams of textured objects on a textured table, rendered with mitsuba.

Every pixel's ray (through the pixel centre, OpenCV / BOP intrinsics written to the files) is cast
with mitsuba at the table and the objects placed in the world frame; its colour is a solid texture
of the 3D hit point (a sum of random sinusoids, so every surface carries texture at many scales
without UV maps) shaded by the angle to the ray, and its depth is the hit's z in the camera (mm).
The world frame has z up and the table top at z = 0. The camera walks a wobbly loop around the
scene at 380-520 mm, looking at its middle with a few degrees of jitter, as a hand-held phone does.

Written as a capture folder: ``rgb/{i:06d}.png``, ``depth/{i:06d}.png`` (16-bit, ``depth_scale``
mm per unit), ``intrinsics.json`` (``cam_K``, OpenCV convention, ``width``, ``height``) and, for
evaluation only, ``gt/scene_camera.json`` (the true cameras, BOP) and ``gt/scene_gt.json`` plus
``gt/models/`` (the objects).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.experiments.scenes.procedural_models import (
    procedural_models,
    write_models,
)
from autoalign.experiments.scenes.synthetic import (
    default_K,
    pixel_rays,
    random_rotation,
)
from autoalign.geometry.camera import Camera, look_at
from autoalign.geometry.mesh import Mesh, mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.bop import scene_gt_of
from autoalign.runtime.backend import jit_array, mitsuba

DEPTH_SCALE = 0.1
"""mm per unit of the written 16-bit depth (BOP's usual 0.1: 0.1 mm steps up to 6.5 m)."""


@dataclass
class Stream:
    """A rendered stream: the true cameras (world: z up, table top at z = 0, mm), the objects
    (meshes and world-from-model poses) and the folder it was written to."""

    folder: Path
    cameras: list[Camera]
    meshes: list[Mesh]
    poses: list[NDArray[np.float64]]


def table_mesh(size_mm: float = 600.0, thickness_mm: float = 20.0) -> Mesh:
    """A square table top (mm) whose upper face is z = 0."""
    import trimesh

    box = trimesh.creation.box((size_mm, size_mm, thickness_mm))
    box.apply_translation((0.0, 0.0, -thickness_mm / 2.0))
    return mesh_from_trimesh(box, "table")


class SolidTexture:
    """Colour (RGB in [0, 1]) of world points: a sum of random sinusoids per channel."""

    def __init__(self, rng: np.random.Generator, n: int = 24) -> None:
        periods = np.exp(rng.uniform(np.log(8.0), np.log(80.0), n))  # mm
        dirs = rng.normal(size=(n, 3))
        self.freq = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * (2 * np.pi / periods)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, n)
        self.mix = rng.uniform(0.2, 1.0, (n, 3))

    def __call__(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        s = np.sin(X @ self.freq.T + self.phase)  # (N, n)
        c = s @ self.mix / np.sqrt(len(self.phase))
        return np.clip(0.5 + 0.9 * np.tanh(1.5 * c), 0.0, 1.0)


def hand_held_path(n: int, rng: np.random.Generator, K: NDArray[np.float64], width: int, height: int,
                   target: tuple[float, float, float] = (0.0, 0.0, 40.0)) -> list[Camera]:
    """``n`` cameras along a wobbly loop around ``target`` (mm): 1.2 turns, distance 380-520 mm,
    elevation 30-55 degrees, the aim jittered by a few degrees, small jerks frame to frame."""
    t = np.linspace(0.0, 1.2 * 2 * np.pi, n)
    wob = lambda f, a: a * np.sin(f * t + rng.uniform(0, 2 * np.pi))  # noqa: E731
    dist = 450.0 + wob(3.0, 70.0)
    elev = np.radians(42.0 + wob(2.0, 12.0))
    aim = np.asarray(target) + np.stack([wob(5.0, 20.0), wob(4.0, 20.0), wob(3.0, 10.0)], 1)
    cams = []
    for k in range(n):
        d = np.array([np.cos(elev[k]) * np.cos(t[k]), np.cos(elev[k]) * np.sin(t[k]), np.sin(elev[k])])
        eye = np.asarray(target) + dist[k] * d + rng.normal(0.0, 1.0, 3)
        cams.append(look_at(eye, aim[k], K, width, height, up=np.array([0.0, 0.0, 1.0])))
    return cams


def render_stream(folder: str | Path, n_frames: int = 200, width: int = 640, height: int = 480, n_objects: int = 5,
                  seed: int = 0, depth: bool = True) -> Stream:
    """Render and write a stream (see the module doc)."""
    folder = Path(folder)
    rng = np.random.default_rng(seed)
    pool = procedural_models()
    chosen = [pool[int(i)] for i in rng.choice(len(pool), n_objects, replace=False)]
    write_models(folder / "gt" / "models", chosen)
    meshes = [mesh_from_trimesh(pm.mesh, pm.name) for pm in chosen]
    poses = []
    for j, m in enumerate(meshes):  # on a ring on the table, resting on their lowest point
        a = 2 * np.pi * j / n_objects + rng.uniform(-0.2, 0.2)
        R = random_rotation(rng)
        low = float((m.vertices @ R.T)[:, 2].min())
        poses.append(make_pose(R, np.array([110.0 * np.cos(a), 110.0 * np.sin(a), -low])))
    K = default_K(width, height, 0.9 * width)
    cams = hand_held_path(n_frames, rng, K, width, height)
    table = table_mesh()
    tex = SolidTexture(rng)
    mi = mitsuba()
    shapes = {}
    for name, mesh, T in [("table", table, np.eye(4))] + [(f"obj{j}", m, T) for j, (m, T) in enumerate(zip(meshes, poses))]:
        V = transform_points(T, mesh.vertices)
        sh = mi.Mesh(name, vertex_count=len(V), face_count=len(mesh.faces), has_vertex_normals=False,
                     has_vertex_texcoords=False)
        params = mi.traverse(sh)
        params["vertex_positions"] = jit_array(mi.Float, V.ravel(), np.float32)
        params["faces"] = jit_array(mi.UInt32, mesh.faces.ravel(), np.uint32)
        params.update()
        shapes[name] = sh
    scene = mi.load_dict({"type": "scene", **shapes})
    for sub in ("rgb", "depth", "gt"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(cams):
        o, d = pixel_rays(cam)
        dn = d / np.linalg.norm(d, axis=1, keepdims=True)
        ray = mi.Ray3f(mi.Point3f(*[jit_array(mi.Float, np.full(len(dn), o[k]), np.float32) for k in range(3)]),
                       mi.Vector3f(*[jit_array(mi.Float, dn[:, k], np.float32) for k in range(3)]))
        si = scene.ray_intersect(ray)
        t = np.array(si.t, dtype=np.float64)
        hit = np.isfinite(t)
        P = o + dn * np.where(hit, t, 0.0)[:, None]
        n = np.stack([np.array(si.n[k], dtype=np.float64) for k in range(3)], 1)
        shade = 0.35 + 0.65 * np.abs(np.einsum("ij,ij->i", n, dn))
        rgb = np.where(hit[:, None], tex(P) * shade[:, None], 0.15)
        img = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8).reshape(height, width, 3)
        cv2.imwrite(str(folder / "rgb" / f"{i:06d}.png"), img[:, :, ::-1])
        if depth:
            z = np.where(hit, t * (dn @ cam.R_w2c[2]), 0.0).reshape(height, width)
            cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), np.round(z / DEPTH_SCALE).astype(np.uint16))
    intr = {"cam_K": [float(x) for x in cams[0].K_opencv.ravel()], "width": width, "height": height}
    (folder / "intrinsics.json").write_text(json.dumps(intr, indent=1))
    gt_cams = {str(i): {"cam_K": [float(x) for x in c.K_opencv.ravel()], "cam_R_w2c": [float(x) for x in c.R_w2c.ravel()],
                        "cam_t_w2c": [float(x) for x in c.t_w2c], "depth_scale": DEPTH_SCALE} for i, c in enumerate(cams)}
    (folder / "gt" / "scene_camera.json").write_text(json.dumps(gt_cams, indent=1))
    gt = scene_gt_of([(j + 1, T) for j, T in enumerate(poses)], cams, list(range(len(cams))))
    (folder / "gt" / "scene_gt.json").write_text(json.dumps(gt))
    if not depth:
        (folder / "depth").rmdir()
    return Stream(folder, cams, meshes, poses)
