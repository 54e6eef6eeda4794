"""Benchmark of the capture-to-dataset pipeline: ``recon`` -> ``refine`` -> ``export`` on a
synthetic hand-held RGB-D stream (``experiments/scenes/stream.py``: 200 frames of 640x480, five textured
objects on a textured table, true cameras and poses known).

The segmenter is played by open3d: visible masks of every fifth frame, ray-cast at the true
poses through the true cameras (the keyframes a user would segment). The coarse ``--init`` is the
truth 10 mm / 15 degrees off, given in the first keyframe's camera frame (as a user's coarse
label). The labels are judged in every keyframe's camera frame (``scene_gt.json``), which needs no
alignment of the reconstruction. With ``--rgb-only`` the depth is withheld: ``recon`` leaves the
scale free and ``refine`` solves it from the objects (the 7th parameter), and ``export`` takes the
metric cameras ``refine`` wrote. Each command runs as a child process; their wall times and the
accuracy of each stage are reported. Results: ``experiments/results/bench_pipeline[_rgb].md``.

``python -m autoalign.experiments.benchmarks.bench_pipeline [--frames 200] [--size 640x480] [--rgb-only]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from autoalign.experiments import RESULTS
from autoalign.experiments.commands import run_autoalign
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.stream import DEPTH_SCALE, Stream, render_stream
from autoalign.experiments.scenes.synthetic import perturb_pose, raycast_visible_masks
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import rotation_angle_deg
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import read_cameras, scene_gt_of

KEYFRAME_EVERY = 5


def rigid_alignment(ours: dict, truth: dict, scaling: bool) -> np.ndarray:
    """``T`` (4x4, with scale if ``scaling``) mapping our camera centres onto the true ones (open3d)."""
    ids = sorted(ours)
    c = [np.array([-R.T @ t for _, R, t in (cams[i] for i in ids)]) for cams in (ours, truth)]
    pcs = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x)) for x in c]
    corr = o3d.utility.Vector2iVector(np.stack([np.arange(len(ids))] * 2, 1))
    return o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=scaling).compute_transformation(
        pcs[0], pcs[1], corr)


def aligned_camera_errors(ours: dict, truth: dict, T: np.ndarray) -> tuple[list[float], list[float]]:
    """Per camera of ``ours`` (``read_cameras`` tables), its centre's distance (mm) and rotation
    error (degrees) from the true one once ``T`` (a similarity: ours -> truth) is applied."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    R_align = T[:3, :3] / s
    pos, rot = [], []
    for i, (_, R, t) in ours.items():
        centre = T[:3, :3] @ (-R.T @ t) + T[:3, 3]
        pos.append(float(np.linalg.norm(centre + truth[i][1].T @ truth[i][2])))
        rot.append(rotation_angle_deg(R @ R_align.T, truth[i][1]))
    return pos, rot


def recon_row(a: argparse.Namespace, rec: dict, t_render: float, t_recon: float, pos: list[float], rot: list[float],
              sim3: np.ndarray, normal: np.ndarray) -> int:
    """Write ``bench_recon_{frames}.md/json``: recon alone on a long stream."""
    row = {"frames": a.frames, "size": a.size, "render_s": t_render, "recon_s": t_recon, "registered": rec["registered"],
           "reprojection_px": rec["reprojection_error_px"], "trajectory_median_mm": float(np.median(pos)),
           "trajectory_median_deg": float(np.median(rot)), "trajectory_max_mm": float(np.max(pos)),
           "trajectory_max_deg": float(np.max(rot)), "scale_error": float(np.cbrt(np.linalg.det(sim3[:3, :3])) - 1.0),
           "table_normal_deg": float(np.degrees(np.arccos(np.clip(normal[2], -1, 1))))}
    print(json.dumps(row), flush=True)
    lines = [f"# recon on a {a.frames}-frame stream", "",
             f"`python -m autoalign.experiments.benchmarks.bench_pipeline --frames {a.frames} --size {a.size} --recon-only` on "
             f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}: the synthetic hand-held "
             "RGB-D stream; keyframes (every 4th frame) mapped, the other frames registered to them.", "",
             "| frames | wall s | registered | reprojection px | median mm / deg (SE(3)) | max mm / deg | scale error | "
             "table normal deg |", "|---|---|---|---|---|---|---|---|",
             f"| {a.frames} | {t_recon:.1f} | {rec['registered']} | {rec['reprojection_error_px']:.2f} | "
             f"{row['trajectory_median_mm']:.2f} / {row['trajectory_median_deg']:.3f} | {row['trajectory_max_mm']:.2f} / "
             f"{row['trajectory_max_deg']:.3f} | {row['scale_error']:+.3%} | {row['table_normal_deg']:.3f} |"]
    write_results(f"bench_recon_{a.frames}", row, lines, a.out)
    return 0


def label_errors(scene_gt: dict, truth: dict, stream: Stream, refine_json: dict) -> list[tuple[float, float, str]]:
    """Per instance of ``refine_json``: the largest position (mm) and rotation (degrees) error of its
    label (``scene_gt``: camera from model) over the images, against the true camera from the true
    pose, and its verdict."""
    worst: dict[int, list[float]] = {}
    for im, entries in scene_gt.items():
        T_cw = np.eye(4)
        T_cw[:3, :3], T_cw[:3, 3] = truth[int(im)][1], truth[int(im)][2]
        for e in entries:
            j = e["obj_id"] - 1  # stream object j is obj_id j + 1
            est = np.eye(4)
            est[:3, :3], est[:3, 3] = np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"]
            err = pose_errors(est, T_cw @ stream.poses[j], stream.meshes[j].centre, None, Symmetries())
            w = worst.setdefault(j, [0.0, 0.0])
            w[0], w[1] = max(w[0], err.pos_err_mm), max(w[1], err.rot_err_deg)
    return [(worst[r["obj_id"] - 1][0], worst[r["obj_id"] - 1][1], r["verdict"]) for r in refine_json["instances"]]


def proposal_assignment(scene: Path, stream: Stream, T: np.ndarray) -> dict[int, int]:
    """Which stream object each ``recon --propose`` proposal is (the user's instances file): the
    object whose centre is nearest the proposal's (ours -> true frame by ``T``), within 30 mm."""
    props = json.loads((scene / "proposals.json").read_text())["instances"]
    centres = [P[:3, :3] @ m.centre + P[:3, 3] for m, P in zip(stream.meshes, stream.poses)]
    out = {}
    for k, v in props.items():
        c = T[:3, :3] @ np.asarray(v["centre_mm"]) + T[:3, 3]
        d = [float(np.linalg.norm(c - x)) for x in centres]
        if min(d) < 30.0:
            out[int(k)] = int(np.argmin(d))
    return out


def keyframe_masks(scene: Path, stream: Stream, T: np.ndarray, keys: list[int], propose: bool) -> dict[int, int]:
    """Masks of the ``keys`` frames in ``scene/mask_visib``: ``recon --propose``'s (the other frames'
    removed) when ``propose``, else ray cast from the truth (the user's segmenter); returns which
    stream object each mask's instance is."""
    if propose:  # the proposals' masks of the keyframes; the user says which object each is
        for f in (scene / "mask_visib").iterdir():
            if int(f.name[:6]) % KEYFRAME_EVERY:
                f.unlink()
        return proposal_assignment(scene, stream, T)
    masks = raycast_visible_masks(stream.meshes, stream.poses, [stream.cameras[i] for i in keys])
    (scene / "mask_visib").mkdir()
    for i, per in zip(keys, masks):
        for k, m in enumerate(per):
            if m.any():
                cv2.imwrite(str(scene / "mask_visib" / f"{i:06d}_{k:06d}.png"), m.astype(np.uint8) * 255)
    return {k: k for k in range(len(stream.meshes))}


def write_coarse_init(path: Path, stream: Stream, truth: dict, k0: int, assignment: dict[int, int],
                      size: tuple[int, int]) -> None:
    """``--init`` for refine: every object's true pose 10 mm / 15 deg off (seeded), in frame
    ``k0``'s true camera frame (``size``: W, H px), one entry per instance of ``assignment``
    (a placeholder where an instance has no object)."""
    rng = np.random.default_rng(1)
    coarse = [perturb_pose(P, 10.0, 15.0, rng, m.centre) for P, m in zip(stream.poses, stream.meshes)]
    cam0 = Camera.from_opencv(*truth[k0], *size)  # the coarse labels in the first keyframe's camera frame
    entries = scene_gt_of([(j + 1, coarse[j]) for j in range(len(stream.meshes))], [cam0], [k0])[str(k0)]
    placeholder = {"obj_id": 0, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0.0, 0.0, 0.0]}
    write_json_atomic(path, {str(k0): [entries[assignment[k]] if k in assignment else placeholder
                                       for k in range(max(assignment) + 1)]})


def export_mask_ious(bop: Path, stream: Stream) -> tuple[dict, list[float]]:
    """The exported ``bop/scene_gt.json``, and the IoUs of its ``mask_visib`` in 10 of its frames
    against open3d ray casting at the truth."""
    gt = json.loads((bop / "scene_gt.json").read_text())
    check = sorted(int(i) for i in gt)[:: max(1, len(gt) // 10)]
    ious = []
    ref = raycast_visible_masks(stream.meshes, stream.poses, [stream.cameras[i] for i in check])
    for i, per in zip(check, ref):
        for k, e in enumerate(gt[str(i)]):
            mine = cv2.imread(str(bop / "mask_visib" / f"{i:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            m = per[e["obj_id"] - 1]
            u = np.count_nonzero(mine | m)
            if u:
                ious.append(np.count_nonzero(mine & m) / u)
    return gt, ious


def pipeline_table(a: argparse.Namespace, row: dict, rec: dict, n_keys: int, n_gt: int, solved: float | None
                   ) -> list[str]:
    """The lines of ``bench_pipeline*.md``: one row per stage (``row``: the JSON row, ``rec``: recon.json,
    ``solved``: the scale refine solved, mm per unit)."""
    n_obj, rgb = row["objects"], a.rgb_only
    return ["# Capture to dataset: recon -> refine -> export", "",
            f"`python -m autoalign.experiments.benchmarks.bench_pipeline --frames {a.frames} --size {a.size}"
            f"{' --rgb-only' if rgb else ''}{' --propose' if a.propose else ''}` on {platform.machine()}, "
            f"{os.cpu_count()} cores, Python {platform.python_version()}: a synthetic hand-held RGB-D stream, {n_obj} "
            f"objects{' (RGB only: depth withheld)' if rgb else ''}; masks of every {KEYFRAME_EVERY}th frame "
            + (f"from `recon --propose` (no segmenter; {row['matched_objects']} of {n_obj} objects have a proposal of "
               "their own, assigned by their centres as a user would)" if a.propose else "from the truth (the segmenter)")
            + ", `--init` 10 mm / 15 deg off; "
            "each command a child process.", "",
            "| stage | wall s | result |", "|---|---|---|",
            f"| recon | {row['recon_s']:.1f} | {rec['registered']} of {a.frames} frames registered, reprojection "
            f"{rec['reprojection_error_px']:.2f} px; trajectory after {'Sim(3)' if rgb else 'SE(3)'} alignment: "
            f"median {row['trajectory_median_mm']:.2f} mm / {row['trajectory_median_deg']:.3f} deg; "
            + ("scale left free (no depth)" if rgb else
               f"scale error {row['scale_error']:+.3%} (spread {rec['scale_spread']:.2%})")
            + f"; table normal {row['table_normal_deg']:.3f} deg |",
            f"| refine ({n_obj} objects, {n_keys} keyframes) | {row['refine_s']:.1f} | "
            + (f"scale solved from the objects: {row['solved_scale_error']:+.3%} from the true one (from object 1 "
               f"alone: {row['solved_scale_error_one_object']:+.3%}); " if solved else "")
            + "label errors, worst keyframe per object: "
            f"{', '.join(f'{mm:.2f} mm / {deg:.2f} deg' for mm, deg in zip(row['pose_err_mm'], row['pose_err_deg']))}; "
            f"verdicts {', '.join(row['verdicts'])} |",
            f"| export ({n_gt} frames, COCO) | {row['export_s']:.1f} | mask_visib against open3d ray casting at the truth: "
            f"IoU median {row['export_mask_iou_median']:.3f}, min {row['export_mask_iou_min']:.3f} (10 frames) |",
            f"| **pipeline** | **{row['pipeline_s']:.1f}** | rendering the stream itself: {row['render_s']:.1f} s "
            "(not counted) |"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--size", default="640x480")
    p.add_argument("--rgb-only", action="store_true", help="withhold the depth: the scale is solved by refine")
    p.add_argument("--recon-only", action="store_true", help="only recon (for long streams): bench_recon_N.md")
    p.add_argument("--propose", action="store_true",
                   help="masks from recon --propose instead of the truth (no segmenter): bench_pipeline_propose.md")
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    W, H = (int(x) for x in a.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        stream = render_stream(root / "capture", n_frames=a.frames, width=W, height=H, seed=0)
        t_render = time.perf_counter() - t0
        if a.rgb_only:
            (root / "capture" / "depth").rename(root / "depth_withheld")
        t_recon = run_autoalign("recon", str(root / "capture"), "--intrinsics", str(root / "capture" / "intrinsics.json"),
                                "--depth-scale", str(DEPTH_SCALE), "--out", str(root / "scene"), "--quiet",
                                *(["--propose"] if a.propose else [])).check().wall_s
        rec = json.loads((root / "scene" / "recon.json").read_text())
        ours, truth = read_cameras(root / "scene"), read_cameras(root / "capture" / "gt")
        sim3 = rigid_alignment(ours, truth, True)
        T = sim3 if a.rgb_only else rigid_alignment(ours, truth, False)
        pos, rot = aligned_camera_errors(ours, truth, T)
        normal = T[:3, :3] @ np.array([0.0, 0.0, 1.0]) / np.cbrt(np.linalg.det(T[:3, :3]))  # without Sim(3)'s scale
        if a.recon_only:
            return recon_row(a, rec, t_render, t_recon, pos, rot, sim3, normal)
        # keyframe masks in the reconstruction's scene folder
        keys = [i for i in sorted(ours) if i % KEYFRAME_EVERY == 0]
        n_obj = len(stream.meshes)
        assignment = keyframe_masks(root / "scene", stream, T, keys, a.propose)
        write_json_atomic(root / "instances.json", {"instances": {str(k): j + 1 for k, j in assignment.items()}})
        write_coarse_init(root / "init.json", stream, truth, keys[0], assignment, (W, H))
        t_refine = run_autoalign("refine", str(root / "scene"), "--models", str(root / "capture" / "gt" / "models"),
                                 "--instances", str(root / "instances.json"), "--init", str(root / "init.json"),
                                 "--out", str(root / "labels"), "--quiet").check().wall_s
        labels = json.loads((root / "labels" / "refine.json").read_text())
        errs = label_errors(json.loads((root / "labels" / "scene_gt.json").read_text()), truth, stream, labels)
        true_scale = float(np.cbrt(np.linalg.det(sim3[:3, :3])))  # mm per reconstruction unit
        solved = labels.get("scale", {}).get("mm_per_unit")
        solved_one = None
        if a.rgb_only:  # the scale from one known object alone (the others unmodelled)
            write_json_atomic(root / "one.json", {"instances": {"0": 1}})
            run_autoalign("refine", str(root / "scene"), "--models", str(root / "capture" / "gt" / "models"),
                          "--instances", str(root / "one.json"), "--init", str(root / "init.json"),
                          "--out", str(root / "labels_one"), "--quiet").check()
            solved_one = json.loads((root / "labels_one" / "refine.json").read_text())["scale"]["mm_per_unit"]
        t_export = run_autoalign("export", str(root / "scene"), "--labels", str(root / "labels" / "scene_gt.json"),
                                 "--models", str(root / "capture" / "gt" / "models"), "--out", str(root / "bop"),
                                 "--coco", "--quiet").check().wall_s
        gt, ious = export_mask_ious(root / "bop", stream)
    row = {
        "frames": a.frames, "size": f"{W}x{H}", "objects": n_obj, "render_s": t_render,
        "recon_s": t_recon, "refine_s": t_refine, "export_s": t_export, "pipeline_s": t_recon + t_refine + t_export,
        "registered": rec["registered"], "reprojection_px": rec["reprojection_error_px"],
        "trajectory_median_mm": float(np.median(pos)), "trajectory_median_deg": float(np.median(rot)),
        "rgb_only": a.rgb_only, "propose": a.propose, "matched_objects": len(assignment), "scale_error": None if a.rgb_only else true_scale - 1.0,
        "scale_spread": rec["scale_spread"], "solved_scale_error": None if solved is None else solved / true_scale - 1.0,
        "solved_scale_error_one_object": None if solved_one is None else solved_one / true_scale - 1.0,
        "table_normal_deg": float(np.degrees(np.arccos(np.clip(normal[2], -1, 1)))),
        "pose_err_mm": [e[0] for e in errs], "pose_err_deg": [e[1] for e in errs], "verdicts": [e[2] for e in errs],
        "export_mask_iou_min": float(min(ious)) if ious else None, "export_mask_iou_median": float(np.median(ious)) if ious else None,
    }
    print(json.dumps(row), flush=True)
    lines = pipeline_table(a, row, rec, len(keys), len(gt), solved)
    name = "bench_pipeline" + ("_rgb" if a.rgb_only else "") + ("_propose" if a.propose else "")
    write_results(name, row, lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
