"""Benchmark of memory and time for large photos: 24 views of 12-megapixel masks (4000 x 3000).

The scene's masks are ray-cast by open3d at 640 x 480 and enlarged 6.25 times (nearest pixel),
with the cameras scaled exactly (:meth:`Camera.scaled`), so that building it takes seconds; the
object is a procedural mug, the start 10 mm / 15 degrees off. The whole ``autoalign refine``
command runs in a child process, once as it ships (masks read downscaled to at most
:data:`autoalign.bop.MAX_IMAGE_PIXELS`) and once reading them at full size, in the same session;
the peak resident memory of each child is its ``ru_maxrss``. Results:
``experiments/results/bench_memory.md``.

``python -m autoalign.experiments.bench_memory``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from autoalign.atomic_files import write_json_atomic, write_text_atomic
from autoalign.bop import Scene, scene_gt_dict, write_scene
from autoalign.mesh import mesh_from_trimesh
from autoalign.se3 import make_pose, rotation_angle_deg
from autoalign.experiments.procedural_models import procedural_models
from autoalign.experiments.synthetic import make_scene, perturb_pose, random_rotation, ring_cameras

RESULTS = Path(__file__).resolve().parent / "results"
ENLARGE = 6.25  # 640 x 480 -> 4000 x 3000
# The command with the downscaling switched off: read_scene's pixel budget lifted before main runs.
_FULL_SIZE = ("import functools, sys, autoalign.bop as b; "
              "b.read_scene = functools.partial(b.read_scene, max_pixels=None); "
              "from autoalign.cli.main import main; sys.exit(main(sys.argv[1:]))")


def build_scene(root: Path, views: int = 24, seed: int = 0) -> np.ndarray:
    """Write ``root/scene`` (BOP), ``root/model.ply`` and ``root/init.json``; return the true pose."""
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
    write_json_atomic(root / "init.json", scene_gt_dict(T0, big[:1], small.image_ids[:1]))
    return T


def run_command(root: Path, out: Path, full_size: bool) -> dict:
    """Run ``autoalign refine`` in a child process; its wall time and peak memory."""
    args = ["refine", str(root / "scene"), "--model", str(root / "model.ply"), "--init", str(root / "init.json"),
            "--out", str(out), "--quiet"]
    cmd = [sys.executable, "-c", _FULL_SIZE, *args] if full_size else [sys.executable, "-m", "autoalign.cli.main", *args]
    t0 = time.perf_counter()
    pid = subprocess.Popen(cmd).pid
    _, status, usage = os.wait4(pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed with {os.waitstatus_to_exitcode(status)}")
    return {"wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        T = build_scene(root)
        for label, full in (("downscaled on reading (default)", False), ("full size", True)):
            r = run_command(root, root / f"out_{int(full)}", full)
            rec = json.loads((root / f"out_{int(full)}" / "refine.json").read_text())
            P = np.asarray(rec["pose"]["T_wm"])
            r.update(reading=label, image_scale=rec["image_scale"], err_mm=float(np.linalg.norm(P[:3, 3] - T[:3, 3])),
                     err_deg=rotation_angle_deg(P[:3, :3], T[:3, :3]), mean_iou=rec["mean_iou_after"])
            rows.append(r)
            print(json.dumps(r), flush=True)
    base = rows[0]
    lines = ["# autoalign memory benchmark: 24 views of 12-megapixel masks", "",
             f"`python -m autoalign.experiments.bench_memory` on {platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()}; the whole `autoalign refine --init` command in a child process, "
             "peak resident memory from `wait4`. Ratios are against the first row, run in the same session.", "",
             "| masks read | image scale | peak memory MB | ratio | wall s | ratio | err mm | err deg | mean IoU |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['reading']} | {r['image_scale']:g} | {r['peak_rss_mb']:.0f} | "
                     f"{r['peak_rss_mb'] / base['peak_rss_mb']:.2f} | {r['wall_s']:.1f} | {r['wall_s'] / base['wall_s']:.2f} | "
                     f"{r['err_mm']:.3f} | {r['err_deg']:.3f} | {r['mean_iou']:.4f} |")
    a.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(a.out / "bench_memory.json", rows)
    write_text_atomic(a.out / "bench_memory.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
