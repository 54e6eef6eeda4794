"""How the real SAM masks of the LM-O dev scenes fail: per object and view, the share of the object's
visible silhouette (the dataset's labels ray-cast with open3d, every annotated object an occluder)
that its SAM mask covers, and the share of the mask that lies off it. The synthetic scenes of the
photo study (:mod:`autoalign.experiments.studies.photo_evidence`) cut their masks at these rates.

Also how far each mask's outline lies outside the silhouette's (px, the median over its outline
pixels; masks on the object only, IoU >= 0.5), and per object the median over its views: the shift
every mask of an object shares, which the covariance's prior
(:data:`~autoalign.engine.uncertainty.BOUNDARY_BIAS_PX`) stands for.

``python -m autoalign.experiments.studies.sam_mask_rates [--data ../shared/real/lmo_dev]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.synthetic import raycast_visible_masks
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import load_mesh
from autoalign.geometry.se3 import invert, make_pose
from autoalign.io.bop import read_cameras, read_mask
from autoalign.losses.outline_offset import OCCLUSION_PX, ON_OBJECT_IOU, outline_offset


def scene_rates(scene: Path) -> list[dict]:
    """One row per (image, instance) with a label: ``coverage`` (mask within the visible
    silhouette / silhouette), ``off`` (mask outside it / mask; NaN without a mask), ``outline_px``
    (:func:`outline_offset`; NaN without a mask on the object)."""
    gt = json.loads((scene / "scene_gt.json").read_text())
    cams = read_cameras(scene)
    meshes: dict[int, object] = {}
    rows = []
    for im, entries in sorted(gt.items(), key=lambda kv: int(kv[0])):
        K, R, t = cams[int(im)]
        cam = Camera.from_opencv(K, R, t, 640, 480)
        placed, objs = [], []
        for e in entries:
            o = int(e["obj_id"])
            if o not in meshes:
                meshes[o] = load_mesh(scene / "models" / f"obj_{o:06d}.ply")
            T_cm = make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"])
            placed.append(invert(cam.T_cw) @ T_cm)
            objs.append(o)
        visible = raycast_visible_masks([meshes[o] for o in objs], placed, [cam])[0]
        for k, (o, vis) in enumerate(zip(objs, visible)):
            path = scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png"
            mask = read_mask(path)[0] if path.is_file() else np.zeros_like(vis)
            area = int(vis.sum())
            if area < 50:
                continue
            iou = (mask & vis).sum() / max((mask | vis).sum(), 1)
            others = np.any([v for j, v in enumerate(visible) if j != k], axis=0) if len(visible) > 1 else np.zeros_like(vis)
            rows.append({"scene": scene.name, "image": int(im), "obj_id": o, "area_px": area,
                         "coverage": float((mask & vis).sum() / area),
                         "off": float((mask & ~vis).sum() / mask.sum()) if mask.any() else float("nan"),
                         "outline_px": outline_offset(mask, vis, others) if iou >= ON_OBJECT_IOU else float("nan")})
    return rows


def shared_shift_table(rows: list[dict]) -> list[str]:
    """Per scene and object, the median of its views' outline offsets (the shift its masks share)
    and their spread, and over all of them the RMS and range."""
    lines = ["", "How far the masks' outlines lie outside the silhouettes' (px; per view the median over the mask's "
             f"outline pixels, those within {OCCLUSION_PX} px of another object or the border left out; masks with "
             f"IoU >= {ON_OBJECT_IOU:g} only). Per object, the median over its views is the shift its masks share.", "",
             "| scene | object | views | shared shift px (median) | views' quartiles px |", "|---|---|---|---|---|"]
    shared = []
    for scene in sorted({r["scene"] for r in rows}):
        for o in sorted({r["obj_id"] for r in rows if r["scene"] == scene}):
            v = np.array([r["outline_px"] for r in rows if r["scene"] == scene and r["obj_id"] == o])
            v = v[np.isfinite(v)]
            if len(v) < 3:
                continue
            shared.append(float(np.median(v)))
            q1, q3 = np.percentile(v, [25, 75])
            lines.append(f"| {scene} | {o} | {len(v)} | {shared[-1]:+.2f} | {q1:+.2f} .. {q3:+.2f} |")
    s = np.array(shared)
    lines += ["", f"Shared shift over the {len(s)} (scene, object) pairs: RMS {np.sqrt(np.mean(s ** 2)):.2f} px, "
              f"from {s.min():+.2f} to {s.max():+.2f} px."]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=REAL_SCENES)
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rows = [r for scene in sorted(d for d in a.data.iterdir() if (d / "scene_gt.json").is_file())
            for r in scene_rates(scene)]
    cov = np.array([r["coverage"] for r in rows])
    off = np.array([r["off"] for r in rows])
    has = np.isfinite(off)
    lines = ["# How the real SAM masks of the LM-O dev scenes fail", "",
             "`python -m autoalign.experiments.studies.sam_mask_rates`: per object and view, the share of the visible "
             "silhouette (the dataset's labels ray-cast with open3d) the SAM mask covers, and the share of the mask "
             "off it.", "",
             f"{len(rows)} labelled (object, view) pairs with at least 50 visible pixels; {int((~has).sum())} without a mask.", "",
             "| measure | share of pairs |", "|---|---|",
             f"| no mask | {np.mean(~has):.0%} |",
             f"| mask covers < 40% of the silhouette (misses more than 60%) | {np.mean(cov < 0.4):.0%} |",
             f"| mask covers 40-70% (misses 30-60%) | {np.mean((cov >= 0.4) & (cov < 0.7)):.0%} |",
             f"| mask covers >= 70% | {np.mean(cov >= 0.7):.0%} |",
             f"| more than half of the mask off the object (on another) | {np.mean(off[has] > 0.5):.0%} of the masks |",
             "", f"Median coverage {np.median(cov):.2f}, median share off {np.nanmedian(off):.2f}.", "",
             "| object | pairs | median coverage | covers < 70% | median off | off > 50% |", "|---|---|---|---|---|---|"]
    for o in sorted({r["obj_id"] for r in rows}):
        c = np.array([r["coverage"] for r in rows if r["obj_id"] == o])
        f = np.array([r["off"] for r in rows if r["obj_id"] == o])
        f = f[np.isfinite(f)]
        lines.append(f"| {o} | {len(c)} | {np.median(c):.2f} | {np.mean(c < 0.7):.0%} | "
                     f"{np.median(f) if len(f) else float('nan'):.2f} | {np.mean(f > 0.5) if len(f) else float('nan'):.0%} |")
    lines += shared_shift_table(rows)
    write_results("sam_mask_rates", rows, lines, a.out)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
