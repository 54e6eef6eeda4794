"""Tests of the synthetic-scene tools: cameras, open3d ray-cast masks, corruptions, pose perturbation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from autoalign.experiments.scenes.synthetic import (
    corrupt_views,
    default_K,
    dilate_mask,
    erode_mask,
    make_scene,
    occluder_blob,
    perturb_pose,
    random_rotation,
    raycast_masks,
    ring_cameras,
    shift_mask,
    sphere_cameras,
    translate_mask,
    write_synthetic_scene,
)
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.bop import read_init_pose, read_scene


def _check_rotation(R: np.ndarray) -> None:
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def test_sphere_cameras_look_at_target_from_all_around():
    rng = np.random.default_rng(0)
    target = np.array([12.0, -7.0, 30.0])
    cams = sphere_cameras(300, rng, dist_range=(300.0, 750.0), target=target)
    assert len(cams) == 300
    dirs = []
    for c in cams:
        _check_rotation(c.R_w2c)
        assert (c.width, c.height) == (640, 480)
        assert np.allclose(c.K, [[600, 0, 320], [0, 600, 240], [0, 0, 1]])
        uv = c.project(target[None])[0]
        assert np.abs(uv - [320.0, 240.0]).max() < 1e-6
        assert c.to_camera(target[None])[0, 2] > 0  # in front
        d = np.linalg.norm(c.centre - target)
        assert 300.0 <= d <= 750.0
        dirs.append((c.centre - target) / d)
    dirs = np.array(dirs)
    # uniform on the sphere: mean direction near zero, every octant populated
    assert np.linalg.norm(dirs.mean(axis=0)) < 0.15
    octants = {tuple(s) for s in (dirs > 0).astype(int)}
    assert len(octants) == 8


def test_sphere_cameras_custom_intrinsics():
    K = np.array([[500.0, 0, 200.3], [0, 510.0, 150.7], [0, 0, 1]])
    cams = sphere_cameras(5, np.random.default_rng(1), K=K, width=400, height=300)
    for c in cams:
        assert np.abs(c.project(np.zeros((1, 3)))[0] - [200.3, 150.7]).max() < 1e-6
        assert (c.width, c.height) == (400, 300)


def test_ring_cameras_elevation_distance_azimuth():
    rng = np.random.default_rng(2)
    target = np.array([5.0, 5.0, 20.0])
    n = 24
    cams = ring_cameras(n, rng, elev_range_deg=(20.0, 50.0), dist_range=(300.0, 750.0), target=target)
    az = []
    for c in cams:
        _check_rotation(c.R_w2c)
        assert np.abs(c.project(target[None])[0] - [320.0, 240.0]).max() < 1e-6
        off = c.centre - target
        d = np.linalg.norm(off)
        assert 300.0 <= d <= 750.0
        el = np.degrees(np.arcsin(off[2] / d))
        assert 20.0 - 1e-9 <= el <= 50.0 + 1e-9
        az.append(np.degrees(np.arctan2(off[1], off[0])) % 360)
        # world up (+z) goes up in the image (smaller v)
        assert c.project((target + [0, 0, 10.0])[None])[0, 1] < 240.0
    a = np.sort(az)
    gaps = np.diff(np.r_[a, a[0] + 360.0])
    assert gaps.max() < 2 * 360.0 / n  # one camera per azimuth sector: spread all around


def test_ring_cameras_jitter_moves_the_look_at_point():
    cams = ring_cameras(30, np.random.default_rng(3), jitter_mm=10.0)
    offs = []
    for c in cams:
        # the optical axis passes within sqrt(3)*10 mm of the target
        ray = c.R_w2c[2]
        to_t = -c.centre
        perp = to_t - (to_t @ ray) * ray
        offs.append(np.linalg.norm(perp))
    offs = np.array(offs)
    assert offs.max() <= np.sqrt(3) * 10.0 + 1e-9
    assert offs.max() > 1.0  # not all centred


# --------------------------------------------------------------------------------------------
# Ray casting against an analytic silhouette
# --------------------------------------------------------------------------------------------

def _frontal_camera(z0: float, cx: float = 320.0, cy: float = 240.0) -> Camera:
    """World origin on the optical axis at depth z0; camera axes = world axes."""
    K = np.array([[600.0, 0, cx], [0, 600.0, cy], [0, 0, 1]])
    return Camera(K, np.eye(3), np.array([0.0, 0.0, z0]), 640, 480)


def _expected_box_mask(cam: Camera, x_lo, x_hi, y_lo, y_hi, z_front) -> np.ndarray:
    """Pixels whose centre ray hits the front face [x_lo,x_hi] x [y_lo,y_hi] at camera depth z_front."""
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    u = np.arange(cam.width) + 0.5
    v = np.arange(cam.height) + 0.5
    X = (u - cx) / fx * z_front
    Y = (v - cy) / fy * z_front
    return ((Y[:, None] > y_lo) & (Y[:, None] < y_hi)) & ((X[None, :] > x_lo) & (X[None, :] < x_hi))


def test_raycast_box_matches_analytic_silhouette_with_half_pixel_rule():
    z0, depth = 600.0, 40.0
    cam = _frontal_camera(z0)
    z_front = z0 - depth / 2  # camera depth of the face nearest the camera
    # choose the box so its front edges project to u = 380.25 / 250.75 and v = 290.25 / 200.75
    s = z_front / 600.0
    x_hi, x_lo = (380.25 - 320) * s, (250.75 - 320) * s
    y_hi, y_lo = (290.25 - 240) * s, (200.75 - 240) * s
    box = trimesh.creation.box(extents=(x_hi - x_lo, y_hi - y_lo, depth))
    T_wm = make_pose(np.eye(3), [(x_hi + x_lo) / 2, (y_hi + y_lo) / 2, 0.0])
    mesh = mesh_from_trimesh(box, "box")
    m = raycast_masks(mesh, T_wm, [cam])[0]
    assert m.dtype == bool and m.shape == (480, 640)
    # +0.5 centre rule: col 379 (centre 379.5) in, col 380 (380.5) out; col 250 (250.5) out, 251 in
    row = 245
    assert m[row, 379] and not m[row, 380]
    assert m[row, 251] and not m[row, 250]
    col = 300
    assert m[289, col] and not m[290, col]
    assert m[201, col] and not m[200, col]
    assert np.array_equal(m, _expected_box_mask(cam, x_lo, x_hi, y_lo, y_hi, z_front))
    assert m.sum() == (379 - 251 + 1) * (289 - 201 + 1)


def test_raycast_uses_pose_and_off_centre_principal_point():
    # rotate the box 90 deg about the optical axis and move it: width/height swap, centre shifts
    z0, depth = 500.0, 30.0
    cam = _frontal_camera(z0, cx=311.3, cy=250.6)
    z_front = z0 - depth / 2
    box = trimesh.creation.box(extents=(120.0, 60.0, depth))
    Rz = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    shift = np.array([-33.3, 21.7, 0.0])
    T_wm = make_pose(Rz, shift)
    m = raycast_masks(mesh_from_trimesh(box), T_wm, [cam])[0]
    exp = _expected_box_mask(cam, shift[0] - 30, shift[0] + 30, shift[1] - 60, shift[1] + 60, z_front)
    assert np.array_equal(m, exp)
    r0, r1 = np.flatnonzero(m.any(1))[[0, -1]]
    c0, c1 = np.flatnonzero(m.any(0))[[0, -1]]
    assert (r1 - r0) > (c1 - c0)  # the 120 mm side now runs along the image rows


def test_raycast_agrees_with_projected_vertices_from_random_views():
    # every projected vertex that falls on a pixel centre's neighbourhood lies inside the mask's dilation
    tm = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    mesh = mesh_from_trimesh(tm)
    rng = np.random.default_rng(5)
    T_wm = make_pose(random_rotation(rng), [10.0, -5.0, 3.0])
    cams = sphere_cameras(4, rng, target=(10.0, -5.0, 3.0))
    masks = raycast_masks(mesh, T_wm, cams)
    for c, m in zip(cams, masks):
        uv = c.project(transform_points(T_wm, mesh.vertices))
        ij = np.floor(uv[:, ::-1]).astype(int)
        # vertices are on the silhouette or inside it: the pixel or a 4-neighbour is set
        pad = np.pad(m, 1)
        near = (pad[ij[:, 0] + 1, ij[:, 1] + 1] | pad[ij[:, 0], ij[:, 1] + 1] | pad[ij[:, 0] + 2, ij[:, 1] + 1]
                | pad[ij[:, 0] + 1, ij[:, 1]] | pad[ij[:, 0] + 1, ij[:, 1] + 2])
        assert near.all()
        # a sphere of radius 50 at distance d covers about pi (f r / d)^2 pixels
        d = np.linalg.norm(c.centre - [10.0, -5.0, 3.0])
        area = np.pi * (600 * 50 / np.sqrt(d**2 - 50**2)) ** 2
        assert m.sum() == pytest.approx(area, rel=0.05)


def test_make_scene_and_write_round_trip(tmp_path):
    tm = trimesh.creation.box(extents=(80.0, 50.0, 30.0))
    mesh = mesh_from_trimesh(tm)
    rng = np.random.default_rng(6)
    T_wm = make_pose(random_rotation(rng), [3.0, 4.0, 5.0])
    cams = sphere_cameras(3, rng, target=(3.0, 4.0, 5.0))
    scene = make_scene(mesh, T_wm, cams)
    assert scene.image_ids == [0, 1, 2]
    assert all(m.dtype == np.float32 and set(np.unique(m)) <= {0.0, 1.0} for m in scene.masks)
    assert all(m.sum() > 500 for m in scene.masks)
    written = write_synthetic_scene(tmp_path / "scene", mesh, T_wm, cams)
    back = read_scene(tmp_path / "scene")
    assert back.image_ids == [0, 1, 2]
    for a, b, w in zip(scene.masks, back.masks, written.masks):
        assert np.array_equal(a, b) and np.array_equal(a, w)
    for a, b in zip(cams, back.cameras):
        assert np.allclose(a.K, b.K) and np.allclose(a.R_w2c, b.R_w2c) and np.allclose(a.t_w2c, b.t_w2c)
    T_back = read_init_pose(tmp_path / "scene" / "scene_gt.json", back)
    assert np.allclose(T_back, T_wm, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Corruptions
# --------------------------------------------------------------------------------------------

def _square_mask(side: int = 101, H: int = 240, W: int = 320) -> np.ndarray:
    m = np.zeros((H, W), bool)
    r0, c0 = (H - side) // 2, (W - side) // 2
    m[r0:r0 + side, c0:c0 + side] = True
    return m


def _bbox(m):
    r, c = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return r[0], r[-1] + 1, c[0], c[-1] + 1


def test_shift_mask_translates_by_10_to_30_px():
    m = _square_mask()
    rng = np.random.default_rng(7)
    for _ in range(30):
        s = shift_mask(m, rng)
        assert s.sum() == m.sum()  # the square stays inside the image
        (a0, _, b0, _), (a1, _, b1, _) = _bbox(m), _bbox(s)
        dy, dx = a1 - a0, b1 - b0
        assert 10.0 <= np.hypot(dx, dy) <= 30.0
        assert np.array_equal(s, translate_mask(m, dx, dy))


def test_erode_and_dilate_by_kernel_radius():
    side = 101
    m = _square_mask(side)
    rng = np.random.default_rng(8)
    seen = set()
    for _ in range(40):
        e = erode_mask(m, rng)
        k = side - int(np.sqrt(e.sum())) + 1
        assert e.sum() == (side - k + 1) ** 2 and k in (7, 9, 11, 13, 15)
        assert not (e & ~m).any()
        seen.add(k)
        d = dilate_mask(m, rng)
        r0, r1, c0, c1 = _bbox(d)
        kd = (r1 - r0) - side + 1
        assert kd in (7, 9, 11, 13, 15) and (c1 - c0) == side + kd - 1
        assert not (m & ~d).any()
        assert side**2 + 2 * side * (kd - 1) < d.sum() < (side + kd - 1) ** 2
    assert len(seen) >= 3


def test_occluder_blob_removes_or_adds_20_to_50_percent_of_bbox():
    m = _square_mask(121)
    rng = np.random.default_rng(9)
    for _ in range(30):
        o = occluder_blob(m, rng, mode="remove")
        removed = (m & ~o).sum()
        assert not (o & ~m).any()
        assert 0.2 * 0.97 * m.sum() <= removed <= 0.5 * 1.03 * m.sum()
    # add: a ring-shaped object gets new pixels inside its bbox only
    H, W = 240, 320
    yy, xx = np.mgrid[:H, :W]
    rr = np.hypot(yy + 0.5 - 120, xx + 0.5 - 160)
    ring = (rr < 60) & (rr > 45)
    r0, r1, c0, c1 = _bbox(ring)
    added_any = False
    for _ in range(30):
        o = occluder_blob(ring, rng, mode="add")
        assert not (ring & ~o).any()
        added = o & ~ring
        assert added[:r0].sum() == added[r1:].sum() == added[:, :c0].sum() == added[:, c1:].sum() == 0
        assert added.sum() <= 0.5 * 1.03 * (r1 - r0) * (c1 - c0)
        added_any |= added.any()
    assert added_any
    assert np.array_equal(occluder_blob(np.zeros((10, 10), bool), rng), np.zeros((10, 10), bool))


@pytest.mark.parametrize("n,fraction", [(10, 0.0), (10, 0.3), (10, 0.25), (7, 0.5), (12, 1.0)])
def test_corrupt_views_corrupts_exactly_round_fraction(n, fraction):
    rng = np.random.default_rng(10)
    masks = [_square_mask(61 + 2 * i).astype(np.float32) for i in range(n)]
    out, idx = corrupt_views(masks, fraction, rng, kinds=("shift",))
    assert len(idx) == round(fraction * n) and idx == sorted(set(idx))
    for i, (a, b) in enumerate(zip(masks, out)):
        assert b.dtype == np.float32
        assert np.array_equal(a, b) != (i in idx)


def test_corrupt_views_mixed_kinds_keeps_bool_and_copies():
    rng = np.random.default_rng(11)
    masks = [_square_mask(81) for _ in range(20)]
    out, idx = corrupt_views(masks, 0.5, rng)
    assert len(idx) == 10
    assert all(o.dtype == bool for o in out)
    assert all(o is not m for o, m in zip(out, masks))
    changed = [i for i, (a, b) in enumerate(zip(masks, out)) if not np.array_equal(a, b)]
    assert set(changed) <= set(idx) and len(changed) >= 7  # 'add' inside a full square may change nothing


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------

def test_random_rotation_is_uniform_rotation():
    rng = np.random.default_rng(12)
    Rs = np.array([random_rotation(rng) for _ in range(4000)])
    for R in Rs[:50]:
        _check_rotation(R)
    assert np.abs(Rs.mean(axis=0)).max() < 0.05  # E[R] = 0 for the Haar measure
    # rotation angles follow (1 - cos t) / pi: mean angle = pi/2 + 2/pi
    ang = Rotation.from_matrix(Rs).magnitude()
    assert ang.mean() == pytest.approx(np.pi / 2 + 2 / np.pi, abs=0.03)


@pytest.mark.parametrize("trans,rot", [(0.0, 0.0), (5.0, 2.0), (20.0, 10.0), (0.0, 45.0), (37.5, 179.0)])
def test_perturb_pose_errors_are_exact(trans, rot):
    rng = np.random.default_rng(13)
    T = make_pose(random_rotation(rng), rng.uniform(-100, 100, 3))
    centre = np.array([4.0, -12.0, 7.5])
    for _ in range(5):
        P = perturb_pose(T, trans, rot, rng, centre)
        _check_rotation(P[:3, :3])
        c0 = transform_points(T, centre[None])[0]
        c1 = transform_points(P, centre[None])[0]
        assert np.linalg.norm(c1 - c0) == pytest.approx(trans, abs=1e-9)
        ang = np.degrees(Rotation.from_matrix(T[:3, :3].T @ P[:3, :3]).magnitude())
        assert ang == pytest.approx(rot, abs=1e-7)
    # default centre is the model origin
    P = perturb_pose(T, 10.0, 5.0, rng)
    assert np.linalg.norm(P[:3, 3] - T[:3, 3]) == pytest.approx(10.0, abs=1e-9)


def test_default_K():
    assert np.allclose(default_K(), [[600, 0, 320], [0, 600, 240], [0, 0, 1]])


def test_pixel_rays_pass_through_pixel_centres():
    from autoalign.experiments.scenes.synthetic import pixel_rays

    K = np.array([[600.0, 0.4, 320.2], [0.0, 610.0, 240.7], [0.0, 0.0, 1.0]])
    cam = sphere_cameras(1, np.random.default_rng(14), K=K)[0]
    o, d = pixel_rays(cam)
    assert np.allclose(o, cam.centre)
    assert d.shape == (480 * 640, 3)
    for i, j in [(0, 0), (0, 639), (479, 0), (123, 456)]:
        uv = cam.project((o + 350.0 * d[i * 640 + j])[None])[0]
        assert np.abs(uv - [j + 0.5, i + 0.5]).max() < 1e-9


def _full_image_hits(meshes, poses, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """open3d's first hits of one ray per pixel centre of the whole image (``t_hit`` finite, and the
    geometry hit), cast here without the box the product casts in."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = [scene.add_triangles(o3d.core.Tensor(transform_points(T, m.vertices).astype(np.float32)),
                               o3d.core.Tensor(m.faces.astype(np.uint32))) for m, T in zip(meshes, poses)]
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T @ cam.R_w2c
    rays = np.hstack([np.broadcast_to(cam.centre, d.shape), d]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    shape = (cam.height, cam.width)
    return np.isfinite(hit["t_hit"].numpy()).reshape(shape), np.asarray(ids), hit["geometry_ids"].numpy().reshape(shape)


@pytest.mark.parametrize("where", ["inside", "across the border", "around the camera"])
def test_masks_cast_in_the_projections_box_are_the_whole_images(where):
    """Only the rays through the box of the meshes' projection are cast: the masks are those of one ray
    per pixel of the whole image, with an object cut by the image's border and with the camera
    inside an object's extent (some vertices behind it: the whole image is cast)."""
    from autoalign.experiments.scenes.synthetic import raycast_visible_masks

    cam = _frontal_camera(500.0)
    offset = {"inside": [0.0, 0.0, 0.0], "across the border": [210.0, -60.0, 0.0],
              "around the camera": [0.0, 0.0, -470.0]}[where]
    rng = np.random.default_rng(11)
    meshes = [mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=r)) for r in (60.0, 35.0)]
    poses = [make_pose(random_rotation(rng), np.add(offset, [0.0, 0.0, 0.0])),
             make_pose(random_rotation(rng), np.add(offset, [-90.0, 40.0, -20.0]))]
    single = raycast_masks(meshes[0], poses[0], [cam])[0]
    full, _, _ = _full_image_hits(meshes[:1], poses[:1], cam)
    assert np.array_equal(single, full) and full.any()
    visible = raycast_visible_masks(meshes, poses, [cam])[0]
    full, ids, geom = _full_image_hits(meshes, poses, cam)
    for g, m in zip(ids, visible):
        assert np.array_equal(m, full & (geom == g))
    assert visible[0].any()  # (around the camera the big sphere hides the small one)
