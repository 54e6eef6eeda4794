"""A seed is evidence (issue 29, item 4): a result beyond the seed's stated uncertainty is returned
only when it fits clearly better than the best pose within it, and is flagged either way."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.refine import RefineOptions, refine
from autoalign.engine.seed_region import SEED_RADIUS, SeedRegion
from autoalign.experiments.scenes.synthetic import perturb_pose, random_rotation, raycast_masks, ring_cameras
from autoalign.experiments.studies.refine_study import study_meshes
from autoalign.geometry.se3 import apply_twist, make_pose, pose_change, transform_points
from autoalign.io.bop import Scene
from autoalign.quality.verdict import PoseEvidence, judge


def test_the_penalty_is_zero_inside_and_its_derivatives_match_finite_differences():
    rng = np.random.default_rng(3)
    centre = np.array([5.0, -3.0, 20.0])
    seed = make_pose(random_rotation(rng), rng.normal(size=3) * 50)
    region = SeedRegion(seed, centre, (10.0, 15.0), 100.0)
    inside = apply_twist(seed, np.array([3.0, -2.0, 1.0, 0.05, 0.02, -0.1]), transform_points(seed, centre[None])[0])
    assert region.term(inside).value == 0.0
    far = apply_twist(seed, np.array([20.0, 5.0, -4.0, 0.4, -0.2, 0.1]), transform_points(seed, centre[None])[0])
    t = region.term(far)
    assert t.value > 0
    c = transform_points(far, centre[None])[0]
    num = np.zeros(6)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        num[k] = (region.term(apply_twist(far, d, c)).value - region.term(apply_twist(far, -d, c)).value) / 2e-6
    np.testing.assert_allclose(t.grad, num, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_masks_pulling_to_a_far_basin_leave_the_result_within_the_seed_radius_and_flagged():
    """A mug 5 mm / 5 deg from its seed; in 3 of 4 views the mask is another object's, 45 mm away.
    The masks alone pull the mug beyond the seed's radius (25 mm / 30 deg) to a pose that fits them
    only a little better: the result is the best pose within the radius, flagged with the far one."""
    meshes = study_meshes()
    mesh, other = meshes[2], meshes[5 % len(meshes)]
    rng = np.random.default_rng([31, 2])
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    cams = ring_cameras(24, rng)
    W = T.copy()
    W[:3, 3] += np.array([45.0, 0.0, 0.0])
    W_other = W.copy()
    W_other[:3, 3] = transform_points(W, mesh.centre[None])[0] - W[:3, :3] @ other.centre  # centred where the mug was put
    good, wrong = raycast_masks(mesh, T, cams), raycast_masks(other, W_other, cams)
    scene = Scene(cams, [(wrong[i] if i % 4 else good[i]).astype(np.float32) for i in range(len(cams))],
                  list(range(len(cams))))
    seed = perturb_pose(T, 5.0, 5.0, rng, mesh.centre)

    free = refine(scene, mesh, seed, RefineOptions(seed_radius=None))
    moved = pose_change(seed, free.T_wm, mesh.centre)
    assert moved[0] > SEED_RADIUS[0] or moved[1] > SEED_RADIUS[1], moved  # the pull is real

    held = refine(scene, mesh, seed)
    assert held.seed_hold is not None and not held.seed_hold.kept_far
    assert free.holds == () and [type(t).__name__ for t in held.holds] == ["SeedRegion"]  # kept by --models' joint stage
    assert held.holds[0].term(held.T_wm).value == pytest.approx(0.0, abs=1e-6)  # the result lies within the region
    assert held.seed_hold.far_loss > 0.5 * held.seed_hold.near_loss  # the far pose fits only a little better
    mm, deg = pose_change(seed, held.T_wm, mesh.centre)
    assert mm <= SEED_RADIUS[0] * 1.02 and deg <= SEED_RADIUS[1] * 1.02, (mm, deg)
    v = judge(PoseEvidence(held.iou_after, held.weights, held.image_ids, uncertainty=held.uncertainty,
              seed_move=(mm, deg), seed_hold=held.seed_hold))
    assert v.status != "ok" and any("kept the best pose within it" in r for r in v.reasons), v.reasons


def _can_spun(degrees: float):
    """The plain can (continuous symmetry about model z, a half turn about x) in 12 views with
    exact masks, its true pose, and that pose turned by ``degrees`` about the can's own axis: the
    same silhouettes, a pose as right."""
    from autoalign.experiments.scenes.procedural_models import procedural_models
    from autoalign.experiments.scenes.synthetic import make_scene
    from autoalign.geometry.mesh import mesh_from_trimesh
    from autoalign.geometry.se3 import Symmetries, so3_exp

    pm = procedural_models()[4]
    assert pm.name == "can_plain"
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    rng = np.random.default_rng(5)
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    spun = T @ make_pose(so3_exp(np.array([0.0, 0.0, np.radians(degrees)])), np.zeros(3))
    symmetries = Symmetries(tuple(np.asarray(d) for d in pm.symmetries_discrete),
                            tuple((np.asarray(c["axis"], float), np.asarray(c["offset"], float))
                                  for c in pm.symmetries_continuous))
    return mesh, make_scene(mesh, T, ring_cameras(12, rng)), T, spun, symmetries


@pytest.mark.slow
def test_a_turn_about_an_axis_of_symmetry_is_no_move_from_the_seed():
    """Issue 45: the seed's hold measured the move with the free spin of a symmetric object in it, so
    a right pose turned 90 deg about the can's axis from its seed was 'beyond the radius' and held.
    Modulo the model's symmetries (as refine.json's move is measured) the penalty is zero and there
    is no hold; without them declared, the same pose is held, as before."""
    from autoalign.engine.objective import Level, SilhouetteObjective
    from autoalign.engine.refine import Finalist, Hypothesis, Stage, _held_near_seed
    from autoalign.rasterizers.pyramid import MeshPyramid

    mesh, scene, T, spun, symmetries = _can_spun(90.0)
    region = SeedRegion(T, mesh.centre, SEED_RADIUS, 1e3, symmetries)
    assert region.term(spun).value == 0.0
    assert SeedRegion(T, mesh.centre, SEED_RADIUS, 1e3).term(spun).value > 0.0
    for declared, held in ((symmetries, False), (None, True)):
        pyramid = MeshPyramid(mesh) if declared is None else MeshPyramid(mesh, declared)
        obj = SilhouetteObjective(pyramid, scene)
        ev = obj.evaluate(spun, Level(1.0, 0.5, 0))
        best = Finalist(Hypothesis(spun, spun, ev.value / len(ev.weights), float(np.mean(ev.terms.iou)), Stage.FINAL),
                        ev.weights)
        kept, _, _, hold = _held_near_seed(obj, T, best, ev, RefineOptions(), None)
        assert (hold is not None) == held, (declared, hold)
        if not held:
            assert kept is best


@pytest.mark.slow
def test_the_joint_stage_keeps_a_held_pose_within_its_seeds_radius(tmp_path):
    """Issue 45: the joint stage had no seed region, so it let go of a pose held within its seed's
    radius alone. A mug whose masks are another object's, 45 mm away, in 3 of 4 views, beside a box
    with right masks: alone the mug is held at the radius (25 mm); after the joint stage it is still
    there (without the region in the joint solve it ended 29.2 mm / 18.8 deg from its seed), and the
    box is unaffected."""
    from autoalign.experiments.scenes.procedural_models import procedural_models, write_models
    from autoalign.experiments.scenes.synthetic import raycast_visible_masks, write_multi_scene
    from autoalign.geometry.mesh import load_mesh, mesh_from_trimesh
    from autoalign.io.instances import read_instance_scenes, read_instances
    from autoalign.io.models import ModelSet
    from autoalign.scene.refine import refine_scene

    pms = procedural_models()
    write_models(tmp_path / "models", [pms[2], pms[1]])  # the mug (obj 1) and a box (obj 2)
    meshes = [load_mesh(tmp_path / "models" / f"obj_{i:06d}.ply") for i in (1, 2)]
    other = mesh_from_trimesh(pms[5].mesh, pms[5].name)
    rng = np.random.default_rng([31, 2])
    R, Rb = random_rotation(rng), random_rotation(rng)
    T = make_pose(R, -R @ meshes[0].centre)
    T_box = make_pose(Rb, np.array([0.0, 130.0, 0.0]) - Rb @ meshes[1].centre)
    W = T.copy()
    W[:3, 3] = transform_points(T, meshes[0].centre[None])[0] + [45.0, 0.0, 0.0] - T[:3, :3] @ other.centre
    cams = ring_cameras(24, rng)
    right = raycast_visible_masks(meshes, [T, T_box], cams)
    wrong = raycast_visible_masks([other, meshes[1]], [W, T_box], cams)
    write_multi_scene(tmp_path / "scene", meshes, [1, 2], [T, T_box], cams,
                      [[wrong[v][0] if v % 4 else right[v][0], right[v][1]] for v in range(len(cams))])
    seeds = {0: perturb_pose(T, 5.0, 5.0, rng, meshes[0].centre), 1: perturb_pose(T_box, 5.0, 5.0, rng, meshes[1].centre)}
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    done = refine_scene(found, ModelSet.read(tmp_path / "models"), seeds, RefineOptions())
    mug, box = done.results
    assert mug.result.seed_hold is not None and not mug.result.seed_hold.kept_far  # held alone
    mm, deg = pose_change(seeds[0], mug.result.T_wm, meshes[0].centre)
    assert mm <= SEED_RADIUS[0] * 1.02 and deg <= SEED_RADIUS[1] * 1.02, (mm, deg)
    assert mug.verdict.status != "ok"
    e_mm, e_deg = pose_change(T_box, box.result.T_wm, meshes[1].centre)
    assert e_mm < 1.0 and e_deg < 1.0 and box.verdict.status == "ok", (e_mm, e_deg, box.verdict)
