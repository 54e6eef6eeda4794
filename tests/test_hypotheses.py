"""Orientation hypotheses: coarse-to-fine scoring, the pattern-search polish, half-turn flips,
near-symmetry orbits.

The end-to-end cases are simulated trials (``autoalign simulate``'s protocol, open3d masks) on
which the search used to settle on a wrong pose: a half turn of a pen and of a flat frame, and
a 1/12 turn of a gear whose key and pin only show at full resolution.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import autoalign
from autoalign.engine.hypotheses import (
    best_poses,
    climb_poses,
    flips,
    orbit,
    poses_at,
    score_poses,
)
from autoalign.engine.refine import DisambiguationOptions, RankingOptions, SearchOptions
from autoalign.engine.seeding import hull_centre, rotation_grid
from autoalign.experiments.scenes.synthetic import make_scene, translate_mask
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.experiments.studies.protocol import ImageSetup, make_trial
from autoalign.experiments.studies.runner import get_model, model_ids
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, rotation_angle_deg, transform_points
from autoalign.losses.compared_views import ComparedViews
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer


def _trial(name: str, trial: int):
    """Mesh, symmetries, trial geometry and scene of a trial of the main study (seed 0, 40 views)."""
    model_id = next(i for i in model_ids("procedural44") if get_model("procedural44", i).name == name)
    entry = get_model("procedural44", model_id)
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, model_id, trial, 40, 100.0, ImageSetup())
    return entry.mesh, entry.sym, geo, make_scene(entry.mesh, geo.T_gt, geo.cameras)


def test_principal_axes_of_a_box_follow_its_extents() -> None:
    mesh = mesh_from_trimesh(trimesh.creation.box((100.0, 10.0, 40.0)))
    axes = mesh.principal_axes
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(np.abs(axes), np.array([[1, 0, 0], [0, 0, 1], [0, 1, 0]]), atol=0.02)


def test_flips_are_half_turns_about_the_axes_through_the_centre() -> None:
    rng = np.random.default_rng(0)
    T = make_pose(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3) * 100)
    axes = Rotation.random(random_state=2).as_matrix()
    c = np.array([5.0, -3.0, 12.0])
    F = flips(T, axes, c)
    assert F.shape == (3, 4, 4)
    for a, Tf in zip(axes, F):
        assert rotation_angle_deg(T[:3, :3], Tf[:3, :3]) == pytest.approx(180.0, abs=1e-6)
        np.testing.assert_allclose(transform_points(Tf, c[None]), transform_points(T, c[None]), atol=1e-9)
        np.testing.assert_allclose(transform_points(Tf, (c + a)[None]), transform_points(T, (c + a)[None]), atol=1e-9)
        np.testing.assert_allclose(flips(Tf, a[None], c)[0], T, atol=1e-9)  # twice is the identity


def _turn(deg: float, axis, point) -> np.ndarray:
    R = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    return make_pose(R, np.asarray(point) - R @ np.asarray(point))


@pytest.mark.parametrize("n", [3, 5, 12])
def test_orbit_completes_the_cyclic_group(n: int) -> None:
    T_a = make_pose(Rotation.random(random_state=3).as_matrix(), [10.0, 20.0, 500.0])
    D = _turn(360.0 / n, [0.2, -1.0, 0.4], [3.0, 4.0, -2.0])
    cands = orbit(T_a, T_a @ D)
    expected = [T_a @ np.linalg.matrix_power(D, k) for k in range(2, n)]
    np.testing.assert_allclose(cands[:n - 2], expected, atol=1e-9)
    # the last of those is D^(n-1) = D^-1: the group closes
    np.testing.assert_allclose(cands[n - 3] @ D, T_a, atol=1e-9)
    # then every other turn of the groups of order 2n, 3n, ... up to 12, each once, about the same axis
    fine = {3: [60, 180, 300, 40, 80, 160, 200, 280, 320, 30, 90, 150, 210, 270, 330],  # orders 6, 9, 12
            5: [36, 108, 180, 252, 324], 12: []}[n]
    assert len(cands) == n - 2 + len(fine)
    for T, deg in zip(cands[n - 2:], fine):
        np.testing.assert_allclose(T, T_a @ _turn(deg, [0.2, -1.0, 0.4], [3.0, 4.0, -2.0]), atol=1e-9)


@pytest.mark.parametrize("deg", [180.0, 100.0, 7.0, 0.0])
def test_orbit_is_empty_without_a_small_cyclic_group(deg: float) -> None:
    T_a = make_pose(np.eye(3), [0.0, 0.0, 400.0])
    assert len(orbit(T_a, T_a @ _turn(deg, [0, 0, 1], [0, 0, 0]))) == 0


@pytest.mark.slow
def test_coarse_to_fine_scoring_keeps_the_best_of_full_scoring() -> None:
    mesh, _, _, scene = _trial("mug", 0)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    poses = poses_at(rotation_grid(384), hull_centre(scene, mesh.diameter), mesh.centre)
    scores, rescored = score_poses(rast, ComparedViews.of(scene), poses)
    full_top = rescored[np.argsort(-scores)[:8]]
    top = best_poses(rast, ComparedViews.of(scene), poses, 8)
    assert top.shape == (8, 4, 4)
    np.testing.assert_allclose(top, full_top, atol=1e-9)


@pytest.mark.parametrize("name", ["l_bracket", "mug"])
def test_the_climb_walks_back_turns_about_the_model_axes(name: str) -> None:
    """A pose turned 10 degrees about the model x axis then 5 about y (through the centre) is
    walked back by the two rounds: each round's best candidate is the undoing turn (re-centring
    may shift it by a fraction of a low-resolution pixel, not turn it)."""
    mesh, _, geo, scene = _trial(name, 0)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    c = mesh.centre
    start = geo.T_gt @ _turn(5.0, [0, 1, 0], c) @ _turn(10.0, [1, 0, 0], c)
    climbed = climb_poses(rast, ComparedViews.of(scene), start[None], (10.0, 5.0))[0]
    assert rotation_angle_deg(climbed[:3, :3], geo.T_gt[:3, :3]) < 1e-6
    shift = np.linalg.norm(transform_points(climbed, c[None]) - transform_points(geo.T_gt, c[None]))
    assert shift < 1.0, shift


@pytest.mark.slow
def test_the_climb_moves_the_grid_poses_closer() -> None:
    mesh, sym, geo, scene = _trial("z_bracket", 0)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    poses = poses_at(rotation_grid(384), hull_centre(scene, mesh.diameter), mesh.centre)
    top = best_poses(rast, ComparedViews.of(scene), poses, 8)
    climbed = climb_poses(rast, ComparedViews.of(scene), top)
    err = np.array([[pose_errors(T, geo.T_gt, mesh.centre, None, sym).rot_err_deg for T in P] for P in (top, climbed)])
    assert err[1].min() < err[0].min() and np.median(err[1]) < np.median(err[0]), err


@pytest.mark.slow
def test_recentring_stays_near_the_seed_it_is_anchored_to() -> None:
    """Masks whose centroids pull away from the seed (here: the object really sits 1.5 radii from
    it) move the poses at most ANCHOR_REACH radii from an anchor through the whole search, and
    further without one (each step re-centres again)."""
    from autoalign.engine.hypotheses import ANCHOR_REACH

    mesh, _, geo, scene = _trial("mug", 0)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    radius = float(np.linalg.norm(rast.hull - mesh.centre, axis=1).max())
    truth_c = transform_points(geo.T_gt, mesh.centre[None])[0]
    anchor = truth_c + np.array([1.5 * radius, 0.0, 0.0])
    poses = poses_at(rotation_grid(96), anchor, mesh.centre)
    drift = {}
    for name, a in (("anchored", anchor), ("free", None)):
        top = best_poses(rast, ComparedViews.of(scene), poses, 4, anchor=a)
        climbed = climb_poses(rast, ComparedViews.of(scene), top, anchor=a)
        centres = climbed[:, :3, :3] @ mesh.centre + climbed[:, :3, 3]
        drift[name] = float(np.linalg.norm(centres - anchor, axis=1).max())
    assert drift["anchored"] <= ANCHOR_REACH * radius + 1e-6
    assert drift["free"] > ANCHOR_REACH * radius, drift  # the masks do pull: the bound is what held them


def test_recentring_leaves_out_masks_on_another_object(monkeypatch: pytest.MonkeyPatch) -> None:
    """A quarter of the masks on another object 120 px away: the true orientation, placed 20 mm
    off, is re-centred close to the truth; with every view in the least squares (no outlier
    rule) those views pull it several times further away."""
    import autoalign.engine.hypotheses as hyp

    mesh, _, geo, scene = _trial("mug", 0)
    wrong = set(range(0, len(scene), 4))
    # those views' masks are on a neighbour
    masks = [translate_mask(m, 120, 120).astype(m.dtype) if k in wrong else m for k, m in enumerate(scene.masks)]
    scene = type(scene)(scene.cameras, masks, scene.image_ids)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    truth_c = transform_points(geo.T_gt, mesh.centre[None])[0]
    start = geo.T_gt.copy()
    start[:3, 3] += [20.0, -10.0, 5.0]
    off = {}
    for rule, factor in (("robust", hyp.CENTROID_OUTLIER), ("every view", np.inf)):
        monkeypatch.setattr(hyp, "CENTROID_OUTLIER", factor)
        _, moved = score_poses(rast, ComparedViews.of(scene), start[None])
        off[rule] = float(np.linalg.norm(transform_points(moved[0], mesh.centre[None])[0] - truth_c))
    assert off["robust"] < 5.0, off
    assert off["every view"] > 3 * off["robust"], off


@pytest.mark.slow
@pytest.mark.parametrize("name,trial", [("pen", 1), ("hollow_frame", 1), ("gear_keyed", 1)])
def test_search_finds_the_pose_it_used_to_miss(name: str, trial: int) -> None:
    mesh, sym, geo, scene = _trial(name, trial)
    res = autoalign.refine(scene, mesh)
    e = pose_errors(res.T_wm, geo.T_gt, mesh.centre, None, sym)
    assert e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, (e.pos_err_mm, e.rot_err_deg)


@pytest.mark.slow
def test_without_orbits_the_keyed_gear_fails() -> None:
    """The gear case above is real: without the orbit the search misses the gear's key. (The flat
    frame and the pen, which needed the flips, are found without them since the search keeps 16
    scored orientations, ``RefineOptions.search.n_starts``, and counts one basin once; none of the 88
    trials 1-2 of the 44 procedural models needs them then, so they stay as a safety net.)"""
    mesh, sym, geo, scene = _trial("gear_keyed", 1)
    res = autoalign.refine(scene, mesh, options=autoalign.RefineOptions(disambiguation=DisambiguationOptions(orbits=False)))
    e = pose_errors(res.T_wm, geo.T_gt, mesh.centre, None, sym)
    assert e.rot_err_deg > 10.0, e.rot_err_deg


def _calibration_instance(root, scene: int, name: str):
    """Instance ``name`` of the calibration study's scene ``scene`` (SAM's failures and systematic
    outline errors in the masks, written under ``root``): its scene, mesh, symmetries, coarse
    start and true pose."""
    from autoalign.experiments.studies.sam_failures import make_sam_scene
    from autoalign.experiments.studies.uncertainty_calibration import SYSTEMATIC
    from autoalign.io.instances import read_init_poses, read_instance_scenes, read_instances
    from autoalign.io.models import ModelSet

    truth, _, names = make_sam_scene(root, scene, systematic=SYSTEMATIC, seed=29)
    k = names.index(name)
    found = read_instance_scenes(root / "scene", read_instances(root / "scene"))
    models = ModelSet.read(root / "models")
    obj = found.instances[k].obj_id
    seed = read_init_poses(root / "init_gt.json", found)[k]
    return found.scenes[k], models.mesh(obj), Symmetries.from_info(models.info[obj]), seed, truth[k]


@pytest.mark.slow
def test_near_turns_leave_a_local_minimum_half_a_tooth_off(tmp_path) -> None:
    """On a scene of the calibration study a plain 10-tooth gear (D10) descended from its coarse
    start to half a tooth (18 deg) off and was ``ok``; the near turns' 10-20 deg probe finds the
    teeth, and the result is within a degree of a symmetric equivalent of the truth."""
    from autoalign.engine.refine import RefineOptions

    scene, mesh, sym, seed, T_gt = _calibration_instance(tmp_path, 36, "gear_plain")
    # the weak turns (30-180 deg about a turn the views barely see) can find the teeth too, where the
    # refits widen that turn's sigma past the weak limit: left out of both runs, so that the near
    # turns are what is tested
    stuck = autoalign.refine(scene, mesh, seed,
                             RefineOptions(disambiguation=DisambiguationOptions(near_turns=(), weak_turns=())))
    assert pose_errors(stuck.T_wm, T_gt, mesh.centre, None, sym).rot_err_deg > 10.0
    res = autoalign.refine(scene, mesh, seed, RefineOptions(disambiguation=DisambiguationOptions(weak_turns=())))
    e = pose_errors(res.T_wm, T_gt, mesh.centre, None, sym)
    assert e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, (e.pos_err_mm, e.rot_err_deg)


@pytest.mark.slow
def test_near_turns_try_both_sides_of_a_keyed_gear(tmp_path, monkeypatch) -> None:
    """On a scene of the calibration study a keyed 12-tooth gear descended from its coarse start to
    half a tooth off. Its turns either way reach a tooth, and at 1/4 resolution the key, which
    tells them apart, barely shows: refining the better-scoring side alone ended one tooth (30
    deg) off. Refining both sides lets the orbit compare them at full resolution."""
    import autoalign.engine.refine as refine_module
    from autoalign.engine.refine import RefineOptions

    scene, mesh, sym, seed, T_gt = _calibration_instance(tmp_path, 15, "gear_keyed")
    options = RefineOptions(disambiguation=DisambiguationOptions(weak_turns=()))  # the near turns are tested
    res = autoalign.refine(scene, mesh, seed, options)
    e = pose_errors(res.T_wm, T_gt, mesh.centre, None, sym)
    assert e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, (e.pos_err_mm, e.rot_err_deg)
    one_side = refine_module._with_best_turn
    monkeypatch.setattr(refine_module, "_with_best_turn", lambda *a, **kw: one_side(*a, **{**kw, "both_ways": False}))
    monkeypatch.setattr(refine_module, "_alike_turns", lambda *a, **kw: np.zeros((0, 4, 4)))  # which would find it too
    res = autoalign.refine(scene, mesh, seed, options)
    assert abs(pose_errors(res.T_wm, T_gt, mesh.centre, None, sym).rot_err_deg - 30.0) < 2.0


@pytest.mark.slow
def test_a_keyed_gear_seeded_a_tooth_off_is_turned_to_its_key(monkeypatch) -> None:
    """A keyed 12-tooth gear seeded 20 deg off about its axis (nearer the next tooth than its own) and
    2 mm off: descent ends a tooth (30 deg) off, where every silhouette but the key's fits (a 4-object
    scene with cameras up to scale ended so, ``ok``). Turned about the axis it is nearly round about,
    the gear looks alike again 30 deg on at 1/4 resolution, having looked clearly different at 15; those
    turns, scored at full resolution, show the key, and the result is within 1 mm / 1 deg. The near and
    weak turns are left out (they are not what is tested); without the alike turns it stays a tooth off."""
    import autoalign.engine.refine as refine_module
    from autoalign.engine.hypotheses import turns
    from autoalign.engine.refine import RefineOptions

    mesh, sym, geo, scene = _trial("gear_keyed", 1)
    axis = mesh.round_axes[0]
    seed = turns(geo.T_gt, axis, mesh.centre, (20.0,))[0]
    seed[:3, 3] += [2.0, 0.0, 0.0]
    options = RefineOptions(disambiguation=DisambiguationOptions(near_turns=(), weak_turns=()))
    res = autoalign.refine(scene, mesh, seed, options)
    e = pose_errors(res.T_wm, geo.T_gt, mesh.centre, None, sym)
    assert e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, (e.pos_err_mm, e.rot_err_deg)
    monkeypatch.setattr(refine_module, "_alike_turns", lambda *a, **kw: np.zeros((0, 4, 4)))
    res = autoalign.refine(scene, mesh, seed, options)
    assert abs(pose_errors(res.T_wm, geo.T_gt, mesh.centre, None, sym).rot_err_deg - 30.0) < 2.0


@pytest.mark.slow
def test_pruning_saves_renders_not_answers() -> None:
    """Giving up hopeless hypotheses in the search (``abandon``) and polishing only the best
    finalist at full resolution cost nothing in the answer: the same pose, fewer renders.
    The z-bracket's search has many starts that settle on half turns; the can's two finalists
    are equivalent poses (it is symmetric), so the result is ambiguous either way."""
    for name, expect_ambiguous in (("z_bracket", False), ("can_plain", True)):
        mesh, sym, geo, scene = _trial(name, 0)
        pruned = autoalign.refine(scene, mesh)
        everything = autoalign.RefineOptions(search=SearchOptions(abandon=np.inf),
                                             ranking=RankingOptions(competitive=np.inf, polish_margin=-np.inf))
        full = autoalign.refine(scene, mesh, options=everything)
        assert pruned.renders < full.renders, (name, pruned.renders, full.renders)
        assert pruned.ambiguous == expect_ambiguous
        # iterations and history follow the winner's whole path, search levels included (a
        # flip of the search's best continues that one's path: two search-level entries)
        scales = [h["scale"] for h in pruned.history]
        assert scales[-2:] == [0.25, 1.0] and scales[:-2] in ([0.125], [0.125, 0.125]), scales
        assert pruned.iterations == sum(h["iterations"] for h in pruned.history)
        for res in (pruned, full):
            e = pose_errors(res.T_wm, geo.T_gt, mesh.centre, None, sym)
            assert e.pos_err_mm < 0.05 and e.rot_err_deg < 0.1, (name, e.pos_err_mm, e.rot_err_deg)


def test_posed_hit_sums_match_casting_each_pose() -> None:
    """The fused kernel (rays moved to each pose's model frame, cast and summed per view) against
    casting each pose's rays on their own and summing in numpy."""
    mesh, _, geo, scene = _trial("l_bracket", 0)
    rast = SoftSilhouetteRasterizer(mesh.simplified(1500))
    rng = np.random.default_rng(4)
    cams = [c.scaled(0.125) for c in scene.cameras[:6]]
    crops = rast.crops(geo.T_gt, CameraBatch.of(cams), margin=4)  # rays around the object, x0 y0 w h
    uv = [np.column_stack([rng.uniform(x0, x0 + w, 400), rng.uniform(y0, y0 + h, 400)]) for x0, y0, w, h in crops]
    view = np.repeat(np.arange(len(cams)), 400)
    dirs = np.concatenate([c.ray_directions(p) for c, p in zip(cams, uv)])
    centres = np.array([c.centre for c in cams])
    weights = np.column_stack([np.ones(len(view)), rng.uniform(size=len(view)), np.concatenate(uv)])
    poses = np.stack([geo.T_gt, geo.T_gt @ _turn(20.0, [1, 2, 0], mesh.centre), geo.T_init])
    sums = rast.caster.posed_hit_sums(poses, centres, dirs, view, weights)
    assert sums.shape == (3, 4, len(cams))
    assert sums[:2, 0].min() > 30  # near the truth the rays see the object in every view
    for k, T in enumerate(poses):
        hits = rast.caster.pixel_hits(T, CameraBatch.of(cams), view, np.concatenate(uv))  # the same rays
        expected = np.stack([np.bincount(view, weights=weights[:, c] * hits, minlength=len(cams)) for c in range(4)])
        # model-frame directions rounded to float32 in a different order: at most a grazing ray apart
        assert np.abs(sums[k, 0] - expected[0]).max() <= 1
        np.testing.assert_allclose(sums[k], expected, atol=weights.max() + 1e-6)


REAL_SCENE = REAL_SCENES / "lmo_im0480_0695"


@pytest.mark.slow
@pytest.mark.skipif(not (REAL_SCENE / "gt_world.json").is_file(), reason=f"real scene {REAL_SCENE} not present")
@pytest.mark.parametrize("obj_id", [1, 5])
def test_search_finds_real_objects_not_their_half_turns(obj_id: int) -> None:
    """Real photos' SAM masks, no seed: the ape and the watering can, whose half turns about their
    long axis fit the masks at 1/8 resolution about as well, end in the right basin (the dataset's
    labels are a few px off, so within 20 mm and 15 degrees is right). They ended 157 and 180
    degrees off while copies of one half-turned basin filled the search's places and a runner-up
    estimated lower than the best was left unpolished."""
    import json

    from autoalign.io.instances import Instance, read_instance_scenes
    from autoalign.io.models import ModelSet

    world = json.loads((REAL_SCENE / "gt_world.json").read_text())
    first = json.loads((REAL_SCENE / "scene_gt.json").read_text())
    objs = [e["obj_id"] for e in first[min(first, key=int)]]
    group = [int(o) for o in world["rigid_group"]]
    found = read_instance_scenes(REAL_SCENE, [Instance(objs.index(o), o) for o in group])
    mesh = ModelSet.read(REAL_SCENE / "models").mesh(obj_id)
    res = autoalign.refine(found.scenes[group.index(obj_id)], mesh)
    T = np.asarray(world["T_world_from_model_mm"][str(obj_id)])
    e = pose_errors(res.T_wm, T, mesh.centre, None, Symmetries())
    assert e.pos_err_mm < 20.0 and e.rot_err_deg < 15.0, (e.pos_err_mm, e.rot_err_deg)
