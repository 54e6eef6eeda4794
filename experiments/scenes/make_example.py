"""Regenerate the bundled example scene ``autoalign/data/example`` (deterministic).

A procedural mug (asymmetric: its handle) with vertex colours, 24 views of 640x480 from a ring
20-50 degrees above a table, masks ray-cast by open3d, photos ray-cast by mitsuba, and a coarse
``init_gt.json`` 10 mm / 20 degrees off the truth. Written into ``DIR``:

* ``scene/``: ``scene_camera.json``, ``scene_gt.json`` (the truth), ``mask_visib/`` and ``rgb/``
  (JPEG photos: the mug's vertex colours, shaded, on a plain table whose top touches the mug's
  lowest point);
* ``model.ply`` (mm, vertex colours) and the same mesh as a BOP models folder, ``models/``
  (``obj_000001.ply``, ``models_info.json``), for ``--models`` (``check``, ``export``, ``label``);
* ``init_gt.json``: the coarse pose, BOP ``scene_gt.json`` of image 0.

``python -m autoalign.experiments.scenes.make_example [DIR] [--force]`` (default ``DIR``: the package's
own ``autoalign/data/example``). An existing non-empty ``DIR`` is refused unless ``--force`` is
given; then only the files listed above are replaced, nothing else in ``DIR`` is touched.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

import autoalign
from autoalign.errors import AutoalignError
from autoalign.experiments.scenes.procedural_models import (
    models_info_entry,
    procedural_models,
)
from autoalign.experiments.scenes.synthetic import (
    perturb_pose,
    pixel_rays,
    random_rotation,
    ring_cameras,
    write_synthetic_scene,
)
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh, mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import scene_gt_dict

DEFAULT_OUT = Path(autoalign.__file__).resolve().parent / "data" / "example"
"""The package's own example (in a checkout: ``autoalign/data/example`` of the repository)."""

PARTS = ("scene", "models", "model.ply", "init_gt.json")
"""What :func:`make_example` writes into its folder (and ``--force`` replaces)."""

JPEG_QUALITY = 75
TABLE_BGR = (150, 172, 190)
"""The table's colour (a light wood tone, BGR); plain, so the photos compress well."""


def vertex_colours(vertices: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.uint8]:
    """RGBA colours (N, 4) of model-frame vertices (mm): bold blotches of a few colours, a sum of
    random sinusoids with periods of 15-60 mm thresholded into a palette, so that the rendered
    object has corners and colour edges for SIFT (its triangles are 5-10 mm across)."""
    n = 12
    periods = np.exp(rng.uniform(np.log(15.0), np.log(60.0), n))
    dirs = rng.normal(size=(n, 3))
    freq = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * (2 * np.pi / periods)[:, None]
    phase = rng.uniform(0, 2 * np.pi, (2, n))
    a = np.sin(vertices @ freq.T + phase[0]).sum(1)
    b = np.sin(vertices @ freq[::-1].T + phase[1]).sum(1)
    palette = np.array([[200, 40, 30], [240, 200, 40], [30, 90, 170], [245, 245, 235]], dtype=np.uint8)  # RGB
    index = (a > 0).astype(int) * 2 + (b > 0).astype(int)
    return np.concatenate([palette[index], np.full((len(vertices), 1), 255, np.uint8)], axis=1)


def render_photos(mesh: Mesh, colours: NDArray[np.uint8], T_wm: NDArray[np.float64], cameras: list[Camera],
                  table_z: float) -> list[NDArray[np.uint8]]:
    """BGR photos (H, W, 3) of the mesh placed by ``T_wm`` on a plain table (the plane
    ``z = table_z``), one ray per pixel centre cast by mitsuba (as the masks' by open3d): the
    object's colour is the barycentric blend of its vertex colours (what ``autoalign check``
    renders), shaded by the angle between ray and surface; the table's fades with distance."""
    from autoalign.runtime.backend import jit_array, mitsuba

    mi = mitsuba()
    V = transform_points(T_wm, mesh.vertices)
    shape = mi.Mesh("object", vertex_count=len(V), face_count=len(mesh.faces), has_vertex_normals=False,
                    has_vertex_texcoords=False)
    params = mi.traverse(shape)
    params["vertex_positions"] = jit_array(mi.Float, V.ravel(), np.float32)
    params["faces"] = jit_array(mi.UInt32, mesh.faces.ravel(), np.uint32)
    params.update()
    scene = mi.load_dict({"type": "scene", "object": shape})
    rgb = colours[:, :3].astype(np.float64) / 255.0
    table = np.asarray(TABLE_BGR, dtype=np.float64)[::-1] / 255.0
    photos = []
    for cam in cameras:
        o, d = pixel_rays(cam)
        dn = d / np.linalg.norm(d, axis=1, keepdims=True)
        ray = mi.Ray3f(mi.Point3f(*[jit_array(mi.Float, np.full(len(dn), o[k]), np.float32) for k in range(3)]),
                       mi.Vector3f(*[jit_array(mi.Float, dn[:, k], np.float32) for k in range(3)]))
        si = scene.ray_intersect(ray)
        hit = np.isfinite(np.array(si.t, dtype=np.float64))
        prim = np.where(hit, np.array(si.prim_index, dtype=np.int64), 0)
        b1, b2 = (np.array(si.uv[k], dtype=np.float64) for k in range(2))  # barycentric (no texcoords)
        f = mesh.faces[prim]
        colour = (1 - b1 - b2)[:, None] * rgb[f[:, 0]] + b1[:, None] * rgb[f[:, 1]] + b2[:, None] * rgb[f[:, 2]]
        n = np.stack([np.array(si.n[k], dtype=np.float64) for k in range(3)], 1)
        colour *= (0.45 + 0.55 * np.abs(np.einsum("ij,ij->i", n, dn)))[:, None]
        t_table = (table_z - o[2]) / np.where(dn[:, 2] < 0, dn[:, 2], -1.0)  # the table, seen from above
        fade = np.clip(1.15 - t_table / 2500.0, 0.5, 1.0) * (dn[:, 2] < 0) + 0.25 * (dn[:, 2] >= 0)
        img = np.where(hit[:, None], colour, table[None, :] * fade[:, None])
        photos.append((np.clip(img, 0, 1) * 255).round().astype(np.uint8).reshape(cam.height, cam.width, 3)[:, :, ::-1])
    return photos


def make_example(out: str | os.PathLike[str] = DEFAULT_OUT, seed: int = 7, force: bool = False) -> Path:
    """Write the example (see the module doc) into ``out``; return ``out``.

    An existing non-empty ``out`` is refused (:class:`~autoalign.errors.AutoalignError`) unless
    ``force``; then only :data:`PARTS` are replaced. Everything is made in a temporary folder
    beside ``out`` first, so a failure leaves ``out`` as it was."""
    import cv2

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AutoalignError(f"{out}: is a file; pass a folder for the example")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise AutoalignError(f"{out}: exists and is not empty; pass --force to replace its "
                             f"{', '.join(PARTS)}, or choose another folder")
    rng = np.random.default_rng(seed)
    model = next(m for m in procedural_models() if m.name == "mug")
    mesh = mesh_from_trimesh(model.mesh, model.name)
    R = random_rotation(rng)
    T_gt = make_pose(R, np.array([12.0, -8.0, 40.0]) - R @ mesh.centre)  # above a table, near its origin
    cams = ring_cameras(24, rng, jitter_mm=10.0, target=(0.0, 0.0, 40.0))
    T0 = perturb_pose(T_gt, 10.0, 20.0, rng, mesh.centre)
    colours = vertex_colours(mesh.vertices, np.random.default_rng([seed, 1]))
    tm = mesh.trimesh.copy()
    tm.visual.vertex_colors = colours
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        scene = write_synthetic_scene(tmp / "scene", mesh, T_gt, cams)
        table_z = float(transform_points(T_gt, mesh.vertices)[:, 2].min())  # the mug rests on it
        (tmp / "scene" / "rgb").mkdir()
        for im, photo in zip(scene.image_ids, render_photos(mesh, colours, T_gt, cams, table_z)):
            cv2.imwrite(str(tmp / "scene" / "rgb" / f"{im:06d}.jpg"), photo, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        tm.export(tmp / "model.ply")
        (tmp / "models").mkdir()
        shutil.copyfile(tmp / "model.ply", tmp / "models" / "obj_000001.ply")
        write_json_atomic(tmp / "models" / "models_info.json", {"1": models_info_entry(model)})
        write_json_atomic(tmp / "init_gt.json", scene_gt_dict(T0, scene.cameras[:1], scene.image_ids[:1]))
        out.mkdir(exist_ok=True)
        for name in PARTS:
            target = out / name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            elif target.exists() or target.is_symlink():
                target.unlink()
            os.replace(tmp / name, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m autoalign.experiments.scenes.make_example``; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m autoalign.experiments.scenes.make_example",
        description="Write the bundled example scene (a mug: masks, photos, cameras, model, coarse pose) into "
                    "DIR, deterministically.")
    parser.add_argument("dir", metavar="DIR", nargs="?", default=str(DEFAULT_OUT),
                        help=f"output folder (default: the package's own example, {DEFAULT_OUT})")
    parser.add_argument("--force", action="store_true",
                        help=f"replace {', '.join(PARTS)} in an existing non-empty DIR (other files there are "
                             "left alone)")
    parser.add_argument("--seed", type=int, default=7, help="random seed (default 7: the bundled example)")
    args = parser.parse_args(argv)
    try:
        print(make_example(Path(args.dir), seed=args.seed, force=args.force))
    except AutoalignError as exc:
        print(f"make_example: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
