"""Tests of the ``autoalign`` command line: one-line errors for user mistakes, help, outputs, start-up.

A small synthetic scene (12 views, 320x240, fx = fy = 300, an asymmetric procedural bracket) is
ray-cast once per session with open3d; the bad inputs are variants of it.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from autoalign.cli.main import OUTPUT_FILES, main
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import (
    default_K,
    perturb_pose,
    random_rotation,
    sphere_cameras,
    translate_mask,
    write_synthetic_scene,
)
from autoalign.geometry.mesh import load_mesh
from autoalign.geometry.se3 import make_pose, rotation_angle_deg
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import scene_gt_dict

N_VIEWS, W, H, F = 12, 320, 240, 300.0
ERROR_PREFIX = "autoalign: error:"


# --------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------

class Data:
    """Paths of the session's synthetic scene and its true pose."""

    root: Path
    scene: Path
    model: Path
    init: Path
    T_true: np.ndarray
    T_init: np.ndarray


@pytest.fixture(scope="session")
def data(tmp_path_factory) -> Data:
    root = tmp_path_factory.mktemp("cli")
    pm = next(m for m in procedural_models() if m.name == "l_bracket")
    assert pm.symmetry == "none"
    d = Data()
    d.root = root
    d.model = root / "obj_000001.ply"
    pm.mesh.export(str(d.model))
    mesh = load_mesh(d.model)
    rng = np.random.default_rng(7)
    d.T_true = make_pose(random_rotation(rng), [4.0, -3.0, 2.0])
    cams = sphere_cameras(N_VIEWS, rng, dist_range=(350.0, 500.0), K=default_K(W, H, F), width=W, height=H)
    d.scene = root / "scene"
    write_synthetic_scene(d.scene, mesh, d.T_true, cams)
    d.T_init = perturb_pose(d.T_true, 5.0, 10.0, rng, centre=mesh.centre)
    d.init = root / "coarse_scene_gt.json"
    write_json_atomic(d.init, scene_gt_dict(d.T_init, cams, list(range(N_VIEWS))))
    return d


def _copy_scene(data: Data, tmp_path: Path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(data.scene, dst)
    return dst


def _mask(scene: Path, im: int) -> Path:
    return scene / "mask_visib" / f"{im:06d}_000000.png"


def _no_outputs(out: Path) -> bool:
    return not any((out / name).exists() for name in OUTPUT_FILES) and not (
        out.is_dir() and any(p.name.endswith(".tmp") for p in out.iterdir()))


# --------------------------------------------------------------------------------------------
# Bad inputs: exit code 2, one line naming the file/option, no traceback, no outputs
# --------------------------------------------------------------------------------------------

def _bad_scene_camera_missing(d, tmp):
    s = _copy_scene(d, tmp)
    (s / "scene_camera.json").unlink()
    return {"scene": s}, "scene_camera.json"


def _bad_camera_without_R(d, tmp):
    s = _copy_scene(d, tmp)
    cams = json.loads((s / "scene_camera.json").read_text())
    del cams["3"]["cam_R_w2c"]
    (s / "scene_camera.json").write_text(json.dumps(cams))
    return {"scene": s}, "cam_R_w2c"


def _bad_mask_size(d, tmp):
    s = _copy_scene(d, tmp)
    m = cv2.imread(str(_mask(s, 5)), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(_mask(s, 5)), cv2.resize(m, (W // 2, H // 2)))
    return {"scene": s}, "000005_000000.png"


def _bad_masks_all_empty(d, tmp):
    s = _copy_scene(d, tmp)
    for im in range(N_VIEWS):
        cv2.imwrite(str(_mask(s, im)), np.zeros((H, W), np.uint8))
    return {"scene": s}, "mask_visib"


def _bad_scene_dir_missing(d, tmp):
    return {"scene": tmp / "no_such_scene"}, "no_such_scene"


def _bad_mesh_missing(d, tmp):
    return {"model": tmp / "missing.ply"}, "missing.ply"


def _bad_mesh_garbage(d, tmp):
    p = tmp / "garbage.ply"
    p.write_bytes(b"\x00\x01 this is not a mesh \xff" * 20)
    return {"model": p}, "garbage.ply"


def _bad_mesh_vertices_only(d, tmp):
    p = tmp / "points.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "end_header\n0 0 0\n10 0 0\n0 10 0\n")
    return {"model": p}, "points.ply"


def _bad_mesh_zero_faces(d, tmp):
    p = tmp / "nofaces.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 0\n")
    return {"model": p}, "nofaces.ply"


def _bad_mesh_empty_file(d, tmp):
    p = tmp / "empty.obj"
    p.write_text("")
    return {"model": p}, "empty.obj"


def _bad_click_outside(d, tmp):
    return {"seed": ["--click", f"0:{W + 5},10"]}, "--click"


def _bad_click_off_masks(d, tmp):
    return {"seed": ["--click", "0:1.5,1.5"]}, "--click"


def _bad_click_syntax(d, tmp):
    return {"seed": ["--click", "0-12-14"]}, "--click"


def _bad_click_unknown_image(d, tmp):
    return {"seed": ["--click", "99:100,100"]}, "image 99 is not a view of the scene"


def _bad_click_in_view_with_empty_mask(d, tmp):
    """The mask of the clicked view is empty: said so, not that the image is no view of the scene."""
    s = _copy_scene(d, tmp)
    cv2.imwrite(str(_mask(s, 3)), np.zeros((H, W), np.uint8))
    return {"scene": s, "seed": ["--click", "3:160,120"]}, "mask in image 3 is empty"


def _bad_click_in_view_without_mask_file(d, tmp):
    s = _copy_scene(d, tmp)
    _mask(s, 4).unlink()
    return {"scene": s, "seed": ["--click", "4:160,120"]}, "image 4 has no mask file"


def _write_init(tmp, content) -> Path:
    p = tmp / "init_gt.json"
    p.write_text(json.dumps(content) if not isinstance(content, str) else content)
    return p


def _bad_init_list(d, tmp):
    return {"seed": ["--init", str(_write_init(tmp, [1, 2, 3]))]}, "init_gt.json"


def _bad_init_no_t(d, tmp):
    gt = json.loads(d.init.read_text())
    for v in gt.values():
        del v[0]["cam_t_m2c"]
    return {"seed": ["--init", str(_write_init(tmp, gt))]}, "init_gt.json"


def _bad_init_8_numbers(d, tmp):
    gt = json.loads(d.init.read_text())
    for v in gt.values():
        v[0]["cam_R_m2c"] = v[0]["cam_R_m2c"][:8]
    return {"seed": ["--init", str(_write_init(tmp, gt))]}, "init_gt.json"


def _bad_init_not_json(d, tmp):
    return {"seed": ["--init", str(_write_init(tmp, "{not json"))]}, "init_gt.json"


def _bad_init_missing(d, tmp):
    return {"seed": ["--init", str(tmp / "nope_gt.json")]}, "nope_gt.json"


def _bad_out_is_file(d, tmp):
    out = tmp / "out_file"
    out.write_text("I am a file")
    return {"out": out}, "--out"


def _bad_out_parent_is_file(d, tmp):
    parent = tmp / "regular_file"
    parent.write_text("I am a file")
    return {"out": parent / "sub" / "out"}, "--out"


def _bad_init_and_click(d, tmp):
    return {"seed": ["--init", str(d.init), "--click", "0:160,120"]}, "--click"


def _bad_loss(d, tmp):
    return {"seed": ["--loss", "l3"]}, "--loss"


def _bad_optimizer(d, tmp):
    return {"seed": ["--optimizer", "sgd"]}, "--optimizer"


def _bad_instance(d, tmp):
    return {"seed": ["--instance", "-1"]}, "--instance"


def _bad_missing_model(d, tmp):
    return {"model": None}, "--model"


def _bad_missing_instance_masks(d, tmp):
    return {"seed": ["--instance", "3"]}, "--instance"


def _set_fx(d, tmp, fx):
    s = _copy_scene(d, tmp)
    cams = json.loads((s / "scene_camera.json").read_text())
    cams["4"]["cam_K"][0] = fx
    (s / "scene_camera.json").write_text(json.dumps(cams))
    return {"scene": s}, "cam_K"


def _bad_focal_negative(d, tmp):
    return _set_fx(d, tmp, -300.0)


def _bad_focal_zero(d, tmp):
    return _set_fx(d, tmp, 0.0)


def _bad_mask_without_camera(d, tmp):
    s = _copy_scene(d, tmp)
    shutil.copy(_mask(s, 2), _mask(s, 99))
    return {"scene": s}, "000099_000000.png"


def _bad_masks_of_mixed_kinds(d, tmp):
    s = _copy_scene(d, tmp)
    m = cv2.imread(str(_mask(s, 3)), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(_mask(s, 3)), (m > 0).astype(np.uint8))  # 0/1 among 0/255 masks
    return {"scene": s}, "000003_000000.png"


def _bad_mesh_in_metres(d, tmp):
    p = tmp / "metres.ply"
    tm = procedural_models()[0].mesh.copy()
    tm.apply_scale(0.001)
    tm.export(str(p))
    return {"model": p}, "--units m"


def _bad_units(d, tmp):
    return {"seed": ["--init", str(d.init), "--units", "cm"]}, "--units"


def _bad_models_folder_missing(d, tmp):
    return {"model": None, "seed": ["--models", str(tmp / "no_models"), "--init", str(d.init)]}, "no_models"


def _bad_models_folder_lacks_the_object(d, tmp):
    (tmp / "models").mkdir()
    return {"model": None, "seed": ["--models", str(tmp / "models"), "--init", str(d.init)]}, "obj_000001.ply"


def _bad_instances_without_models(d, tmp):
    f = tmp / "instances.json"
    f.write_text('{"instances": {"0": 1}}')
    return {"seed": ["--init", str(d.init), "--instances", str(f)]}, "--instances"


def _bad_click_with_models(d, tmp):
    return {"model": None, "seed": ["--models", str(d.root), "--click", "0:160,120"]}, "--click"


def _bad_instances_file_malformed(d, tmp):
    f = tmp / "instances.json"
    f.write_text('{"instances": ["obj 1"]}')
    return {"model": None, "seed": ["--models", str(d.root), "--instances", str(f)]}, "instances.json"


BAD_INPUTS = {name[5:]: fn for name, fn in dict(globals()).items() if name.startswith("_bad_")}


def _argv(data: Data, tmp: Path, spec: dict) -> tuple[list[str], Path]:
    out = spec.get("out", tmp / "out")
    argv = ["refine", str(spec.get("scene", data.scene)), "--out", str(out)]
    model = spec.get("model", data.model)
    if model is not None:
        argv += ["--model", str(model)]
    argv += spec.get("seed", ["--init", str(data.init)])
    return argv, Path(out)


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_gives_one_line_error(case, data, tmp_path, capsys):
    spec, token = BAD_INPUTS[case](data, tmp_path)
    argv, out = _argv(data, tmp_path, spec)
    rc = main(argv)
    cap = capsys.readouterr()
    lines = cap.err.splitlines()
    assert rc == 2, cap.err
    assert len(lines) == 1, cap.err
    assert lines[0].startswith(ERROR_PREFIX)
    assert token in lines[0], lines[0]
    assert "Traceback" not in cap.err
    assert cap.out == ""
    assert _no_outputs(out)
    if case != "out_is_file":
        assert not out.exists(), "a folder created for a failed run should be removed"


@pytest.mark.slow
@pytest.mark.parametrize("case", ["scene_camera_missing", "mesh_garbage", "init_and_click"])
def test_bad_input_subprocess(case, data, tmp_path):
    """The same in a real process: exit status 2 and exactly one line on stderr."""
    spec, token = BAD_INPUTS[case](data, tmp_path)
    argv, out = _argv(data, tmp_path, spec)
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", *argv], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(ERROR_PREFIX) and token in lines[0], p.stderr
    assert p.stdout == ""
    assert _no_outputs(out) and not out.exists()


def test_no_command_is_an_error(capsys):
    assert main([]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(ERROR_PREFIX)


def test_internal_error_keeps_traceback_and_leaves_nothing(data, tmp_path, monkeypatch):
    """A bug (not a user mistake) propagates as an exception; the run's outputs and folder are removed."""
    import autoalign.engine.refine

    def broken(*args, **kwargs):
        raise RuntimeError("engine bug")

    monkeypatch.setattr(autoalign.engine.refine, "refine", broken)
    out = tmp_path / "a" / "out"
    with pytest.raises(RuntimeError, match="engine bug"):
        main(["refine", str(data.scene), "--model", str(data.model), "--out", str(out), "--init", str(data.init),
              "--quiet"])
    assert not (tmp_path / "a").exists()


# --------------------------------------------------------------------------------------------
# Help, version, start-up
# --------------------------------------------------------------------------------------------

REFINE_OPTIONS = ["SCENE_DIR", "--model", "--out", "--obj-id", "--instance", "--init", "--click", "--loss",
                  "--optimizer", "--no-robust", "--quiet", "--json", "--units"]


def test_help_mentions_every_option(capsys):
    assert main(["refine", "--help"]) == 0
    text = capsys.readouterr().out
    for opt in REFINE_OPTIONS:
        assert opt in text, opt
    flowing = " ".join(text.split())  # phrases may wrap across lines
    for word in ("mm", "scene_gt.json", "refine.json", "overlay.png", "cam_R_m2c", "cam_t_m2c",
                 "top-left pixel's centre is 0,0", "default", "l2", "bce", "iou", "dice", "lm", "gn", "adam"):
        assert word in flowing, word
    assert main(["--help"]) == 0
    assert "refine" in capsys.readouterr().out


def test_version(capsys):
    import autoalign

    assert main(["--version"]) == 0
    assert autoalign.__version__ in capsys.readouterr().out


def test_startup_imports_no_heavy_modules():
    code = (
        "import contextlib, io, json, sys\n"
        "import autoalign.cli.main as m\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    rcs = [m.main(['--help']), m.main(['refine', '--help'])]\n"
        "heavy = sorted(k for k in sys.modules if k.split('.')[0] in ('torch', 'jax', 'jaxlib', 'mitsuba', 'drjit')\n"
        "               or k in ('autoalign.engine.refine', 'autoalign.rasterizers.soft_silhouette'))\n"
        "print(json.dumps({'rcs': rcs, 'heavy': heavy}))\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res == {"rcs": [0, 0], "heavy": []}


def test_simulate_subcommand_registered_when_available(monkeypatch, capsys):
    import types

    import autoalign.experiments

    fake = types.ModuleType("autoalign.experiments.studies.simulate")

    def add_simulate_parser(subparsers):
        p = subparsers.add_parser("simulate", help="fake simulate")
        p.add_argument("--n", type=int, default=1)
        p.set_defaults(func=lambda args: 0 if args.n == 3 else 1)

    fake.add_simulate_parser = add_simulate_parser
    monkeypatch.setitem(sys.modules, "autoalign.experiments.studies.simulate", fake)
    monkeypatch.setattr(autoalign.experiments, "simulate", fake, raising=False)
    assert main(["simulate", "--n", "3"]) == 0
    assert main(["simulate", "--n", "x"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(ERROR_PREFIX) and "--n" in err[0]


# --------------------------------------------------------------------------------------------
# Successful runs
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def json_run(data):
    """One real ``autoalign refine --init ... --json`` run (progress bar on stderr)."""
    out = data.root / "out_json"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(data.scene), "--model",
                        str(data.model), "--out", str(out), "--init", str(data.init), "--json"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    return p, out


@pytest.mark.slow
def test_refine_writes_valid_scene_gt(json_run, data):
    _, out = json_run
    gt = json.loads((out / "scene_gt.json").read_text())
    true = json.loads((data.scene / "scene_gt.json").read_text())
    assert sorted(gt, key=int) == [str(i) for i in range(N_VIEWS)]
    for im, entries in gt.items():
        assert len(entries) == 1
        e = entries[0]
        assert e["obj_id"] == 1
        R = np.array(e["cam_R_m2c"], dtype=float).reshape(3, 3)
        t = np.array(e["cam_t_m2c"], dtype=float)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
        R0 = np.array(true[im][0]["cam_R_m2c"]).reshape(3, 3)
        t0 = np.array(true[im][0]["cam_t_m2c"])
        assert rotation_angle_deg(R, R0) < 1.0
        assert np.linalg.norm(t - t0) < 1.0


def test_refine_json_report(json_run, data):
    _, out = json_run
    r = json.loads((out / "refine.json").read_text())
    for key in ("autoalign_version", "pose", "pose_before", "seed", "image_ids", "iou_before", "iou_after",
                "weights", "iterations", "renders", "timings", "hypotheses", "ambiguous", "runner_up", "options",
                "skipped", "mean_iou_before", "mean_iou_after", "low_weight_ids"):
        assert key in r, key
    T = np.array(r["pose"]["T_wm"])
    assert T.shape == (4, 4)
    assert np.allclose(np.array(r["pose"]["R"]).reshape(3, 3), T[:3, :3])
    assert np.allclose(r["pose"]["t"], T[:3, 3])
    assert np.linalg.norm(T[:3, 3] - data.T_true[:3, 3]) < 1.0
    assert rotation_angle_deg(T[:3, :3], data.T_true[:3, :3]) < 1.0
    assert np.allclose(r["pose_before"]["T_wm"], data.T_init, atol=1e-6)
    assert r["seed"]["kind"] == "init"
    assert r["image_ids"] == list(range(N_VIEWS))
    assert len(r["iou_before"]) == len(r["iou_after"]) == len(r["weights"]) == N_VIEWS
    assert min(r["iou_after"]) > 0.97 and r["mean_iou_after"] > r["mean_iou_before"]
    assert r["ambiguous"] is False and r["skipped"] == [] and r["low_weight_ids"] == []
    assert r["iterations"] > 0 and r["renders"] > 0 and r["timings"]["total"] > 0
    assert len(r["hypotheses"]) >= 1
    h = r["hypotheses"][0]
    assert {"stage", "loss", "mean_iou", "pose", "pose_init"} <= set(h)
    assert np.allclose(h["pose"]["T_wm"], T)
    assert r["options"]["loss"] == "l2" and r["options"]["optimizer"]["name"] == "lm" and r["options"]["robust"] is True
    import autoalign

    assert r["autoalign_version"] == autoalign.__version__


def test_overlay_png(json_run):
    from autoalign.quality.overlay import GAP, LEGEND_H, TILE_H, TILE_W

    _, out = json_run
    img = cv2.imread(str(out / "overlay.png"), cv2.IMREAD_COLOR)
    assert img is not None
    assert img.shape == (LEGEND_H + 3 * TILE_H + 4 * GAP, 4 * TILE_W + 5 * GAP, 3)
    # red (before) and green (after) outlines are drawn
    b, g, r = (img[..., c].astype(int) for c in range(3))
    assert ((r > 180) & (g < 100) & (b < 100)).sum() > 500
    assert ((g > 150) & (r < 100) & (b < 100)).sum() > 500


def test_json_stdout(json_run):
    p, out = json_run
    lines = p.stdout.splitlines()
    assert len(lines) == 1
    s = json.loads(lines[0])
    assert s["mean_iou_after"] > s["mean_iou_before"]
    assert s["ambiguous"] is False and s["time_s"] > 0
    assert np.array(s["pose"]["T_wm"]).shape == (4, 4)
    for key, name in (("scene_gt", "scene_gt.json"), ("refine", "refine.json"), ("overlay", "overlay.png")):
        assert Path(s["outputs"][key]) == (out / name).absolute()
    assert not [q for q in out.iterdir() if q.name.endswith(".tmp")]


def test_human_summary_and_skipped_view(data, tmp_path, capsys):
    scene = _copy_scene(data, tmp_path)
    _mask(scene, 11).unlink()
    out = tmp_path / "out"
    rc = main(["refine", str(scene), "--model", str(data.model), "--out", str(out), "--init", str(data.init)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "IoU over 11 views" in cap.out and str(out) in cap.out and "cam_t_m2c" in cap.out
    warn = [ln for ln in cap.err.replace("\r", "\n").splitlines() if ln.startswith("autoalign: warning:")]
    assert len(warn) == 1 and "skipped" in warn[0] and "11" in warn[0]
    gt = json.loads((out / "scene_gt.json").read_text())
    assert len(gt) == N_VIEWS  # every image of scene_camera.json, also the one without a mask
    r = json.loads((out / "refine.json").read_text())
    assert r["skipped"] == [11] and r["image_ids"] == list(range(11))


def test_quiet_run_warns_about_a_bad_mask(data, tmp_path, capsys):
    scene = _copy_scene(data, tmp_path)
    m = cv2.imread(str(_mask(scene, 4)), cv2.IMREAD_GRAYSCALE) > 127
    cv2.imwrite(str(_mask(scene, 4)), translate_mask(m, 25, 0).astype(np.uint8) * 255)
    out = tmp_path / "out"
    rc = main(["refine", str(scene), "--model", str(data.model), "--out", str(out), "--init", str(data.init),
               "--quiet"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert cap.out == ""
    lines = cap.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("autoalign: warning:") and "low weight" in lines[0], cap.err
    assert "4 (IoU" in lines[0]
    r = json.loads((out / "refine.json").read_text())
    assert r["low_weight_ids"] == [4]


# --------------------------------------------------------------------------------------------
# Pieces
# --------------------------------------------------------------------------------------------

def test_write_outputs_leaves_nothing_on_failure(tmp_path, monkeypatch):
    import errno
    import os

    from autoalign.cli.main import write_outputs
    from autoalign.errors import AutoalignError

    with pytest.raises(TypeError):
        write_outputs(tmp_path, {"scene_gt.json": b"{}", "refine.json": b"{}", "overlay.png": "not bytes"})
    assert list(tmp_path.iterdir()) == []

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(AutoalignError, match="--out"):
        write_outputs(tmp_path, {"scene_gt.json": b"{}", "refine.json": b"{}"})
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    paths = write_outputs(tmp_path, {"a.json": b"{}", "b.png": b"x"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.png"]
    assert paths["b.png"].read_bytes() == b"x"


def test_overlay_views_include_the_worst():
    from autoalign.quality.overlay import choose_views

    for n, worst in ((30, 5), (30, 28), (12, 7), (5, 2), (40, 0)):
        iou = np.full(n, 0.99)
        iou[worst] = 0.5
        idx = choose_views(iou)
        assert worst in idx and len(idx) == min(12, n) and idx == sorted(set(idx))


@pytest.mark.slow
@pytest.mark.parametrize("seed_args", [["--click", "CLICK"], []], ids=["click", "no-seed"])
def test_click_and_no_seed_runs_find_the_pose(data, tmp_path, seed_args):
    """The real command with a click (deepest mask pixel of image 0) or no seed at all."""
    import cv2

    mask = cv2.imread(str(_mask(data.scene, 0)), cv2.IMREAD_GRAYSCALE) > 127
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    args = [a.replace("CLICK", f"0:{j},{i}") for a in seed_args]  # OpenCV pixel coordinates
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(data.scene), "--model",
                        str(data.model), "--out", str(out), "--quiet", *args],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "refine.json").read_text())
    assert rec["seed"]["kind"] == ("click" if seed_args else "hull")
    T = np.asarray(rec["pose"]["T_wm"], dtype=float)
    mesh = load_mesh(data.model)
    c = mesh.centre
    assert np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - (data.T_true[:3, :3] @ c + data.T_true[:3, 3])) < 1.0
    assert rotation_angle_deg(T[:3, :3], data.T_true[:3, :3]) < 1.0


# --------------------------------------------------------------------------------------------
# Inputs that are read, refused or reported (issue 13, hardening)
# --------------------------------------------------------------------------------------------

def _one_error_line(capsys, token: str) -> None:
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(ERROR_PREFIX) and token in err[0], err


def test_out_equal_to_the_scene_folder_is_refused(data, tmp_path, capsys):
    scene = _copy_scene(data, tmp_path)
    before = {p.name: p.read_bytes() for p in scene.iterdir() if p.is_file()}
    rc = main(["refine", str(scene), "--model", str(data.model), "--out", str(scene / "." / ""), "--init",
               str(data.init), "--quiet"])
    assert rc == 2
    _one_error_line(capsys, "scene folder")
    assert {p.name: p.read_bytes() for p in scene.iterdir() if p.is_file()} == before


def test_output_that_would_replace_an_input_is_refused(data, tmp_path, capsys):
    out = tmp_path / "labels"
    out.mkdir()
    init = out / "scene_gt.json"  # the coarse labels live where the refined ones would go
    shutil.copy(data.init, init)
    rc = main(["refine", str(data.scene), "--model", str(data.model), "--out", str(out), "--init", str(init),
               "--quiet"])
    assert rc == 2
    _one_error_line(capsys, "scene_gt.json")
    assert init.read_bytes() == data.init.read_bytes() and sorted(p.name for p in out.iterdir()) == ["scene_gt.json"]


def test_empty_masks_are_missing_views_not_an_absent_object(data, tmp_path, capsys):
    """A segmentation dropout (empty masks in 2 of 12 views): the views are left out and reported,
    and the pose is still found (compared as targets, they pull the silhouette out of those views)."""
    scene = _copy_scene(data, tmp_path)
    for im in (2, 7):
        cv2.imwrite(str(_mask(scene, im)), np.zeros((H, W), np.uint8))
    out = tmp_path / "out"
    assert main(["refine", str(scene), "--model", str(data.model), "--out", str(out), "--init", str(data.init),
                 "--quiet"]) == 0
    assert "2 image(s) with an empty mask" in capsys.readouterr().err
    rec = json.loads((out / "refine.json").read_text())
    assert rec["empty_masks"] == [2, 7] and rec["image_ids"] == [i for i in range(N_VIEWS) if i not in (2, 7)]
    assert len(json.loads((out / "scene_gt.json").read_text())) == N_VIEWS  # labels for every image
    T = np.asarray(rec["pose"]["T_wm"])
    c = load_mesh(data.model).centre
    assert np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - data.T_true[:3, :3] @ c - data.T_true[:3, 3]) < 1.0
    assert rotation_angle_deg(T[:3, :3], data.T_true[:3, :3]) < 1.0
    assert rec["pixel_convention"]["files"].startswith("OpenCV/BOP")


@pytest.mark.parametrize("kind", ["0/1", "colour", "alpha only", "cut-out", "colour, opaque alpha"])
def test_masks_stored_as_0_1_in_colour_or_in_alpha_read_like_0_255(data, tmp_path, kind):
    """Every way of storing a mask gives the same masks. RGBA: an alpha channel that varies is the
    mask, whatever the colours (a cut-out's colours are the photo's); an opaque one says nothing."""
    from autoalign.io.bop import read_scene

    scene = _copy_scene(data, tmp_path)
    photo = np.random.default_rng(0).integers(1, 256, (H, W, 3), dtype=np.uint8)  # no zero anywhere
    for im in range(N_VIEWS):
        m = cv2.imread(str(_mask(scene, im)), cv2.IMREAD_GRAYSCALE) > 0
        img = np.zeros((H, W, 4), np.uint8)
        if kind == "0/1":
            img = m.astype(np.uint8)
        elif kind == "colour":  # the instance painted in a colour with a zero red channel, on black
            img = np.zeros((H, W, 3), np.uint8)
            img[m] = (200, 40, 0)
        elif kind == "alpha only":  # black everywhere, the mask in the alpha channel
            img[..., 3] = 255 * m
        elif kind == "cut-out":  # the photo's colours everywhere, transparent off the object
            img[..., :3], img[..., 3] = photo, 255 * m
        else:
            img[m, :3], img[..., 3] = (0, 40, 200), 255
        cv2.imwrite(str(_mask(scene, im)), img)
        assert cv2.imread(str(_mask(scene, im)), cv2.IMREAD_UNCHANGED).shape == img.shape  # RGBA stays RGBA
    ref, got = read_scene(data.scene), read_scene(scene)
    assert got.image_ids == ref.image_ids
    for a, b in zip(ref.masks, got.masks):
        np.testing.assert_array_equal(a, b)


def test_stl_loads_as_the_same_mesh_as_ply(data, tmp_path):
    """An STL stores each triangle's corners apart: loading merges them, so it renders like the PLY."""
    from autoalign.experiments.scenes.synthetic import sphere_cameras as cams_on_sphere
    from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

    ply = load_mesh(data.model)
    stl_path = tmp_path / "model.stl"
    ply.trimesh.export(str(stl_path))
    stl = load_mesh(stl_path)
    assert (len(stl.vertices), len(stl.faces)) == (len(ply.vertices), len(ply.faces))
    # unmerged, every STL edge would be open (a contour candidate in every view)
    assert np.sum(stl.edge_faces[:, 1] < 0) == np.sum(ply.edge_faces[:, 1] < 0)
    cams = cams_on_sphere(4, np.random.default_rng(0), dist_range=(350.0, 500.0), K=default_K(W, H, F),
                          width=W, height=H)
    for a, b in zip(SoftSilhouetteRasterizer(ply).hard_masks(data.T_true, cams),
                    SoftSilhouetteRasterizer(stl).hard_masks(data.T_true, cams)):
        np.testing.assert_array_equal(a, b)


def test_mesh_in_metres_loads_with_units_m(data, tmp_path):
    tm = load_mesh(data.model).trimesh
    tm.apply_scale(0.001)
    p = tmp_path / "metres.ply"
    tm.export(str(p))
    np.testing.assert_allclose(load_mesh(p, units="m").vertices, load_mesh(data.model).vertices, atol=1e-6)
    assert load_mesh(p, units="mm").diameter < 1.0  # --units mm keeps a really small object as it is


@pytest.mark.slow
def test_ctrl_c_at_any_moment_exits_130_and_writes_nothing(tmp_path):
    """SIGINT at moments spread over a run of the bundled example (imports, the backend's start-up,
    seeding, refinement): every run exits 130 with one line and no output. Before, an interrupt
    during the imports (trimesh swallows it in its optional imports) let the run finish with 0, and
    about one run in ten interrupted while drjit's backend started crashed in Python's finalization
    (SIGSEGV, or an abort on the GIL): the command now ends without it. The moments count from the end of ``import autoalign`` (Python's ``-X importtime`` reports
    it): before that the interpreter itself is starting, where no program can handle a signal."""
    import re
    import signal
    import threading
    import time

    from autoalign.experiments.scenes.make_example import DEFAULT_OUT as example

    if not (example / "scene").is_dir():  # installed without the source tree: the packaged copy
        import autoalign

        example = Path(autoalign.__file__).parent / "data" / "example"
    imported = re.compile(r"\|\s+autoalign$")
    for k, delay in enumerate(np.linspace(0.0, 2.4, 25)):
        out = tmp_path / f"out{k}"
        p = subprocess.Popen([sys.executable, "-X", "importtime", "-m", "autoalign.cli.main", "refine",
                              str(example / "scene"), "--model", str(example / "model.ply"), "--out", str(out), "--quiet"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ready, lines = threading.Event(), []

        def drain(stream=p.stderr, ready=ready, lines=lines) -> None:
            for line in stream:
                if line.startswith("import time:"):
                    if imported.search(line.rstrip()):
                        ready.set()
                else:
                    lines.append(line.rstrip("\n"))
            ready.set()

        reader = threading.Thread(target=drain)
        reader.start()
        assert ready.wait(60)
        time.sleep(float(delay))
        p.send_signal(signal.SIGINT)
        stdout = p.stdout.read()
        p.wait(timeout=120)
        reader.join(timeout=10)
        assert p.returncode == 130, (delay, p.returncode, lines)
        assert [x for x in lines if x.strip()] == ["autoalign: interrupted"], (delay, lines)
        assert not out.exists() and stdout == "", delay


def test_ctrl_c_inside_the_import_machinery_is_remembered_not_raised():
    """The command's handler meeting Ctrl-C in importlib's own code (its module-lock weakref callback,
    where Python prints an exception's traceback and drops it: a CI run printed one) only remembers
    it, and :meth:`Interrupts.check` raises it; anywhere else it raises at once."""
    import signal

    from autoalign.runtime.interrupts import Interrupts

    def frame_in(filename: str):
        scope: dict = {"sys": sys}
        exec(compile("def where():\n    return sys._getframe()\n", filename, "exec"), scope)
        return scope["where"]()

    try:
        Interrupts.reset()
        Interrupts.handler(signal.SIGINT, frame_in("<frozen importlib._bootstrap>"))
        assert Interrupts.seen
        with pytest.raises(KeyboardInterrupt):
            Interrupts.check()
        Interrupts.reset()
        with pytest.raises(KeyboardInterrupt):
            Interrupts.handler(signal.SIGTERM, frame_in(__file__))
        assert Interrupts.seen and Interrupts.exit_status() == 143
    finally:
        Interrupts.reset()


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.1])
def test_ctrl_c_after_the_outputs_are_written_keeps_the_result(data, tmp_path, delay):
    """SIGINT just after ``wrote ...``: the outputs are complete, so the run keeps its own exit status
    (0 here) and, if the signal came before the command ended, says that it came after the outputs
    were written. (Before: exit 130 with no message, the outputs complete.)"""
    import signal
    import time

    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "autoalign.cli.main", "refine", str(data.scene), "--model",
                          str(data.model), "--out", str(out), "--init", str(data.init)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in p.stdout:
        if line.startswith("wrote "):
            break
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    p.stdout.read()
    stderr = p.stderr.read()
    p.wait(timeout=60)
    assert p.returncode == 0, (p.returncode, stderr)
    said = [x for x in stderr.splitlines() if x.startswith("autoalign:")]  # the rest is the progress bar
    assert said in ([], ["autoalign: Ctrl-C came after the outputs were written; they are complete"]), stderr
    assert "Traceback" not in stderr
    assert all((out / name).is_file() for name in ("scene_gt.json", "refine.json", "overlay.png"))
    assert json.loads((out / "refine.json").read_text())["verdict"] == "ok"


def test_large_images_are_read_downscaled_with_their_cameras(data, tmp_path):
    """Images above the pixel budget are read at a whole-factor reduction, cameras scaled with them
    (here a budget of a quarter of the image: factor 2), and the pose is still found; a click is
    typed in the files' pixels. The 12-megapixel case is measured in experiments/benchmarks/bench_memory.py."""
    from autoalign.engine.refine import refine
    from autoalign.engine.seeding import Click, check_click
    from autoalign.io.bop import read_scene

    full = read_scene(data.scene)
    half = read_scene(data.scene, max_pixels=W * H // 4)
    assert (full.image_scale, half.image_scale) == (1.0, 0.5)
    for a, b in zip(full.cameras, half.cameras):
        assert (b.width, b.height) == (W // 2, H // 2)
        np.testing.assert_allclose(b.K_opencv[:2, 2], (a.K_opencv[:2, 2] + 0.5) / 2 - 0.5)
    for a, b in zip(full.masks, half.masks):  # each small pixel is the majority of its 2x2 block
        block = a.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))
        np.testing.assert_array_equal(b[block != 0.5], block[block != 0.5] > 0.5)
    mesh = load_mesh(data.model)
    result = refine(half, mesh, data.T_init)
    c = mesh.centre
    T = result.T_wm
    assert np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - data.T_true[:3, :3] @ c - data.T_true[:3, 3]) < 1.0
    assert rotation_angle_deg(T[:3, :3], data.T_true[:3, :3]) < 1.0
    # the deepest mask pixel of image 0, typed in full-resolution OpenCV pixels, lands on the small mask
    dist = cv2.distanceTransform((full.masks[0] > 0.5).astype(np.uint8), cv2.DIST_L2, 5)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    check_click(half, Click.parse(f"0:{j},{i}").scaled(half.image_scale))
