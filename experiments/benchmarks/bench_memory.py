"""Benchmark of memory and time for large photos: 24 views of 12-megapixel photos and masks (4000 x 3000).

The scene's masks are ray-cast by open3d at 640 x 480 and enlarged 6.25 times (nearest pixel),
with the cameras scaled exactly (:meth:`Camera.scaled`), so that building it takes seconds; the
object is a procedural mug, the start 10 mm / 15 degrees off. Its photos (JPEG) are the mug with
smooth random vertex colours on a random-texture floor, rendered at 640 x 480 and enlarged the same
way, with pixel noise at full size (:func:`write_photos`). The whole ``autoalign refine`` command
runs in a child process, once as it ships (masks read downscaled to at most
:data:`autoalign.io.bop.MAX_IMAGE_PIXELS`) and once reading them at full size; then ``autoalign check``
of the true labels on all 24 photos (``--out``: check.json and check.png), as it ships and with its
downscaling switched off, all in the same session; the peak resident memory of each child is its
``ru_maxrss``, and check's wall time is compared with refine's (as shipped) of the same session.
The scene is built in a child process of its own: Linux keeps a process's peak resident memory
across ``exec``, so a command started from a process that held the scene's 12-megapixel arrays
would report that process's peak as its own (the results before this fix did, for refine: 1472 MB).
Results: ``experiments/results/bench_memory.md``.

``python -m autoalign.experiments.benchmarks.bench_memory``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.commands import autoalign_command
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import (
    make_scene,
    perturb_pose,
    random_rotation,
    ring_cameras,
    write_scene,
)
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, rotation_angle_deg
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import Scene, scene_gt_dict

if TYPE_CHECKING:
    import trimesh

ENLARGE = 6.25  # 640 x 480 -> 4000 x 3000
# The commands with the downscaling switched off: the pixel budget lifted before main runs.
_FULL_SIZE = {
    "refine": ("import functools, sys, autoalign.io.bop as b; "
               "b.read_scene = functools.partial(b.read_scene, max_pixels=None); "
               "from autoalign.cli.main import main; sys.exit(main(sys.argv[1:]))"),
    "check": ("import functools, sys, autoalign.quality.scene_check as sc; "
              "sc.check_prepared = functools.partial(sc.check_prepared, max_pixels=None); "
              "from autoalign.cli.main import main; sys.exit(main(sys.argv[1:]))"),
}


def build_scene(root: Path, views: int = 24, seed: int = 0) -> np.ndarray:
    """Write ``root/scene`` (BOP, with photos), ``root/model.ply``, ``root/models/`` (coloured, for check)
    and ``root/init.json``; return the true pose."""
    rng = np.random.default_rng(seed)
    pm = next(m for m in procedural_models() if m.name == "mug")
    mesh = mesh_from_trimesh(pm.mesh, "mug")
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    small = make_scene(mesh, T, ring_cameras(views, rng))
    big = [c.scaled(ENLARGE) for c in small.cameras]
    masks = [cv2.resize(m.astype(np.uint8), (c.width, c.height), interpolation=cv2.INTER_NEAREST).astype(np.float32)
             for m, c in zip(small.masks, big)]
    write_scene(root / "scene", Scene(big, masks, small.image_ids), T)
    mesh.trimesh.export(root / "model.ply")
    T0 = perturb_pose(T, 10.0, 15.0, rng, mesh.centre)
    write_photos(root, pm.mesh, T, small, big, np.random.default_rng([seed, 1]))  # refine's scene as before
    write_json_atomic(root / "init.json", scene_gt_dict(T0, big[:1], small.image_ids[:1]))
    return T


def write_photos(root: Path, tm: "trimesh.Trimesh", T_wm: np.ndarray, small: Scene, big: list, rng: np.random.Generator
                 ) -> None:
    """Photos for ``autoalign check``: ``root/scene/rgb/*.jpg`` (4000 x 3000, JPEG quality 90) and
    ``root/models/obj_000001.ply``, the mug cut into triangles of at most 3 mm with smooth random
    vertex colours (blobs of about 10 mm, as SIFT needs texture). Each photo is that model
    ray-cast at 640 x 480 over a random-texture floor, enlarged 6.25 times (bilinear) like the
    masks, with pixel noise at full size (sigma 4 grey levels) so the full-size image has fine
    detail as a photo does."""
    import trimesh

    from autoalign.geometry.mesh import ColouredMesh
    from autoalign.rasterizers.label_rendering import PlacedMesh, render_labels

    V, F = trimesh.remesh.subdivide_to_size(tm.vertices, tm.faces, 3.0)
    freqs, phases = rng.normal(size=(3, 6, 3)) / 6.0, rng.uniform(0.0, 2 * np.pi, (3, 6))
    C = np.stack([0.5 + 0.5 * np.tanh(np.sin(V @ freqs[c].T + phases[c]).sum(1)) for c in range(3)], 1)
    (root / "models").mkdir()
    trimesh.Trimesh(V, F, vertex_colors=(C * 255).astype(np.uint8), process=False).export(
        root / "models" / "obj_000001.ply")
    mesh = ColouredMesh(np.asarray(V, np.float64), np.asarray(F, np.int64), C.astype(np.float32), True)
    (root / "scene" / "rgb").mkdir()
    for im, cam, cam_big in zip(small.image_ids, small.cameras, big):
        T_cm = cam.T_cw @ T_wm
        r = render_labels([PlacedMesh(0, mesh, T_cm[:3, :3], T_cm[:3, 3])], cam.K_opencv, cam.width, cam.height)
        floor = cv2.resize(rng.uniform(60, 200, (cam.height // 8, cam.width // 8, 3)).astype(np.float32),
                           (cam.width, cam.height), interpolation=cv2.INTER_CUBIC)
        small_bgr = np.where((r.instance >= 0)[..., None], r.rgb[..., ::-1].astype(np.float32), floor)
        photo = cv2.resize(small_bgr, (cam_big.width, cam_big.height), interpolation=cv2.INTER_LINEAR)
        photo += rng.normal(0.0, 4.0, photo.shape).astype(np.float32)
        cv2.imwrite(str(root / "scene" / "rgb" / f"{im:06d}.jpg"), np.clip(photo, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, 90])


def build_scene_apart(root: Path) -> np.ndarray:
    """:func:`build_scene` in a child process (see the module docstring); the true pose."""
    code = ("import json, sys; from pathlib import Path; from autoalign.experiments.benchmarks.bench_memory import build_scene; "
            "T = build_scene(Path(sys.argv[1])); Path(sys.argv[1], 'truth.json').write_text(json.dumps(T.tolist()))")
    subprocess.run([sys.executable, "-c", code, str(root)], check=True)
    return np.asarray(json.loads((root / "truth.json").read_text()))


def own_peak_mb() -> float:
    """This process's peak resident memory (MB): a floor under every child's ``ru_maxrss``."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_command(root: Path, out: Path, command: str, full_size: bool) -> dict:
    """Run ``autoalign refine`` or ``autoalign check`` in a child process; its wall time and peak memory."""
    scene = str(root / "scene")
    if command == "refine":
        args = ["refine", scene, "--model", str(root / "model.ply"), "--init", str(root / "init.json")]
    else:
        args = ["check", scene, "--labels", str(root / "scene" / "scene_gt.json"), "--models", str(root / "models")]
    args += ["--out", str(out), "--quiet"]
    cmd = ([sys.executable, "-c", _FULL_SIZE[command], *args] if full_size
           else autoalign_command(*args))
    t0 = time.perf_counter()
    pid = subprocess.Popen(cmd, stdout=subprocess.DEVNULL).pid
    _, status, usage = os.wait4(pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed with {os.waitstatus_to_exitcode(status)}")
    return {"command": command, "wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0, "floor_mb": own_peak_mb()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        T = build_scene_apart(root)
        for label, full in (("downscaled on reading (default)", False), ("full size", True)):
            out = root / f"refine_{int(full)}"
            r = run_command(root, out, "refine", full)
            rec = json.loads((out / "refine.json").read_text())
            P = np.asarray(rec["pose"]["T_wm"])
            r.update(reading=label, image_scale=rec["image_scale"], err_mm=float(np.linalg.norm(P[:3, 3] - T[:3, 3])),
                     err_deg=rotation_angle_deg(P[:3, :3], T[:3, :3]), mean_iou=rec["mean_iou_after"])
            rows.append(r)
            print(json.dumps(r), flush=True)
        for label, full in (("downscaled on reading (default)", False), ("full size", True)):
            out = root / f"check_{int(full)}"
            r = run_command(root, out, "check", full)
            rec = json.loads((out / "check.json").read_text())
            r.update(reading=label, image_scale=rec["image_scale"], images=len(rec["image_ids"]),
                     mean_px=rec["mean_px"], edge_px=rec["edge_px"], n_matches=rec["n_matches"],
                     check_png_bytes=(out / "check.png").stat().st_size)
            rows.append(r)
            print(json.dumps(r), flush=True)
    refine = [r for r in rows if r["command"] == "refine"]
    check = [r for r in rows if r["command"] == "check"]
    base = refine[0]
    lines = ["# autoalign memory benchmark: 24 views of 12-megapixel photos and masks", "",
             f"`python -m autoalign.experiments.benchmarks.bench_memory` on {platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()}; each whole command in a child process, peak resident memory from "
             f"`wait4` (the benchmark's own process, whose peak every child inherits as a floor, peaked at "
             f"{max(r['floor_mb'] for r in rows):.0f} MB). Ratios are against the first row (`refine` as shipped), run "
             "in the same session.", "",
             "`autoalign refine --init`:", "",
             "| masks read | image scale | peak memory MB | ratio | wall s | ratio | err mm | err deg | mean IoU |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in refine:
        lines.append(f"| {r['reading']} | {r['image_scale']:g} | {r['peak_rss_mb']:.0f} | "
                     f"{r['peak_rss_mb'] / base['peak_rss_mb']:.2f} | {r['wall_s']:.1f} | {r['wall_s'] / base['wall_s']:.2f} | "
                     f"{r['err_mm']:.3f} | {r['err_deg']:.3f} | {r['mean_iou']:.4f} |")
    lines += ["", "`autoalign check --out` of the true labels on all 24 photos (feature and edge distance in the "
              "files' pixels: check.json's px divided by its image scale):", "",
              "| photos and masks read | image scale | peak memory MB | wall s | wall / refine | matches | "
              "feature distance px | edge distance px |",
              "|---|---|---|---|---|---|---|---|"]
    for r in check:
        s = r["image_scale"]
        lines.append(f"| {r['reading']} | {s:g} | {r['peak_rss_mb']:.0f} | {r['wall_s']:.1f} | "
                     f"{r['wall_s'] / base['wall_s']:.2f} | {r['n_matches']} | {r['mean_px'] / s:.2f} | "
                     f"{r['edge_px'] / s:.2f} |")
    write_results("bench_memory", rows, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
