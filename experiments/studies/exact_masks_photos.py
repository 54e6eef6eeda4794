"""Exact masks with photos added: how far the photos move the pose the masks alone give.

Issue 43's must-show 4: with masks that fit, the photos must not pull the pose away. The scenes
are the refine study's ``init`` scenes (:func:`~autoalign.experiments.studies.refine_study.make_study_scene`:
40 views, exact open3d masks, a seed 10 mm and 5-25 deg off) with photos rendered by mitsuba
(:func:`~autoalign.experiments.scenes.make_example.render_photos`: the bundled example's blotched
vertex colours over a plain table below the object), and the bundled example itself. Each is refined
from its seed with the masks alone and with masks and photos (the Python API); the table gives the
move between the two and each one's error against the truth.

``python -m autoalign.experiments.studies.exact_masks_photos --scenes 10``
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

import autoalign
from autoalign.experiments import RESULTS
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.make_example import render_photos, vertex_colours
from autoalign.experiments.studies.refine_study import make_study_scene, study_meshes
from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import pose_change, transform_points
from autoalign.io.bop import Scene

EXAMPLE = Path(autoalign.__file__).resolve().parent / "data" / "example"
"""The bundled example, in a checkout and in an installed package alike."""


@dataclass(frozen=True)
class Case:
    """A scene with exact masks and photos, its mesh, the true and the seed world-from-model poses (mm)."""

    name: str
    scene: Scene
    mesh: Mesh
    T_true: NDArray[np.float64]
    T_seed: NDArray[np.float64]


@dataclass(frozen=True)
class Moves:
    """Where the photos put the pose against the masks alone, and both against the truth (mm, deg)."""

    photos_vs_masks: tuple[float, float]
    masks_vs_truth: tuple[float, float]
    photos_vs_truth: tuple[float, float]


def study_case(k: int, seed: int = 0) -> Case:
    """The refine study's ``init`` scene ``k`` with photos of the object over a table below it."""
    s = make_study_scene(k, "init", study_meshes(), seed)
    colours = vertex_colours(s.mesh.vertices, np.random.default_rng([seed, k]))
    table_z = float(transform_points(s.T_gt, s.mesh.vertices)[:, 2].min()) - 1.0
    photos = render_photos(s.mesh, colours, s.T_gt, s.scene.cameras, table_z)
    return Case(s.name, replace(s.scene, photos=photos), s.mesh, s.T_gt, s.T_init)


def example_case() -> Case:
    """The bundled example (``autoalign/data/example``) from its ``init_gt.json``."""
    from autoalign.geometry.mesh import load_mesh
    from autoalign.io.bop import read_init_pose
    from autoalign.io.evidence import read_evidence

    scene = read_evidence(EXAMPLE / "scene", modalities=("masks", "photos"))
    return Case("example", scene, load_mesh(EXAMPLE / "model.ply"), read_init_pose(EXAMPLE / "scene" / "scene_gt.json", scene),
                read_init_pose(EXAMPLE / "init_gt.json", scene))


def photo_moves(case: Case) -> Moves:
    """Refine ``case`` from its seed with the masks alone and with the photos added."""
    from autoalign.engine.refine import refine

    masks_only = refine(replace(case.scene, photos=None), case.mesh, case.T_seed).T_wm
    with_photos = refine(case.scene, case.mesh, case.T_seed).T_wm
    c = case.mesh.centre
    return Moves(pose_change(masks_only, with_photos, c), pose_change(case.T_true, masks_only, c),
                 pose_change(case.T_true, with_photos, c))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=10, help="refine-study init scenes besides the bundled example")
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = []
    for case in [example_case()] + [study_case(k) for k in range(a.scenes)]:
        m = photo_moves(case)
        rows.append({"scene": case.name, "photos_vs_masks": m.photos_vs_masks, "masks_vs_truth": m.masks_vs_truth,
                     "photos_vs_truth": m.photos_vs_truth})
        print(json.dumps(rows[-1]), flush=True)
    worst = np.max([r["photos_vs_masks"] for r in rows], axis=0)
    lines = ["# Exact masks with the photos added", "",
             f"`python -m autoalign.experiments.studies.exact_masks_photos --scenes {a.scenes}`: the bundled example "
             "and the refine study's `init` scenes with mitsuba photos, refined from the seed with the masks alone "
             "and with masks and photos.", "",
             f"Largest move by the photos: {worst[0]:.4f} mm, {worst[1]:.4f} deg.", "",
             "| scene | photos vs masks mm / deg | masks vs truth mm / deg | photos vs truth mm / deg |",
             "|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['photos_vs_masks'][0]:.4f} / {r['photos_vs_masks'][1]:.4f} | "
              f"{r['masks_vs_truth'][0]:.4f} / {r['masks_vs_truth'][1]:.4f} | "
              f"{r['photos_vs_truth'][0]:.4f} / {r['photos_vs_truth'][1]:.4f} |" for r in rows]
    write_results("exact_masks_photos", {"rows": rows}, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
