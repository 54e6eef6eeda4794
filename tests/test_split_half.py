"""Precision without ground truth (issue 29, item 2): ``autoalign check --split-half`` and
``autoalign.check(..., split_half=True)``.

* The comparison by hand: two poses a known twist apart give that twist in the model's axes, its
  parts along and across the median view's ray, z per axis and the chi-square from known
  covariances; a failed half or poses far apart are not the same solution.
* A synthetic scene (two procedural objects, an L bracket and a box with a knob, 16 views of
  320x240 on a ring, masks by open3d ray casting): from the true labels the halves agree within
  0.06 mm / 0.1 deg (measured; asserted < 0.5 mm / 0.5 deg); from labels 10 mm / 5 deg off too, and
  both near the truth; with every odd view's masks shifted 4 px to the right the halves end
  1.3-5.8 mm and 1.4-2.2 deg apart (still one solution). In sigma units (the uncertainty of
  a1cd3bd; it is being reworked, so z is asserted only against 3 and the chi-square against its
  99% point): right masks max |z| 1.5, chi-square 7; shifted, the L bracket max |z| 16 and
  chi-square 2000, the box 4.4 and 100.
* ``instances``: only some of the labels' instances are checked, the others' masks left
  unmodelled (the real LM-O scenes, where some objects move between sub-sequences).
* The command: ``--json`` prints the ``split_half`` block, ``--out`` writes it as check.json, the
  table names both verdicts; 5 views of an instance (a half with 2) is one line on stderr naming
  the masks and the fix, exit 2, nothing on stdout and no report folder.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import autoalign
from autoalign.errors import AutoalignError
from autoalign.experiments.scenes.procedural_models import procedural_models, write_models
from autoalign.experiments.scenes.synthetic import (
    default_K,
    perturb_pose,
    random_rotation,
    ring_cameras,
    translate_mask,
    write_multi_scene,
)
from autoalign.geometry.camera import look_at
from autoalign.geometry.mesh import Mesh, load_mesh
from autoalign.geometry.se3 import make_pose, pose_change, so3_exp, transform_points
from autoalign.io.bop import scene_gt_of
from autoalign.quality.split_half import (
    SAME_BASIN_DEG,
    HalfLabel,
    SplitHalfReport,
    compare_halves,
    interleaved_halves,
)

ROOT = Path(__file__).resolve().parents[1]
N_VIEWS, W, H = 16, 320, 240
NAMES = ("l_bracket", "box_knob")
SHIFT_PX = 4
CHI2_6_99 = 16.81
"""The 99th percentile of the chi-square distribution with 6 degrees of freedom."""


class Synthetic:
    root: Path
    scene: Path
    shifted: Path
    models: Path
    off: Path
    truth: list[np.ndarray]
    meshes: list[Mesh]


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> Synthetic:
    d = Synthetic()
    d.root = tmp_path_factory.mktemp("split_half")
    d.models = d.root / "models"
    write_models(d.models, [p for p in procedural_models() if p.name in NAMES])
    d.meshes = [load_mesh(d.models / f"obj_{k:06d}.ply") for k in (1, 2)]
    rng = np.random.default_rng(5)
    d.truth = []
    for k, m in enumerate(d.meshes):  # 110 mm apart: they hide each other in a few views
        R = random_rotation(rng)
        centre = np.array([55.0 * np.cos(np.pi * k), 55.0 * np.sin(np.pi * k), 30.0])
        d.truth.append(make_pose(R, centre - R @ m.centre))
    cams = ring_cameras(N_VIEWS, rng, target=(0, 0, 30.0), K=default_K(W, H, 300.0), width=W, height=H)
    d.scene, d.shifted = d.root / "scene", d.root / "shifted"
    masks = write_multi_scene(d.scene, d.meshes, [1, 2], d.truth, cams)
    off = [perturb_pose(T, 10.0, 5.0, rng, m.centre) for T, m in zip(d.truth, d.meshes)]
    d.off = d.root / "off_gt.json"
    d.off.write_text(json.dumps(scene_gt_of(list(zip([1, 2], off)), cams, list(range(N_VIEWS)))))
    shifted = [[translate_mask(m, SHIFT_PX, 0) if v % 2 else m for m in per_view] for v, per_view in enumerate(masks)]
    write_multi_scene(d.shifted, d.meshes, [1, 2], d.truth, cams, masks=shifted)
    return d


def _errors(d: Synthetic, report: SplitHalfReport) -> list[tuple[float, float, float, float]]:
    """Per instance, half A's and half B's distance from the truth (mm, deg)."""
    return [(*pose_change(T, s.a.T_wm, m.centre), *pose_change(T, s.b.T_wm, m.centre))
            for s, T, m in zip(report.instances, d.truth, d.meshes)]


# ------------------------------------------------------------------------------------------
# The comparison, by hand
# ------------------------------------------------------------------------------------------

def test_interleaved_halves_are_even_and_odd_positions_in_order() -> None:
    assert interleaved_halves([7, 3, 5, 1, 9]) == ([1, 5, 9], [3, 7])


def test_a_known_twist_is_reported_in_model_axes_along_the_ray_and_in_sigmas() -> None:
    """B is A with its centre moved 2 mm along the world x axis (the median view looks along +x)
    and 0.5 mm along world y, and turned 1 degree about the model's z axis; sigmas 0.5 mm and
    0.5 deg per axis in each half."""
    rng = np.random.default_rng(1)
    centre_m = np.array([5.0, -3.0, 10.0])
    A = make_pose(random_rotation(rng), [10.0, 20.0, 400.0])
    c_w = transform_points(A, centre_m[None])[0]
    turn = so3_exp(np.radians([0.0, 0.0, 1.0]))
    R_b = A[:3, :3] @ turn
    B = make_pose(R_b, c_w + [2.0, 0.5, 0.0] - R_b @ centre_m)
    K = default_K(640, 480, 600.0)
    mid = c_w + [1.0, 0.25, 0.0]  # the centre midway between the halves, where the rays point
    cameras = [look_at(mid - [500.0, 0.0, 0.0], mid, K, 640, 480),  # along +x: the median view
               look_at(mid - [400.0, 300.0, 0.0], mid, K, 640, 480),
               look_at(mid - [400.0, -300.0, 0.0], mid, K, 640, 480)]
    cov = np.diag([0.5**2] * 3 + [np.radians(0.5) ** 2] * 3)
    a = HalfLabel([0, 2], A, "ok", [], cov, np.full(3, 0.5), np.full(3, 0.5))
    b = HalfLabel([1], B, "ok", [], cov, np.full(3, 0.5), np.full(3, 0.5))
    s = compare_halves(0, 1, centre_m, 100.0, a, b, cameras, [10, 11, 12])
    assert s.translation_mm == pytest.approx(np.hypot(2.0, 0.5), abs=1e-9)
    assert s.rotation_deg == pytest.approx(1.0, abs=1e-6)
    assert s.median_view == 10
    assert s.along_ray_mm == pytest.approx(2.0, abs=1e-6) and s.across_ray_mm == pytest.approx(0.5, abs=1e-6)
    R_mid = A[:3, :3] @ so3_exp(np.radians([0.0, 0.0, 0.5]))
    expected = np.concatenate([R_mid.T @ [2.0, 0.5, 0.0], np.radians([0.0, 0.0, 1.0])])
    np.testing.assert_allclose(s.twist, expected, atol=1e-9)
    combined = np.sqrt(2.0) * np.array([0.5] * 3 + [np.radians(0.5)] * 3)
    np.testing.assert_allclose(s.z, expected / combined, atol=1e-9)
    assert s.z[5] == pytest.approx(1.0 / (0.5 * np.sqrt(2.0)))
    assert s.mahalanobis_sq == pytest.approx(float(np.sum((expected / combined) ** 2)))
    assert s.along_ray_z == pytest.approx(2.0 / (0.5 * np.sqrt(2.0)))
    assert s.fraction_within == 1.0 and s.same_basin and s.basin_reason == ""
    rec = s.record()
    assert rec["within_3_sigma"] == [True] * 6 and rec["a"]["views"] == 2 and json.dumps(rec)

    # the other way round: the same sizes, opposite signs
    back = compare_halves(0, 1, centre_m, 100.0, b, a, cameras, [10, 11, 12])
    np.testing.assert_allclose(back.twist, -expected, atol=1e-9)
    assert back.along_ray_mm == pytest.approx(-2.0, abs=1e-6)

    # not one solution: a failed half, 10% of the diameter, 10 degrees; no sigmas: no z
    assert not compare_halves(0, 1, centre_m, 100.0, a, HalfLabel([1], B, "failed"), cameras, [10, 11, 12]).same_basin
    far = compare_halves(0, 1, centre_m, 20.0, a, b, cameras, [10, 11, 12])  # 2.06 mm >= 10% of 20 mm
    assert not far.same_basin and "apart" in far.basin_reason
    R_far = A[:3, :3] @ so3_exp(np.radians([SAME_BASIN_DEG + 1.0, 0.0, 0.0]))
    turned = HalfLabel([1], make_pose(R_far, c_w - R_far @ centre_m), "ok")
    none = compare_halves(0, 1, centre_m, 100.0, a, turned, cameras, [10, 11, 12])
    assert not none.same_basin and none.z is None and none.mahalanobis_sq is None and none.record()["z"] is None

    # a symmetric object's halves that differ by its symmetry agree: B half-turned about model x
    S = make_pose(so3_exp([np.pi, 0.0, 0.0]), np.zeros(3))
    flipped = HalfLabel([1], B @ S, "ok", [], cov, np.full(3, 0.5), np.full(3, 0.5))
    assert not compare_halves(0, 1, centre_m, 100.0, a, flipped, cameras, [10, 11, 12]).same_basin
    sym = compare_halves(0, 1, centre_m, 100.0, a, flipped, cameras, [10, 11, 12], ([S], []))
    assert sym.rotation_deg == pytest.approx(1.0, abs=1e-6) and sym.same_basin and sym.symmetric


# ------------------------------------------------------------------------------------------
# The synthetic scene
# ------------------------------------------------------------------------------------------

def test_true_labels_give_halves_that_agree(synthetic: Synthetic) -> None:
    """Measured: 0.05 and 0.04 mm, 0.06 and 0.10 deg apart, |z| <= 1.5."""
    report = autoalign.check(synthetic.scene, synthetic.scene / "scene_gt.json", synthetic.models, split_half=True)
    assert isinstance(report, SplitHalfReport)
    assert report.halves == (list(range(0, N_VIEWS, 2)), list(range(1, N_VIEWS, 2)))
    assert [(s.index, s.obj_id) for s in report.instances] == [(0, 1), (1, 2)]
    for s in report.instances:
        assert s.same_basin and s.a.status != "failed" and s.b.status != "failed"
        assert s.translation_mm < 0.5 and s.rotation_deg < 0.5, (s.translation_mm, s.rotation_deg)
        assert abs(s.along_ray_mm) <= s.translation_mm + 1e-9 and s.across_ray_mm <= s.translation_mm + 1e-9
        assert s.z is not None and np.all(np.isfinite(s.z)) and s.fraction_within == 1.0
        assert set(s.a.image_ids) <= set(report.halves[0]) and set(s.b.image_ids) <= set(report.halves[1])
        assert s.a.sigma_mm is not None and s.b.sigma_deg is not None
    assert report.fraction_within == 1.0


def test_labels_10_mm_off_reach_the_same_solution_from_both_halves(synthetic: Synthetic) -> None:
    """Measured: 0.05 mm and 0.05-0.13 deg apart, each half within 0.05 mm / 0.13 deg of the truth."""
    report = autoalign.check(synthetic.scene, synthetic.off, synthetic.models, split_half=True)
    for s, err in zip(report.instances, _errors(synthetic, report)):
        assert s.same_basin and s.translation_mm < 0.5 and s.rotation_deg < 0.5, (s.translation_mm, s.rotation_deg)
        assert err[0] < 0.5 and err[2] < 0.5 and err[1] < 0.5 and err[3] < 0.5, err


@pytest.mark.slow
def test_a_half_with_shifted_masks_is_far_off_in_sigma_units(synthetic: Synthetic) -> None:
    """Every odd view's masks 4 px to the right: half A (even views) stays on the truth, half B
    moves; measured 5.8 mm / 2.2 deg apart (L bracket, max |z| 16, chi-square 2000) and 1.3 mm /
    1.4 deg (box, max |z| 4.4, chi-square 100)."""
    exact = autoalign.check(synthetic.scene, synthetic.scene / "scene_gt.json", synthetic.models, split_half=True)
    report = autoalign.check(synthetic.shifted, synthetic.shifted / "scene_gt.json", synthetic.models,
                             split_half=True)
    for s, before, err in zip(report.instances, exact.instances, _errors(synthetic, report)):
        assert s.same_basin  # one solution, imprecise
        assert s.translation_mm > 0.8 and s.translation_mm > 10 * before.translation_mm, s.translation_mm
        assert err[0] < 0.5 and err[2] > 0.8, err  # the even half is right, the odd one moved
        assert s.mahalanobis_sq is not None and s.mahalanobis_sq > CHI2_6_99 > before.mahalanobis_sq
        var = np.diag(s.a.covariance + s.b.covariance)
        np.testing.assert_allclose(s.z, s.twist / np.sqrt(var))
    worst = max(report.instances, key=lambda s: s.translation_mm)
    assert worst.translation_mm > 3.0 and np.max(np.abs(worst.z)) > 3.0 and worst.fraction_within < 1.0
    assert report.fraction_within < exact.fraction_within


def test_instances_checks_only_those_and_leaves_the_others_masks_unmodelled(synthetic: Synthetic,
                                                                               tmp_path: Path) -> None:
    """``instances=[1]``: only mask 1 is checked, as ``refine --instances`` refines only some (the
    real LM-O scenes: objects moved between sub-sequences have no one pose). Here the labels list
    mask 0 as an object whose model is not even given, and mask 1 10 mm / 5 deg off: the check
    reads neither model 7 nor mask 0's label and reaches one solution for mask 1. Instances the
    labels do not list, none at all, or instances with the photo check are one-line errors."""
    labels = json.loads(synthetic.off.read_text())
    for entries in labels.values():
        entries[0]["obj_id"] = 7  # no obj_000007.ply in the models
    path = tmp_path / "labels.json"
    path.write_text(json.dumps(labels))
    with pytest.raises(AutoalignError):  # every instance: model 7 is missing
        autoalign.check(synthetic.scene, path, synthetic.models, split_half=True)
    report = autoalign.check(synthetic.scene, path, synthetic.models, split_half=True, instances=[1])
    assert [(s.index, s.obj_id) for s in report.instances] == [(1, 2)]
    s = report.instances[0]
    assert s.same_basin and s.translation_mm < 0.5 and s.rotation_deg < 0.5, (s.translation_mm, s.rotation_deg)
    assert pose_change(synthetic.truth[1], s.a.T_wm, synthetic.meshes[1].centre)[0] < 0.5
    with pytest.raises(AutoalignError, match=r"lists no instance 3 \(it lists 0, 1\)"):
        autoalign.check(synthetic.scene, path, synthetic.models, split_half=True, instances=[1, 3])
    with pytest.raises(AutoalignError, match="none given"):
        autoalign.check(synthetic.scene, path, synthetic.models, split_half=True, instances=[])
    with pytest.raises(AutoalignError, match="only the split-half check"):
        autoalign.check(synthetic.scene, path, synthetic.models, instances=[1])


def test_cli_instances_checks_only_those(synthetic: Synthetic, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """``check --split-half --instances 1``: the labels' mask 0 names a model that is not given, so
    only with the option does the check run, on mask 1 alone; a list that is not one of whole
    numbers, or the option without --split-half, is a one-line error and exit 2."""
    from autoalign.cli.main import main

    labels = json.loads(synthetic.off.read_text())
    for entries in labels.values():
        entries[0]["obj_id"] = 7
    path = tmp_path / "labels.json"
    path.write_text(json.dumps(labels))
    args = ["check", str(synthetic.scene), "--labels", str(path), "--models", str(synthetic.models), "--quiet"]
    assert main([*args, "--split-half", "--instances", "1", "--json"]) == 0
    block = json.loads(capsys.readouterr().out)["split_half"]
    assert [(i["instance"], i["obj_id"]) for i in block["instances"]] == [(1, 2)] and block["instances"][0]["same_basin"]
    for bad, words in ((["--split-half", "--instances", "1,x"], "'x' is not a whole number"),
                       (["--instances", "1"], "--instances: only with --split-half")):
        assert main([*args, *bad]) == 2
        captured = capsys.readouterr()
        assert captured.out == "" and words in captured.err and len(captured.err.strip().splitlines()) == 1, captured.err


# ------------------------------------------------------------------------------------------
# The command
# ------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_cli_split_half_json_table_and_report(synthetic: Synthetic, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    from autoalign.cli.main import main

    labels, out = synthetic.scene / "scene_gt.json", tmp_path / "report"
    args = ["check", str(synthetic.scene), "--labels", str(labels), "--models", str(synthetic.models), "--split-half",
            "--quiet"]
    assert main([*args, "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    block = printed["split_half"]
    assert printed["outputs"] == {"check.json": str(out / "check.json")}
    assert json.loads((out / "check.json").read_text()) == {"split_half": block}
    assert block["halves"] == {"a": list(range(0, N_VIEWS, 2)), "b": list(range(1, N_VIEWS, 2))}
    assert [i["obj_id"] for i in block["instances"]] == [1, 2]
    for i in block["instances"]:
        assert i["same_basin"] and i["translation_mm"] < 0.5 and len(i["z"]) == 6
        assert i["a"]["status"] in ("ok", "check") and i["b"]["status"] in ("ok", "check")
        assert i["fraction_within_3_sigma"] == 1.0 and i["along_ray_mm"] is not None and len(i["a"]["sigma_mm"]) == 3
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "same solution" in text and "sigma A" in text and "views A/B" in text and text.count("yes") == 2


def test_cli_split_half_bad_input_is_one_line_and_exit_2(synthetic: Synthetic, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """5 views of every instance (halves of 3 and 2): exit 2, one line naming mask_visib and the fix,
    nothing on stdout, no --out folder; --images with --split-half is refused too."""
    from autoalign.cli.main import main

    few = tmp_path / "few"
    shutil.copytree(synthetic.scene, few)
    for p in (few / "mask_visib").glob("*.png"):
        if int(p.name.split("_")[0]) >= 5:
            p.unlink()
    out = tmp_path / "report"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "check", str(few), "--labels",
                          str(few / "scene_gt.json"), "--models", str(synthetic.models), "--split-half", "--out",
                          str(out)], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert run.returncode == 2 and run.stdout == "", (run.returncode, run.stdout, run.stderr)
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and str(few / "mask_visib") in lines[0] and "3 and 2" in lines[0], run.stderr
    assert "at least 3" in lines[0] and not out.exists()
    with pytest.raises(AutoalignError, match="at least 3"):
        autoalign.check(few, few / "scene_gt.json", synthetic.models, split_half=True)

    assert main(["check", str(synthetic.scene), "--labels", str(synthetic.scene / "scene_gt.json"), "--models",
                 str(synthetic.models), "--split-half", "--images", "2", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "--images" in captured.err and len(captured.err.strip().splitlines()) == 1
    assert not out.exists()


def test_check_without_split_half_is_the_photo_check() -> None:
    """``autoalign.check`` without ``split_half``: the SIFT / edge check of one image of the example."""
    from autoalign.quality.check_report import CheckReport

    example = ROOT / "autoalign" / "data" / "example"
    stages = []
    report = autoalign.check(example / "scene", example / "scene" / "scene_gt.json", example / "models", images=1,
                             progress=lambda stage, done, total: stages.append((stage, done, total)))
    assert isinstance(report, CheckReport) and report.image_ids == [0] and len(report.instances) == 1
    assert stages[-1] == ("checking images", 1, 1)
