"""The paper's discrete argmax-IoU baseline: move set, batched scoring against brute force, the loop."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import (
    make_scene,
    perturb_pose,
    random_rotation,
)
from autoalign.experiments.studies.metrics import Symmetries, pose_errors, success
from autoalign.experiments.studies.paper_method import (
    DISCRETISATIONS,
    CandidateScorer,
    PaperOptions,
    candidate_parameters,
    candidate_poses,
    refine_paper,
)
from autoalign.experiments.studies.protocol import ImageSetup, make_trial
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, se3_exp, transform_points

SETUP = ImageSetup(width=320, height=240, focal=300.0)


@pytest.fixture(scope="module")
def mug_case():
    pm = procedural_models()[2]  # the mug: asymmetric, a hole and a handle (self-occlusion)
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    tr = make_trial(mesh.centre, mesh.diameter, seed=1, model_id=3, trial=0, n_views=8, setup=SETUP)
    scene = make_scene(mesh, tr.T_gt, tr.cameras)
    from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

    return mesh, tr, scene, SoftSilhouetteRasterizer(mesh)


def test_candidate_poses_are_the_papers_twists():
    rng = np.random.default_rng(0)
    tr = make_trial(np.array([1.0, 2.0, 3.0]), 100.0, 0, 1, 0, n_views=2)
    cam = tr.cameras[1]
    centre_m = np.array([1.0, 2.0, 3.0])
    T = make_pose(random_rotation(rng), rng.normal(0, 30, 3))
    disc = DISCRETISATIONS["geo4"]
    th1, dirs, th2 = candidate_parameters(disc)
    assert len(th1) == disc.n_candidates and th1[0] == 0 and th2[0] == 0 and dirs[0] == -1
    for axis, w in (("x", cam.R_w2c[0]), ("z", cam.R_w2c[2])):
        P = candidate_poses(T, cam, centre_m, axis, th1, dirs, th2, disc.n_directions)
        assert np.allclose(P[0], T)
        v_o = transform_points(T, centre_m[None])[0]
        for k in rng.choice(len(th1), 25, replace=False):
            alpha = 2 * np.pi * max(dirs[k], 0) / disc.n_directions
            v = (np.cos(alpha) * cam.R_w2c[0] + np.sin(alpha) * cam.R_w2c[1]) * (dirs[k] >= 0)
            xi1 = np.concatenate([-np.cross(w, v_o), w])
            xi2 = np.concatenate([v, np.zeros(3)])
            expect = se3_exp(xi1 * th1[k]) @ se3_exp(xi2 * th2[k]) @ T
            assert np.allclose(P[k], expect, atol=1e-9)
    # pure rotations keep the centre and turn about the camera x axis; pure translations stay in
    # the plane parallel to the image
    P = candidate_poses(T, cam, centre_m, "x", th1, dirs, th2, disc.n_directions)
    c0 = transform_points(T, centre_m[None])[0]
    for k in np.flatnonzero(th2 == 0)[1:]:
        assert np.allclose(transform_points(P[k], centre_m[None])[0], c0, atol=1e-9)
        dR = P[k][:3, :3] @ T[:3, :3].T
        axis = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
        assert abs(abs(axis @ cam.R_w2c[0]) - np.linalg.norm(axis)) < 1e-9
    for k in np.flatnonzero(th1 == 0)[1:]:
        d = transform_points(P[k], centre_m[None])[0] - c0
        assert np.linalg.norm(d) == pytest.approx(th2[k]) and abs(d @ cam.R_w2c[2]) < 1e-9


def test_batched_scoring_matches_brute_force(mug_case):
    mesh, tr, scene, rast = mug_case
    disc = DISCRETISATIONS["geo4"]
    th1, dirs, th2 = candidate_parameters(disc)
    fast = CandidateScorer(rast, scene, top_k=8)
    brute = CandidateScorer(rast, scene, top_k=10 ** 6, band=False)
    rng = np.random.default_rng(3)
    for view, (mm, deg) in ((0, (2.0, 1.0)), (3, (20.0, 15.0)), (5, (60.0, 90.0))):
        T = perturb_pose(tr.T_gt, mm, deg, rng, centre=mesh.centre)
        P = candidate_poses(T, scene.cameras[view], mesh.centre, "x", th1, dirs, th2, disc.n_directions)
        a = fast.score(view, P)
        b = brute.score(view, P)
        assert not np.isnan(b).any()
        done = ~np.isnan(a)
        assert np.abs(a[done] - b[done]).max() < 1e-12  # exact wherever the fast path scores
        assert np.nanargmax(a) == np.argmax(b)
        # brute force against independent per-candidate hard masks
        for k in (0, int(np.argmax(b)), len(P) - 1):
            m = rast.hard_masks(P[k], [scene.cameras[view]])[0]
            t = scene.masks[view] > 0.5
            assert b[k] == pytest.approx((m & t).sum() / max((m | t).sum(), 1))
    assert fast.rays < brute.rays / 3


def test_refine_paper_converges_near_the_ground_truth(mug_case):
    mesh, tr, scene, rast = mug_case
    sym = Symmetries()
    T0 = perturb_pose(tr.T_gt, 6.0, 6.0, np.random.default_rng(4), centre=mesh.centre)

    def stop(T):
        return success(pose_errors(T, tr.T_gt, mesh.centre, None, sym), "cols")

    res = refine_paper(rast, scene, T0, PaperOptions(discretisation="geo4", max_iters=40), stop=stop)
    assert res.stopped == "success", (res.stopped, pose_errors(res.T_wm, tr.T_gt, mesh.centre, None, sym))
    assert res.iterations == len(res.poses) == len(res.views) == len(res.moved)
    assert res.views == [k % len(scene) for k in range(res.iterations)]  # cycle order
    assert res.view_renders > 0 and res.rays > 0
    assert all(i2 >= 0 for i2 in res.ious)


def test_refine_paper_stalls_at_the_optimum(mug_case):
    mesh, tr, scene, rast = mug_case
    res = refine_paper(rast, scene, tr.T_gt, PaperOptions(discretisation="geo4", max_iters=30))
    assert res.stopped == "stall" and res.iterations == len(scene)  # a full cycle without a move
    assert not any(res.moved) and np.allclose(res.T_wm, tr.T_gt)
    already = refine_paper(rast, scene, tr.T_gt, PaperOptions(discretisation="geo4"), stop=lambda T: True)
    assert already.stopped == "success" and already.iterations == 0


def test_options_are_validated():
    with pytest.raises(ValueError):
        PaperOptions(rot_axis="y")
    with pytest.raises(ValueError):
        PaperOptions(discretisation="nope")
    with pytest.raises(ValueError):
        PaperOptions(camera_order="first")
