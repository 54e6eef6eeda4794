"""``autoalign export`` (issue 14): BOP labels for every frame, checked against independent code:
open3d ray casting for the masks (the visible one: the nearest surface of all objects) and the
silhouettes on a canvas three times the image (the bop_toolkit's px_count_all and bbox_obj), and
pycocotools for the boxes, areas and the COCO file.

The scene: three procedural objects, the third placed off to the side so that it is truncated by
the image border in some views and out of view in others, 8 views of 320x240.
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
from pycocotools import mask as coco_mask

from autoalign.experiments.scenes.procedural_models import (
    procedural_models,
    write_models,
)
from autoalign.experiments.scenes.synthetic import (
    default_K,
    random_rotation,
    raycast_masks,
    raycast_visible_masks,
    ring_cameras,
    write_multi_scene,
)
from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_labels
from autoalign.io.export import export_frames
from autoalign.io.models import ModelSet

W, H, VIEWS = 320, 240, 8


class Exported:
    root: Path
    scene: Path
    models: ModelSet
    meshes: list
    truth: list[np.ndarray]
    cams: list[Camera]


@pytest.fixture(scope="module")
def ex(tmp_path_factory) -> Exported:
    d = Exported()
    d.root = tmp_path_factory.mktemp("export")
    write_models(d.root / "models", procedural_models()[:3])
    d.models = ModelSet.read(d.root / "models")
    d.meshes = [d.models.mesh(i) for i in (1, 2, 3)]
    rng = np.random.default_rng(3)
    places = [(-30.0, 0.0), (35.0, 10.0), (280.0, -20.0)]  # the third near the edge of the views
    d.truth = []
    for m, (x, y) in zip(d.meshes, places):
        R = random_rotation(rng)
        d.truth.append(make_pose(R, np.array([x, y, 30.0]) - R @ m.centre))
    d.cams = ring_cameras(VIEWS, rng, dist_range=(380.0, 420.0), target=(0.0, 0.0, 30.0),
                          K=default_K(W, H, 300.0), width=W, height=H, elev_range_deg=(25.0, 40.0))
    d.scene = d.root / "scene"
    write_multi_scene(d.scene, d.meshes, [1, 2, 3], d.truth, d.cams)
    return d


def _canvas_camera(cam: Camera) -> Camera:
    """The same camera on a canvas three times as wide and high, the image in its middle."""
    K = cam.K.copy()
    K[0, 2] += cam.width
    K[1, 2] += cam.height
    return replace(cam, K=K, width=3 * cam.width, height=3 * cam.height)


def _coco_bbox_as_bop(mask: np.ndarray, dx: int = 0, dy: int = 0) -> list[int]:
    """pycocotools' box of ``mask`` (w = x_max - x_min + 1) in the bop_toolkit's convention (w = x_max - x_min)."""
    x, y, w, h = coco_mask.toBbox(coco_mask.encode(np.asfortranarray(mask.astype(np.uint8))))
    return [int(x) - dx, int(y) - dy, int(w) - 1, int(h) - 1]


def test_masks_and_info_match_open3d_and_pycocotools(ex):
    labels = read_labels(ex.scene / "scene_gt.json")
    frames = export_frames(ex.scene, labels, ex.models, ex.scene / "scene_gt.json")
    visible = raycast_visible_masks(ex.meshes, ex.truth, ex.cams)
    dropped = truncated = 0
    for f, cam, vis_ref in zip(frames, ex.cams, visible):
        full_ref = [raycast_masks(m, T, [cam])[0] for m, T in zip(ex.meshes, ex.truth)]
        in_view = [k for k in range(3) if full_ref[k].any()]
        assert [lab.obj_id for lab in f.labels] == [k + 1 for k in in_view]  # out of view: no entry, renumbered
        assert [lab.instance for lab in f.labels] == list(range(len(in_view)))
        dropped += 3 - len(in_view)
        canvas = _canvas_camera(cam)
        for j, k in enumerate(in_view):
            for mine, ref in ((f.masks[j], full_ref[k]), (f.visib[j], vis_ref[k])):
                inter, union = np.count_nonzero(mine & ref), np.count_nonzero(mine | ref)
                assert union == 0 or inter / union >= 0.99, (f.image_id, k, inter / max(union, 1))
            all_ref = raycast_masks(ex.meshes[k], ex.truth[k], [canvas])[0]
            info = f.info[j]
            n_all, n_vis = int(all_ref.sum()), int(vis_ref[k].sum())
            assert abs(info.px_count_all - n_all) <= max(3, 0.005 * n_all)
            assert abs(info.px_count_visib - n_vis) <= max(3, 0.005 * n_vis)
            assert info.px_count_valid == int(f.masks[j].sum())  # no depth: every silhouette pixel counts
            assert abs(info.visib_fract - n_vis / n_all) < 0.01
            truncated += n_all > int(full_ref[k].sum()) + 50
            if n_vis:
                assert np.abs(np.subtract(info.bbox_obj, _coco_bbox_as_bop(all_ref, W, H))).max() <= 1
                assert np.abs(np.subtract(info.bbox_visib, _coco_bbox_as_bop(vis_ref[k]))).max() <= 1
            else:
                assert info.bbox_obj == info.bbox_visib == (-1, -1, -1, -1)
    assert dropped > 0 and truncated > 0  # the scene does exercise both


def test_measured_depth_hides_what_an_unmodelled_occluder_covers(ex, tmp_path):
    """A depth image with a surface 200 mm from the camera over the left third of the image (an
    unmodelled occluder, the objects are ~400 mm away) and no measurement elsewhere: mask_visib
    loses exactly that third; px_count_valid counts the silhouette pixels with a measurement."""
    scene = tmp_path / "scene"
    shutil.copytree(ex.scene, scene)
    (scene / "depth").mkdir()
    depth = np.zeros((H, W), np.uint16)
    depth[:, :W // 3] = 200
    for im in range(VIEWS):
        cv2.imwrite(str(scene / "depth" / f"{im:06d}.png"), depth)
    labels = read_labels(scene / "scene_gt.json")
    plain = export_frames(ex.scene, labels, ex.models, scene / "scene_gt.json")
    deep = export_frames(scene, labels, ex.models, scene / "scene_gt.json")
    left = np.zeros((H, W), bool)
    left[:, :W // 3] = True
    hidden = 0
    for a, b in zip(plain, deep):
        for j in range(len(a.labels)):
            np.testing.assert_array_equal(b.visib[j], a.visib[j] & ~left)
            assert b.info[j].px_count_valid == int((a.masks[j] & left).sum())
            hidden += int((a.visib[j] & left).sum())
    assert hidden > 0


def test_command_writes_a_bop_folder_with_coco(ex, tmp_path):
    out = tmp_path / "bop"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "export", str(ex.scene), "--labels",
                        str(ex.scene / "scene_gt.json"), "--models", str(ex.root / "models"), "--out", str(out),
                        "--coco", "--quiet"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    gt = json.loads((out / "scene_gt.json").read_text())
    info = json.loads((out / "scene_gt_info.json").read_text())
    coco = json.loads((out / "scene_gt_coco.json").read_text())
    assert json.loads((out / "scene_camera.json").read_text()) == json.loads((ex.scene / "scene_camera.json").read_text())
    n_ann = 0
    for im, entries in gt.items():
        assert len(info[im]) == len(entries)
        for k in range(len(entries)):
            vis = cv2.imread(str(out / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            assert (out / "mask" / f"{int(im):06d}_{k:06d}.png").is_file()
            assert int(vis.sum()) == info[im][k]["px_count_visib"]
            anns = [a for a in coco["annotations"] if a["image_id"] == int(im) and a["bop_gt_index"] == k]
            if vis.any():
                (a,) = anns
                rle = dict(a["segmentation"], counts=a["segmentation"]["counts"].encode())
                np.testing.assert_array_equal(coco_mask.decode(rle).astype(bool), vis)
                assert a["category_id"] == entries[k]["obj_id"] and a["area"] == int(vis.sum())
                n_ann += 1
            else:
                assert not anns
        assert not (out / "mask_visib" / f"{int(im):06d}_{len(entries):06d}.png").exists()
    assert n_ann == len(coco["annotations"]) > 0


@pytest.mark.slow
def test_bad_inputs_are_one_line_errors_and_write_nothing(ex, tmp_path):
    def run(scene, labels):
        out = tmp_path / "out"
        p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "export", str(scene), "--labels", str(labels),
                            "--models", str(ex.root / "models"), "--out", str(out), "--quiet"],
                           capture_output=True, text=True, timeout=600)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
        assert not out.exists()
        return p.stderr

    gt = json.loads((ex.scene / "scene_gt.json").read_text())
    gt["0"][1]["obj_id"] = 9
    bad = tmp_path / "labels.json"
    bad.write_text(json.dumps(gt))
    assert "object 9 has no model" in run(ex.scene, bad)
    scene = tmp_path / "scene"
    shutil.copytree(ex.scene, scene)
    (scene / "depth").mkdir()
    cv2.imwrite(str(scene / "depth" / "000003.png"), np.zeros((H // 2, W // 2), np.uint16))
    assert "depth is 160x120 but the image is 320x240" in run(scene, scene / "scene_gt.json")


@pytest.mark.slow
def test_cameras_come_from_beside_the_labels_and_unscaled_ones_are_refused(ex, tmp_path):
    """refine writes the cameras it corrected or scaled beside its scene_gt.json: export takes those;
    a scene whose recon.json says its cameras have no metric scale is not exported with them."""
    scene = tmp_path / "scene"
    shutil.copytree(ex.scene, scene)
    labels = tmp_path / "labels"
    labels.mkdir()
    shutil.copy(scene / "scene_gt.json", labels / "scene_gt.json")
    cams = json.loads((scene / "scene_camera.json").read_text())
    for c in cams.values():  # the scene's own cameras in an unknown unit, refine's in mm
        c["cam_t_w2c"] = (np.asarray(c["cam_t_w2c"]) / 173.0).tolist()
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "recon.json").write_text(json.dumps({"metric": False}))

    def run(*extra):
        return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "export", str(scene), "--labels",
                               str(labels / "scene_gt.json"), "--models", str(ex.root / "models"), "--out",
                               str(tmp_path / "bop"), "--quiet", *extra], capture_output=True, text=True, timeout=600)

    p = run()
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "no metric scale" in p.stderr, p.stderr
    assert not (tmp_path / "bop").exists()
    shutil.copy(ex.scene / "scene_camera.json", labels / "scene_camera.json")
    p = run()
    assert p.returncode == 0, p.stderr
    assert (json.loads((tmp_path / "bop" / "scene_camera.json").read_text())
            == json.loads((ex.scene / "scene_camera.json").read_text()))
    assert json.loads((tmp_path / "bop" / "export.json").read_text())["cameras"] == str((labels / "scene_camera.json").absolute())


def _export(ex: Exported, scene: Path, labels: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "export", str(scene), "--labels", str(labels),
                           "--models", str(ex.root / "models"), "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_an_export_replaces_an_earlier_one_and_has_only_its_images(ex, tmp_path):
    """An export of all 8 images, then one of 4 of them into the same --out: the folder holds
    exactly the second (no mask/, mask_visib/ or rgb/ file of the other 4 beside a smaller
    scene_gt.json), its scene_camera.json the 4 images' cameras, and nothing is left beside it.
    (Before: the old files stayed, exit 0; and a fresh export of 4 of 8 images wrote 8 cameras.)"""
    scene = tmp_path / "scene"
    shutil.copytree(ex.scene, scene)
    (scene / "rgb").mkdir()
    for im in range(VIEWS):
        cv2.imwrite(str(scene / "rgb" / f"{im:06d}.png"), np.zeros((H, W, 3), np.uint8))
    gt = json.loads((scene / "scene_gt.json").read_text())
    half = tmp_path / "half.json"
    half.write_text(json.dumps({k: v for k, v in gt.items() if int(k) % 2 == 0}))
    kept = {0, 2, 4, 6}
    out = tmp_path / "bop"
    p = _export(ex, scene, scene / "scene_gt.json", out)
    assert p.returncode == 0, p.stderr
    assert len(list((out / "rgb").iterdir())) == VIEWS
    assert len(json.loads((out / "scene_camera.json").read_text())) == VIEWS
    p = _export(ex, scene, half, out)
    assert p.returncode == 0, p.stderr
    files = [f.relative_to(out) for f in out.rglob("*") if f.is_file()]
    assert {int(f.name[:6]) for f in files if len(f.parts) == 2} == kept  # mask/, mask_visib/, rgb/
    assert {f.parts[0] for f in files if len(f.parts) == 2} == {"mask", "mask_visib", "rgb"}
    out_gt = json.loads((out / "scene_gt.json").read_text())
    assert {int(k) for k in out_gt} == kept
    assert len([f for f in files if f.parts[0] == "mask_visib"]) == sum(len(v) for v in out_gt.values())
    cams = json.loads((scene / "scene_camera.json").read_text())
    assert json.loads((out / "scene_camera.json").read_text()) == {k: v for k, v in cams.items() if int(k) in kept}
    assert json.loads((out / "export.json").read_text())["images"] == len(kept)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["bop", "half.json", "scene"]  # no temporary folder left


@pytest.mark.slow
def test_an_export_into_a_folder_it_did_not_make_is_refused(ex, tmp_path):
    """A non-empty --out without export.json (not an earlier export): exit 2, one line naming it,
    why and the fix; its files untouched. An earlier export's folder that holds an input (the
    labels) likewise: the export replaces the whole folder."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    p = _export(ex, ex.scene, ex.scene / "scene_gt.json", out)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert f"--out {out}: is not empty and has no export.json" in p.stderr and "new or empty folder" in p.stderr
    assert [f.name for f in out.iterdir()] == ["notes.txt"] and (out / "notes.txt").read_text() == "keep me"
    (out / "notes.txt").unlink()
    (out / "export.json").write_text("{}")
    shutil.copy(ex.scene / "scene_gt.json", out / "labels.json")
    p = _export(ex, ex.scene, out / "labels.json", out)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert f"holds the input {out / 'labels.json'} (--labels)" in p.stderr and "another folder" in p.stderr
    assert sorted(f.name for f in out.iterdir()) == ["export.json", "labels.json"]
