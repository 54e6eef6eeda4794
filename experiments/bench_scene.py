"""Benchmark of ``autoalign refine --models``: the whole command against the number of objects.

Scenes of 1, 4 and 8 procedural objects on a circle (they hide each other), 40 views of 640x480
with visible masks ray-cast by open3d, coarse starts 10 mm / 15 degrees off; the command runs in a
child process (start-up included) after one warm-up run. Ratios are against the 1-object row of
the same run. Results: ``experiments/results/bench_scene.md``.

``python -m autoalign.experiments.bench_scene [--objects 1,4,8] [--repeats 1]``
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

import numpy as np

from autoalign.atomic_files import write_json_atomic, write_text_atomic
from autoalign.bop import scene_gt_of
from autoalign.models import ModelSet
from autoalign.se3 import make_pose
from autoalign.experiments.metrics import Symmetries, pose_errors
from autoalign.experiments.procedural_models import procedural_models, write_models
from autoalign.experiments.synthetic import default_K, perturb_pose, random_rotation, ring_cameras, write_multi_scene

RESULTS = Path(__file__).resolve().parent / "results"


def make_bench_scene(root: Path, n_obj: int, views: int = 40, seed: int = 0) -> list[np.ndarray]:
    """``root/scene``, ``root/models``, ``root/init_gt.json`` for ``n_obj`` objects; the true poses."""
    rng = np.random.default_rng([seed, n_obj])
    pool = procedural_models()
    chosen = [pool[int(i)] for i in rng.choice(len(pool), n_obj, replace=False)]
    write_models(root / "models", chosen)
    models = ModelSet.read(root / "models")
    meshes = [models.mesh(i + 1) for i in range(n_obj)]
    radius = 0.0 if n_obj == 1 else 40.0 * n_obj / np.pi  # neighbours ~80 mm apart
    truth = []
    for j, m in enumerate(meshes):
        a = 2 * np.pi * j / n_obj
        R = random_rotation(rng)
        truth.append(make_pose(R, np.array([radius * np.cos(a), radius * np.sin(a), 40.0]) - R @ m.centre))
    cams = ring_cameras(views, rng, dist_range=(450.0 + 2 * radius, 750.0 + 2 * radius), target=(0.0, 0.0, 40.0),
                        K=default_K(640, 480, 600.0))
    write_multi_scene(root / "scene", meshes, list(range(1, n_obj + 1)), truth, cams)
    coarse = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(truth, meshes)]
    write_json_atomic(root / "init_gt.json", scene_gt_of([(j + 1, T) for j, T in enumerate(coarse)], cams[:1], [0]))
    return truth


def time_command(root: Path) -> tuple[float, dict]:
    cmd = [sys.executable, "-m", "autoalign.cli.main", "refine", str(root / "scene"), "--models", str(root / "models"),
           "--init", str(root / "init_gt.json"), "--out", str(root / "out"), "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return wall, json.loads((root / "out" / "refine.json").read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", default="1,4,8")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm = Path(tmp) / "warm"
        make_bench_scene(warm, 1, seed=99)
        time_command(warm)  # page cache, compiled kernels' files
        for n in (int(x) for x in a.objects.split(",")):
            walls, errs, verdicts = [], [], []
            for rep in range(a.repeats):
                root = Path(tmp) / f"n{n}_{rep}"
                truth = make_bench_scene(root, n, seed=rep)
                wall, rec = time_command(root)
                walls.append(wall)
                models = ModelSet.read(root / "models")
                for r in rec["instances"]:
                    info = models.info[r["obj_id"]]
                    sym = Symmetries.from_info({"symmetries_discrete": info.get("symmetries_discrete", []),
                                                "symmetries_continuous": info.get("symmetries_continuous", [])})
                    e = pose_errors(np.asarray(r["pose"]["T_wm"]), truth[r["instance"]], models.mesh(r["obj_id"]).centre,
                                    None, sym)
                    errs.append((e.pos_err_mm, e.rot_err_deg))
                    verdicts.append(r["verdict"])
            e = np.array(errs)
            row = {"objects": n, "views": 40, "wall_s": float(np.median(walls)), "per_object_s": float(np.median(walls)) / n,
                   "max_err_mm": float(e[:, 0].max()), "max_err_deg": float(e[:, 1].max()),
                   "within_1mm_1deg": float(np.mean((e[:, 0] <= 1) & (e[:, 1] <= 1))),
                   "ok": int(sum(v == "ok" for v in verdicts)), "instances": len(verdicts)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    base = rows[0]
    lines = ["# autoalign refine --models benchmark", "",
             f"`python -m autoalign.experiments.bench_scene --objects {a.objects} --repeats {a.repeats}` on "
             f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}: the whole command "
             "(process start included), 40 views of 640x480, starts 10 mm / 15 deg off; ratios against the first row "
             "of the same run.", "",
             "| objects | wall s | ratio | s per object | within 1 mm, 1 deg | verdict ok | max err mm | max err deg |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['objects']} | {r['wall_s']:.1f} | {r['wall_s'] / base['wall_s']:.2f} | {r['per_object_s']:.2f} | "
                     f"{r['within_1mm_1deg']:.0%} | {r['ok']}/{r['instances']} | {r['max_err_mm']:.3f} | {r['max_err_deg']:.3f} |")
    a.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(a.out / "bench_scene.json", rows)
    write_text_atomic(a.out / "bench_scene.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
