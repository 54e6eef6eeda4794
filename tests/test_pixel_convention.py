"""Where pixel centres are for BOP ``cam_K``: checked against OpenCV's ``projectPoints`` and open3d
ray casting, not against our own renderer alone.

BOP and OpenCV put the centre of pixel (row i, col j) at (j, i); autoalign's renderer works with
pixel edges on integers (centre at (j + 0.5, i + 0.5)) and converts ``cam_K`` on import and export.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from autoalign.engine.seeding import Click
from autoalign.experiments.scenes.synthetic import write_scene
from autoalign.geometry.camera import Camera, K_from_opencv, K_to_opencv, uv_from_opencv
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_scene
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

W, H = 64, 48


def _bop_camera(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV intrinsics (fx != fy, off-centre principal point; OpenCV has no skew) and a generic pose."""
    K = np.array([[rng.uniform(500, 700), 0.0, rng.uniform(0.4, 0.6) * W],
                  [0.0, rng.uniform(500, 700), rng.uniform(0.4, 0.6) * H],
                  [0.0, 0.0, 1.0]])
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    return K, R, rng.uniform(-300, 300, 3)


def _write_bop(tmp_path, K, R, t, masks=None) -> None:
    """A one-view BOP scene written by hand (not by autoalign), with an all-ones mask."""
    (tmp_path / "mask_visib").mkdir()
    cv2.imwrite(str(tmp_path / "mask_visib" / "000000_000000.png"),
                np.full((H, W), 255, np.uint8) if masks is None else masks)
    (tmp_path / "scene_camera.json").write_text(json.dumps(
        {"0": {"cam_K": K.ravel().tolist(), "cam_R_w2c": R.ravel().tolist(), "cam_t_w2c": t.tolist()}}))


def _point_projecting_to(K, R, t, u, v, depth):
    """World point whose OpenCV projection is (u, v), found by inverting K (checked with projectPoints)."""
    X_c = depth * np.linalg.solve(K, [u, v, 1.0])
    X_w = R.T @ (X_c - t)
    uv, _ = cv2.projectPoints(X_w[None], cv2.Rodrigues(R)[0], t, K, None)
    np.testing.assert_allclose(uv.ravel(), [u, v], atol=1e-6)
    return X_w


@pytest.mark.parametrize("seed", range(3))
def test_point_that_opencv_projects_to_integer_ij_lights_pixel_ij(tmp_path, seed):
    """A 0.05 px sphere at the 3-D point OpenCV projects to (j, i): after reading the BOP scene,
    our ray-cast mask is exactly pixel (row i, col j)."""
    rng = np.random.default_rng(seed)
    K, R, t = _bop_camera(rng)
    _write_bop(tmp_path, K, R, t)
    cam = read_scene(tmp_path).cameras[0]
    depth = 400.0
    sphere = mesh_from_trimesh(trimesh.creation.icosphere(2, radius=0.05 * depth / K[0, 0]), "dot")
    rast = SoftSilhouetteRasterizer(sphere)
    for i, j in [(0, 0), (H - 1, W - 1)] + [(int(rng.integers(1, H - 1)), int(rng.integers(1, W - 1))) for _ in range(3)]:
        X = _point_projecting_to(K, R, t, float(j), float(i), depth)
        mask = rast.hard_masks(make_pose(np.eye(3), X), [cam])[0]
        assert np.argwhere(mask).tolist() == [[i, j]], (i, j)


@pytest.mark.parametrize("seed", range(3))
def test_check_renders_the_dot_opencv_projects_to_ij_at_pixel_ij(seed):
    """The check's renderer (``render_labels``, mitsuba) keeps the same convention as the refine's
    (above): a 0.05 px sphere at the point OpenCV projects to (j, i) lights pixel (row i, col j)
    only, and the ray it casts through pixel (i, j) projects to (j, i) in ``cv2.projectPoints``."""
    from autoalign.geometry.mesh import ColouredMesh
    from autoalign.rasterizers.label_rendering import PlacedMesh, pixel_rays, render_labels

    rng = np.random.default_rng(seed)
    K, R, t = _bop_camera(rng)
    depth = 400.0
    ico = trimesh.creation.icosphere(2, radius=0.05 * depth / K[0, 0])
    dot = ColouredMesh(np.asarray(ico.vertices), np.asarray(ico.faces), np.ones((len(ico.vertices), 3), np.float32), True)
    for i, j in [(0, 0), (H - 1, W - 1)] + [(int(rng.integers(1, H - 1)), int(rng.integers(1, W - 1))) for _ in range(3)]:
        X_c = R @ _point_projecting_to(K, R, t, float(j), float(i), depth) + t
        seen = render_labels([PlacedMesh(0, dot, np.eye(3), X_c)], K, W, H).instance >= 0
        assert np.argwhere(seen).tolist() == [[i, j]], (i, j)
    rays = pixel_rays(K_from_opencv(K), W, H).astype(np.float64) * depth  # camera frame, z = depth
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, None)
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    np.testing.assert_allclose(uv.reshape(-1, 2), np.column_stack([jj.ravel(), ii.ravel()]), atol=1e-3)


def test_bop_masks_match_open3d_rays_through_opencv_pixel_centres(tmp_path):
    """A mesh seen through a BOP camera: our mask equals open3d's, cast through (j, i) with K^-1."""
    rng = np.random.default_rng(5)
    K, R, t = _bop_camera(rng)
    _write_bop(tmp_path, K, R, t)
    cam = read_scene(tmp_path).cameras[0]
    box = trimesh.creation.box(extents=(14.0, 9.0, 11.0))
    box.apply_transform(make_pose(Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix(), np.zeros(3)))
    T_wm = make_pose(np.eye(3), _point_projecting_to(K, R, t, 31.3, 22.7, 300.0))
    ours = SoftSilhouetteRasterizer(mesh_from_trimesh(box, "box")).hard_masks(T_wm, [cam])[0]

    scene = o3d.t.geometry.RaycastingScene()
    posed = box.copy().apply_transform(T_wm)
    scene.add_triangles(o3d.core.Tensor(np.asarray(posed.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(posed.faces, np.uint32)))
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))  # OpenCV centres
    d = np.stack([jj.ravel(), ii.ravel(), np.ones(W * H)], 1) @ np.linalg.inv(K).T @ R  # R^T d_c, world
    o = np.broadcast_to(-R.T @ t, d.shape)
    rays = o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32))
    theirs = np.isfinite(scene.cast_rays(rays)["t_hit"].numpy()).reshape(H, W)
    assert 50 < theirs.sum() < W * H - 50
    np.testing.assert_array_equal(ours, theirs)


def test_cam_K_round_trips_and_scaling_keeps_pixel_edges():
    rng = np.random.default_rng(1)
    K, R, t = _bop_camera(rng)
    np.testing.assert_allclose(K_to_opencv(K_from_opencv(K)), K, atol=1e-12)
    cam = Camera.from_opencv(K, R, t, W, H)
    np.testing.assert_allclose(cam.K[:2, 2], K[:2, 2] + 0.5)
    np.testing.assert_allclose(cam.K_opencv, K, atol=1e-12)
    # Half resolution: OpenCV's rule for resizing intrinsics is cx' = (cx + 0.5) / 2 - 0.5.
    half = cam.scaled(0.5)
    np.testing.assert_allclose(half.K_opencv[:2, 2], (K[:2, 2] + 0.5) / 2 - 0.5, atol=1e-12)


def test_written_cam_K_is_opencv(tmp_path):
    """write_scene writes the OpenCV intrinsics, and reading them back gives the same camera."""
    from autoalign.io.bop import Scene

    rng = np.random.default_rng(2)
    K, R, t = _bop_camera(rng)
    cam = Camera.from_opencv(K, R, t, W, H)
    write_scene(tmp_path, Scene([cam], [np.ones((H, W), np.float32)], [0]), np.eye(4))
    written = json.loads((tmp_path / "scene_camera.json").read_text())["0"]["cam_K"]
    np.testing.assert_allclose(np.reshape(written, (3, 3)), K, atol=1e-12)
    np.testing.assert_allclose(read_scene(tmp_path).cameras[0].K, cam.K, atol=1e-12)


def test_click_is_typed_in_opencv_coordinates():
    c = Click.parse("3:10,20")
    assert (c.image_id, c.u, c.v) == (3, 10.5, 20.5)
    np.testing.assert_allclose(uv_from_opencv([10.0, 20.0]), [c.u, c.v])


@pytest.mark.parametrize("seed", range(3))
def test_the_ray_through_pixel_ij_reaches_what_opencv_projects_to_ij(seed):
    """``Camera.pixel_rays(j, i)`` (the one place pixel indices become coordinates,
    :func:`~autoalign.geometry.camera.pixel_centres`) points at the world points that OpenCV's
    ``projectPoints`` puts at ``(j, i)`` with the file's ``cam_K``."""
    rng = np.random.default_rng([seed, 7])
    K, R, t = _bop_camera(rng)
    cam = Camera.from_opencv(K, R, t, W, H)
    cols, rows = rng.integers(0, W, 20), rng.integers(0, H, 20)
    d = cam.pixel_rays(cols, rows)
    X = cam.centre + 500.0 * d
    uv, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, None)
    np.testing.assert_allclose(uv.reshape(-1, 2), np.column_stack([cols, rows]), atol=1e-6)


# Where ``+ 0.5`` may still be written outside geometry/camera.py: not a pixel centre.
NOT_PIXEL_CENTRES = {
    "autoalign/engine/seeding.py": "the super-Fibonacci spiral's sample offsets",
    "rasterizers/outline.py": "the midpoints of an edge's sub-segments",
}


def test_pixel_indices_become_coordinates_in_one_place():
    """No product module adds the half pixel to a pixel index by hand (issue 44: ``+ 0.5`` was
    written in about 12 places): they call ``pixel_centres``, ``Camera.pixel_rays`` or
    ``uv_from_opencv``; the few ``+ 0.5`` left are listed with what they are."""
    import io
    import tokenize
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    found = []
    for package in ("autoalign", "losses", "rasterizers", "recon", "cli"):
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            if rel == "autoalign/geometry/camera.py" or rel.startswith("autoalign/experiments") or rel in NOT_PIXEL_CENTRES:
                continue
            tokens = [t for t in tokenize.generate_tokens(io.StringIO(path.read_text()).readline)
                      if t.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.COMMENT, tokenize.INDENT,
                                        tokenize.DEDENT)]
            for before, number, after in zip(tokens, tokens[1:], tokens[2:]):
                if (number.type == tokenize.NUMBER and number.string in ("0.5", ".5") and before.string in ("+", "-")
                        and after.string not in ("*", "/")):
                    found.append(f"{rel}:{number.start[0]}: {number.line.strip()}")
    assert not found, "\n".join(found)
