"""Bad inputs refused when they are read (issue 43, items 8 and 9): each case is the exact input,
and either a one-line error naming the file (or argument) and the fix, exit status 2 and nothing
written, or the right result. All on copies of the bundled example (24 views of a mug, 640x480),
before any refinement, so each case takes a second or two.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

import autoalign
from autoalign.cli.main import OUTPUT_FILES, main
from autoalign.errors import AutoalignError
from autoalign.io.bop import find_photo, read_init_pose, read_scene
from autoalign.io.evidence import read_evidence
from autoalign.io.instances import read_instances
from autoalign.io.models import ModelSet, read_models_info

EXAMPLE = Path(autoalign.__file__).resolve().parent / "data" / "example"
ERROR = "autoalign: error:"


@pytest.fixture
def example(tmp_path: Path) -> Path:
    """A copy of the bundled example (scene/, models/, model.ply, init_gt.json) to spoil."""
    shutil.copytree(EXAMPLE, tmp_path / "example")
    return tmp_path / "example"


def refused(argv: list[str], capsys: pytest.CaptureFixture[str], *tokens: str) -> str:
    """Run ``autoalign ARGV`` (its ``--out`` the word after it) and check it stopped with exit 2, one
    line naming every token, nothing on stdout and no output folder; returns that line."""
    out = Path(argv[argv.index("--out") + 1])
    rc = main(argv)
    cap = capsys.readouterr()
    lines = cap.err.splitlines()
    assert rc == 2, cap.err
    assert len(lines) == 1 and lines[0].startswith(ERROR), cap.err
    for token in tokens:
        assert token in lines[0], (token, lines[0])
    assert cap.out == "" and "Traceback" not in cap.err
    assert not out.exists(), sorted(p.name for p in out.iterdir() if p.name in OUTPUT_FILES)
    return lines[0]


def refine_argv(ex: Path, *extra: str, out: str = "out") -> list[str]:
    """``autoalign refine`` of the example's scene with one model and the example's coarse pose."""
    argv = ["refine", str(ex / "scene"), "--out", str(ex.parent / out), "--quiet"]
    if "--models" not in extra:
        argv += ["--model", str(ex / "model.ply")]
    if "--init" not in extra and "--click" not in extra:
        argv += ["--init", str(ex / "init_gt.json")]
    return argv + list(extra)


def models_argv(ex: Path, *extra: str) -> list[str]:
    return refine_argv(ex, "--models", str(ex / "models"), "--init", str(ex / "init_gt.json"), *extra)


def write_json(path: Path, content: object) -> Path:
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


def coarse_entry(ex: Path) -> dict:
    """The example's coarse pose of obj 1 in image 0 (a ``scene_gt.json`` entry)."""
    return json.loads((ex / "init_gt.json").read_text())["0"][0]


# --------------------------------------------------------------------------------------------
# models_info.json (item 8): a malformed symmetry was a ValueError / LinAlgError at the verdict
# --------------------------------------------------------------------------------------------

def spoil_info(ex: Path, **fields: object) -> Path:
    path = ex / "models" / "models_info.json"
    info = json.loads(path.read_text())
    info["1"].update(fields)
    return write_json(path, info)


def test_models_info_discrete_symmetry_of_three_numbers(example, capsys) -> None:
    spoil_info(example, symmetries_discrete=[[1, 2, 3]])
    refused(models_argv(example), capsys, "models_info.json", "object 1 symmetries_discrete[0]", "4x4")


def test_models_info_zero_continuous_axis(example, capsys) -> None:
    spoil_info(example, symmetries_continuous=[{"axis": [0, 0, 0], "offset": [0, 0, 0]}])
    refused(models_argv(example), capsys, "models_info.json", "symmetries_continuous[0]", "not all zero")


def test_simulate_models_info_checked_when_read(example, capsys) -> None:
    """``simulate --models`` reads the same checked models_info.json: one line, before any trial."""
    spoil_info(example, symmetries_discrete=[[1, 2, 3]])
    refused(["simulate", "--models", str(example / "models"), "--trials", "1", "--out", str(example.parent / "sim")],
            capsys, "models_info.json", "object 1 symmetries_discrete[0]", "4x4")


@pytest.mark.parametrize("fields, token", [
    ({"symmetries_discrete": [list((2 * np.eye(4)).ravel())]}, "symmetries_discrete[0]"),  # scaled: det 8
    ({"symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 2]]}, "last row"),
    ({"symmetries_discrete": [list(np.diag([1.0, 1.0, -1.0, 1.0]).ravel())]}, "det +1"),  # a mirror
    ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0]}]}, "'offset' must be 3 numbers"),
    ({"symmetries_continuous": [{"offset": [0, 0, 0]}]}, "needs an 'axis'"),
    ({"symmetries_continuous": {"axis": [0, 0, 1]}}, "must be lists"),
    ({"diameter": -5}, "diameter -5"),
    ({"diameter": "big"}, "diameter 'big'"),
])
def test_models_info_entries_checked_when_read(example, fields, token) -> None:
    path = spoil_info(example, **fields)
    with pytest.raises(AutoalignError, match="^" + str(path)) as exc:
        ModelSet.read(example / "models")
    assert token in str(exc.value) and "\n" not in str(exc.value)


def test_models_info_duplicate_object_ids(example) -> None:
    path = example / "models" / "models_info.json"
    entry = json.loads(path.read_text())["1"]
    write_json(path, {"1": entry, "01": entry})
    with pytest.raises(AutoalignError, match="keys '1' and '01' both name object id 1"):
        read_models_info(path)


def test_bop_symmetries_as_written_are_read(tmp_path) -> None:
    """The right result: BOP's own forms (a flat 16 with few decimals, a continuous axis not of unit
    length) are read, the axis made unit."""
    R = np.array([[-0.999964, -0.00333777, -0.0077452], [0.00321462, -0.999869, 0.0158593],
                  [-0.00779712, 0.0158338, 0.999844]])  # LM's eggbox, as models_info.json stores it
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.232611, 0.694388, -0.0326157]
    write_json(tmp_path / "models_info.json", {"10": {"diameter": 164.6, "symmetries_discrete": [list(T.ravel())],
                                                      "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 0]}]}})
    models = ModelSet.read(tmp_path)
    discrete, continuous = models.symmetries(10)
    assert np.allclose(discrete[0], T) and np.allclose(continuous[0][0], [0, 0, 1])


# --------------------------------------------------------------------------------------------
# refine(seed=...) of the Python API (item 8)
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def api_inputs():
    scene = autoalign.read_scene(EXAMPLE / "scene")
    return scene, autoalign.load_mesh(EXAMPLE / "model.ply"), read_init_pose(EXAMPLE / "init_gt.json", scene)


@pytest.mark.parametrize("make, token", [
    (lambda T: np.diag([2.0, 2.0, 2.0, 1.0]) @ T, "det 8"),  # a scaled pose: was refined to a det-8 pose at IoU 0
    (lambda T: T[:3, :3], "shape (3, 3)"),  # was IndexError
    (lambda T: "identity", "seed='identity' is not a pose"),  # was ValueError
    (lambda T: np.where(np.eye(4) > 0, np.nan, T), "not a finite 4x4 pose"),
    (lambda T: np.diag([1.0, 1.0, -1.0, 1.0]) @ T, "mirrored"),
])
def test_refine_refuses_a_seed_that_is_no_pose(api_inputs, make, token) -> None:
    scene, mesh, T = api_inputs
    with pytest.raises(AutoalignError, match="^seed") as exc:
        autoalign.refine(scene, mesh, seed=make(T))
    assert token in str(exc.value) and "4x4 world-from-model pose" in str(exc.value)


def test_refine_refuses_a_folder_or_a_path_for_scene_and_mesh(api_inputs) -> None:
    scene, mesh, T = api_inputs
    with pytest.raises(AutoalignError, match=r"^scene: a str is not a Scene; read the folder with autoalign.read_scene"):
        autoalign.refine(str(EXAMPLE / "scene"), mesh, seed=T)
    with pytest.raises(AutoalignError, match=r"^mesh: a PosixPath is not a Mesh; load it with autoalign.load_mesh"):
        autoalign.refine(scene, EXAMPLE / "model.ply", seed=T)


def test_jax_refine_refuses_a_scaled_start(api_inputs) -> None:
    import autoalign.jax as aj  # the test command installs jax: a missing one must fail, not skip
    scene, mesh, T = api_inputs
    with pytest.raises(AutoalignError, match=r"^T_init: its upper 3x3 is not a rotation \(det 8"):
        aj.refine(scene, mesh, np.diag([2.0, 2.0, 2.0, 1.0]) @ T)
    with pytest.raises(AutoalignError, match="^scene: a str is not a Scene"):
        aj.refine(str(EXAMPLE / "scene"), mesh, T)


def test_a_seed_with_rounding_error_is_taken_as_its_rotation() -> None:
    from autoalign.engine.refine import checked_seed

    R = cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R + 2e-4, [1.0, 2.0, 300.0]  # a few decimals off, as files store it
    seed = checked_seed(T)
    assert np.allclose(seed[:3, :3] @ seed[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.abs(seed[:3, :3] - R).max() < 5e-4 and np.array_equal(seed[:3, 3], T[:3, 3])
    T[:3, :3] = R
    assert np.array_equal(checked_seed(T), T)  # an exact pose is kept as it is


# --------------------------------------------------------------------------------------------
# --init (item 9)
# --------------------------------------------------------------------------------------------

def test_init_without_the_models_obj_id_is_refused(example, capsys) -> None:
    """It seeded from another object's entry (150 mm away) without a word."""
    other = {**coarse_entry(example), "obj_id": 2, "cam_t_m2c": [150.0, 0.0, 500.0]}
    init = write_json(example / "coarse.json", {"0": [other]})
    refused(refine_argv(example, "--init", str(init)), capsys, str(init), "no entry has obj_id 1",
            "it lists obj_id 2", "--obj-id")


def test_init_entry_of_the_models_obj_id_is_used_wherever_it_stands(example) -> None:
    """The right result: with another object's entry first, the model's own is the seed."""
    scene = read_scene(example / "scene")
    expected = read_init_pose(example / "init_gt.json", scene)
    other = {**coarse_entry(example), "obj_id": 2, "cam_t_m2c": [150.0, 0.0, 500.0]}
    init = write_json(example / "coarse.json", {"0": [other, coarse_entry(example)]})
    assert np.allclose(read_init_pose(init, scene, obj_id=1), expected)
    assert not np.allclose(read_init_pose(init, scene, obj_id=2), expected)


@pytest.mark.parametrize("content", [
    "entries", "entry"  # image 0's list (or its one entry) without the image id around it
])
def test_init_not_keyed_by_image_says_so(example, capsys, content) -> None:
    entry = coarse_entry(example)
    init = write_json(example / "coarse.json", [entry] if content == "entries" else entry)
    refused(refine_argv(example, "--init", str(init)), capsys, str(init), "not keyed by image id", '{"0": [...]}')


def test_init_of_images_the_scene_lacks_names_them(example, capsys) -> None:
    init = write_json(example / "coarse.json", {"99": [coarse_entry(example)], "100": [coarse_entry(example)]})
    refused(refine_argv(example, "--init", str(init)), capsys, str(init), "gives poses in image(s) 99, 100",
            "cameras only for image(s) 0, 1, 2, 3, ..., 23 (24)", "key each pose by the id of the image")


def test_init_in_an_image_without_a_mask_uses_its_camera(example) -> None:
    """The right result: image 0's mask is gone, but its camera still places the pose given in it."""
    expected = read_init_pose(example / "init_gt.json", read_scene(example / "scene"))
    (example / "scene" / "mask_visib" / "000000_000000.png").unlink()
    scene = read_scene(example / "scene")
    assert 0 not in scene.image_ids
    assert np.allclose(read_init_pose(example / "init_gt.json", scene), expected)


def test_init_of_images_the_scene_lacks_names_them_with_models(example, capsys) -> None:
    init = write_json(example / "coarse.json", {"99": [coarse_entry(example)]})
    refused(refine_argv(example, "--models", str(example / "models"), "--init", str(init)), capsys,
            str(init), "gives poses in image(s) 99")


# --------------------------------------------------------------------------------------------
# Photos (item 9): two of one image; --photos auto and on with one missing
# --------------------------------------------------------------------------------------------

def test_two_photos_of_one_image_are_refused(example, capsys) -> None:
    rgb = example / "scene" / "rgb"
    cv2.imwrite(str(rgb / "000003.png"), cv2.imread(str(rgb / "000003.jpg")))
    line = refused(refine_argv(example), capsys, "000003.png and ", "000003.jpg", "two photos of image 3",
                   "keep one")
    assert str(rgb) in line
    with pytest.raises(AutoalignError, match="two photos of image 3"):
        find_photo(example / "scene", 3)


class Stop(Exception):
    """Raised by the stand-in for the refinement once it has the job."""


def job_of(argv: list[str], monkeypatch) -> object:
    """The job ``autoalign ARGV`` hands to the refinement (which is not run)."""
    import autoalign.cli.main as cli

    jobs = []

    def capture(job, *args, **kwargs):
        jobs.append(job)
        raise Stop

    monkeypatch.setattr(cli, "refine_folder", capture)
    with pytest.raises(Stop):
        main(argv)
    return jobs[0]


def test_photos_auto_goes_on_without_photos_when_one_is_missing(example, capsys, monkeypatch) -> None:
    (example / "scene" / "rgb" / "000005.jpg").unlink()
    job = job_of(refine_argv(example), monkeypatch)
    warnings = capsys.readouterr().err.splitlines()
    assert job.photos == "off" and not job.uses_photos
    assert len(warnings) == 1 and warnings[0].startswith("autoalign: warning:"), warnings
    assert "no photo of image(s) 5" in warnings[0] and "not used (--photos auto)" in warnings[0]
    job = job_of(models_argv(example), monkeypatch)  # every instance's views: the same
    assert job.photos == "off"


def test_photos_auto_with_every_photo_uses_them(example, capsys, monkeypatch) -> None:
    job = job_of(refine_argv(example), monkeypatch)
    assert job.photos == "auto" and job.uses_photos and capsys.readouterr().err == ""


def test_check_split_half_photos_auto_goes_on_without_photos(example, capsys, monkeypatch) -> None:
    import autoalign.jobs.check as check

    (example / "scene" / "rgb" / "000005.jpg").unlink()
    asked = {}

    def capture(*args, **kwargs):
        asked.update(kwargs)
        raise Stop

    monkeypatch.setattr(check, "prepare_split_half", capture)
    with pytest.raises(Stop):
        main(["check", str(example / "scene"), "--labels", str(example / "scene" / "scene_gt.json"), "--models",
              str(example / "models"), "--split-half"])
    warnings = capsys.readouterr().err.splitlines()
    assert asked["photos"] == "off" and len(warnings) == 1 and "no photo of image(s) 5" in warnings[0]


def test_photos_on_stops_at_a_missing_photo(example, capsys) -> None:
    (example / "scene" / "rgb" / "000005.jpg").unlink()
    refused(refine_argv(example, "--photos", "on"), capsys, "000005.png (or .jpg): not found", "--photos off")


# --------------------------------------------------------------------------------------------
# Instances file (item 9): two keys naming one instance refined its mask twice
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, token", [
    ('{"instances": {"0": 1, "00": 1}}', "keys '0' and '00' both name instance number 0"),
    ('{"instances": {"0": 1, "0": 1}}', "the key '0' appears twice"),
])
def test_instances_naming_one_instance_twice(example, capsys, text, token) -> None:
    table = write_json(example / "instances.json", text)
    refused(models_argv(example, "--instances", str(table)), capsys, str(table), token)
    with pytest.raises(AutoalignError, match=token):
        read_instances(example / "scene", table)


def test_scene_camera_with_two_keys_for_one_image(example, capsys) -> None:
    path = example / "scene" / "scene_camera.json"
    cams = json.loads(path.read_text())
    cams["03"] = cams["3"]
    write_json(path, cams)
    refused(refine_argv(example), capsys, str(path), "keys '3' and '03' both name image id 3")


# --------------------------------------------------------------------------------------------
# Depth (item 9): 8-bit refused, a wrong unit named with depth_scale
# --------------------------------------------------------------------------------------------

def true_depths(ex: Path) -> dict[int, np.ndarray]:
    """The example's depth (mm along the optical axis, 0: none) ray-cast by open3d at the true pose."""
    scene = read_scene(ex / "scene")
    mesh = autoalign.load_mesh(ex / "model.ply")
    T = read_init_pose(ex / "scene" / "scene_gt.json", scene)
    caster = o3d.t.geometry.RaycastingScene()
    V = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    caster.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    out = {}
    for im, cam in zip(scene.image_ids, scene.cameras):
        u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        z1 = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(cam.K_opencv).T  # depth 1
        rays = np.hstack([np.tile(cam.centre, (len(z1), 1)), z1 @ cam.R_w2c]).astype(np.float32)
        t = caster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(cam.height, cam.width)
        out[im] = np.where(np.isfinite(t), t, 0.0)
    return out


@pytest.fixture(scope="module")
def depth_mm() -> dict[int, np.ndarray]:
    return true_depths(EXAMPLE)


def with_depth_files(ex: Path, depth_mm: dict[int, np.ndarray], per_mm: float, dtype=np.uint16,
                     depth_scale: float | None = None) -> None:
    """Write ``depth/`` (``per_mm`` values a mm) and, if given, ``depth_scale`` in scene_camera.json."""
    (ex / "scene" / "depth").mkdir()
    for im, d in depth_mm.items():
        cv2.imwrite(str(ex / "scene" / "depth" / f"{im:06d}.png"), np.round(d * per_mm).astype(dtype))
    if depth_scale is not None:
        path = ex / "scene" / "scene_camera.json"
        write_json(path, {k: {**v, "depth_scale": depth_scale} for k, v in json.loads(path.read_text()).items()})


def test_depth_in_tenths_of_a_mm_without_depth_scale(example, depth_mm, capsys) -> None:
    """It gave 'failed' with no hint at depth_scale; now it is named before anything is refined."""
    with_depth_files(example, depth_mm, per_mm=10.0)
    refused(refine_argv(example), capsys, str(example / "scene" / "depth"),
            "inside the masks is 9.58 times the cameras' distance", "set depth_scale in " + str(example / "scene" / "scene_camera.json"), "about 0.1 would fit",
            "--depth off")
    refused(models_argv(example), capsys, "depth_scale")


def test_depth_with_its_depth_scale_is_read_in_mm(example, depth_mm) -> None:
    """The right result: the same files with depth_scale 0.1 are the depth in mm."""
    with_depth_files(example, depth_mm, per_mm=10.0, depth_scale=0.1)
    scene = read_evidence(example / "scene", modalities=("masks", "depth"))
    assert scene.depths is not None and len(scene.depths) == 24
    for im, d in zip(scene.image_ids, scene.depths):
        assert np.abs(d - depth_mm[im]).max() <= 0.05 + 1e-4


def test_eight_bit_depth_is_refused(example, depth_mm, capsys) -> None:
    with_depth_files(example, depth_mm, per_mm=0.25, dtype=np.uint8)
    refused(refine_argv(example), capsys, str(example / "scene" / "depth" / "000000.png"), "8-bit depth",
            "16-bit PNG")


def test_depth_scale_that_is_no_number(example, depth_mm, capsys) -> None:
    with_depth_files(example, depth_mm, per_mm=1.0, depth_scale="0.1")
    refused(refine_argv(example), capsys, "scene_camera.json", "image 0 depth_scale '0.1' is not a positive number")


# --------------------------------------------------------------------------------------------
# recon (item 8): depth in 0.1 mm without --depth-scale was an open3d RuntimeError after 28 s
# --------------------------------------------------------------------------------------------

def capture_with_depth(folder: Path, depth_value: int, dtype=np.uint16) -> Path:
    """Three textured 96x72 frames and their depth, every pixel ``depth_value``."""
    rng = np.random.default_rng(0)
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / "rgb" / f"{k:06d}.png"), rng.integers(0, 255, (72, 96, 3), dtype=np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{k:06d}.png"), np.full((72, 96), depth_value, dtype))
    return folder


def test_recon_depth_in_tenths_of_a_mm_without_depth_scale(tmp_path, capsys) -> None:
    import pycolmap  # noqa: F401 - installed by the test command: a missing one must fail, not skip
    capture = capture_with_depth(tmp_path / "capture", 6000)  # a table 600 mm away, in 0.1 mm
    refused(["recon", str(capture), "--out", str(tmp_path / "scene"), "--quiet"], capsys, str(capture / "depth"),
            "the median depth is 6000 mm with --depth-scale 1", "pass the --depth-scale", "probably 0.1")


def test_recon_depth_in_metres(tmp_path, capsys) -> None:
    import pycolmap  # noqa: F401 - installed by the test command: a missing one must fail, not skip
    capture = capture_with_depth(tmp_path / "capture", 1)
    refused(["recon", str(capture), "--out", str(tmp_path / "scene"), "--quiet"], capsys,
            "the median depth is 1 mm", "probably 1000")


def test_recon_eight_bit_depth(tmp_path, capsys) -> None:
    import pycolmap  # noqa: F401 - installed by the test command: a missing one must fail, not skip
    capture = capture_with_depth(tmp_path / "capture", 60, np.uint8)
    refused(["recon", str(capture), "--out", str(tmp_path / "scene"), "--quiet", "--depth-scale", "10"], capsys,
            str(capture / "depth" / "000000.png"), "8-bit depth")


@pytest.mark.parametrize("scale", ["nan", "inf", "0"])
def test_recon_depth_scale_that_is_no_factor(tmp_path, capsys, scale) -> None:
    import pycolmap  # noqa: F401 - installed by the test command: a missing one must fail, not skip
    capture = capture_with_depth(tmp_path / "capture", 6000)
    refused(["recon", str(capture), "--out", str(tmp_path / "scene"), "--quiet", "--depth-scale", scale], capsys,
            f"--depth-scale {float(scale)}: must be positive")


def test_recon_depth_with_its_scale_is_taken(tmp_path) -> None:
    """The right result: the same capture with --depth-scale 0.1 is read, in mm."""
    from autoalign.recon.capture import read_capture

    capture = capture_with_depth(tmp_path / "capture", 6000)
    read = read_capture(capture, tmp_path / "work", depth_scale=0.1)
    assert read.depth_scale == 0.1 and [p.name for p in read.depth] == ["000000.png", "000001.png", "000002.png"]


def test_recon_intrinsics_with_nan(tmp_path, capsys) -> None:
    import pycolmap  # noqa: F401 - installed by the test command: a missing one must fail, not skip
    capture = capture_with_depth(tmp_path / "capture", 6000)
    K = write_json(tmp_path / "K.json", '{"fx": NaN, "fy": 80, "cx": 48, "cy": 36}')
    refused(["recon", str(capture), "--out", str(tmp_path / "scene"), "--quiet", "--depth-scale", "0.1",
             "--intrinsics", str(K)], capsys, str(K), "every number finite")
