"""The simulated study's protocol and metrics: camera placement, initial-pose noise, success tests."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.experiments.scenes.synthetic import axis_angle_matrix, random_rotation
from autoalign.experiments.studies.metrics import (
    Symmetries,
    add_mm,
    adds_mm,
    auc,
    axis_dot_axis_angle,
    axis_dot_columns,
    closest_equivalent,
    label_difference,
    pose_errors,
    success,
    track_fit,
)
from autoalign.experiments.studies.protocol import (
    ALT_SIGMA_MM,
    PAPER_SIGMA_MM,
    ImageSetup,
    make_trial,
    origin_cameras,
    sphere_radius,
)
from autoalign.geometry.se3 import make_pose

CENTRE = np.array([3.0, -2.0, 5.0])  # a model whose bbox centre is not its origin


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def test_cameras_look_at_the_origin_from_one_sphere():
    setup = ImageSetup()
    rng = np.random.default_rng(0)
    cams = origin_cameras(40, 500.0, rng, setup)
    assert len(cams) == 40
    for c in cams:
        R = c.R_w2c
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.linalg.norm(c.centre) == pytest.approx(500.0)
        # the z axis points at the origin, which projects to the principal point
        assert R[2] @ (-c.centre / np.linalg.norm(c.centre)) == pytest.approx(1.0, abs=1e-12)
        assert np.allclose(c.project(np.zeros((1, 3)))[0], [setup.width / 2, setup.height / 2], atol=1e-9)
    dirs = np.array([c.centre for c in cams]) / 500.0
    assert np.linalg.norm(dirs.mean(0)) < 0.4  # spread all around, not one cap
    # random roll: camera x axes are not all horizontal (look_at's default up would make them so)
    assert np.abs(np.array([c.R_w2c[0, 2] for c in cams])).max() > 0.5


def test_trial_geometry_size_and_ground_truth():
    setup = ImageSetup()
    diam = 150.0
    tr = make_trial(CENTRE, diam, seed=3, model_id=7, trial=2, setup=setup)
    assert np.allclose(tr.T_gt[:3, :3] @ CENTRE + tr.T_gt[:3, 3], 0.0, atol=1e-12)  # centre at the origin
    assert setup.size_frac[0] <= tr.size_frac <= setup.size_frac[1]
    assert tr.radius_mm == pytest.approx(sphere_radius(diam, tr.size_frac, setup))
    # the diameter at the origin spans size_frac of the image height
    assert setup.focal * diam / tr.radius_mm == pytest.approx(tr.size_frac * setup.height)
    assert {np.linalg.norm(c.centre).round(6) for c in tr.cameras} == {round(tr.radius_mm, 6)}


def test_trials_are_deterministic_and_shared_across_conditions():
    a = make_trial(CENTRE, 100.0, 0, 1, 0)
    b = make_trial(CENTRE, 100.0, 0, 1, 0, n_views=5)
    c = make_trial(CENTRE, 100.0, 0, 1, 0, sigma_mm=ALT_SIGMA_MM)
    d = make_trial(CENTRE, 100.0, 0, 1, 1)
    assert np.array_equal(a.T_gt, b.T_gt) and np.array_equal(a.T_init, b.T_init)
    assert all(np.array_equal(x.R_w2c, y.R_w2c) and np.array_equal(x.t_w2c, y.t_w2c)
               for x, y in zip(a.cameras[:5], b.cameras))
    assert np.array_equal(a.T_init[:3, :3], c.T_init[:3, :3])
    assert np.allclose(c.init_offset_mm, a.init_offset_mm * ALT_SIGMA_MM / PAPER_SIGMA_MM)
    assert not np.allclose(a.T_gt, d.T_gt)


@pytest.mark.slow
def test_initial_pose_noise_statistics():
    n = 1500
    offs, cos_rel, traces = [], [], []
    for t in range(n):
        tr = make_trial(CENTRE, 100.0, 11, 3, t, n_views=1)
        c0 = tr.T_init[:3, :3] @ CENTRE + tr.T_init[:3, 3]  # the initial position of the model centre
        assert np.allclose(c0, tr.init_offset_mm)
        offs.append(c0)
        traces.append(np.trace(tr.T_init[:3, :3]))
        rel = tr.T_gt[:3, :3].T @ tr.T_init[:3, :3]
        cos_rel.append((np.trace(rel) - 1) / 2)
    X = np.array(offs)
    sigma = PAPER_SIGMA_MM
    assert np.all(np.abs(X.mean(0)) < 4 * sigma / np.sqrt(n))
    assert np.allclose(X.std(0), sigma, rtol=0.06)
    C = np.corrcoef(X.T)
    assert np.abs(C[np.triu_indices(3, 1)]).max() < 0.1
    # orientation uniform on SO(3) and independent of the ground truth: E[tr R] = 0 and
    # P(angle(R_gt, R_init) < 90 deg) = (pi/2 - 1) / pi for Haar-distributed relative rotations
    assert abs(np.mean(traces)) < 4 * 1.0 / np.sqrt(n)
    p90 = np.mean(np.array(cos_rel) > 0.0)
    assert p90 == pytest.approx((np.pi / 2 - 1) / np.pi, abs=0.035)


# --------------------------------------------------------------------------------------------
# Success criteria and errors
# --------------------------------------------------------------------------------------------

def _rot(axis, deg):
    return axis_angle_matrix(np.asarray(axis, dtype=float), np.radians(deg))


def _pose_err(T_est, T_gt, sym=Symmetries()):
    return pose_errors(T_est, T_gt, np.zeros(3), None, sym)


def test_success_hand_made_cases_asymmetric():
    R = random_rotation(np.random.default_rng(5))
    T_gt = make_pose(R, [0, 0, 0])
    ok = _pose_err(make_pose(R @ _rot([0, 0, 1], 5.0), [0.9, 0, 0]), T_gt)
    assert ok.rot_err_deg == pytest.approx(5.0)
    assert ok.dot_cols == pytest.approx(np.cos(np.radians(5.0)))
    assert success(ok, "cols") and not success(ok, "strict")
    far = _pose_err(make_pose(R @ _rot([0, 0, 1], 5.0), [1.1, 0, 0]), T_gt)
    assert not success(far, "cols") and not success(far, "axis_angle")
    tilted = _pose_err(make_pose(R @ _rot([1, 1, 0], 9.0), [0.2, 0, 0]), T_gt)
    assert tilted.dot_cols < 0.99 and not success(tilted, "cols")
    exact = _pose_err(T_gt, T_gt)
    assert all(success(exact, c, diameter_mm=100.0) for c in ("cols", "axis_angle", "strict"))


def test_axis_angle_reading_ignores_the_angle():
    # R_gt and R_est turn about the same axis by 60 and 90 degrees: 30 degrees apart, axes parallel
    T_gt = make_pose(_rot([0, 0, 1], 60.0), [0, 0, 0])
    T_est = make_pose(_rot([0, 0, 1], 90.0), [0.5, 0, 0])
    e = _pose_err(T_est, T_gt)
    assert axis_dot_axis_angle(T_est[:3, :3], T_gt[:3, :3]) == pytest.approx(1.0)
    assert e.rot_err_deg == pytest.approx(30.0)
    assert success(e, "axis_angle") and not success(e, "cols")
    assert axis_dot_columns(T_est[:3, :3], T_gt[:3, :3]) == pytest.approx(np.cos(np.radians(30.0)))


def test_success_modulo_symmetries():
    R = random_rotation(np.random.default_rng(8))
    T_gt = make_pose(R, [10.0, 0, 0])
    cylinder = Symmetries.from_info({"symmetries_discrete": [make_pose(_rot([1, 0, 0], 180.0), [0, 0, 0])],
                                     "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
    box = Symmetries.from_info({"symmetries_discrete": [make_pose(_rot(a, 180.0), [0, 0, 0]).ravel().tolist()
                                                        for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1])]})
    # turned about its own axis by 73 degrees, and flipped upside down: the same cylinder
    for S in (_rot([0, 0, 1], 73.0), _rot([1, 0, 0], 180.0) @ _rot([0, 0, 1], -20.0)):
        e = _pose_err(make_pose(R @ S, [10.3, 0, 0]), T_gt, cylinder)
        assert e.rot_err_deg < 1e-5 and success(e, "cols") and success(e, "strict")
        assert e.rot_err_raw_deg > 10.0
    tilted = _pose_err(make_pose(R @ _rot([1, 0, 0], 10.0) @ _rot([0, 0, 1], 40.0), [10, 0, 0]), T_gt, cylinder)
    assert tilted.rot_err_deg == pytest.approx(10.0, abs=1e-6) and not success(tilted, "cols")
    e = _pose_err(make_pose(R @ _rot([0, 1, 0], 180.0), [10, 0, 0]), T_gt, box)
    assert e.rot_err_deg < 1e-6 and success(e, "cols")
    e = _pose_err(make_pose(R @ _rot([0, 1, 0], 90.0), [10, 0, 0]), T_gt, box)
    assert e.rot_err_deg == pytest.approx(90.0) and not success(e, "cols")


def test_continuous_symmetry_with_offset_keeps_positions_consistent():
    # a symmetry axis through (0, 20, 0) mm: rotating about it moves the model origin
    sym = Symmetries.from_info({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 20, 0]}]})
    R = random_rotation(np.random.default_rng(2))
    T_gt = make_pose(R, [0, 0, 0])
    S = make_pose(_rot([0, 0, 1], 50.0), np.array([0, 20, 0]) - _rot([0, 0, 1], 50.0) @ np.array([0, 20, 0]))
    T_est = T_gt @ S
    eq = closest_equivalent(T_est, T_gt, sym)
    assert np.allclose(eq, T_est, atol=1e-9)
    e = pose_errors(T_est, T_gt, np.array([0.0, 20.0, 0.0]), None, sym)
    assert e.pos_err_mm < 1e-9 and e.rot_err_deg < 1e-5


def test_add_adds_and_auc():
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 30, (500, 3))
    T = np.eye(4)
    T2 = make_pose(np.eye(3), [2.0, 0, 0])
    assert add_mm(pts, T2, T) == pytest.approx(2.0)
    assert adds_mm(pts, T2, T) <= 2.0
    ring = np.array([[50 * np.cos(a), 50 * np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 720, endpoint=False)])
    Tz = make_pose(_rot([0, 0, 1], 33.0), [0, 0, 0])
    assert add_mm(ring, Tz, T) > 25.0 and adds_mm(ring, Tz, T) < 0.3
    assert auc(np.zeros(10)) == pytest.approx(1.0)
    assert auc(np.full(10, 0.2)) == pytest.approx(0.0)
    assert auc(np.array([0.05, np.nan])) == pytest.approx(0.25, abs=0.01)


def test_label_difference_along_and_across_the_ray_and_in_pixels():
    """Against OpenCV's projectPoints (BOP's K as it is) and scipy's rotations: a label 30 mm
    farther along its viewing ray and 2 mm across it, turned 1 degree, seen by a 572 px camera."""
    import cv2
    from scipy.spatial.transform import Rotation

    K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
    pts = np.random.default_rng(1).normal(0, 30, (400, 3)) + CENTRE
    R = random_rotation(np.random.default_rng(2))
    ref = make_pose(R, np.array([80.0, -40.0, 900.0]) - R @ CENTRE)  # centre at (80, -40, 900) in the camera
    ray = np.array([80.0, -40.0, 900.0]) / np.linalg.norm([80.0, -40.0, 900.0])
    across = np.cross(ray, [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    turn = Rotation.from_rotvec(np.radians(1.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    R2 = turn @ R
    c2 = np.array([80.0, -40.0, 900.0]) + 30.0 * ray + 2.0 * across
    lab = make_pose(R2, c2 - R2 @ CENTRE)
    d = label_difference(lab, ref, K, CENTRE, pts, Symmetries())
    assert d.along_ray_mm == pytest.approx(30.0) and d.across_ray_mm == pytest.approx(2.0)
    assert d.pos_mm == pytest.approx(np.hypot(30.0, 2.0)) and d.rot_deg == pytest.approx(1.0, abs=1e-6)

    def cv_project(T):
        uv, _ = cv2.projectPoints(pts, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, None)
        return uv[:, 0]

    px = np.linalg.norm(cv_project(lab) - cv_project(ref), axis=1)
    assert d.mean_px == pytest.approx(px.mean(), rel=1e-6) and d.mspd_px == pytest.approx(px.max(), rel=1e-6)
    assert 2.0 < d.mspd_px < 20.0  # 30 mm along the ray is a few pixels at 900 mm


def test_track_fit_finds_the_one_camera_that_is_off():
    """Tracks projected by OpenCV's projectPoints (BOP's K as it is) with 0.3 px of keypoint noise:
    with the true cameras every view's median reprojection error is that noise's size; with one
    camera turned by 0.5 degree about its y axis (5 px at 572 px focal length), that view alone
    stands out, by about the turn's size."""
    import cv2
    from scipy.spatial.transform import Rotation

    from autoalign.geometry.camera import look_at

    rng = np.random.default_rng(3)
    K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
    X = rng.uniform(-150.0, 150.0, (300, 3))
    T_cw = {}
    for k, az in enumerate(np.radians(np.arange(0, 100, 10))):
        eye = 900.0 * np.array([np.cos(az), np.sin(az), 0.8])
        T_cw[100 + k] = look_at(eye, np.zeros(3), K, 640, 480).T_cw
    obs = {}
    for im, T in T_cw.items():
        uv, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, None)
        obs[im] = (uv[:, 0] + rng.normal(0.0, 0.3, (len(X), 2)), np.arange(len(X)))
    fit = track_fit(obs, T_cw, K)
    assert fit.tracks == 300 and fit.median_px < 0.5 and max(fit.per_view_px.values()) < 0.5
    off = dict(T_cw)
    turn = make_pose(Rotation.from_euler("y", 0.5, degrees=True).as_matrix(), np.zeros(3))
    off[104] = turn @ T_cw[104]
    bad = track_fit(obs, off, K)
    assert bad.per_view_px[104] > 3.0
    assert max(v for im, v in bad.per_view_px.items() if im != 104) < bad.per_view_px[104] / 3
    with pytest.raises(ValueError):
        track_fit(obs, {100: T_cw[100]}, K)
