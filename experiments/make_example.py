"""Regenerate the bundled example scene ``autoalign/data/example`` (deterministic).

A procedural mug (asymmetric: its handle), 24 views of 640x480 from a ring 20-50 degrees above a
table, masks ray-cast by open3d, and a coarse ``init_gt.json`` 10 mm / 20 degrees off the truth.
``python -m autoalign.experiments.make_example [OUT_DIR]``.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np

from autoalign.atomic_files import write_json_atomic
from autoalign.bop import scene_gt_dict
from autoalign.mesh import mesh_from_trimesh
from autoalign.se3 import make_pose
from autoalign.experiments.procedural_models import procedural_models
from autoalign.experiments.synthetic import perturb_pose, random_rotation, ring_cameras, write_synthetic_scene

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"


def make_example(out: Path = DEFAULT_OUT, seed: int = 7) -> Path:
    """Write ``scene/`` (BOP), ``model.ply`` (mm) and ``init_gt.json`` into ``out``; return ``out``."""
    rng = np.random.default_rng(seed)
    model = next(m for m in procedural_models() if m.name == "mug")
    mesh = mesh_from_trimesh(model.mesh, model.name)
    R = random_rotation(rng)
    T_gt = make_pose(R, np.array([12.0, -8.0, 40.0]) - R @ mesh.centre)  # above a table, near its origin
    cams = ring_cameras(24, rng, jitter_mm=10.0, target=(0.0, 0.0, 40.0))
    if out.exists():
        shutil.rmtree(out)
    scene = write_synthetic_scene(out / "scene", mesh, T_gt, cams)
    mesh.trimesh.export(out / "model.ply")
    T0 = perturb_pose(T_gt, 10.0, 20.0, rng, mesh.centre)
    write_json_atomic(out / "init_gt.json", scene_gt_dict(T0, scene.cameras[:1], scene.image_ids[:1]))
    return out


if __name__ == "__main__":
    print(make_example(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_OUT))
