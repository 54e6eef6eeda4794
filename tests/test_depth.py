"""The depth term (:mod:`autoalign.losses.depth`, issue 28): its residuals against depth ray-cast by
open3d (independent of our caster and of our pixel convention), its occlusion rule, and what it
does on real sensor depth (YCB-Video), where masks alone leave the object far along the ray."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from autoalign.engine.refine import RefineOptions, refine
from autoalign.experiments.scenes.synthetic import make_scene
from autoalign.experiments.studies.rgbd_depth import eroded_folder, start_along_ray, starts_along_rays
from autoalign.experiments.studies.shared_data import YCBV_RGBD
from autoalign.geometry.mesh import load_mesh
from autoalign.geometry.se3 import (
    apply_twist,
    make_pose,
    rotation_angle_deg,
    transform_points,
)
from autoalign.io.bop import read_scene, with_depth
from autoalign.losses.depth import DepthNoise, DepthTerms, depth_terms
from autoalign.losses.term import TermEvidence
from autoalign.quality.verdict import PoseEvidence, judge
from autoalign.rasterizers.ray_casting import RayCaster

def test_residuals_vanish_at_the_pose_open3d_measured(box_with_depth) -> None:
    mesh, T, cams, depths = box_with_depth
    centre = transform_points(T, mesh.centre[None])[0]
    terms = depth_terms(RayCaster(mesh), mesh, T, cams, depths, centre)
    assert terms.used.min() > 300 and terms.hidden.sum() == 0
    assert np.nanmax(terms.rms_mm) < 0.05  # float32 casting, not a half-pixel shift (that is millimetres here)
    off = depth_terms(RayCaster(mesh), mesh, apply_twist(T, np.array([0, 0, 3.0, 0, 0, 0]), centre), cams, depths,
                      centre)
    assert np.nanmin(off.rms_mm) > 0.5


def test_gauss_newton_on_the_depth_term_walks_back_a_shift_and_a_turn(box_with_depth) -> None:
    mesh, T, cams, depths = box_with_depth
    centre = transform_points(T, mesh.centre[None])[0]
    start = apply_twist(T, np.array([4.0, -3.0, 6.0, *np.radians([3.0, -2.0, 2.0])]), centre)
    caster, X = RayCaster(mesh), start
    for _ in range(6):
        c = transform_points(X, mesh.centre[None])[0]
        terms = depth_terms(caster, mesh, X, cams, depths, c)
        step = -np.linalg.solve(terms.gn.sum(0), terms.grad.sum(0))
        X = apply_twist(X, step, c)
    moved = transform_points(X, mesh.centre[None])[0]
    assert np.linalg.norm(moved - centre) < 0.05 and rotation_angle_deg(X[:3, :3], T[:3, :3]) < 0.05


def test_a_nearer_measurement_is_an_occluder_not_a_residual(box_with_depth) -> None:
    mesh, T, cams, depths = box_with_depth
    centre = transform_points(T, mesh.centre[None])[0]
    blocked = [d.copy() for d in depths]
    for d in blocked:  # something 100 mm in front of the object over the left half of each image
        half = d.shape[1] // 2
        d[:, :half] = np.where(d[:, :half] > 0, d[:, :half] - 100.0, 0.0)
    terms = depth_terms(RayCaster(mesh), mesh, T, cams, blocked, centre)
    clear = depth_terms(RayCaster(mesh), mesh, T, cams, depths, centre)
    assert (terms.hidden > 0).all() and (terms.used < clear.used).all()
    assert np.nanmax(terms.rms_mm) < 0.05  # the hidden pixels are not residuals
    assert DepthNoise().sigma(np.array([600.0, 1200.0])) == pytest.approx([1.51, 6.05], abs=0.01)


def test_depth_joins_the_mask_term_in_refine(box_with_depth) -> None:
    """With masks that miss a third of the object in every view, depth keeps the pose."""
    mesh, T, cams, depths = box_with_depth
    scene = make_scene(mesh, T, cams)
    cut = [np.where(np.arange(m.shape[1])[None, :] < np.median(np.nonzero(m)[1]) - 10, m, 0).astype(np.float32)
           for m in scene.masks]
    centre = transform_points(T, mesh.centre[None])[0]
    start = apply_twist(T, np.array([3.0, 2.0, 10.0, *np.radians([4.0, 0.0, -3.0])]), centre)
    errors = {}
    for name, depth in (("masks", None), ("masks + depth", depths)):
        res = refine(replace(scene, masks=cut, depths=depth), mesh, start)
        errors[name] = (np.linalg.norm(transform_points(res.T_wm, mesh.centre[None])[0] - centre),
                        rotation_angle_deg(res.T_wm[:3, :3], T[:3, :3]))
    assert errors["masks + depth"][0] < 0.5 and errors["masks + depth"][1] < 0.5, errors
    assert errors["masks"][0] > 2 * errors["masks + depth"][0], errors


@pytest.mark.slow
@pytest.mark.skipif(not YCBV_RGBD.is_dir(), reason=f"no real RGB-D scene at {YCBV_RGBD}")
def test_real_sensor_depth_pins_objects_the_masks_leave_far_along_the_ray() -> None:
    """YCB-Video frames, masks eroded by 4 px with 1 in 3 cut in half, a start 20 mm along the viewing
    ray and 10 degrees off: with depth the gelatin box and the foam brick end within 3 mm / 2 deg of
    the dataset's labels; the masks alone leave them tens of millimetres along the ray."""
    gt = json.loads((YCBV_RGBD / "scene_gt.json").read_text())["1"]  # world = camera of image 1
    rng = np.random.default_rng(0)
    for k, entry in enumerate(gt):
        if entry["obj_id"] not in (8, 21):
            continue
        mesh = load_mesh(YCBV_RGBD / "models" / f"obj_{entry['obj_id']:06d}.ply")
        scene = read_scene(YCBV_RGBD, k)
        masks = []
        for v, m in enumerate(scene.masks):
            m = cv2.erode((m > 0.5).astype(np.uint8), np.ones((9, 9), np.uint8))
            if v % 3 == 0:
                m[:, int(np.median(np.nonzero(m)[1])):] = 0
            masks.append(m.astype(np.float32))
        scene = with_depth(replace(scene, masks=masks))
        assert scene.depths is not None and len(scene.depths) == len(scene)
        T = make_pose(np.reshape(entry["cam_R_m2c"], (3, 3)), np.asarray(entry["cam_t_m2c"], dtype=np.float64))
        c = transform_points(T, mesh.centre[None])[0]
        axis = rng.normal(size=3)
        start = start_along_ray(T, mesh.centre, 20.0, np.radians(10.0) * axis / np.linalg.norm(axis))
        found = {}
        for name, opts in (("depth", RefineOptions()), ("masks", RefineOptions(depth=None))):
            res = refine(scene, mesh, start, opts)
            found[name] = (np.linalg.norm(transform_points(res.T_wm, mesh.centre[None])[0] - c),
                           rotation_angle_deg(res.T_wm[:3, :3], T[:3, :3]))
        assert found["depth"][0] < 3.0 and found["depth"][1] < 2.0, (entry["obj_id"], found)
        assert found["masks"][0] > 10.0, (entry["obj_id"], found)


@pytest.mark.slow
@pytest.mark.skipif(not YCBV_RGBD.is_dir(), reason=f"no real RGB-D scene at {YCBV_RGBD}")
def test_the_command_uses_the_scenes_depth_unless_told_off(tmp_path) -> None:
    """``autoalign refine`` on a copy of the YCB-Video scene with eroded masks: ``refine.json`` says what
    the depth term saw in each view, and ``--depth off`` leaves the foam brick far along the ray."""
    import shutil
    import subprocess
    import sys

    scene = tmp_path / "scene"
    scene.mkdir()
    for part in ("scene_camera.json", "depth", "mask_visib"):
        (shutil.copytree if (YCBV_RGBD / part).is_dir() else shutil.copy)(YCBV_RGBD / part, scene / part)
    gt = json.loads((YCBV_RGBD / "scene_gt.json").read_text())["1"]
    k = next(i for i, e in enumerate(gt) if e["obj_id"] == 21)
    for p in (scene / "mask_visib").glob(f"*_{k:06d}.png"):
        cv2.imwrite(str(p), cv2.erode(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), np.ones((9, 9), np.uint8)))
    T = make_pose(np.reshape(gt[k]["cam_R_m2c"], (3, 3)), np.asarray(gt[k]["cam_t_m2c"], dtype=np.float64))
    mesh = load_mesh(YCBV_RGBD / "models" / "obj_000021.ply")
    c = transform_points(T, mesh.centre[None])[0]
    start = start_along_ray(T, mesh.centre, 20.0, np.radians([6.0, -5.0, 5.0]))
    init = tmp_path / "init.json"
    coarse = [dict(e) for e in gt]  # the instance's entry moved, at its index
    coarse[k].update(cam_R_m2c=start[:3, :3].ravel().tolist(), cam_t_m2c=start[:3, 3].tolist())
    init.write_text(json.dumps({"1": coarse}))
    errors = {}
    for mode in ("auto", "off"):
        out = tmp_path / mode
        p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(scene), "--model",
                            str(YCBV_RGBD / "models" / "obj_000021.ply"), "--obj-id", "21", "--instance", str(k),
                            "--init", str(init), "--depth", mode, "--out", str(out), "--quiet"],
                           capture_output=True, text=True, timeout=600)
        assert p.returncode in (0, 3), p.stderr
        report = json.loads((out / "refine.json").read_text())
        T_found = np.asarray(report["pose"]["T_wm"])  # world = camera of image 1
        errors[mode] = np.linalg.norm(transform_points(T_found, mesh.centre[None])[0] - c)
        if mode == "auto":
            depth = report["depth"]
            assert len(depth["rms_mm"]) == len(report["image_ids"]) == 10
            assert min(depth["used_px"]) > 500 and max(depth["rms_mm"]) < 5.0
            terms = report["terms"]  # each term per view: the depth carries part of every view's loss
            assert len(terms["depth_share"]) == len(terms["mask_loss"]) == len(terms["weight"]) == 10
            assert all(0.0 < s < 1.0 for s in terms["depth_share"]) and min(terms["mask_loss"]) >= 0.0
        else:
            assert "depth" not in report and sorted(report["terms"]) == ["mask_loss", "weight"]
    assert errors["auto"] < 3.0 and errors["off"] > 10.0, errors


@pytest.mark.slow
@pytest.mark.skipif(not YCBV_RGBD.is_dir(), reason=f"no real RGB-D scene at {YCBV_RGBD}")
def test_every_instance_of_a_scene_and_the_joint_stage_use_the_depth(tmp_path, refine_models_command) -> None:
    """``autoalign refine --models`` on the YCB-Video frames with eroded masks, every instance from a
    start 20 mm along its viewing ray: with depth the gelatin box and the foam brick end within 3 mm
    of the dataset's labels after the joint stage, and ``refine.json`` gives each instance's depth."""
    from autoalign.io.models import ModelSet

    scene = eroded_folder(YCBV_RGBD, tmp_path / "scene", ("scene_camera.json", "scene_gt.json", "depth"))
    models = ModelSet.read(YCBV_RGBD / "models")
    labels, coarse = starts_along_rays(YCBV_RGBD, models, 20.0, np.zeros(3))
    truth = [transform_points(T, models.mesh(e["obj_id"]).centre[None])[0] for T, e in zip(labels, coarse)]
    report = refine_models_command(scene, YCBV_RGBD / "models", coarse)
    for inst in report["instances"]:
        k, obj = inst["instance"], inst["obj_id"]
        assert inst["depth"] is not None and min(inst["depth"]["used_px"]) > 300, inst["depth"]
        assert len(inst["terms"]["depth_share"]) == len(inst["image_ids"])
        if obj in (8, 21):
            found = transform_points(np.asarray(inst["pose"]["T_wm"]), models.mesh(obj).centre[None])[0]
            assert np.linalg.norm(found - truth[k]) < 3.0, (obj, np.linalg.norm(found - truth[k]))
            assert inst["verdict"] != "failed", inst["reasons"]


def _depth_evidence(share: float, views: int = 6, used: int = 800) -> tuple[TermEvidence, ...]:
    """What a depth term of ``views`` views says whose ``share`` of ``used`` samples each agree with
    the measurement (nothing, with too few samples)."""
    none = np.zeros(0, np.int64)
    found = DepthTerms(np.zeros(views), np.zeros((views, 6)), np.zeros((views, 6, 6)), np.full(views, used),
                       np.zeros(views, np.int64), np.ones(views), np.full(views, share), [(none, none)] * views,
                       np.ones(views, np.int64)).evidence()
    return () if found is None else (found,)


def test_the_verdict_weighs_the_depth_against_the_masks() -> None:
    """Depth that agrees keeps a pose with loose masks from being flagged and one with partial masks
    from failing (a look, not a failure: depth agrees with a pose pushed into the table too), and
    says so; depth that disagrees fails a pose the masks fit; a view with too few samples says nothing."""
    ids = list(range(6))
    loose, partial, fitting, w = np.full(6, 0.6), np.full(6, 0.43), np.full(6, 0.95), np.ones(6)
    assert judge(PoseEvidence(partial, w, ids)).status == "failed"
    supported = judge(PoseEvidence(loose, w, ids, terms=_depth_evidence(0.97)))
    assert supported.status == "ok" and "the measured depth agrees" in supported.reasons[0]
    partly = judge(PoseEvidence(partial, w, ids, terms=_depth_evidence(0.97)))
    assert partly.status == "check" and "though the measured depth agrees" in partly.reasons[0]
    contradicted = judge(PoseEvidence(fitting, w, ids, terms=_depth_evidence(0.1)))
    assert contradicted.status == "failed" and "the measured depth disagrees" in contradicted.reasons[0]
    # too few samples to judge; then a share that neither supports nor contradicts
    assert judge(PoseEvidence(fitting, w, ids, terms=_depth_evidence(0.1, used=10))).status == "ok"
    assert judge(PoseEvidence(partial, w, ids, terms=_depth_evidence(0.6))).status == "failed"


def test_a_turn_neither_the_masks_nor_the_depth_fix_is_not_called_ok(depth_caster) -> None:
    """Issue 43, item 11: seen from nearly one viewpoint with depth, a can (its symmetry not
    declared) turned 10-20 deg about its axis fits within NEAR_TURN_RISE as well, so it is
    ``check``, the reason naming that axis, whatever its sigma; an L-bracket, round about no axis,
    is not measured, and it is ``ok`` (both within 1 mm / 1 deg, symmetry aside)."""
    from autoalign.experiments.scenes.photo_scene import near_one_viewpoint
    from autoalign.experiments.scenes.procedural_models import procedural_models
    from autoalign.experiments.scenes.synthetic import perturb_pose, random_rotation
    from autoalign.geometry.mesh import mesh_from_trimesh
    from autoalign.quality.verdict import NEAR_TURN_RISE

    rng = np.random.default_rng(5)
    cams = near_one_viewpoint(6, rng)
    pool = {p.name: p for p in procedural_models()}
    for name in ("can_plain", "l_bracket"):
        mesh = mesh_from_trimesh(pool[name].mesh, name)
        R = random_rotation(rng)
        T = make_pose(R, np.array([0.0, 0.0, 30.0]) - R @ mesh.centre)
        scene = replace(make_scene(mesh, T, cams), depths=[depth_caster(mesh, T, c) for c in cams])
        res = refine(scene, mesh, perturb_pose(T, 5.0, 8.0, rng, mesh.centre), RefineOptions(region=None))
        verdict = judge(PoseEvidence.of(res))
        centre = transform_points(T, mesh.centre[None])[0]
        assert np.linalg.norm(transform_points(res.T_wm, mesh.centre[None])[0] - centre) < 1.0, name
        if name == "can_plain":
            axis = res.turn_rise_axis_m
            assert res.turn_rise < NEAR_TURN_RISE and abs(axis[2]) > 0.99, (res.turn_rise, axis)
            assert verdict.status == "check" and any("the turn about model z" in r for r in verdict.reasons)
        else:
            assert rotation_angle_deg(res.T_wm[:3, :3], R) < 1.0  # round about no axis: nothing to measure
            assert res.turn_rise is None and verdict.status == "ok", (res.turn_rise, verdict)
