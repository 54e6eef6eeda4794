"""How well the region term's colour models tell each object from its surroundings, at the true poses:
clear and frosted glass, metal and opaque objects in the path-traced scenes of
:mod:`~autoalign.experiments.studies.glass_photos`, the textured objects of
:mod:`~autoalign.experiments.studies.photo_evidence`, and the real LM-O objects at their dataset
labels with their SAM masks.

Per instance and view, :func:`~autoalign.losses.region.region_target` at the labelled pose gives the
separation (:func:`~autoalign.losses.region.colour_separation`: the band's mean leave-one-out posterior
inside less that outside): with the instance's mask, as the region term learns it, and without it, as
``autoalign check`` would measure it at a label, at the label and at a label 10 mm / 10 deg off; per
instance the medians over the views (and the smallest view, with the mask), and per kind of object
their ranges. It says whether a weight on the photo by its own separation could leave clear glass
out while leaving every opaque object as it is, what the region target's own weight on the colours
(:func:`~autoalign.losses.region.colour_weight`) is for each kind, and whether ``check`` could tell
glass by its colours without mistaking a wrong label for glass. Results: ``experiments/results/colour_separation.md``.

``python -m autoalign.experiments.studies.colour_separation [--glass 8] [--glass-kept DIR] [--textured 3] [--data DIR]``
(``--glass-kept``: the folder ``glass_photos --keep`` left, whose renders are reused).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.synthetic import perturb_pose
from autoalign.experiments.studies import glass_photos, photo_evidence
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.io.instances import instances_of_scene_gt, read_init_poses, read_instance_scenes
from autoalign.io.models import ModelSet
from autoalign.io.photos import with_photos
from autoalign.losses.region import RegionOptions, region_target


def separations(scene: Path, models: Path, kinds: dict[int, str], source: str) -> list[dict]:
    """One row per instance of ``scene`` (its ``scene_gt.json`` gives the instances and, at the lowest
    image listing each, their poses): its kind (``kinds`` by obj_id), median and smallest separation."""
    found = read_instance_scenes(scene, instances_of_scene_gt(scene / "scene_gt.json"))
    poses = read_init_poses(scene / "scene_gt.json", found)
    model_set = ModelSet.read(models)
    rng = np.random.default_rng(0)
    rows = []
    for inst, views in zip(found.instances, found.scenes):
        if inst.index not in poses:
            continue
        views, pyramid, T = with_photos(views), model_set.pyramid(inst.obj_id), poses[inst.index]
        off = perturb_pose(T, 10.0, 10.0, rng, pyramid.mesh.centre)

        def per_view(T_wm: np.ndarray, with_mask: bool) -> tuple[np.ndarray, np.ndarray]:
            got = [region_target(v.photo, s, v.mask if with_mask else None, v.ignore, RegionOptions(), separation=True)
                   for v, s in zip(views.views, pyramid.fine().hard_masks(T_wm, views.cameras))]
            sep, weight = np.array([g.separation for g in got]), np.array([g.weight for g in got])
            return sep[np.isfinite(sep)], weight[np.isfinite(sep)]

        sep, weight = per_view(T, True)
        if len(sep):
            rows.append({"source": source, "scene": scene.parent.name if scene.name == "scene" else scene.name,
                         "obj_id": inst.obj_id, "kind": kinds.get(inst.obj_id, "opaque"), "views": len(sep),
                         "median": float(np.median(sep)), "min": float(sep.min()),
                         "weight_median": float(np.median(weight)), "weight_min": float(weight.min()),
                         "weight_one": float(np.mean(weight == 1.0)),
                         "median_no_mask": float(np.median(per_view(T, False)[0])),
                         "median_no_mask_off": float(np.median(per_view(off, False)[0]))})
            print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--glass", type=int, default=8, help="path-traced scenes (glass_photos' seeds 0..N-1)")
    p.add_argument("--glass-kept", type=Path, help="glass_photos --keep's folder: its renders are reused")
    p.add_argument("--textured", type=int, default=3, help="textured scenes (photo_evidence's, seeds 100, 102, ...)")
    p.add_argument("--data", type=Path, default=REAL_SCENES, help="the real LM-O scenes")
    args = p.parse_args(argv)
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.glass):
            work = (args.glass_kept or Path(tmp)) / f"scene_{seed}"
            work.mkdir(parents=True, exist_ok=True)
            _, materials, _ = glass_photos.make_scene(seed, work, 32, 32)
            rows += separations(work / "scene", work / "models", dict(enumerate(materials, 1)), "path-traced")
        pool = photo_evidence.object_pool(None)
        for k in range(args.textured):
            work = Path(tmp) / f"textured_{k}"
            photo_evidence.make_scene(work, 100 + 2 * k, "around", pool)
            rows += separations(work / "scene", work / "models", {}, "textured")
    for scene in sorted(d for d in args.data.iterdir() if (d / "scene_gt.json").is_file()):
        rows += separations(scene, scene / "models", {}, "real LM-O (SAM masks)")
    kinds = sorted({(r["source"], r["kind"]) for r in rows})
    lines = ["# Colour separation at the true poses", "",
             "`python -m autoalign.experiments.studies.colour_separation`: per instance, the median and smallest "
             "over its views of the region term's colour separation (the band's mean leave-one-out posterior "
             "inside less that outside, `losses/region.py: colour_separation`) at its labelled pose with its mask "
             "(as the region term learns), and without it (as `autoalign check` measures) at the label and at a "
             "label 10 mm / 10 deg off; and the weight the region target gives the colours' log-odds "
             "(`colour_weight`: the tempering under which they best predict pixels left out of their histograms, "
             "at most 1) with the mask: its medians per instance, the smallest view, the share of views at 1.",
             "", "| source | kind | instances | with the mask: medians | smallest view | without: medians | "
             "without, 10 mm / 10 deg off | weight: medians | smallest view | views at 1 |",
             "|---|---|---|---|---|---|---|---|---|---|"]

    def spread(mine: list[dict], key: str) -> str:
        return f"{min(r[key] for r in mine):.2f}-{max(r[key] for r in mine):.2f}"

    for source, kind in kinds:
        mine = [r for r in rows if (r["source"], r["kind"]) == (source, kind)]
        lines.append(f"| {source} | {kind} | {len(mine)} | {spread(mine, 'median')} | "
                     f"{min(r['min'] for r in mine):.2f} | {spread(mine, 'median_no_mask')} | "
                     f"{spread(mine, 'median_no_mask_off')} | {spread(mine, 'weight_median')} | "
                     f"{min(r['weight_min'] for r in mine):.2f} | {np.mean([r['weight_one'] for r in mine]):.0%} |")
    lines += ["", "| source | scene | obj | kind | views | median | smallest | without the mask | without, off | "
              "weight median | weight smallest |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['source']} | {r['scene']} | {r['obj_id']} | {r['kind']} | {r['views']} | {r['median']:.2f} | "
              f"{r['min']:.2f} | {r['median_no_mask']:.2f} | {r['median_no_mask_off']:.2f} | "
              f"{r['weight_median']:.2f} | {r['weight_min']:.2f} |" for r in rows]
    write_results("colour_separation", rows, lines, shown=len(kinds) + 6)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
