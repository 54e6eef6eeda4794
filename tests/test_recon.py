"""``autoalign recon`` (issue 14) on a synthetic hand-held RGB-D stream rendered with mitsuba
(``experiments/stream.py``: textured objects on a textured table, true cameras known): frames
registered, the trajectory after alignment (open3d's point-to-point estimation, Sim(3) and SE(3),
``experiments/bench_pipeline.py``),
the scale from depth and the table frame; RGB only is flagged; bad inputs are one-line errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from autoalign.bop import read_cameras
from autoalign.experiments.bench_pipeline import aligned_camera_errors, rigid_alignment
from autoalign.experiments.stream import DEPTH_SCALE, render_stream

FRAMES = 30


@pytest.fixture(scope="module")
def stream(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("stream") / "capture"
    render_stream(folder, n_frames=FRAMES, width=320, height=240, seed=1)
    return folder


def _recon(capture: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "recon", str(capture), "--out", str(out),
                           "--quiet", *extra], capture_output=True, text=True, timeout=900)


def test_rgbd_stream_cameras_scale_and_table(stream, tmp_path):
    out = tmp_path / "scene"
    p = _recon(stream, out, "--intrinsics", str(stream / "intrinsics.json"), "--depth-scale", str(DEPTH_SCALE))
    assert p.returncode == 0, p.stderr
    ours, truth = read_cameras(out), read_cameras(stream / "gt")
    assert len(ours) >= 0.98 * FRAMES
    sim3 = rigid_alignment(ours, truth, scaling=True)
    assert abs(np.cbrt(np.linalg.det(sim3[:3, :3])) - 1.0) < 0.005  # the scale from depth, within 0.5%
    T = rigid_alignment(ours, truth, scaling=False)  # metric: a rigid motion is all that may differ
    pos, rot = aligned_camera_errors(ours, truth, T)
    assert np.median(pos) <= 2.0 and np.median(rot) <= 0.2, (np.median(pos), np.median(rot))
    normal = T[:3, :3] @ np.array([0.0, 0.0, 1.0])  # our table normal in the true frame, whose table is z = 0
    assert np.degrees(np.arccos(np.clip(normal[2], -1, 1))) <= 0.5
    assert abs(T[2, 3]) < 2.0  # and our table plane at the true one's height
    rec = json.loads((out / "recon.json").read_text())
    assert rec["metric"] and rec["registered"] == len(ours) and rec["scale_spread"] < 0.02
    assert len(list((out / "rgb").iterdir())) == len(ours) == len(list((out / "depth").iterdir()))
    assert o3d.io.read_point_cloud(str(out / "cloud.ply")).has_points()
    assert o3d.io.read_triangle_mesh(str(out / "mesh.ply")).has_triangles()
    assert cv2.imread(str(out / "trajectory.png")) is not None


def test_rgb_only_is_flagged_as_without_scale(stream, tmp_path):
    capture = tmp_path / "rgb_only"
    shutil.copytree(stream / "rgb", capture)
    p = _recon(capture, tmp_path / "scene", "--intrinsics", str(stream / "intrinsics.json"))
    assert p.returncode == 3, p.stderr
    assert "scale is unknown" in p.stderr
    assert not json.loads((tmp_path / "scene" / "recon.json").read_text())["metric"]


def test_bad_captures_are_one_line_errors_and_write_nothing(stream, tmp_path):
    def fails(capture, *extra) -> str:
        out = tmp_path / "out"
        p = _recon(capture, out, *extra)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
        assert not out.exists()
        return p.stderr

    video = tmp_path / "clip.mp4"
    video.write_text("not a video")
    assert "cannot open the video" in fails(video)
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        cv2.imwrite(str(noise / f"{i:06d}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    assert "too few matches" in fails(noise)
    bad_depth = tmp_path / "bad_depth"
    shutil.copytree(stream, bad_depth)
    cv2.imwrite(str(bad_depth / "depth" / "000004.png"), np.zeros((10, 10), np.uint16))
    assert "depth is 10x10 but the frames are 320x240" in fails(bad_depth)
    broken = tmp_path / "broken"
    shutil.copytree(stream / "rgb", broken)
    (broken / "000002.png").write_bytes(b"\x89PNG broken")
    assert "000002.png: cannot read the frame" in fails(broken)
