"""Benchmark of ``autoalign.refine``: time per iteration and per refinement, and optimisers compared.

Axes (one varied at a time around the baseline of 40 views, 640x480, ~5k faces):

* views: 10, 40, 100
* image size: 320x240, 640x480, 1280x960 (focal length scaled with it, same field of view)
* mesh faces: ~500, ~5k, ~50k (the same asymmetric blob, tessellated more finely)
* optimiser: Levenberg-Marquardt, Gauss-Newton, Adam — iterations and seconds to converge.

"per iteration" is one objective evaluation with derivatives at full resolution (render + loss);
"refine" is a whole ``refine`` from a pose 10 mm / 20 degrees off. Each cell is the median over
``--repeats`` scenes; every row also gives its ratio to the baseline measured in the same process,
because these machines are noisy. Results: ``experiments/results/bench_refine.{md,json}``.

``python -m autoalign.experiments.benchmarks.bench_refine [--repeats 3] [--quick]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

from autoalign.engine.objective import Level, SilhouetteObjective
from autoalign.engine.refine import RefineOptions, refine
from autoalign.engine.solver import STEP_RULES
from autoalign.experiments import RESULTS
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.synthetic import (
    default_K,
    make_scene,
    perturb_pose,
    random_rotation,
    sphere_cameras,
)
from autoalign.geometry.mesh import Mesh, mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, rotation_angle_deg, transform_points
from autoalign.rasterizers.pyramid import AS_GIVEN, MeshPyramid


def blob_mesh(target_faces: int) -> Mesh:
    """An asymmetric smooth blob (~120 mm) with about ``target_faces`` triangles."""
    n = max(4, int(round(np.sqrt(target_faces / 3.9))))
    tm = trimesh.creation.uv_sphere(radius=1.0, count=[n, n])
    v = np.asarray(tm.vertices)
    r = 1.0 + 0.18 * np.sin(3 * v[:, 0] + 1.0) * np.cos(2 * v[:, 1]) + 0.12 * np.maximum(v[:, 2] + v[:, 0], 0) ** 2
    v = v * r[:, None] * np.array([70.0, 45.0, 35.0])
    tm = trimesh.Trimesh(v, tm.faces, process=True)
    return mesh_from_trimesh(tm, f"blob{len(tm.faces)}")


def bench_case(mesh: Mesh, n_views: int, width: int, height: int, seed: int, optimizer: str = "lm") -> dict:
    """Time one scene: per-iteration cost at full resolution and a whole refinement."""
    rng = np.random.default_rng(seed)
    f = 600.0 * width / 640.0
    cams = sphere_cameras(n_views, rng, K=default_K(width, height, f), width=width, height=height)
    R = random_rotation(rng)
    T_gt = make_pose(R, -R @ mesh.centre)
    scene = make_scene(mesh, T_gt, cams)
    T0 = perturb_pose(T_gt, 10.0, 20.0, rng, mesh.centre)
    obj = SilhouetteObjective(MeshPyramid(mesh), scene, "l2", detail=AS_GIVEN)
    level = Level(1.0, 1.0, 1)
    obj.evaluate(T0, level)  # warm-up: kernel compilation, target resampling
    reps = 3
    t0 = time.perf_counter()
    for _ in range(reps):
        ev = obj.evaluate(T0, level)
    per_iter = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    res = refine(scene, mesh, seed=T0, options=RefineOptions(optimizer=STEP_RULES[optimizer]))
    wall = time.perf_counter() - t0
    c = mesh.centre[None]
    err_mm = float(np.linalg.norm(transform_points(res.T_wm, c) - transform_points(T_gt, c)))
    return {"per_iter_s": per_iter, "refine_s": wall, "iterations": res.iterations, "renders": res.renders,
            "band_px": int(len(ev.silhouettes.band)), "crop_px": int(len(ev.silhouettes.soft)),
            "err_mm": err_mm, "err_deg": rotation_angle_deg(res.T_wm[:3, :3], T_gt[:3, :3])}


def median_case(mesh: Mesh, n_views: int, width: int, height: int, repeats: int, optimizer: str = "lm") -> dict:
    rows = [bench_case(mesh, n_views, width, height, 100 + r, optimizer) for r in range(repeats)]
    return {k: float(np.median([r[k] for r in rows])) for k in rows[0]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3, help="scenes per cell (median reported)")
    p.add_argument("--quick", action="store_true", help="one scene per cell, smaller axes (smoke test)")
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    reps = 1 if a.quick else a.repeats
    meshes = {n: blob_mesh(n) for n in (500, 5000, 50000)}
    base_mesh = meshes[5000]
    rows: list[dict] = []

    def run(axis: str, value: str, mesh: Mesh, views: int, w: int, h: int, opt: str = "lm") -> None:
        r = median_case(mesh, views, w, h, reps, opt)
        r.update(axis=axis, value=value, faces=len(mesh.faces), views=views, size=f"{w}x{h}", optimizer=opt)
        rows.append(r)
        print(json.dumps(r), flush=True)

    run("baseline", "40 views 640x480 5k faces", base_mesh, 40, 640, 480)
    for v in (10, 100):
        run("views", str(v), base_mesh, v, 640, 480)
    for w, h in ((320, 240), (1280, 960)):
        run("image size", f"{w}x{h}", base_mesh, 40, w, h)
    for n in (500, 50000):
        run("mesh faces", str(len(meshes[n].faces)), meshes[n], 40, 640, 480)
    for opt in ("gn", "adam"):
        run("optimiser", opt, base_mesh, 40, 640, 480, opt)

    base = rows[0]
    lines = ["# autoalign refine benchmark", "",
             f"`python -m autoalign.experiments.benchmarks.bench_refine --repeats {reps}` on {platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()}; median of {reps} scene(s) per row. "
             "Ratios are against the baseline row of the same run.", "",
             "| axis | value | faces | views | size | optimiser | s/iteration | ratio | refine s | ratio | iterations | renders | band px | crop px | err mm | err deg |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['axis']} | {r['value']} | {r['faces']} | {r['views']} | {r['size']} | {r['optimizer']} | "
                     f"{r['per_iter_s']:.3f} | {r['per_iter_s'] / base['per_iter_s']:.2f} | {r['refine_s']:.2f} | "
                     f"{r['refine_s'] / base['refine_s']:.2f} | {r['iterations']:.0f} | {r['renders']:.0f} | "
                     f"{r['band_px']:.0f} | {r['crop_px']:.0f} | {r['err_mm']:.3f} | {r['err_deg']:.3f} |")
    write_results("bench_refine", rows, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
