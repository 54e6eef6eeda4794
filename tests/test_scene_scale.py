"""The scene scale of cameras known only up to scale (issue 14: RGB-only captures), solved by
``autoalign refine`` from the objects' known size (:mod:`autoalign.scene.scale`, the 7th parameter
of :func:`autoalign.scene.joint.refine_jointly`).

Scenes: the scene benchmark's (procedural objects, 40 views of 640x480, masks ray-cast by open3d)
with every camera translation divided by a unit that only the test knows.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from autoalign.experiments.benchmarks.bench_scene import make_bench_scene, symmetries
from autoalign.experiments.scenes.synthetic import (
    default_K,
    random_rotation,
    translate_mask,
)
from autoalign.experiments.studies.metrics import pose_errors
from autoalign.geometry.camera import look_at
from autoalign.geometry.se3 import make_pose, transform_points
from autoalign.io.instances import read_instance_scenes, read_instances
from autoalign.io.models import ModelSet
from autoalign.scene.scale import grown_pose, rescaled, scale_from_masks, scaled_cameras

UNIT_MM = 173.0  # mm per unit of the cameras as written


def unscaled_scene(root: Path, n_obj: int, seed: int = 3) -> list[np.ndarray]:
    """A benchmark scene whose cameras' translations are in units of ``UNIT_MM``, with a
    ``recon.json`` that says so; the true world-from-model poses (mm)."""
    truth = make_bench_scene(root, n_obj, seed=seed)
    path = root / "scene" / "scene_camera.json"
    cams = json.loads(path.read_text())
    for c in cams.values():
        c["cam_t_w2c"] = (np.asarray(c["cam_t_w2c"]) / UNIT_MM).tolist()
    path.write_text(json.dumps(cams))
    (root / "scene" / "recon.json").write_text(json.dumps({"metric": False}))
    return truth


def test_scaled_cameras_see_a_grown_scene_as_before():
    """Checked with OpenCV's projection: cameras moved ``f`` times as far from a point see points
    moved ``f`` times as far from it where they saw the originals; ``grown_pose`` moves a model's
    centre that way and keeps its orientation."""
    rng = np.random.default_rng(0)
    K = default_K(640, 480, 600.0)
    cams = {i: look_at(rng.normal(0, 300, 3) + [0, 0, 600], np.zeros(3), K, 640, 480) for i in range(5)}
    X = rng.normal(0, 50, (30, 3))
    about = np.array([10.0, -20.0, 5.0])
    for f in (0.3, 2.5):
        grown = scaled_cameras(cams, f, about)
        for i, c in cams.items():
            before = cv2.projectPoints(X, cv2.Rodrigues(c.R_w2c)[0], c.t_w2c, c.K_opencv, None)[0]
            g = grown[i]
            after = cv2.projectPoints(about + f * (X - about), cv2.Rodrigues(g.R_w2c)[0], g.t_w2c, g.K_opencv, None)[0]
            np.testing.assert_allclose(after, before, atol=1e-6)
            np.testing.assert_allclose(g.R_w2c, c.R_w2c)
        T = make_pose(random_rotation(rng), rng.normal(0, 100, 3))
        centre = np.array([3.0, 4.0, 5.0])
        G = grown_pose(T, centre, f)
        np.testing.assert_allclose(transform_points(G, centre[None]), f * transform_points(T, centre[None]), atol=1e-9)
        np.testing.assert_allclose(G[:3, :3], T[:3, :3])


def test_scale_guess_from_the_masks(tmp_path):
    """Cauchy's mean projected area gives the unit roughly (this scene's object is a 137 x 20 x
    43 mm bar, seen from above more than edge-on: 39% off; seven other seeds' objects: within 11%);
    the model drawn in its true orientation (which needs no scale) gives it within 3% (all eight:
    within 1.7%)."""
    truth = unscaled_scene(tmp_path, 1)
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    models = ModelSet.read(tmp_path / "models")
    rough = scale_from_masks(found, models)
    assert abs(rough.factor / UNIT_MM - 1) < 0.45, rough
    better = scale_from_masks(rescaled(found, rough.factor), models, {0: truth[0][:3, :3]})
    assert abs(rough.factor * better.factor / UNIT_MM - 1) < 0.03, (rough, better)
    assert better.views == 40


def _moved(mask: np.ndarray, shift_px: int = 150) -> np.ndarray:
    """The mask moved ``shift_px`` to the right and down: a segmenter that masked a neighbour."""
    return translate_mask(mask, shift_px, shift_px).astype(mask.dtype)


def test_scale_guess_leaves_out_masks_on_another_object(tmp_path, monkeypatch):
    """A third of the masks on another object: the object's centre, from the rays through the
    masks' centroids, leaves those rays out, and the guess in its true orientation stays within 1%
    (-0.4%); with every ray in the least squares it is 3.1% off. The first guess (no orientation)
    sees the cameras in their own unit: it must leave out the same rays there as in mm."""
    from autoalign.scene import scale as scene_scale

    truth = unscaled_scene(tmp_path, 1)
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    sc = found.scenes[0]
    masks = [_moved(m) if k % 3 == 0 else m for k, m in enumerate(sc.masks)]
    found = replace(found, scenes=[replace(sc, masks=masks)])
    models = ModelSet.read(tmp_path / "models")
    off = {}
    for rule, outlier in (("robust", scene_scale.CENTROID_OUTLIER), ("every ray", None)):
        monkeypatch.setattr(scene_scale, "CENTROID_OUTLIER", outlier)
        in_mm = rescaled(found, UNIT_MM)
        off[rule] = abs(scale_from_masks(in_mm, models, {0: truth[0][:3, :3]}).factor - 1)
        off[f"first guess, {rule}"] = (scale_from_masks(in_mm, models).factor,
                                       scale_from_masks(found, models).factor / UNIT_MM)  # in mm, in the unit
    assert off["robust"] < 0.01 and off["every ray"] > 0.02, off
    mm, unit = off["first guess, robust"]
    assert abs(unit / mm - 1) < 1e-6, off
    assert abs(mm / off["first guess, every ray"][0] - 1) > 1e-3, off  # the same rays left out in both


def test_scale_guess_leaves_out_where_another_object_may_hide_it(tmp_path):
    """Three objects that hide each other in some views, at the true scale and orientations: the guess
    compares the rendered silhouette with the mask only where no other instance's mask lies (measured
    1.010); counting the hidden pixels too, every occluded view grew it (1.140)."""
    truth = unscaled_scene(tmp_path, 3, seed=3)
    found = rescaled(read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene")), UNIT_MM)
    models = ModelSet.read(tmp_path / "models")
    rotations = {k: T[:3, :3] for k, T in enumerate(truth)}
    assert all(sc.ignore is not None and any(g.any() for g in sc.ignore) for sc in found.scenes)  # they do hide
    guess = scale_from_masks(found, models, rotations)
    blind = scale_from_masks(replace(found, scenes=[replace(sc, ignore=None) for sc in found.scenes]), models,
                             rotations)
    assert abs(guess.factor - 1) < 0.02 and blind.factor > 1.1, (guess, blind)


def test_scale_guess_from_the_instances_asked(tmp_path):
    """``use`` leaves instances out of the guess: the one whose masks are all another object's
    (as the real egg box's) pulls the guess from both; alone, the other gives it within 3%."""
    truth = unscaled_scene(tmp_path, 2, seed=5)
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    bad = found.scenes[1]
    found = rescaled(replace(found, scenes=[found.scenes[0], replace(bad, masks=[_moved(m, 60) for m in bad.masks])]),
                     UNIT_MM)
    models = ModelSet.read(tmp_path / "models")
    rotations = {0: truth[0][:3, :3], 1: truth[1][:3, :3]}
    both = scale_from_masks(found, models, rotations)
    good = scale_from_masks(found, models, rotations, use=[True, False])
    assert abs(good.factor - 1) < 0.03 and good.views == 40, good
    assert abs(both.factor - 1) > 2 * abs(good.factor - 1), (both, good)  # -5.5% against +1.7%


def run_refine(root: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(root / "scene"), "--models",
                           str(root / "models"), "--out", str(root / "out"), "--quiet", *extra],
                          capture_output=True, text=True)


def check_labels(root: Path, truth: list[np.ndarray], mm: float = 1.0, deg: float = 1.0) -> dict:
    """The refined scene's scale, metric cameras and labels against the truth; refine.json."""
    rec = json.loads((root / "out" / "refine.json").read_text())
    assert abs(rec["scale"]["mm_per_unit"] / UNIT_MM - 1) < 0.005, rec["scale"]
    written = json.loads((root / "out" / "scene_camera.json").read_text())
    given = json.loads((root / "scene" / "scene_camera.json").read_text())
    for im, c in written.items():  # the cameras written are in mm, orientation kept
        np.testing.assert_allclose(c["cam_t_w2c"], np.asarray(given[im]["cam_t_w2c"]) * UNIT_MM, rtol=0.005, atol=1.0)
        np.testing.assert_allclose(c["cam_R_w2c"], given[im]["cam_R_w2c"], atol=1e-9)
    models = ModelSet.read(root / "models")
    gt = json.loads((root / "out" / "scene_gt.json").read_text())
    for im, entries in gt.items():  # the labels, in each camera's frame, mm
        c = given[im]
        T_cw = make_pose(np.reshape(c["cam_R_w2c"], (3, 3)), np.asarray(c["cam_t_w2c"]) * UNIT_MM)
        for k, e in enumerate(entries):
            est = make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"])
            err = pose_errors(est, T_cw @ truth[k], models.mesh(e["obj_id"]).centre, None, symmetries(models, e["obj_id"]))
            assert err.pos_err_mm < mm and err.rot_err_deg < deg, (im, k, err)
    return rec


@pytest.mark.slow
def test_refine_solves_the_scale_of_one_object_scene_from_init(tmp_path):
    """recon.json says the cameras are not metric: refine solves the scale by itself, within 0.5%,
    writes metric cameras, and the labels are within 1 mm / 1 deg in every view."""
    truth = unscaled_scene(tmp_path, 1)
    proc = run_refine(tmp_path, "--init", str(tmp_path / "init_gt.json"))
    assert proc.returncode == 0, proc.stderr
    assert "no metric scale" in proc.stderr
    rec = check_labels(tmp_path, truth)
    assert rec["instances"][0]["verdict"] == "ok"
    assert rec["scale"]["sigma_relative"] < 0.01


@pytest.mark.slow
def test_refine_solves_the_scale_without_a_seed(tmp_path):
    """Two objects, no --init, --solve-scale given explicitly (no recon.json)."""
    truth = unscaled_scene(tmp_path, 2, seed=5)
    (tmp_path / "scene" / "recon.json").unlink()
    proc = run_refine(tmp_path, "--solve-scale")
    assert proc.returncode == 0, proc.stderr
    rec = check_labels(tmp_path, truth)
    assert [r["verdict"] for r in rec["instances"]] == ["ok", "ok"]


def test_solve_scale_needs_models(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(tmp_path), "--model",
                           str(tmp_path / "m.ply"), "--out", str(tmp_path / "out"), "--solve-scale"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "--solve-scale needs --models" in proc.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_scale_that_does_not_settle_flags_every_instance(tmp_path, monkeypatch):
    """With one round allowed, a scene started 10% off cannot settle (the joint stage moves the
    scale by more than SCALE_SETTLED): every label's depth follows the scale, so every instance is
    flagged; with the default rounds the same start settles and stays ok."""
    from autoalign.io.instances import read_init_poses
    from autoalign.scene import refine as scene_refine

    unscaled_scene(tmp_path, 1)
    found = read_instance_scenes(tmp_path / "scene", read_instances(tmp_path / "scene"))
    found = rescaled(found, UNIT_MM * 1.1)
    models = ModelSet.read(tmp_path / "models")
    seeds = read_init_poses(tmp_path / "init_gt.json", found)
    done = scene_refine.refine_scene(found, models, seeds, solve_scale=True)
    assert done.scale_settled and abs(done.scale * 1.1 - 1) < 0.005 and done.results[0].verdict.status == "ok"
    monkeypatch.setattr(scene_refine, "SCALE_ROUNDS", 1)
    undone = scene_refine.refine_scene(found, models, seeds, solve_scale=True)
    assert not undone.scale_settled
    assert undone.results[0].verdict.status in ("check", "failed")
    assert any("scale did not settle" in r for r in undone.results[0].verdict.reasons)


EXAMPLE = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"


@pytest.mark.slow
@pytest.mark.parametrize("true_scale,photos", [(1.0, "on"), (1.0, "off"), (0.97, "on")])
def test_the_bundled_example_gives_its_scale_with_photos_on_and_off(tmp_path, true_scale, photos):
    """The bundled example (masks and photos) with its cameras' translations written in a unit of
    ``true_scale`` mm: ``--solve-scale`` gives that scale within 0.002, and every label within 1 mm /
    1 deg of the truth. With the photos the scale came out 0.9879 +- 0.0005 for 1, every label 6.5 mm
    off and ``ok``: the fused targets grew every outline (tests/test_photo_fusion.py). With the photos
    the result reports their evidence: a second round of the scale once took the first one's colour
    targets for the masks, and the photos were then neither used nor reported."""
    scene = tmp_path / "scene"
    shutil.copytree(EXAMPLE / "scene", scene)
    cams = json.loads((scene / "scene_camera.json").read_text())
    for c in cams.values():
        c["cam_t_w2c"] = (np.asarray(c["cam_t_w2c"]) / true_scale).tolist()
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(scene), "--models",
                           str(EXAMPLE / "models"), "--init", str(EXAMPLE / "init_gt.json"), "--solve-scale",
                           "--photos", photos, "--out", str(out), "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rec = json.loads((out / "refine.json").read_text())
    assert abs(rec["scale"]["mm_per_unit"] - true_scale) < 0.002, rec["scale"]
    assert rec["instances"][0]["verdict"] == "ok"
    assert ("photo" in rec["instances"][0]) == (photos == "on"), sorted(rec["instances"][0])
    models = ModelSet.read(EXAMPLE / "models")
    truth = json.loads((EXAMPLE / "scene" / "scene_gt.json").read_text())
    for im, entries in json.loads((out / "scene_gt.json").read_text()).items():
        est, gt = (make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"]) for e in (entries[0], truth[im][0]))
        err = pose_errors(est, gt, models.mesh(1).centre, None, symmetries(models, 1))
        assert err.pos_err_mm < 1.0 and err.rot_err_deg < 1.0, (im, err)


@pytest.mark.slow
def test_objects_that_disagree_on_the_scale_are_never_ok(tmp_path):
    """Two objects whose masks disagree on the scene's scale by 4% (the second model file 4% smaller
    than the object its masks show): the scale solved between them puts every label mm off, and no
    view left out shows it. Each object's say left out in turn moves the scale by 1.8%: both labels
    are ``check``, with that reason; the same scene with the right model stays ``ok``."""
    import trimesh

    unscaled_scene(tmp_path, 2, seed=5)
    (tmp_path / "scene" / "recon.json").unlink()
    path = tmp_path / "models" / "obj_000002.ply"
    mesh = trimesh.load(path)
    mesh.apply_scale(0.96)
    mesh.export(path)
    info = json.loads((tmp_path / "models" / "models_info.json").read_text())
    info["2"] = {k: v * 0.96 if k in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z") else v
                 for k, v in info["2"].items()}
    (tmp_path / "models" / "models_info.json").write_text(json.dumps(info))
    proc = run_refine(tmp_path, "--solve-scale")
    assert proc.returncode == 3, proc.stderr
    rec = json.loads((tmp_path / "out" / "refine.json").read_text())
    assert abs(rec["scale"]["mm_per_unit"] / UNIT_MM - 1) > 0.005  # the scale is wrong ...
    for r in rec["instances"]:  # ... and no label says otherwise
        assert r["verdict"] != "ok" and any("disagree on the scene's scale" in x for x in r["reasons"]), r


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 1], ids=["models-that-all-fit", "masks-guess-too-large"])
def test_right_models_settle_the_scale_and_every_label_is_ok(tmp_path, seed):
    """Three right models settle the scale within 0.5%, and every label is within 1 mm / 1 deg and
    ``ok``.

    Seed 2: the models still disagree on the scale by a few parts in 10^4 (the views' spread is smaller
    still), which moves no label by more than a fraction of a mm, so none is flagged for it (each was
    ``check``, "the objects disagree on the scene's scale", when any disagreement beyond the views'
    spread flagged every label). Seed 1: the masks guess the scale 3.3% too large at the orientations
    found; re-guessed after the joint stage had solved it, the guess undid it in every round, the scale
    "did not settle" and every label was ``check``. It is now trusted once solved from instances that
    fit alone."""
    truth = unscaled_scene(tmp_path, 3, seed=seed)
    proc = run_refine(tmp_path, "--init", str(tmp_path / "init_gt.json"))
    assert proc.returncode == 0, proc.stderr
    rec = check_labels(tmp_path, truth)
    assert rec["scale"]["settled"]
    assert [r["verdict"] for r in rec["instances"]] == ["ok"] * 3, [r["reasons"] for r in rec["instances"]]


@pytest.mark.slow
def test_the_scene_refined_with_photos_keeps_the_instances_own_masks():
    """What ``refine --models`` draws as each instance's mask (overlay.png's tint) is its mask as read,
    not the colour targets the photos made of it (which showed speckles the mask does not have)."""
    from autoalign.io.evidence import instance_scenes_with_photos
    from autoalign.io.instances import read_init_poses
    from autoalign.scene.refine import refine_scene

    found = instance_scenes_with_photos(read_instance_scenes(EXAMPLE / "scene", read_instances(EXAMPLE / "scene")))
    models = ModelSet.read(EXAMPLE / "models")
    refined = refine_scene(found, models, read_init_poses(EXAMPLE / "init_gt.json", found), solve_scale=True)
    for given, kept in zip(found.scenes, refined.found.scenes):
        assert all(np.array_equal(a, b) for a, b in zip(given.masks, kept.masks))
