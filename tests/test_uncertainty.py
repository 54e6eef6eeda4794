"""The pose covariance means something (issue 13, "Uncertainty"): on scenes whose masks have noisy
outlines, the true errors fall within 3 sigma as often as a Gaussian's would, and a nearly
symmetric object names its roll as weakly observed."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.refine import refine
from autoalign.engine.uncertainty import uncertainty_of
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import (
    make_scene,
    perturb_pose,
    random_rotation,
    ring_cameras,
    sphere_cameras,
    wiggle_mask,
)
from autoalign.experiments.studies.refine_study import study_meshes
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, so3_log
from autoalign.io.bop import Scene


def _noisy_scene(mesh, k: int, views: int = 24):
    rng = np.random.default_rng([7, k])
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    cams = sphere_cameras(views, rng) if k % 2 == 0 else ring_cameras(views, rng)
    scene = make_scene(mesh, T, cams)
    noisy = [wiggle_mask(m > 0.5, rng, amplitude_px=1.0, correlation_px=6.0).astype(np.float32) for m in scene.masks]
    return Scene(scene.cameras, noisy, scene.image_ids), T, rng


def _model_frame_errors(T_est, T_gt, centre):
    """Position error along and rotation error (degrees) about the model's axes."""
    e_t = T_gt[:3, :3].T @ ((T_est[:3, :3] @ centre + T_est[:3, 3]) - (T_gt[:3, :3] @ centre + T_gt[:3, 3]))
    return e_t, np.degrees(so3_log(T_gt[:3, :3].T @ T_est[:3, :3]))


@pytest.mark.slow
def test_errors_fall_within_3_sigma_on_noisy_outlines():
    """8 scenes (procedural and LINEMOD models), outlines moved in and out by about 1 px: at least
    85% of the 48 per-axis errors lie within 3 sigma; the naive residual-variance sigma, which
    takes pixels as independent, covers far fewer (why the cluster-robust estimate is reported)."""
    meshes = study_meshes()
    z, z_naive = [], []
    for k in range(8):
        mesh = meshes[k % len(meshes)]
        scene, T, rng = _noisy_scene(mesh, k)
        r = refine(scene, mesh, perturb_pose(T, 10.0, 15.0, rng, mesh.centre))
        e_t, e_r = _model_frame_errors(r.T_wm, T, mesh.centre)
        u = r.uncertainty
        z.append(np.abs(np.r_[e_t / u.sigma_mm, e_r / u.sigma_deg]))
        z_naive.append(np.abs(np.r_[e_t / u.naive_sigma_mm, e_r / u.naive_sigma_deg]))
    within = float(np.mean(np.array(z) < 3.0))
    assert within >= 0.85, within
    assert float(np.mean(np.array(z_naive) < 3.0)) < within - 0.3
    assert float(np.median(z)) > 0.2  # not covering by being huge: a Gaussian's median |z| is 0.67


def _flashlight_scene(seed: list[int]):
    """A flashlight (model z is its axis) in 24 ring views: mesh, scene, true pose, the rng."""
    pm = next(m for m in procedural_models() if m.name == "flashlight")
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    return mesh, make_scene(mesh, T, ring_cameras(24, rng)), T, rng


@pytest.mark.slow
@pytest.mark.parametrize("k", range(3))
def test_flashlight_roll_converges_or_is_named_weak(k):
    """A flashlight (a cylinder with a small button) started 25 degrees off: either within 1 degree,
    or its roll about the model axis is named as weakly observed with a sigma covering the error."""
    mesh, scene, T, rng = _flashlight_scene([3, k])
    scene = Scene(scene.cameras, [wiggle_mask(m > 0.5, rng).astype(np.float32) for m in scene.masks], scene.image_ids)
    r = refine(scene, mesh, perturb_pose(T, 10.0, 25.0, rng, mesh.centre))
    _, e_r = _model_frame_errors(r.T_wm, T, mesh.centre)
    u = r.uncertainty
    assert any(w.startswith("turn about model z") for w in u.weak), u.weak  # its axis is model z
    if np.linalg.norm(e_r) >= 1.0:
        assert abs(e_r[2]) < 3.0 * u.sigma_deg[2], (e_r, u.sigma_deg)


def weak_directions(cov_m: np.ndarray) -> list[str]:
    """The weakly observed directions :func:`uncertainty_of` names for a model-frame covariance."""
    return uncertainty_of(cov_m, cov_m, np.eye(3)).weak


def test_weak_directions_named_by_model_axis():
    c = np.diag([0.02, 0.02, 0.03, np.radians(0.03), np.radians(0.03), np.radians(0.4)]) ** 2
    assert weak_directions(c) == ["turn about model z: 0.4 deg"]
    c[0, 0] = 3.0 ** 2
    assert weak_directions(c) == ["turn about model z: 0.4 deg", "shift along model x: 3 mm"]
    assert weak_directions(np.diag([0.02, 0.02, 0.03, 0.0005, 0.0005, 0.0006]) ** 2) == []


@pytest.mark.slow
@pytest.mark.parametrize("k", range(2))
def test_init_turned_about_the_weak_axis_is_not_returned(k):
    """A flashlight started 3 mm / 3 deg off the truth and then rolled 100-140 deg about its axis
    settles where its button is out of sight (97 and 138 deg off with the turns switched off); the
    turns about the weakly observed roll axis find the true one."""
    from autoalign.engine.hypotheses import turns
    from autoalign.engine.refine import DisambiguationOptions, RefineOptions
    from autoalign.geometry.se3 import rotation_angle_deg

    mesh, scene, T, rng = _flashlight_scene([5, k])
    T0 = turns(perturb_pose(T, 3.0, 3.0, rng, mesh.centre), np.array([0.0, 0.0, 1.0]), mesh.centre, (100.0 + 40 * k,))[0]
    stuck = refine(scene, mesh, T0, RefineOptions(disambiguation=DisambiguationOptions(weak_turns=())))
    assert rotation_angle_deg(stuck.T_wm[:3, :3], T[:3, :3]) > 45.0
    found = refine(scene, mesh, T0)
    assert rotation_angle_deg(found.T_wm[:3, :3], T[:3, :3]) < 1.0


def test_outline_shift_rate_integrates_to_the_perimeter():
    """Per pixel of outward shift a mask gains its perimeter in pixels: a disk of radius 40 and a
    square of side 120 turned 0 and 30 degrees: 1.0 to 1.12 times (the ring's slant error, see its doc)."""
    import cv2

    from autoalign.losses.silhouette import outline_shift_rate

    disk = np.zeros((200, 200), np.uint8)
    cv2.circle(disk, (100, 100), 40, 1, -1)
    assert 1.0 <= outline_shift_rate(disk).sum() / (2 * np.pi * 40) < 1.12
    for angle in (0.0, 30.0):
        square = np.zeros((300, 300), np.uint8)
        box = cv2.boxPoints(((150.0, 150.0), (120.0, 120.0), angle))
        cv2.fillPoly(square, [np.round(box).astype(np.int32)], 1)
        assert 1.0 <= outline_shift_rate(square).sum() / 480.0 < 1.13


def _cameras_from_one_side(n: int, rng: np.random.Generator):
    """``n`` views within 15 degrees of azimuth and 10 of elevation, 700-800 mm from the origin."""
    from autoalign.experiments.scenes.synthetic import default_K
    from autoalign.geometry.camera import look_at

    cams = []
    for _ in range(n):
        a, e = np.radians(rng.uniform(0, 15)), np.radians(rng.uniform(30, 40))
        d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        cams.append(look_at(rng.uniform(700, 800) * d, np.zeros(3), default_K(), 640, 480, up=np.array([0.0, 0.0, 1.0])))
    return cams


@pytest.mark.slow
@pytest.mark.parametrize("k", range(2))
def test_outline_shift_moves_the_pose_as_predicted_and_is_in_the_sigma(k):
    """From one side (10 views in a 15 degree cone), masks moved 1 px in (exact Euclidean erosion
    of open3d-cast masks) push the pose along the viewing ray as the covariance's outline-shift
    term predicts (within 30%), and a mask 2 px tight (1.7 times the prior's sigma) leaves the pose within
    3 sigma along the ray and not ok: the sigma is that of the shared shift, not of pixel noise."""
    from autoalign.experiments.studies.sam_failures import shift_outline
    from autoalign.quality.verdict import PoseEvidence, judge

    mesh = study_meshes()[k]
    rng = np.random.default_rng([29, k])
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    scene = make_scene(mesh, T, _cameras_from_one_side(10, rng))
    exact = refine(scene, mesh, T)

    def centre(T_wm):
        return T_wm[:3, :3] @ mesh.centre + T_wm[:3, 3]

    ray = exact.T_wm[:3, :3] @ exact.uncertainty.view_dir_m
    predicted = exact.T_wm[:3, :3] @ exact.uncertainty.bias_shift[:3]  # per px outwards
    for px in (-1.0, -2.0):
        tight = Scene(scene.cameras, [shift_outline(m > 0.5, px).astype(np.float32) for m in scene.masks], scene.image_ids)
        r = refine(tight, mesh, exact.T_wm)
        moved = centre(r.T_wm) - centre(exact.T_wm)
        if px == -1.0:
            assert np.linalg.norm(moved - px * predicted) < 0.3 * np.linalg.norm(moved), (moved, predicted)
            assert abs(moved @ ray) > 3.0  # the shift is along the ray, and large: a real test of the sigma
        else:
            err = centre(r.T_wm) - centre(T)
            assert abs(err @ ray) < 3.0 * r.uncertainty.sigma_ray_mm, (err @ ray, r.uncertainty.sigma_ray_mm)
            assert r.uncertainty.sigma_ray_mm > 10 * r.uncertainty.sigma_across_mm
            assert judge(PoseEvidence(r.iou_after, r.weights, r.image_ids, uncertainty=r.uncertainty)).status != "ok"


def test_sigmas_along_and_across_the_ray():
    """A covariance with 9 mm^2 along the model's x and 1 mm^2 across, the median view along x."""
    from autoalign.engine.uncertainty import CovarianceParts, compose

    cov = np.diag([9.0, 1.0, 0.25, 1e-6, 1e-6, 1e-6])
    out = compose(CovarianceParts(cov, view_dir_m=np.array([1.0, 0.0, 0.0])))
    assert out.sigma_ray_mm == pytest.approx(3.0) and out.sigma_across_mm == pytest.approx(1.0)
    shifted = out.adding(bias_shift=np.array([0.0, 1.5, 0.0, 0.0, 0.0, 0.0]), outline_px=2.0)
    assert shifted.sigma_mm[1] == pytest.approx(np.sqrt(1.0 + 9.0))  # 2 px of 1.5 mm each


def test_jackknife_is_the_leave_one_view_out_refit():
    """On a linear least-squares problem one Newton step is the exact refit: the jackknife from
    H^-1 (Woodbury, one small block per view) equals the spread of the poses refitted with each
    view left out by numpy's lstsq; with one view that alone fixes a direction, it is far larger
    than the sandwich (the leverage the sandwich ignores)."""
    from autoalign.engine.uncertainty import jackknife, sandwich

    rng = np.random.default_rng(3)
    J = [rng.normal(size=(40, 6)) for _ in range(8)]
    J[0][:, 5] *= 8.0  # view 0 carries most of what fixes the 6th unknown
    for j in J[1:]:
        j[:, 5] *= 0.2
    r = [rng.normal(size=40) + 0.5 * rng.normal() for _ in J]  # each view with an error of its own
    A, b = np.concatenate(J), np.concatenate(r)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    refits = np.array([np.linalg.lstsq(np.concatenate(J[:v] + J[v + 1:]), np.concatenate(r[:v] + r[v + 1:]),
                                       rcond=None)[0] - x for v in range(len(J))])
    refits -= refits.mean(axis=0)
    expected = refits.T @ refits * (len(J) - 1) / len(J)
    H = A.T @ A
    grads = np.array([j.T @ (j @ x - rr) for j, rr in zip(J, r)])  # each view's gradient at the optimum
    blocks = [(np.arange(6), j.T @ j) for j in J]
    got = jackknife(np.linalg.inv(H), blocks, grads)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-12)
    assert got[5, 5] > 2.0 * sandwich(np.linalg.inv(H), grads)[5, 5]


def test_the_jackknife_leaves_out_a_viewpoint_at_a_time():
    """Views in groups of one viewpoint each: on a linear least-squares problem the jackknife over
    the groups equals the spread of the refits with each group's views left out together (numpy's
    lstsq); a single viewpoint's views count as one measurement, their spread times their number."""
    from autoalign.engine.uncertainty import jackknife

    rng = np.random.default_rng(5)
    seen = [rng.normal(size=(30, 6)) for _ in range(4)]  # the views of a viewpoint see alike ...
    J = [seen[v // 3] + 0.05 * rng.normal(size=(30, 6)) for v in range(12)]
    shared = [rng.normal(size=30) for _ in range(4)]  # ... and share their error, as a segmenter's
    r = [shared[v // 3] + 0.2 * rng.normal(size=30) for v in range(12)]
    groups = [np.arange(3 * k, 3 * k + 3) for k in range(4)]
    A, b = np.concatenate(J), np.concatenate(r)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    refits = []
    for g in groups:
        keep = [v for v in range(12) if v not in g]
        refits.append(np.linalg.lstsq(np.concatenate([J[v] for v in keep]), np.concatenate([r[v] for v in keep]),
                                      rcond=None)[0] - x)
    refits = np.array(refits) - np.mean(refits, axis=0)
    expected = refits.T @ refits * 3 / 4
    H_inv = np.linalg.inv(A.T @ A)
    grads = np.array([j.T @ (j @ x - rr) for j, rr in zip(J, r)])
    blocks = [(np.arange(6), j.T @ j) for j in J]
    got = jackknife(H_inv, blocks, grads, groups=groups)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-12)
    per_view = jackknife(H_inv, blocks, grads)
    assert np.trace(got) > 2.0 * np.trace(per_view)  # views of one viewpoint share their error: counted once
    one = jackknife(H_inv, blocks, grads, groups=[np.arange(12)])
    np.testing.assert_allclose(one, 12 * per_view, rtol=1e-12)


def test_viewpoint_groups_cut_a_slow_sweep_and_merge_a_still_camera():
    """Ten frames within 0.2 deg of one direction are one viewpoint; a sweep of 20 frames 0.3 deg
    apart (5.7 deg in all) is cut into pieces at most 2 deg across, not chained into one; views 10
    deg apart are each their own."""
    from autoalign.engine.uncertainty import SAME_VIEWPOINT_DEG, viewpoint_groups

    def dirs(step_deg: float, n: int) -> np.ndarray:
        a = np.radians(step_deg * np.arange(n))
        return np.stack([np.sin(a), np.zeros(n), np.cos(a)], axis=1) * 700.0

    assert len(viewpoint_groups(dirs(0.02, 10))) == 1
    sweep = viewpoint_groups(dirs(0.3, 20))
    assert 3 <= len(sweep) <= 6 and sorted(np.concatenate(sweep)) == list(range(20))
    assert all((g.max() - g.min()) * 0.3 <= SAME_VIEWPOINT_DEG for g in sweep)
    assert len(viewpoint_groups(dirs(10.0, 8))) == 8


@pytest.mark.slow
def test_views_from_one_viewpoint_are_not_ok():
    """Ten views of a still camera (it moves 5 mm, 0.2 deg), exact masks: the pose refined from 3 mm
    / 3 deg off fits every mask, but the views' agreement says nothing of how far off it may be
    (on the YCB-Video frames, poses 2-7 deg off had sigmas of 0.2-0.9 deg): one viewpoint, not ok.
    The same object from ten directions is ok."""
    from autoalign.experiments.scenes.synthetic import default_K
    from autoalign.geometry.camera import look_at
    from autoalign.quality.verdict import PoseEvidence, judge

    mesh = study_meshes()[0]
    rng = np.random.default_rng(41)
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    still = [look_at(np.array([0.0, -600.0, 350.0]) + rng.uniform(-2.5, 2.5, 3), np.zeros(3), default_K(), 640, 480,
                     up=np.array([0.0, 0.0, 1.0])) for _ in range(10)]
    for cams, expected in ((still, 1), (sphere_cameras(10, rng), 10)):
        scene = make_scene(mesh, T, cams)
        r = refine(scene, mesh, perturb_pose(T, 3.0, 3.0, rng, mesh.centre))
        assert r.uncertainty.viewpoints == expected
        assert float(np.median(r.iou_after)) > 0.97
        v = judge(PoseEvidence(r.iou_after, r.weights, r.image_ids, uncertainty=r.uncertainty, turn_gap=r.turn_gap))
        if expected == 1:
            assert v.status == "check" and any(s.startswith("one viewpoint") for s in v.reasons), v
        else:
            assert not any(s.startswith("one viewpoint") for s in v.reasons), v
