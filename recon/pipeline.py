"""From a capture to a BOP scene folder: structure from motion, metric scale from depth, the
table frame, TSDF fusion (``autoalign recon``).

Stages, each its own module: :mod:`~autoalign.recon.capture` (frames, depth, intrinsics) ->
:mod:`~autoalign.recon.sfm` (pycolmap) -> :mod:`~autoalign.recon.scale` (median depth ratio) ->
:mod:`~autoalign.recon.plane` (RANSAC table plane; world z up, table at z = 0) ->
:mod:`~autoalign.recon.fusion` (open3d TSDF; with depth only) -> optionally
:mod:`~autoalign.recon.proposals` (instances on the table and their masks; with depth only).
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.recon.capture import Capture
from autoalign.recon.fusion import fuse_depth
from autoalign.recon.plane import TablePlane, fit_table_plane, table_frame
from autoalign.recon.proposals import Proposal, cluster_above_table, proposal_masks
from autoalign.recon.scale import ScaleEstimate, scale_from_depth
from autoalign.recon.sfm import SfmResult, run_sfm

Progress = Callable[[str, int, int], None]


@dataclass
class Reconstruction:
    """The cameras of the registered frames in the table frame (z up, table at z = 0; mm when
    ``metric``, else the reconstruction's own unit), the scale and plane found, and a coloured
    cloud (N, 3) in the same frame: fused depth, or the SfM points without depth; with ``propose``,
    the proposed instances and their visible masks by image id."""

    cameras: dict[int, Camera]
    metric: bool
    scale: ScaleEstimate | None
    plane: TablePlane
    cloud: NDArray[np.float64]
    cloud_colors: NDArray[np.uint8]
    mesh: Any | None
    sfm: SfmResult
    capture: Capture
    proposals: list[Proposal] | None = None
    proposal_masks: dict[int, list[NDArray[np.bool_]]] | None = None


def reconstruct(capture: Capture, workdir: str | os.PathLike[str], progress: Progress | None = None,
                propose: bool = False) -> Reconstruction:
    """Run the stages on ``capture`` (intermediate files in ``workdir``); with ``propose`` (which
    needs depth) also propose the instances on the table."""
    workdir = Path(workdir)
    sfm = run_sfm(capture, workdir, progress)
    scale = None
    if capture.depth is not None:
        depth = {}
        for fid, p in zip(capture.ids, capture.depth):
            if fid in sfm.T_cw:
                depth[fid] = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) * capture.depth_scale
        scale = scale_from_depth(sfm, depth)
    s = scale.scale if scale is not None else 1.0
    T_cw = {i: _scaled(T, s) for i, T in sfm.T_cw.items()}
    points = sfm.points * s
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in T_cw.values()])
    plane = fit_table_plane(points, centres)
    first = next(iter(T_cw.values()))
    T_tw = table_frame(plane, first[0, :3])  # x along the first camera's x, projected on the table
    T_cw = {i: T @ np.linalg.inv(T_tw) for i, T in T_cw.items()}
    W, H = capture.size
    cams = {i: Camera.from_opencv(sfm.K_opencv, T[:3, :3], T[:3, 3], W, H) for i, T in T_cw.items()}
    mesh = None
    cloud, colors = points @ T_tw[:3, :3].T + T_tw[:3, 3], sfm.colors
    if capture.depth is not None and scale is not None:
        frames = dict(zip(capture.ids, zip(capture.frames, capture.depth)))
        pcd, mesh = fuse_depth(frames, T_cw, sfm.K_opencv, capture.size, capture.depth_scale, progress=progress)
        cloud = np.asarray(pcd.points, dtype=np.float64)
        colors = (np.asarray(pcd.colors) * 255).round().astype(np.uint8)
    proposals = masks = None
    if propose and mesh is not None:
        proposals, labels = cluster_above_table(mesh)
        masks = proposal_masks(mesh, labels, len(proposals), cams, progress)
    return Reconstruction(cams, scale is not None, scale, plane, cloud, colors, mesh, sfm, capture, proposals, masks)


def _scaled(T: NDArray[np.float64], s: float) -> NDArray[np.float64]:
    out = T.copy()
    out[:3, 3] *= s
    return out


def scene_files(rec: Reconstruction) -> dict[str, bytes]:
    """The BOP scene folder's files: ``scene_camera.json``, ``rgb/`` and ``depth/`` of the
    registered frames, ``cloud.ply`` (and ``mesh.ply`` with depth), ``recon.json`` and ``trajectory.png``."""
    import open3d as o3d

    cap = rec.capture
    files: dict[str, bytes] = {}
    cams = {}
    for fid, path in zip(cap.ids, cap.frames):
        if fid not in rec.cameras:
            continue
        c = rec.cameras[fid]
        cams[str(fid)] = {"cam_K": [float(x) for x in c.K_opencv.ravel()], "cam_R_w2c": [float(x) for x in c.R_w2c.ravel()],
                          "cam_t_w2c": [float(x) for x in c.t_w2c], "depth_scale": cap.depth_scale}
        files[f"rgb/{fid:06d}{path.suffix.lower()}"] = path.read_bytes()
    if cap.depth is not None:
        for fid, path in zip(cap.ids, cap.depth):
            if fid in rec.cameras:
                files[f"depth/{fid:06d}.png"] = path.read_bytes()
    files["scene_camera.json"] = json.dumps(cams, indent=1).encode()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rec.cloud))
    pcd.colors = o3d.utility.Vector3dVector(rec.cloud_colors.astype(np.float64) / 255.0)
    files["cloud.ply"] = _ply_bytes(pcd)
    if rec.mesh is not None:
        files["mesh.ply"] = _ply_bytes(rec.mesh)
    if rec.proposals is not None and rec.proposal_masks is not None:
        for im, per in rec.proposal_masks.items():
            for k, m in enumerate(per):
                if m.any():
                    files[f"mask_visib/{im:06d}_{k:06d}.png"] = cv2.imencode(".png", m.astype(np.uint8) * 255)[1].tobytes()
        files["proposals.json"] = json.dumps({
            "instances": {str(p.index): {"centre_mm": p.centre_mm.tolist(), "size_mm": p.size_mm.tolist(),
                                         "points": p.points} for p in rec.proposals},
            "note": "instance k's masks are mask_visib/{im_id:06d}_{k:06d}.png; say which object each is in an "
                    "instances file {\"instances\": {\"k\": obj_id}} for autoalign refine --instances"}, indent=1).encode()
    files["recon.json"] = json.dumps(report(rec), indent=1).encode()
    files["trajectory.png"] = trajectory_png(rec)
    return files


def _ply_bytes(geometry: Any) -> bytes:
    """An open3d point cloud or triangle mesh as binary PLY bytes (open3d writes files only: a
    temporary one)."""
    import tempfile

    import open3d as o3d

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "geometry.ply"
        if isinstance(geometry, o3d.geometry.TriangleMesh):
            o3d.io.write_triangle_mesh(str(p), geometry, write_ascii=False)
        else:
            o3d.io.write_point_cloud(str(p), geometry, write_ascii=False)
        return p.read_bytes()


def report(rec: Reconstruction) -> dict[str, Any]:
    """``recon.json``: frames registered, reprojection error, scale and spread, plane, units."""
    missing = [i for i in rec.capture.ids if i not in rec.cameras]
    return {
        "frames": rec.sfm.n_frames, "registered": len(rec.cameras), "not_registered": missing,
        "reprojection_error_px": rec.sfm.reprojection_error_px, "points": len(rec.sfm.points),
        "intrinsics": {"cam_K": [float(x) for x in rec.sfm.K_opencv.ravel()],
                       "given": rec.capture.K_opencv is not None, "pixel_convention": "OpenCV/BOP"},
        "metric": rec.metric,
        "units": "mm" if rec.metric else "unknown (no depth): the reconstruction's own unit",
        "scale_mm_per_unit": None if rec.scale is None else rec.scale.scale,
        "scale_spread": None if rec.scale is None else rec.scale.spread,
        "scale_samples": None if rec.scale is None else rec.scale.n,
        "table": {"inliers": rec.plane.inliers, "rms": rec.plane.rms,
                  "frame": "world z up along the table normal, table at z = 0"},
        "cloud": {"points": len(rec.cloud), "from": "TSDF fusion of depth" if rec.mesh is not None else "SfM points"},
        "proposals": None if rec.proposals is None else len(rec.proposals),
    }


def trajectory_png(rec: Reconstruction) -> bytes:
    """Top and side views of the camera path over the cloud (PNG bytes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = np.array([c.centre for c in rec.cameras.values()])
    shown = np.random.default_rng(0).choice(len(rec.cloud), min(20000, len(rec.cloud)), replace=False)
    pts, col = rec.cloud[shown], rec.cloud_colors[shown] / 255.0
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    unit = "mm" if rec.metric else "units"
    for ax, (a, b), name in zip(axes, ((0, 1), (0, 2)), ("top (x, y)", "side (x, z)")):
        ax.scatter(pts[:, a], pts[:, b], c=col, s=0.5)
        ax.plot(centres[:, a], centres[:, b], "-", color="tab:red", lw=1.2)
        ax.plot(centres[:1, a], centres[:1, b], "o", color="tab:red")
        ax.set_title(f"{name}: cameras (red, dot = first) over the cloud")
        ax.set_xlabel(f"{'xyz'[a]} {unit}")
        ax.set_ylabel(f"{'xyz'[b]} {unit}")
        ax.set_aspect("equal")
    fig.suptitle(f"{len(rec.cameras)} of {rec.sfm.n_frames} frames registered, reprojection "
                 f"{rec.sfm.reprojection_error_px:.2f} px" + ("" if rec.metric else "; scale unknown (no depth)"))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()
