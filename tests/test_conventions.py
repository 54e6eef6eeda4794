"""Conventions (BOP poses, pixel centres, camera rays) checked against hand-written formulas and an
independent renderer (open3d ray casting in :mod:`autoalign.experiments.scenes.synthetic`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from autoalign.experiments.scenes.synthetic import raycast_masks, write_scene
from autoalign.geometry.camera import Camera, look_at
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.bop import (
    Scene,
    pose_in_camera,
    read_init_pose,
    read_scene,
)
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer


def _random_camera(rng: np.random.Generator, width: int = 64, height: int = 48) -> Camera:
    """A camera with fx != fy, off-centre principal point and a generic (non axis-aligned) pose."""
    K = np.array([[rng.uniform(500, 700), 0.0, rng.uniform(0.4, 0.6) * width],
                  [0.0, rng.uniform(500, 700), rng.uniform(0.4, 0.6) * height],
                  [0.0, 0.0, 1.0]])
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    t = rng.uniform(-300, 300, 3)
    return Camera(K, R, t, width, height)


def _world_point_at(cam: Camera, u: float, v: float, depth: float) -> np.ndarray:
    """World point at camera depth ``depth`` (mm) on the ray through continuous pixel (u, v), by hand."""
    x_c = depth * np.linalg.solve(cam.K, np.array([u, v, 1.0]))
    return cam.R_w2c.T @ (x_c - cam.t_w2c)


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return make_pose(Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(), rng.uniform(-200, 200, 3))


# ------------------------------------------------------------------------------------------- BOP

def test_pose_in_camera_by_hand():
    rng = np.random.default_rng(0)
    for _ in range(20):
        cam = _random_camera(rng)
        T_wm = _random_T(rng)
        R, t = pose_in_camera(T_wm, cam)
        R = np.asarray(R).reshape(3, 3)  # row-major, BOP
        np.testing.assert_allclose(R, cam.R_w2c @ T_wm[:3, :3], atol=1e-13)
        np.testing.assert_allclose(t, cam.R_w2c @ T_wm[:3, 3] + cam.t_w2c, atol=1e-10)


def test_bop_projection_of_model_points_equals_camera_project():
    rng = np.random.default_rng(1)
    X_m = rng.uniform(-50, 50, (30, 3))
    for _ in range(10):
        cam = _random_camera(rng)
        # a pose in front of the camera: model origin 400 mm along the optical axis
        T_wm = make_pose(Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(),
                         _world_point_at(cam, 30.0, 20.0, 400.0))
        R, t = pose_in_camera(T_wm, cam)
        x = np.asarray(cam.K) @ (np.asarray(R).reshape(3, 3) @ X_m.T + np.asarray(t)[:, None])
        uv_bop = (x[:2] / x[2]).T
        np.testing.assert_allclose(uv_bop, cam.project(transform_points(T_wm, X_m)), atol=1e-9)


def test_bop_write_read_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    n = 5
    cams = [_random_camera(rng, 40, 30) for _ in range(n)]
    masks = []
    for k in range(n):
        m = np.zeros((30, 40), np.float32)
        m[3 + k:20, 5:30 - k] = 1.0
        masks.append(m)
    ids = [3, 7, 8, 20, 100]
    T_wm = _random_T(rng)
    write_scene(tmp_path, Scene(cams, masks, ids), T_wm, obj_id=5)

    scene = read_scene(tmp_path)
    assert scene.image_ids == ids
    for c0, c1, m0, m1 in zip(cams, scene.cameras, masks, scene.masks):
        np.testing.assert_array_equal(c1.K, c0.K)
        np.testing.assert_array_equal(c1.R_w2c, c0.R_w2c)
        np.testing.assert_array_equal(c1.t_w2c, c0.t_w2c)
        assert (c1.width, c1.height) == (40, 30)
        np.testing.assert_array_equal(m1, m0)

    gt = json.loads((tmp_path / "scene_gt.json").read_text())
    cam_json = json.loads((tmp_path / "scene_camera.json").read_text())
    for im, cam in zip(ids, cams):
        e = gt[str(im)][0]
        assert e["obj_id"] == 5
        R_w2c = np.asarray(cam_json[str(im)]["cam_R_w2c"]).reshape(3, 3)
        np.testing.assert_allclose(np.asarray(e["cam_R_m2c"]).reshape(3, 3), R_w2c @ T_wm[:3, :3], atol=1e-13)
        np.testing.assert_allclose(e["cam_t_m2c"], R_w2c @ T_wm[:3, 3] + cam.t_w2c, atol=1e-10)

    # read_init_pose uses the first view of the scene it is given: check it through every view
    for k in range(n):
        T = read_init_pose(tmp_path / "scene_gt.json", scene.subset([k]), obj_id=5)
        np.testing.assert_allclose(T, T_wm, atol=1e-9)


# --------------------------------------------------------------------------------- pixel centres

def _sphere(radius_mm: float, subdivisions: int = 3):
    return mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_mm), "sphere")


def _masks_both(mesh, T_wm, cams):
    ours = SoftSilhouetteRasterizer(mesh).hard_masks(T_wm, cams)
    o3d = raycast_masks(mesh, T_wm, cams)
    return ours, o3d


def _only(shape, *pixels) -> np.ndarray:
    m = np.zeros(shape, bool)
    for i, j in pixels:
        m[i, j] = True
    return m


@pytest.mark.parametrize("seed", range(3))
def test_tiny_sphere_at_pixel_centre_lights_that_pixel(seed):
    rng = np.random.default_rng(10 + seed)
    cam = _random_camera(rng)
    depth = 400.0
    r_mm = 0.05 * depth / cam.K[0, 0]  # 0.05 px radius
    mesh = _sphere(r_mm, 2)
    cases = [(int(rng.integers(2, 46)), int(rng.integers(2, 62))) for _ in range(3)] + [(0, 0), (47, 63)]
    for i, j in cases:
        T_wm = make_pose(np.eye(3), _world_point_at(cam, j + 0.5, i + 0.5, depth))
        np.testing.assert_allclose(cam.project(T_wm[:3, 3][None])[0], [j + 0.5, i + 0.5], atol=1e-9)
        ours, o3d = _masks_both(mesh, T_wm, [cam])
        expect = _only((48, 64), (i, j))
        np.testing.assert_array_equal(o3d[0], expect, err_msg=f"open3d, pixel {(i, j)}")
        np.testing.assert_array_equal(ours[0], expect, err_msg=f"ours, pixel {(i, j)}")


def test_small_sphere_lights_the_pixel_whose_centre_it_covers():
    """A ~0.4 px sphere at u = j + 0.7 covers only centre j + 0.5; at j + 1.3 only j + 1.5; at a pixel
    corner (j + 1, i + 1) no centre at all: masks sample pixel centres, not pixel areas."""
    rng = np.random.default_rng(20)
    cam = _random_camera(rng)
    depth = 400.0
    # radius 0.4 px in geometric-mean focal units: 0.34..0.47 px along u and v for fx/fy in 500..700
    mesh = _sphere(0.4 * depth / np.sqrt(cam.K[0, 0] * cam.K[1, 1]), 3)
    i, j = 20, 30
    cases = {(j + 0.7, i + 0.5): [(i, j)], (j + 1.3, i + 0.5): [(i, j + 1)],
             (j + 0.5, i + 0.7): [(i, j)], (j + 0.5, i + 1.3): [(i + 1, j)],
             (j + 1.0, i + 1.0): [], (j + 0.35, i + 0.35): [(i, j)]}
    for (u, v), lit in cases.items():
        T_wm = make_pose(np.eye(3), _world_point_at(cam, u, v, depth))
        ours, o3d = _masks_both(mesh, T_wm, [cam])
        expect = _only((48, 64), *lit)
        np.testing.assert_array_equal(o3d[0], expect, err_msg=f"open3d at {(u, v)}")
        np.testing.assert_array_equal(ours[0], expect, err_msg=f"ours at {(u, v)}")


def test_project_and_floor_rule():
    rng = np.random.default_rng(30)
    for _ in range(10):
        cam = _random_camera(rng)
        i, j = int(rng.integers(0, 47)), int(rng.integers(0, 63))
        for du, col in [(1e-6, j), (0.5, j), (0.999, j), (1.001, j + 1), (-0.001, j - 1)]:
            X = _world_point_at(cam, j + du, i + 0.5, rng.uniform(100, 2000))
            uv = cam.project(X[None])[0]
            np.testing.assert_allclose(uv, [j + du, i + 0.5], atol=1e-9)
            assert int(np.floor(uv[0])) == col and int(np.floor(uv[1])) == i


def test_axis_aligned_rectangle_edges_at_pixel_centres():
    """A fronto-parallel plate whose edges lie 0.02 px either side of pixel centres lights exactly the
    pixels whose centres it covers, in both renderers (and in the soft renderer's hard mask)."""
    rng = np.random.default_rng(40)
    W, H = 64, 48
    K = np.array([[610.0, 0.0, 31.3], [0.0, 590.0, 24.9], [0.0, 0.0, 1.0]])
    cam = Camera(K, Rotation.random(random_state=3).as_matrix(), rng.uniform(-100, 100, 3), W, H)
    depth = 400.0
    box = mesh_from_trimesh(trimesh.creation.box(extents=[1.0, 1.0, 1.0]), "box")
    for _ in range(4):
        j0, j1 = sorted(rng.choice(np.arange(3, 60), 2, replace=False))
        i0, i1 = sorted(rng.choice(np.arange(3, 44), 2, replace=False))
        s = rng.choice([-0.02, 0.02], 4)
        u0, u1, v0, v1 = j0 + 0.5 + s[0], j1 + 0.5 + s[1], i0 + 0.5 + s[2], i1 + 0.5 + s[3]
        # the plate: [u0, u1] x [v0, v1] at depth, 1 um thick (its side walls add < 1e-4 px)
        x0, y0 = (u0 - K[0, 2]) * depth / K[0, 0], (v0 - K[1, 2]) * depth / K[1, 1]
        x1, y1 = (u1 - K[0, 2]) * depth / K[0, 0], (v1 - K[1, 2]) * depth / K[1, 1]
        S = np.diag([x1 - x0, y1 - y0, 1e-3, 1.0])
        T_cm = make_pose(np.eye(3), [(x0 + x1) / 2, (y0 + y1) / 2, depth + 0.5e-3]) @ S
        T_wm = np.linalg.inv(cam.T_cw) @ T_cm
        plate = mesh_from_trimesh(trimesh.Trimesh(transform_points(T_wm, box.vertices), box.faces, process=False))
        jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        expect = (jj > u0) & (jj < u1) & (ii > v0) & (ii < v1)
        ours, o3d = _masks_both(plate, np.eye(4), [cam])
        np.testing.assert_array_equal(o3d[0], expect)
        np.testing.assert_array_equal(ours[0], expect)
        sil = SoftSilhouetteRasterizer(plate).render(np.eye(4), [cam], sigma=0.05, with_jacobian=False)
        np.testing.assert_array_equal(sil.image(0, "hard", (W, H)) > 0.5, expect)
        np.testing.assert_array_equal(sil.image(0, "soft", (W, H)) > 0.5, expect)


def test_scaled_camera_maps_u_to_half_exactly():
    rng = np.random.default_rng(50)
    cam = _random_camera(rng, 65, 47)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (33, 24)
    X = np.array([_world_point_at(cam, u, v, d) for u, v, d in rng.uniform([0, 0, 100], [65, 47, 900], (50, 3))])
    np.testing.assert_allclose(half.project(X), cam.project(X) / 2.0, atol=1e-11)
    # pixel edges stay on integers: the corner (2j, 2i) of the full image is the corner (j, i)
    for u, v in [(0.0, 0.0), (2.0, 4.0), (64.0, 46.0)]:
        np.testing.assert_allclose(half.project(_world_point_at(cam, u, v, 300.0)[None])[0], [u / 2, v / 2], atol=1e-11)
    np.testing.assert_array_equal(cam.scaled(1.0).K, cam.K)


def test_scaled_camera_renders_the_shared_corner_as_one_half_res_pixel():
    """Full-res continuous point (2j + 1, 2i + 1) -- the corner shared by 4 full-res pixels -- is the
    centre of half-res pixel (i, j)."""
    rng = np.random.default_rng(60)
    cam = _random_camera(rng)
    half = cam.scaled(0.5)
    depth = 500.0
    mesh = _sphere(0.1 * depth / cam.K[0, 0], 2)  # 0.1 px at full res, 0.05 at half res
    for i, j in [(5, 7), (11, 3), (0, 0), (23, 31)]:
        T_wm = make_pose(np.eye(3), _world_point_at(cam, 2 * j + 1.0, 2 * i + 1.0, depth))
        ours, o3d = _masks_both(mesh, T_wm, [half, cam])
        expect = _only((24, 32), (i, j))
        np.testing.assert_array_equal(o3d[0], expect)
        np.testing.assert_array_equal(ours[0], expect)
        assert not o3d[1].any() and not ours[1].any()  # at full res it sits on a corner: no centre covered


# ---------------------------------------------------------------------------------------- camera

def test_ray_directions_by_hand():
    rng = np.random.default_rng(70)
    for _ in range(10):
        cam = _random_camera(rng)
        X = np.array([_world_point_at(cam, u, v, d) for u, v, d in rng.uniform([-10, -10, 50], [74, 58, 2000], (20, 3))])
        uv = cam.project(X)
        d = cam.ray_directions(uv)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        to_X = X - cam.centre
        to_X /= np.linalg.norm(to_X, axis=1, keepdims=True)
        np.testing.assert_allclose(d, to_X, atol=1e-9)  # parallel and pointing forwards
        Kinv = np.linalg.inv(cam.K)
        for (u, v), dk in zip(uv, d):
            ref = cam.R_w2c.T @ Kinv @ np.array([u, v, 1.0])
            np.testing.assert_allclose(dk, ref / np.linalg.norm(ref), atol=1e-12)
        # centre really is the camera centre: it maps to the camera-frame origin
        np.testing.assert_allclose(cam.R_w2c @ cam.centre + cam.t_w2c, 0.0, atol=1e-10)


def test_look_at_points_z_at_target_right_handed():
    rng = np.random.default_rng(80)
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    for k in range(20):
        eye = rng.uniform(-800, 800, 3)
        target = rng.uniform(-50, 50, 3)
        if k == 0:
            eye = target + [0.0, 0.0, 500.0]  # looking straight down the default up vector
        cam = look_at(eye, target, K, 640, 480)
        R = cam.R_w2c
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(R) - 1.0) < 1e-12
        np.testing.assert_allclose(np.cross(R[0], R[1]), R[2], atol=1e-12)  # x cross y = z
        fwd = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(R[2], fwd, atol=1e-12)  # +z (optical axis) points at the target
        np.testing.assert_allclose(cam.centre, eye, atol=1e-9)
        np.testing.assert_allclose(cam.project(target[None])[0], [320.0, 240.0], atol=1e-9)
        x_c = cam.to_camera(target[None])[0]
        assert x_c[2] > 0 and abs(x_c[2] - np.linalg.norm(target - eye)) < 1e-9
        if k > 0:
            # world up (+z) appears upwards in the image (smaller v), y is down
            above = target + np.array([0.0, 0.0, 10.0])
            assert cam.project(above[None])[0, 1] < 240.0
