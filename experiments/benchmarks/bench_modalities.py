"""Benchmark of the evidence ``autoalign refine --models`` uses: masks, photos, both, and depth.

One scene of 8 textured procedural objects on a textured table (:mod:`autoalign.experiments.scenes.photo_scene`:
mitsuba photos, open3d masks, sensor-like depth), 40 views of 640x480 around it, starts 10 mm / 15
degrees off; the whole command in a child process (start-up included), after one warm-up run, for
each choice of evidence. Ratios are against the masks-only row of the same run. Results:
``experiments/results/bench_modalities.md``.

``python -m autoalign.experiments.benchmarks.bench_modalities [--objects 8] [--views 40] [--repeats 1]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.commands import run_autoalign
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.photo_scene import write_photo_scene
from autoalign.experiments.scenes.procedural_models import (
    models_info_entry,
    procedural_models,
    write_models,
)
from autoalign.experiments.scenes.synthetic import perturb_pose
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import scene_gt_of

EVIDENCE = {
    "masks": ["--photos", "off", "--depth", "off"],
    "photos": ["--masks", "none", "--depth", "off"],
    "masks + photos": ["--depth", "off"],
    "masks + depth": ["--photos", "off"],
    "masks + photos + depth": [],
}
"""Each row's evidence and the options that choose it."""


def make_scene(root: Path, n_obj: int, views: int, seed: int = 0) -> tuple[list[np.ndarray], list, list[Symmetries]]:
    """``root/scene`` (with depth), ``root/models``, ``root/init_gt.json``; the true poses, meshes, symmetries."""
    rng = np.random.default_rng([seed, n_obj])
    pool = procedural_models()
    chosen = [pool[int(i)] for i in rng.choice(len(pool), n_obj, replace=False)]
    write_models(root / "models", chosen)
    meshes = [mesh_from_trimesh(p.mesh, p.name) for p in chosen]
    ps = write_photo_scene(root / "scene", meshes, views, seed=seed, depth=True, dist_range=(550.0, 800.0))
    coarse = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(ps.poses, meshes)]
    write_json_atomic(root / "init_gt.json", scene_gt_of([(j + 1, T) for j, T in enumerate(coarse)], ps.cameras[:1], [0]))
    return ps.poses, meshes, [Symmetries.from_info(models_info_entry(p)) for p in chosen]


def time_command(root: Path, *extra: str) -> tuple[float, dict]:
    run = run_autoalign("refine", str(root / "scene"), "--models", str(root / "models"), "--init",
                        str(root / "init_gt.json"), "--out", str(root / "out"), "--quiet", *extra).check()
    return run.wall_s, json.loads((root / "out" / "refine.json").read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", type=int, default=8)
    p.add_argument("--views", type=int, default=40)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        truth, meshes, syms = make_scene(root, a.objects, a.views)
        time_command(root, *EVIDENCE["masks"])  # warm-up: page cache, compiled kernels' files
        for name, options in EVIDENCE.items():
            walls, errs, ok = [], [], 0
            for _ in range(a.repeats):
                wall, rec = time_command(root, *options)
                walls.append(wall)
            for r in rec["instances"]:
                k = r["instance"]
                e = pose_errors(np.asarray(r["pose"]["T_wm"]), truth[k], meshes[k].centre, None, syms[k])
                errs.append((e.pos_err_mm, e.rot_err_deg))
                ok += r["verdict"] == "ok"
            e = np.array(errs)
            row = {"evidence": name, "options": options, "objects": a.objects, "views": a.views,
                   "wall_s": float(np.median(walls)), "walls_s": walls, "median_err_mm": float(np.median(e[:, 0])),
                   "max_err_mm": float(e[:, 0].max()), "max_err_deg": float(e[:, 1].max()),
                   "within_1mm_1deg": float(np.mean((e[:, 0] <= 1) & (e[:, 1] <= 1))), "ok": ok}
            rows.append(row)
            print(json.dumps(row), flush=True)
    base = rows[0]["wall_s"]
    lines = ["# Evidence benchmark: masks, photos, depth", "",
             f"`python -m autoalign.experiments.benchmarks.bench_modalities --objects {a.objects} --views {a.views} "
             f"--repeats {a.repeats}` on {platform.machine()}, {os.cpu_count()} cores, Python "
             f"{platform.python_version()}: `autoalign refine --models` on one scene of {a.objects} textured objects, "
             f"{a.views} views of 640x480, starts 10 mm / 15 deg off (the whole command, process start included); "
             "ratios against the masks-only row of the same run.", "",
             "| evidence | options | wall s | ratio | within 1 mm, 1 deg | median err mm | max err mm / deg | verdict ok |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['evidence']} | `{' '.join(r['options']) or '(default)'}` | {r['wall_s']:.1f} | "
                     f"{r['wall_s'] / base:.2f} | {r['within_1mm_1deg']:.0%} | {r['median_err_mm']:.2f} | "
                     f"{r['max_err_mm']:.2f} / {r['max_err_deg']:.2f} | {r['ok']}/{r['objects']} |")
    write_results("bench_modalities", rows, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
