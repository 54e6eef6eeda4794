"""``autoalign recon`` on the real LM-O photos (``../shared/real/lmo_dev``, RGB only, no depth):
frames registered, and the reconstructed cameras against the scenes' own (which come from the
dataset's per-frame labels) after a Sim(3) alignment (the scale
is unknown without depth). Then the rigid group is labelled twice by ``refine`` from the same
coarse start (``real_scenes.scene_inputs``) and the same SAM masks: with the scene's cameras, and
with ours, the scale solved from the objects; the two sets of labels (``scene_gt.json``, each
image's camera frame) are compared. Both camera sets are also judged by the photos' own feature
tracks (:func:`~autoalign.experiments.studies.metrics.track_fit`: tracks of our structure from motion
triangulated with each set held fixed), which needs no labels. Results:
``experiments/results/recon_real.md``.

``python -m autoalign.experiments.studies.recon_real [--data ../shared/real/lmo_dev] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.benchmarks.bench_pipeline import (
    aligned_camera_errors,
    rigid_alignment,
)
from autoalign.experiments.benchmarks.bench_scene import symmetries
from autoalign.experiments.commands import run_autoalign
from autoalign.experiments.result_files import write_results
from autoalign.experiments.studies.metrics import label_difference, track_fit
from autoalign.experiments.studies.photo_tracks import photo_tracks
from autoalign.experiments.studies.real_scenes import scene_inputs
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_cameras
from autoalign.io.models import ModelSet


def run_scene(scene: Path, tmp: Path) -> dict:
    capture = tmp / scene.name / "capture"
    shutil.copytree(scene / "rgb", capture)
    given = read_cameras(scene)
    K = next(iter(given.values()))[0]
    (tmp / scene.name / "K.json").write_text(json.dumps({"cam_K": K.ravel().tolist()}))
    out = tmp / scene.name / "scene"
    run = run_autoalign("recon", str(capture), "--intrinsics", str(tmp / scene.name / "K.json"), "--out", str(out),
                        "--quiet")
    wall = run.wall_s
    if not run.ok:
        return {"scene": scene.name, "error": run.stderr.strip()[-500:], "wall_s": wall, "frames": len(given)}
    rec = json.loads((out / "recon.json").read_text())
    ours = read_cameras(out)
    sim3 = rigid_alignment(ours, given, scaling=True)
    s = float(np.cbrt(np.linalg.det(sim3[:3, :3])))
    pos, rot = aligned_camera_errors(ours, given, sim3)
    along, across = axis_split(ours, given, sim3)
    row = {"scene": scene.name, "frames": len(given), "registered": rec["registered"], "wall_s": wall,
           "reprojection_px": rec["reprojection_error_px"], "median_mm": float(np.median(pos)),
           "median_deg": float(np.median(rot)), "max_mm": float(np.max(pos)), "max_deg": float(np.max(rot)),
           "median_along_axis_mm": float(np.median(along)), "median_across_axis_mm": float(np.median(across)),
           "scale_mm_per_unit": s}
    return {**row, **same_labels(scene, out, tmp / scene.name, s)}


def axis_split(ours: dict, given: dict, sim3: np.ndarray) -> tuple[list[float], list[float]]:
    """Per camera of ``ours`` (``read_cameras`` tables) mapped by ``sim3`` (ours -> given): how far
    its centre is from the given camera's along that camera's optical axis and across it (mm)."""
    along, across = [], []
    for i, (_, R, t) in ours.items():
        _, R_g, t_g = given[i]
        d = R_g @ (sim3[:3, :3] @ (-R.T @ t) + sim3[:3, 3] + R_g.T @ t_g)  # in the given camera's frame
        along.append(float(abs(d[2])))
        across.append(float(np.hypot(d[0], d[1])))
    return along, across


def camera_track_fit(scene: Path, tmp: Path) -> dict:
    """Reprojection errors (px) of the photos' feature tracks (:func:`photo_tracks`) with the
    scene's cameras and with ours held fixed. Ours come from the bundle adjustment of those
    tracks, so they are the floor; a camera set off by a few pixels would show it here."""
    given = read_cameras(scene)
    K = next(iter(given.values()))[0]
    sfm = photo_tracks(scene, tmp)
    fits = {"ours": track_fit(sfm.observations, sfm.T_cw, K),
            "given": track_fit(sfm.observations, {i: make_pose(R, t) for i, (_, R, t) in given.items()}, K)}
    return {k: {"median_px": f.median_px, "mean_px": f.mean_px, "p90_px": f.p90_px, "tracks": f.tracks,
                "per_view_px": {str(i): v for i, v in f.per_view_px.items()}} for k, f in fits.items()}


def _refine(scene: Path, models: Path, instances: Path, init: Path, out: Path) -> dict:
    run_autoalign("refine", str(scene), "--models", str(models), "--instances", str(instances), "--init", str(init),
                  "--out", str(out), "--quiet").check()
    return json.loads((out / "refine.json").read_text())


def same_labels(scene: Path, ours: Path, tmp: Path, aligned_scale: float) -> dict:
    """The rigid group labelled with the scene's cameras and with ours (scale solved by refine):
    per object the median and largest difference of its labels over the images
    (:func:`~autoalign.experiments.studies.metrics.label_difference`)."""
    instances, init, _ = scene_inputs(scene, tmp)
    shutil.copytree(scene / "mask_visib", ours / "mask_visib")
    a = _refine(scene, scene / "models", instances, init, tmp / "given_labels")
    b = _refine(ours, scene / "models", instances, init, tmp / "recon_labels")
    gt_a, gt_b = (json.loads((d / "scene_gt.json").read_text()) for d in (tmp / "given_labels", tmp / "recon_labels"))
    cameras, models = read_cameras(scene), ModelSet.read(scene / "models")
    diffs: dict[int, list[tuple[float, ...]]] = {}
    points = {o: models.mesh(o).sample_points(1000) for o in {e["obj_id"] for es in gt_a.values() for e in es}}
    for im in sorted(set(gt_a) & set(gt_b), key=int):
        for ea, eb in zip(gt_a[im], gt_b[im]):
            o = ea["obj_id"]
            Ta, Tb = (make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"]) for e in (ea, eb))
            d = label_difference(Tb, Ta, cameras[int(im)][0], models.mesh(o).centre, points[o],
                                 symmetries(models, o))
            diffs.setdefault(o, []).append((d.pos_mm, d.rot_deg, d.along_ray_mm, d.across_ray_mm, d.mean_px,
                                            d.mspd_px))
    keys = ("mm", "deg", "along_ray_mm", "across_ray_mm", "mean_px", "mspd_px")
    per = {str(o): {**{f"median_{k}": float(x) for k, x in zip(keys, np.median(v, axis=0))},
                    **{f"max_{k}": float(x) for k, x in zip(keys, np.max(np.abs(v), axis=0))}}
           for o, v in diffs.items()}
    pairs = list(zip(a["instances"], b["instances"]))
    verdicts = {str(vb["obj_id"]): (va["verdict"], vb["verdict"]) for va, vb in pairs}
    ious = {str(vb["obj_id"]): (va["median_iou_after"], vb["median_iou_after"]) for va, vb in pairs}
    return {"solved_mm_per_unit": b["scale"]["mm_per_unit"],
            "scale_vs_sim3": b["scale"]["mm_per_unit"] / aligned_scale - 1.0,
            "labels": per, "verdicts_given_ours": verdicts, "median_iou_given_ours": ious}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=REAL_SCENES)
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--repeats", type=int, default=3,
                   help="runs per scene: COLMAP's multi-threaded reconstruction differs from run to run")
    a = p.parse_args(argv)
    rows = []
    for run in range(a.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            for scene in sorted(d for d in a.data.iterdir() if (d / "scene_camera.json").is_file()):
                rows.append({"run": run, **run_scene(scene, Path(tmp))})
                if run == 0:
                    rows[-1]["track_fit"] = camera_track_fit(scene, Path(tmp) / scene.name)
                print(json.dumps(rows[-1]), flush=True)
    lines = ["# recon on the real LM-O photos (RGB only)", "",
             "`python -m autoalign.experiments.studies.recon_real`: the scenes' photos with their cam_K, no depth; our cameras "
             "against the scenes' own (from the dataset's per-frame labels; the track table below shows how well "
             "each set fits the photos) after a Sim(3) alignment; "
             f"{a.repeats} runs per scene (COLMAP's reconstruction differs from run to run).", "",
             "| scene | run | frames | registered | reprojection px | median mm | along / across axis mm | median deg "
             "| max mm | max deg | wall s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        head = f"| {r['scene']} | {r['run']} | {r['frames']} |"
        if "error" in r:
            lines.append(f"{head} failed: {r['error']} | | | | | | | {r['wall_s']:.1f} |")
        else:
            lines.append(f"{head} {r['registered']} | {r['reprojection_px']:.2f} | {r['median_mm']:.2f} | "
                         f"{r['median_along_axis_mm']:.2f} / {r['median_across_axis_mm']:.2f} | "
                         f"{r['median_deg']:.3f} | {r['max_mm']:.2f} | {r['max_deg']:.3f} | {r['wall_s']:.1f} |")
    lines += ["", "The photos' own feature tracks (our structure from motion's, "
              "at least 3 views each) triangulated with each camera set held fixed: reprojection error "
              "(px; median, mean and 90th percentile over the observations, then the median error of each view: "
              "its median and largest over the views). Our cameras come from the bundle adjustment of these tracks, "
              "so they are the floor; no labels are involved.", "",
              "| scene | cameras | tracks | median px | mean px | p90 px | per view: median px | per view: largest px "
              "(image) |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for k, f in r.get("track_fit", {}).items():
            worst = max(f["per_view_px"], key=f["per_view_px"].get)
            lines.append(f"| {r['scene']} | {k} | {f['tracks']} | {f['median_px']:.2f} | {f['mean_px']:.2f} | "
                         f"{f['p90_px']:.2f} | {np.median(list(f['per_view_px'].values())):.2f} | "
                         f"{f['per_view_px'][worst]:.2f} ({worst}) |")
    lines += ["", "The rigid group labelled by `refine` with the scene's cameras and with ours (the scale solved from "
              "the objects, no depth), from the same coarse start and SAM masks: the difference of the two labels "
              "(`scene_gt.json`, each image's camera frame; the closest symmetric equivalent), median over the images "
              "(largest size in brackets): the centres' distance and the rotation, that distance split along the "
              "viewing ray and across it, and the model points' projection distance (mean; largest = BOP's MSPD); "
              "then how well each label fits the SAM masks (median IoU over the views).", "",
              "| scene | run | scale solved vs Sim(3) | object | mm | deg | along ray mm | across mm | px mean | "
              "MSPD px | verdicts (given, ours) | median IoU (given, ours) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    keys = ("mm", "deg", "along_ray_mm", "across_ray_mm", "mean_px", "mspd_px")
    for r in rows:
        for o, d in r.get("labels", {}).items():
            cells = " | ".join(f"{d['median_' + k]:.1f} ({d['max_' + k]:.1f})" for k in keys)
            lines.append(f"| {r['scene']} | {r['run']} | {r['scale_vs_sim3']:+.2%} | {o} | {cells} | "
                         f"{', '.join(r['verdicts_given_ours'][o])} | "
                         f"{', '.join(f'{x:.3f}' for x in r['median_iou_given_ours'][o])} |")
    write_results("recon_real", rows, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
