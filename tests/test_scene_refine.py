"""Several objects in one scene (issue 13): instances read from scene_gt.json or an instances file,
other instances' masks ignored, every instance refined with a verdict, ``refine --models``.

The scene: five procedural objects close together on a table so that they hide each other, 24 views
of 480x360 around them, visible masks from open3d ray casting of all five (a pixel belongs to the
nearest surface), written as a BOP folder with a models folder beside it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from autoalign.engine.refine import refine
from autoalign.errors import AutoalignError
from autoalign.experiments.scenes.procedural_models import (
    load_bop_models_info,
    procedural_models,
    write_models,
)
from autoalign.experiments.scenes.synthetic import (
    default_K,
    perturb_pose,
    random_rotation,
    ring_cameras,
    write_multi_scene,
)
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.geometry.mesh import load_mesh
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import pose_in_camera, scene_gt_of
from autoalign.io.instances import (
    Instance,
    read_init_poses,
    read_instance_scenes,
    read_instances,
)
from autoalign.quality.verdict import CHECK_IOU, NEAR_SYMMETRY_GAP, PoseEvidence, judge

N_OBJ, N_VIEWS, W, H = 5, 24, 480, 360


class Multi:
    root: Path
    scene: Path
    models: Path
    init: Path
    truth: list[np.ndarray]
    obj_ids: list[int]


@pytest.fixture(scope="module")
def multi(tmp_path_factory) -> Multi:
    d = Multi()
    d.root = tmp_path_factory.mktemp("multi")
    d.models = d.root / "models"
    pms = procedural_models()[:N_OBJ]  # box_knob, box_plain, mug, l_bracket, can_plain
    write_models(d.models, pms)
    meshes = [load_mesh(d.models / f"obj_{i:06d}.ply") for i in range(1, N_OBJ + 1)]
    rng = np.random.default_rng(11)
    d.truth = []
    for k, m in enumerate(meshes):  # on a circle of 70 mm: neighbours overlap in most views
        a = 2 * np.pi * k / N_OBJ
        R = random_rotation(rng)
        d.truth.append(make_pose(R, np.array([70 * np.cos(a), 70 * np.sin(a), 30.0]) - R @ m.centre))
    cams = ring_cameras(N_VIEWS, rng, target=(0.0, 0.0, 30.0), K=default_K(W, H, 450.0), width=W, height=H)
    d.scene = d.root / "scene"
    d.obj_ids = list(range(1, N_OBJ + 1))
    write_multi_scene(d.scene, meshes, d.obj_ids, d.truth, cams)
    coarse = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(d.truth, meshes)]
    d.init = d.root / "init_gt.json"
    d.init.write_text(json.dumps(scene_gt_of(list(zip(d.obj_ids, coarse)), cams[:1], [0])))
    return d


def _errors(d: Multi, refine_json: Path) -> list[tuple[float, float]]:
    info = load_bop_models_info(d.models)
    rec = json.loads(refine_json.read_text())
    out = []
    for r in rec["instances"]:
        k = r["instance"]
        mesh = load_mesh(d.models / f"obj_{r['obj_id']:06d}.ply")
        e = pose_errors(np.asarray(r["pose"]["T_wm"]), d.truth[k], mesh.centre, None,
                        Symmetries.from_info(info[r["obj_id"]]))
        out.append((e.pos_err_mm, e.rot_err_deg))
    return out


# ----------------------------------------------------------------------------------- reading

def test_instances_from_scene_gt_and_from_a_file(multi, tmp_path):
    assert read_instances(multi.scene) == [Instance(k, k + 1) for k in range(N_OBJ)]
    f = tmp_path / "instances.json"
    f.write_text(json.dumps({"instances": {"3": 4, "1": 2}}))
    assert read_instances(multi.scene, f) == [Instance(1, 2), Instance(3, 4)]
    f.write_text(json.dumps({"objects": [1]}))
    with pytest.raises(AutoalignError, match="instances.json"):
        read_instances(multi.scene, f)


def test_scene_gt_whose_entry_changes_object_is_an_error(multi, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(multi.scene, scene)
    gt = json.loads((scene / "scene_gt.json").read_text())
    gt["5"][2]["obj_id"] = 9
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    with pytest.raises(AutoalignError, match="entry 2 is obj_id 3 in image 0 but 9 in image 5"):
        read_instances(scene)


def test_other_masks_are_ignored_and_missing_views_left_out(multi, tmp_path):
    """Instance k's ignored pixels are exactly the other masks' pixels its own mask does not cover;
    an instance without a mask in a view is not in that view; an unmodelled instance still counts."""
    scene = tmp_path / "scene"
    shutil.copytree(multi.scene, scene)
    (scene / "mask_visib" / "000004_000001.png").unlink()
    cv2.imwrite(str(scene / "mask_visib" / "000006_000001.png"), np.zeros((H, W), np.uint8))
    found = read_instance_scenes(scene, [Instance(0, 1), Instance(1, 2)])  # instances 2-4 unmodelled
    assert found.unmodelled == [2, 3, 4]
    s1 = found.scenes[1]
    assert 4 not in s1.image_ids and 6 not in s1.image_ids and s1.skipped == (4,) and s1.empty == (6,)
    for k, im in enumerate(s1.image_ids):
        own = cv2.imread(str(scene / "mask_visib" / f"{im:06d}_000001.png"), cv2.IMREAD_GRAYSCALE) > 0
        others = np.zeros_like(own)
        for j in (0, 2, 3, 4):
            p = scene / "mask_visib" / f"{im:06d}_{j:06d}.png"
            if p.is_file():
                others |= cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0
        np.testing.assert_array_equal(s1.masks[k] > 0.5, own)
        np.testing.assert_array_equal(s1.ignore[k], others & ~own)
    assert sum(m.any() for m in s1.ignore) > N_VIEWS // 2  # the objects do hide each other


def test_init_poses_per_instance(multi):
    found = read_instance_scenes(multi.scene, read_instances(multi.scene))
    seeds = read_init_poses(multi.init, found)
    assert sorted(seeds) == list(range(N_OBJ))
    for k, T in seeds.items():  # 10 mm / 15 deg off the truth, as written
        assert 5.0 < np.linalg.norm(T[:3, 3] - multi.truth[k][:3, 3]) < 60.0


# ------------------------------------------------------------------------------- refinement

@pytest.mark.slow
def test_ignoring_other_masks_is_what_makes_occluded_instances_right(multi):
    """The same start with and without the ignored pixels: with them every instance lands within
    0.2 mm / 0.2 deg; compared with the whole visible mask, the hidden parts pull some off."""
    found = read_instance_scenes(multi.scene, read_instances(multi.scene))
    seeds = read_init_poses(multi.init, found)
    info = load_bop_models_info(multi.models)
    worst = {}
    for ignore in (True, False):
        errs = []
        for inst, scene in zip(found.instances, found.scenes):
            mesh = load_mesh(multi.models / f"obj_{inst.obj_id:06d}.ply")
            r = refine(scene if ignore else replace(scene, ignore=None), mesh, seeds[inst.index])
            e = pose_errors(r.T_wm, multi.truth[inst.index], mesh.centre, None, Symmetries.from_info(info[inst.obj_id]))
            errs.append((e.pos_err_mm, e.rot_err_deg))
        worst[ignore] = np.max(errs, axis=0)
    assert worst[True][0] < 0.2 and worst[True][1] < 0.2, worst
    assert worst[False][0] > 3 * worst[True][0], worst


@pytest.mark.slow
def test_refine_models_from_init_labels_every_instance(multi, tmp_path):
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(multi.scene), "--models",
                        str(multi.models), "--init", str(multi.init), "--out", str(out), "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    for e_mm, e_deg in _errors(multi, out / "refine.json"):
        assert e_mm < 1.0 and e_deg < 1.0
    rec = json.loads((out / "refine.json").read_text())
    assert [r["verdict"] for r in rec["instances"]] == ["ok"] * N_OBJ
    from autoalign.engine.solver import Stop

    assert Stop(rec["joint"]["stop"]).converged, rec["joint"]  # the joint stage says why it stopped
    gt = json.loads((out / "scene_gt.json").read_text())
    assert len(gt) == N_VIEWS and all([e["obj_id"] for e in v] == multi.obj_ids for v in gt.values())
    overlay = cv2.imread(str(out / "overlay.png"))
    assert overlay is not None and overlay.shape[0] > 300


@pytest.mark.slow
def test_instances_refined_side_by_side_end_as_refined_one_after_the_other(multi, tmp_path):
    """With two render threads the instances are refined two at a time (each on one,
    :mod:`autoalign.runtime.parallel`), with one one after the other: the same labels, sigmas,
    verdicts and reasons to the bit, the same joint stage."""
    def run(threads: str) -> tuple[dict, str]:
        out = tmp_path / f"out_{threads}"
        p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(multi.scene), "--models",
                            str(multi.models), "--init", str(multi.init), "--out", str(out), "--quiet"],
                           capture_output=True, text=True, timeout=600,
                           env={**os.environ, "AUTOALIGN_THREADS": threads})
        assert p.returncode == 0, p.stderr
        rec = json.loads((out / "refine.json").read_text())
        for r in rec["instances"]:
            r.pop("timings")
        rec.pop("timings")
        return rec, (out / "scene_gt.json").read_text()

    (two, gt_two), (one, gt_one) = run("2"), run("1")
    assert two["instances"] == one["instances"]
    assert two["joint"] == one["joint"] and two["joint"]["iterations"] >= 1
    assert gt_two == gt_one
    assert len(two["instances"]) == N_OBJ


@pytest.mark.slow
def test_previews_of_instances_refined_side_by_side_come_one_at_a_time(multi, pool_of_two):
    """The label page shows each instance's poses as they come (``refine_scene``'s preview) while the
    instances are refined two at a time: the calls come from both threads but never overlap, and
    every instance shows its poses."""
    from autoalign.io.models import ModelSet
    from autoalign.scene.refine import refine_scene

    found = read_instance_scenes(multi.scene, read_instances(multi.scene))
    seeds = read_init_poses(multi.init, found)
    busy, overlapped, shown, threads = threading.Lock(), [], {}, set()

    def preview(index: int, T_wm: np.ndarray) -> None:
        if not busy.acquire(blocking=False):
            overlapped.append(index)
            return
        try:
            shown.setdefault(index, []).append(T_wm.copy())
            threads.add(threading.get_ident())
            time.sleep(0.01)  # a page's drawing takes a while: another preview would overlap it
        finally:
            busy.release()

    done = refine_scene(found, ModelSet.read(multi.models), seeds, preview=preview)
    assert not overlapped
    assert sorted(shown) == list(range(N_OBJ)) and len(done.results) == N_OBJ
    assert len(threads) == 2  # shown from both threads: the instances ran side by side


@pytest.mark.slow
def test_ctrl_c_while_instances_are_refined_side_by_side_exits_130_and_writes_nothing(multi, tmp_path):
    """SIGINT at 30%, 50% and 70% of a run whose instances are refined two at a time (two render
    threads): the threads under way stop at their next progress report, and the command exits 130
    with one line and writes nothing, as it does one instance after the other."""
    import signal

    env = {**os.environ, "AUTOALIGN_THREADS": "2"}

    def command(out: Path) -> list[str]:
        return [sys.executable, "-m", "autoalign.cli.main", "refine", str(multi.scene), "--models", str(multi.models),
                "--init", str(multi.init), "--out", str(out), "--quiet"]

    t0 = time.perf_counter()
    whole = subprocess.run(command(tmp_path / "whole"), capture_output=True, text=True, timeout=600, env=env)
    seconds = time.perf_counter() - t0
    assert whole.returncode == 0, whole.stderr
    for share in (0.3, 0.5, 0.7):
        out = tmp_path / f"out{share}"
        p = subprocess.Popen(command(out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        time.sleep(share * seconds)
        p.send_signal(signal.SIGINT)
        stdout, stderr = p.communicate(timeout=120)
        assert p.returncode == 130, (share, p.returncode, stderr)
        assert [x for x in stderr.splitlines() if x.strip()] == ["autoalign: interrupted"], (share, stderr)
        assert not out.exists() and stdout == "", share


@pytest.mark.slow
def test_instance_with_wrong_masks_is_flagged_and_exit_is_3(multi, tmp_path):
    """Instance 3's masks replaced by instance 1's in 60% of the views (a segmenter that labelled
    the wrong object): whatever pose it ends at, it is not 'ok', and the command exits 3."""
    scene = tmp_path / "scene"
    shutil.copytree(multi.scene, scene)
    for im in range(0, N_VIEWS):
        if im % 5 < 3:
            src = scene / "mask_visib" / f"{im:06d}_000001.png"
            if src.is_file():
                shutil.copy(src, scene / "mask_visib" / f"{im:06d}_000003.png")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(scene), "--models", str(multi.models),
                        "--init", str(multi.init), "--out", str(out), "--quiet"], capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 3, p.stderr
    rec = json.loads((out / "refine.json").read_text())
    r3 = next(r for r in rec["instances"] if r["instance"] == 3)
    assert r3["verdict"] in ("check", "failed") and r3["reasons"]
    assert "obj 4 (instance 3)" in p.stderr


def test_verdict_rules():
    ids = list(range(10))
    good = judge(PoseEvidence(np.full(10, 0.95), np.ones(10), ids))
    assert good.status == "ok" and good.reasons == []
    loose = judge(PoseEvidence(np.full(10, 0.7), np.ones(10), ids))
    assert loose.status == "check"
    w = np.ones(10)
    w[:4] = 0.05
    # a minority of wrong masks: noted, not doubted
    some = judge(PoseEvidence(np.r_[np.full(4, 0.3), np.full(6, 0.95)], w, ids))
    assert some.status == "ok" and some.set_aside == [0, 1, 2, 3] and "down-weighted" in some.reasons[0]
    w[:6] = 0.05
    most = judge(PoseEvidence(np.r_[np.full(6, 0.9), np.full(4, 0.95)], w, ids))
    assert most.status == "check" and most.set_aside == [0, 1, 2, 3, 4, 5] and "more than 50%" in most.reasons[-1]
    assert judge(PoseEvidence(np.full(10, 0.3), np.ones(10), ids)).status == "failed"
    assert judge(PoseEvidence(np.full(2, 0.99), np.ones(2), ids[:2])).status == "failed"
    assert judge(PoseEvidence(np.full(10, 0.95), np.ones(10), ids, ambiguous=True)).status == "check"
    assert judge(PoseEvidence(np.full(10, 0.95), np.ones(10), ids, ambiguous=True, symmetric=True)).status == "ok"


def test_nearly_symmetric_is_a_reason_unless_turning_clearly_worsens_the_fit():
    """A weakly observed turn (not about an axis of continuous symmetry) flags the pose, unless
    the pose's turns about it were tried and fit clearly worse (``turn_gap``)."""
    from autoalign.engine.uncertainty import Uncertainty

    ids = list(range(10))
    cov = np.diag([0.01, 0.01, 0.01, 1e-6, 1e-6, np.radians(0.3) ** 2])
    u = Uncertainty(cov, np.full(3, 0.1), np.array([0.06, 0.06, 0.3]), ["turn about model z: 0.3 deg"],
                    [np.array([0.0, 0.0, 1.0])])
    fit = (np.full(10, 0.95), np.ones(10), ids)
    assert judge(PoseEvidence(*fit, uncertainty=u)).status == "check"  # not tried: cautious
    assert judge(PoseEvidence(*fit, uncertainty=u, turn_gap=0.5 * NEAR_SYMMETRY_GAP)).status == "check"
    assert judge(PoseEvidence(*fit, uncertainty=u, turn_gap=2 * NEAR_SYMMETRY_GAP)).status == "ok"
    # a true symmetry
    assert judge(PoseEvidence(*fit, uncertainty=u, free_axes_m=(np.array([0.0, 0.0, 1.0]),))).status == "ok"
    # declared symmetries explain a turn that fits as well (a hexagonal bar's 60 deg): the gap says nothing
    assert judge(PoseEvidence(*fit, symmetric=True, uncertainty=u, turn_gap=0.0)).status == "ok"
    # a weak turn whose sigma reaches NEAR_SYMMETRY_DEG: the descent can stop degrees off in it, whatever the gap
    from autoalign.quality.verdict import NEAR_SYMMETRY_DEG

    loose = Uncertainty(np.diag([0.01, 0.01, 0.01, 1e-6, 1e-6, np.radians(NEAR_SYMMETRY_DEG * 1.1) ** 2]),
                        np.full(3, 0.1), np.array([0.06, 0.06, 1.1]), [], [np.array([0.0, 0.0, 1.0])])
    v = judge(PoseEvidence(*fit, uncertainty=loose, turn_gap=2 * NEAR_SYMMETRY_GAP))
    assert v.status == "check" and "the turn about model z (1.1 deg)" in v.reasons[-1]
    # but not the sigma
    assert judge(PoseEvidence(*fit, symmetric=True, uncertainty=loose, turn_gap=0.0)).status == "check"
    # the views' spread decides it, not the prior on a shared outline shift (the large-sigma rule counts that)
    spread = np.diag([0.01, 0.01, 0.01, 1e-6, 1e-6, np.radians(0.8) ** 2])
    prior = replace(loose, spread=spread)
    assert judge(PoseEvidence(*fit, uncertainty=prior, turn_gap=2 * NEAR_SYMMETRY_GAP)).status == "ok"
    assert judge(PoseEvidence(*fit, uncertainty=replace(prior, spread=loose.covariance),
                              turn_gap=2 * NEAR_SYMMETRY_GAP)).status == "check"


def test_a_turn_the_depth_and_masks_barely_see_is_a_reason_whatever_its_sigma():
    """With depth, a pose whose turns of 10-20 deg about a principal axis change the whole fit by
    less than NEAR_TURN_RISE is nearly symmetric, and the reason names that axis, even where the
    sigma is small and the masks' turn gap clear (the tuna can, 8.8 deg off with sigma 0.33 deg);
    a rise above it changes nothing, and declared symmetries explain it."""
    from autoalign.engine.uncertainty import Uncertainty
    from autoalign.quality.verdict import NEAR_TURN_RISE

    ids = list(range(10))
    cov = np.diag([0.01, 0.01, 0.01, 1e-6, 1e-6, np.radians(0.3) ** 2])
    u = Uncertainty(cov, np.full(3, 0.1), np.array([0.06, 0.06, 0.3]), [], [np.array([1.0, 0.0, 0.0])])
    fit = (np.full(10, 0.95), np.ones(10), ids)
    z = np.array([0.0, 0.0, 1.0])
    clear = dict(uncertainty=u, turn_gap=2 * NEAR_SYMMETRY_GAP, turn_rise_axis_m=z)
    assert judge(PoseEvidence(*fit, **clear)).status == "ok"  # no depth: no rise
    assert judge(PoseEvidence(*fit, turn_rise=2 * NEAR_TURN_RISE, **clear)).status == "ok"
    v = judge(PoseEvidence(*fit, turn_rise=-0.004, **clear))
    assert v.status == "check" and "nearly symmetric: the turn about model z (0.3 deg)" in v.reasons[-1]
    assert "changes by -0.4%" in v.reasons[-1] and "model x" not in v.reasons[-1]
    assert judge(PoseEvidence(*fit, symmetric=True, turn_rise=-0.004, **clear)).status == "ok"


def test_partial_masks_with_views_that_agree_are_check_not_failed():
    """Most masks cover part of the object or another one (IoU 0.3, set aside), but 4 of 10 views
    fit the pose well: `check`, with the agreeing views named; with only 2 agreeing, `failed`."""
    ids = list(range(10))
    w = np.r_[np.full(6, 0.05), np.ones(4)]
    v = judge(PoseEvidence(np.r_[np.full(6, 0.3), np.full(4, 0.92)], w, ids))
    assert v.status == "check" and "4 of 10 views fit it well" in v.reasons[0]
    w2 = np.r_[np.full(8, 0.05), np.ones(2)]
    assert judge(PoseEvidence(np.r_[np.full(8, 0.3), np.full(2, 0.92)], w2, ids)).status == "failed"


def test_loose_median_is_judged_by_the_views_whose_masks_agree():
    """A median IoU below CHECK_IOU made by masks the fit sets aside (partial ones, weights of 0.2)
    is no reason to check when at least half the views agree and fit well; when the views that
    agree are fewer, or fit loosely themselves, it is."""
    ids = list(range(10))
    iou = np.r_[np.full(4, 0.5), 0.7, 0.78, np.full(4, 0.9)]
    w = np.r_[np.full(4, 0.2), np.full(6, 1.53)]
    assert np.median(iou) < CHECK_IOU
    v = judge(PoseEvidence(iou, w, ids))
    assert v.status == "ok" and "the 6 of 10 views whose masks agree with the pose fit it well" in v.reasons[0]
    assert v.set_aside == [0, 1, 2, 3]
    loose = judge(PoseEvidence(np.r_[np.full(4, 0.5), np.full(6, 0.7)], w, ids))  # the views that agree fit loosely too
    assert loose.status == "check" and "loose fit" in loose.reasons[0]
    few = judge(PoseEvidence(np.r_[np.full(6, 0.6), np.full(4, 0.9)], np.r_[np.full(6, 0.4), np.full(4, 1.9)], ids))
    assert few.status == "check" and "loose fit" in few.reasons[0]  # 4 of 10 agree


def test_a_turn_its_profile_widened_stays_weak_in_the_joint_stage():
    """The joint stage keeps the turn floors its instances' profiles found alone (``with_turn_floors``):
    their turns are weakly observed whatever the joint spread says, so a floor of 1.5 deg makes the pose
    nearly symmetric (the SAM-like scene 35's blob, 2.3 deg off with a joint spread under 1 deg)."""
    from autoalign.engine.uncertainty import CovarianceParts, TurnFloor, compose, with_turn_floors

    ids = list(range(10))
    spread = np.diag([0.01, 0.01, 0.01, np.radians(0.5) ** 2, np.radians(0.5) ** 2, np.radians(0.8) ** 2])
    u = compose(CovarianceParts(spread))
    assert u.weak_turn_axes == []
    fit = (np.full(10, 0.95), np.ones(10), ids)
    assert judge(PoseEvidence(*fit, uncertainty=u)).status == "ok"
    floored = with_turn_floors(u, [TurnFloor(np.array([0.0, 0.0, 1.0]), np.radians(1.5) ** 2)])
    assert len(floored.weak_turn_axes) == 1 and np.isclose(floored.sigma_deg[2], 1.5)
    v = judge(PoseEvidence(*fit, uncertainty=floored, turn_gap=2 * NEAR_SYMMETRY_GAP))
    assert v.status == "check" and "nearly symmetric: the turn about model z (1.5 deg)" in v.reasons[-1]
    # a floor about a turn already weak is not named twice
    twice = with_turn_floors(floored, [TurnFloor(np.array([0.0, 0.01, 1.0]) / np.hypot(0.01, 1.0), 0.0)])
    assert len(twice.weak_turn_axes) == 1


@pytest.mark.slow
def test_masks_failing_like_sam_leave_poses_right_or_flagged(tmp_path):
    """A five-object scene whose masks fail at the rates measured on the real scenes (42% of the
    masks: empty, another object's, a part missed, leaking, shifted): every instance is within
    2 mm / 2 deg or its verdict is not ok (here a flashlight 11 deg off in roll is 'check')."""
    from autoalign.experiments.studies.sam_failures import (
        MEASURED_RATES,
        measure_rates,
        run_scene,
        within,
    )
    from autoalign.experiments.studies.shared_data import REAL_SCENES

    real = REAL_SCENES
    if real.is_dir():  # the rates replayed are those of the real scenes
        assert measure_rates(real)[0] == MEASURED_RATES
    rows = run_scene(tmp_path, 3)
    assert sum(r["failures"].get("good", 0) for r in rows[:1]) < 0.7 * 5 * 40  # the masks did fail
    assert sum(within(r) for r in rows) >= 4, rows
    assert all(within(r) or r["verdict"] != "ok" for r in rows), rows


@pytest.mark.slow
def test_masks_failing_like_sam_without_a_seed_leave_poses_right_or_flagged(tmp_path):
    """The same kind of scene with no seed: the search finds every object (5 of 5 within 2 mm /
    2 deg measured), and none is wrong with verdict ok. With 8 hypotheses kept from the
    orientation scores instead of 16 (``RefineOptions.search.n_starts``) one was 180 deg off, 'ok'."""
    from autoalign.experiments.studies.sam_failures import run_scene, within

    rows = run_scene(tmp_path, 104, seeds=("none",))
    assert sum(within(r) for r in rows) >= 4, rows
    assert all(within(r) or r["verdict"] != "ok" for r in rows), rows


@pytest.mark.slow
def test_a_runner_up_with_the_better_iou_makes_the_result_ambiguous(tmp_path):
    """Without a seed, on masks failing like SAM's, a box whose small knob is its only asymmetry
    ends half a turn off, at a robust loss 9% lower than its right pose's, the runner-up, but at a
    lower mean IoU (0.7103 against 0.7130). The loss and the IoU disagreeing, the result is
    ambiguous (it was 'ok')."""
    from autoalign.experiments.studies.sam_failures import make_sam_scene
    from autoalign.io.models import ModelSet

    truth, _, names = make_sam_scene(tmp_path, 7)
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    k = names.index("box_knob")
    mesh = ModelSet.read(tmp_path / "models").mesh(found.instances[k].obj_id)
    res = refine(found.scenes[k], mesh)
    e = pose_errors(res.T_wm, truth[k], mesh.centre, None, Symmetries())
    right = e.pos_err_mm < 2.0 and e.rot_err_deg < 2.0
    runner = pose_errors(res.runner_up.T_final, truth[k], mesh.centre, None, Symmetries())
    assert right or (res.ambiguous and runner.rot_err_deg < 2.0), (e.rot_err_deg, res.ambiguous, runner.rot_err_deg)


@pytest.mark.slow
def test_refine_cameras_corrects_perturbed_cameras(multi, tmp_path):
    """The scene's cameras turned by 1 deg and moved by 5 mm (about the scene centre), each its own
    way: with --refine-cameras the corrected cameras in the written scene_camera.json are several
    times closer to the true ones, the objects closer to the truth than refined alone, every
    position sigma below the verdict's 2 mm, and the median per-view misfit lower."""
    from autoalign.geometry.camera import Camera
    from autoalign.geometry.se3 import rotation_angle_deg, transform_points
    from autoalign.io.bop import read_cameras

    scene = tmp_path / "scene"
    shutil.copytree(multi.scene, scene)
    cams = json.loads((scene / "scene_camera.json").read_text())
    rng = np.random.default_rng(4)
    true_T, bad_T = {}, {}
    for im, c in cams.items():
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.reshape(c["cam_R_w2c"], (3, 3)), c["cam_t_w2c"]
        true_T[int(im)] = T
        bad_T[int(im)] = T @ perturb_pose(np.eye(4), 5.0, 1.0, rng, np.array([0.0, 0.0, 30.0]))
        c["cam_R_w2c"], c["cam_t_w2c"] = bad_T[int(im)][:3, :3].ravel().tolist(), bad_T[int(im)][:3, 3].tolist()
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    init = json.loads(multi.init.read_text())  # the same world poses, seen through the perturbed camera 0
    K0 = np.reshape(cams["0"]["cam_K"], (3, 3))
    cam0_true = Camera.from_opencv(K0, true_T[0][:3, :3], true_T[0][:3, 3], W, H)
    cam0_bad = Camera.from_opencv(K0, bad_T[0][:3, :3], bad_T[0][:3, 3], W, H)
    for e in init["0"]:
        T_cm = np.eye(4)
        T_cm[:3, :3], T_cm[:3, 3] = np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"]
        e["cam_R_m2c"], e["cam_t_m2c"] = pose_in_camera(np.linalg.inv(cam0_true.T_cw) @ T_cm, cam0_bad)
    (tmp_path / "init.json").write_text(json.dumps(init))

    def run(out, *extra):
        p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(scene), "--models",
                            str(multi.models), "--init", str(tmp_path / "init.json"), "--out", str(out), "--quiet",
                            *extra], capture_output=True, text=True, timeout=600)
        assert p.returncode in (0, 3), p.stderr
        return json.loads((out / "refine.json").read_text())

    alone, joint = run(tmp_path / "alone"), run(tmp_path / "joint", "--refine-cameras")
    fixed = read_cameras(tmp_path / "joint")

    def cam_errors(Ts):
        centre = lambda T: -T[:3, :3].T @ T[:3, 3]  # noqa: E731
        return np.median([[np.linalg.norm(centre(Ts[im]) - centre(true_T[im])),
                           rotation_angle_deg(Ts[im][:3, :3], true_T[im][:3, :3])] for im in true_T], axis=0)

    fixed_T = {im: np.vstack([np.column_stack([R, t]), [0, 0, 0, 1]]) for im, (K, R, t) in fixed.items()}
    before, after = cam_errors(bad_T), cam_errors(fixed_T)
    assert after[0] < before[0] / 3 and after[1] < before[1] / 3, (before, after)

    def worst_object_mm(rec):
        return max(float(np.linalg.norm(transform_points(np.asarray(r["pose"]["T_wm"]), c[None]) -
                                        transform_points(multi.truth[r["instance"]], c[None])))
                   for r in rec["instances"] for c in [load_mesh(multi.models / f"obj_{r['obj_id']:06d}.ply").centre])

    assert worst_object_mm(joint) < worst_object_mm(alone)
    # the labels' sigma is relative to the cameras that see them: a view left out by the jackknife
    # no longer drags every object with its unpinned camera (6-15 mm world sigmas, all `check`)
    for r in joint["instances"]:
        assert max(r["uncertainty"]["sigma_mm"]) < 2.0, (r["instance"], r["uncertainty"]["sigma_mm"])
    cam = joint["cameras"]
    assert cam["median_view_misfit_after"] < 0.5 * cam["median_view_misfit_before"]
    # each view's recorded correction is what turned its given camera into the written one
    assert sorted(map(int, cam["per_view"])) == sorted(fixed_T)
    for im, view in cam["per_view"].items():
        assert np.allclose(bad_T[int(im)] @ np.asarray(view["T_correction"]), fixed_T[int(im)], atol=1e-5)
