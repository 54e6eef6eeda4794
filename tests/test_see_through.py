"""Depth that sees through an object (issue 45): a glass object's measured depth is what lies behind
it, or nothing. On a synthetic table scene whose sensor depth passes through one of two objects
(holes in blobs on it), refined with ``refine --models --init`` from 10 mm / 15 deg off with the
depth and without the photos: before, the depth pulled the glass 60-100 mm away and failed it.
Now it is recognised (or declared in ``materials.json``): the glass ends where the masks put it,
not failed, its depth recorded as seeing through it with the numbers; the opaque object beside it
keeps its depth as evidence. A malformed ``materials.json`` is a one-line error."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from autoalign.experiments.scenes.photo_scene import write_photo_scene
from autoalign.experiments.scenes.procedural_models import models_info_entry, procedural_models
from autoalign.experiments.scenes.synthetic import perturb_pose
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.io.bop import scene_gt_of
from autoalign.losses.see_through import SEES_THROUGH

GLASS, OPAQUE = "travel_mug", "kettle"


@pytest.fixture(scope="module")
def table(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The glass (obj 1, the depth sees through it) and an opaque object (obj 2) on a table, 12
    views of 320 x 240 with depth, and starts 10 mm / 15 deg off."""
    root = tmp_path_factory.mktemp("glass")
    pool = {p.name: p for p in procedural_models()}
    chosen = [pool[GLASS], pool[OPAQUE]]
    meshes = [mesh_from_trimesh(p.mesh, p.name) for p in chosen]
    ps = write_photo_scene(root / "scene", meshes, 12, seed=3, width=320, height=240, depth=True,
                           dist_range=(350.0, 450.0), see_through=(0,))
    models = root / "models"
    models.mkdir()
    for j, p in enumerate(chosen):
        p.mesh.export(models / f"obj_{j + 1:06d}.ply")
    (models / "models_info.json").write_text(json.dumps({str(j + 1): models_info_entry(p) for j, p in enumerate(chosen)}))
    rng = np.random.default_rng(5)
    starts = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(ps.poses, meshes)]
    (root / "init.json").write_text(json.dumps(scene_gt_of([(j + 1, T) for j, T in enumerate(starts)],
                                                           ps.cameras[:1], [0])))
    return {"root": root, "ps": ps, "models": models,
            "symmetries": [Symmetries.from_info(models_info_entry(p)) for p in chosen]}


def _refine(table: dict, models: Path, out: Path) -> tuple[subprocess.CompletedProcess, dict]:
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(table["root"] / "scene"), "--models",
                        str(models), "--init", str(table["root"] / "init.json"), "--photos", "off", "--out", str(out),
                        "--quiet"], capture_output=True, text=True, timeout=900)
    return p, (json.loads((out / "refine.json").read_text()) if (out / "refine.json").is_file() else {})


def _errors(table: dict, report: dict) -> list[tuple[float, float]]:
    ps = table["ps"]
    out = []
    for inst, T_true, mesh, sym in zip(report["instances"], ps.poses, ps.meshes, table["symmetries"]):
        e = pose_errors(np.asarray(inst["pose"]["T_wm"]), T_true, mesh.centre, None, sym)
        out.append((e.pos_err_mm, e.rot_err_deg))
    return out


@pytest.mark.slow
def test_depth_through_glass_is_recognised_and_neither_pulls_nor_fails_the_pose(table: dict, tmp_path: Path) -> None:
    p, report = _refine(table, table["models"], tmp_path / "out")
    assert p.returncode in (0, 3), p.stderr
    (glass_mm, glass_deg), (opaque_mm, opaque_deg) = _errors(table, report)
    glass, opaque = report["instances"]
    assert glass_mm < 1.0 and glass_deg < 1.0 and glass["verdict"] != "failed"
    depth = glass["depth"]
    assert depth["sees_through"] and not depth["declared"]
    assert np.nanmedian(np.asarray(depth["through_share"], dtype=float)) >= max(SEES_THROUGH, 0.9)
    assert [e["stance"] for e in glass["evidence"]] == ["no evidence"]
    assert any("sees through this object (recognised" in r for r in glass["reasons"])
    # the opaque object's depth is evidence as before: it agrees, and nothing says it sees through
    assert opaque_mm < 1.0 and opaque_deg < 1.0 and opaque["verdict"] == "ok"
    assert "sees_through" not in opaque["depth"] and opaque["evidence"][0]["stance"] == "supports"


@pytest.mark.slow
def test_a_model_declared_transparent_is_refined_without_its_depth(table: dict, tmp_path: Path) -> None:
    models = tmp_path / "models"
    models.mkdir()
    for f in table["models"].iterdir():
        (models / f.name).write_bytes(f.read_bytes())
    (models / "materials.json").write_text(json.dumps({"1": {"material": "transparent"}, "2": {"material": "opaque"}}))
    p, report = _refine(table, models, tmp_path / "out")
    assert p.returncode in (0, 3), p.stderr
    (glass_mm, glass_deg), _ = _errors(table, report)
    glass = report["instances"][0]
    assert glass_mm < 1.0 and glass_deg < 1.0 and glass["verdict"] != "failed"
    assert glass["depth"]["sees_through"] and glass["depth"]["declared"]
    assert any("declared transparent in materials.json" in r for r in glass["reasons"])


@pytest.mark.slow
def test_a_model_declared_opaque_keeps_its_depth_as_evidence_whatever_it_looks_like(table: dict, tmp_path: Path) -> None:
    """The declaration overrides the recognition: the glass declared opaque is refined with its depth
    once and never read as seen through. The table seen through it then pulls it into the table,
    where that depth agrees but its silhouettes miss the masks: flagged, with both said (a person who
    declared it so is told, not silently corrected)."""
    models = tmp_path / "models"
    models.mkdir()
    for f in table["models"].iterdir():
        (models / f.name).write_bytes(f.read_bytes())
    (models / "materials.json").write_text(json.dumps({"1": {"material": "opaque"}}))
    p, report = _refine(table, models, tmp_path / "out")
    assert p.returncode in (0, 3), p.stderr
    glass = report["instances"][0]
    assert "sees_through" not in glass["depth"] and glass["verdict"] == "check"
    assert [(e["term"], e["stance"]) for e in glass["evidence"]] == [("depth", "supports")]
    assert glass["reasons"][0].startswith("silhouettes do not match the masks (median IoU 0.0")
    assert not any("sees through this object" in r for r in glass["reasons"])


EXAMPLE = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"


FIX = '{"material": "transparent"}'


@pytest.mark.parametrize("content, says", [
    ('{"1": {"material": "glass"}}', ["object 1 has material 'glass'", FIX]),
    ('{"one": {"material": "transparent"}}', ["key 'one' is not an object id", "keys must be whole numbers"]),
    ('{"1": "transparent"}', ["object 1 has material None", FIX]),
    ("[1]", ["not a JSON object", FIX]),
])
def test_a_malformed_materials_file_is_a_one_line_error_before_anything_is_refined(tmp_path: Path, capsys,
                                                                                  content: str,
                                                                                  says: list[str]) -> None:
    from autoalign.cli.main import main

    models = tmp_path / "models"
    models.mkdir()
    for f in (EXAMPLE / "models").iterdir():
        (models / f.name).write_bytes(f.read_bytes())
    (models / "materials.json").write_text(content)
    out = tmp_path / "out"
    rc = main(["refine", str(EXAMPLE / "scene"), "--models", str(models), "--init", str(EXAMPLE / "init_gt.json"),
               "--out", str(out), "--quiet"])
    line = capsys.readouterr().err.strip()
    assert rc == 2 and not out.exists()
    assert "\n" not in line and str(models / "materials.json") in line
    assert all(s in line for s in says)  # what is wrong, and the fix


@pytest.mark.slow
def test_an_opaque_object_pushed_under_the_table_pays_for_it(table: dict) -> None:
    """An object pushed behind a surface the masks do not show (issue 45): the table's depth nearer
    than the object outside its masks is an unmodelled occluder there, but the masks' pixels it no
    longer covers and the depth inside them still count. The opaque kettle at its true pose against
    the same pose 30 and 100 mm under the table (measured: 0.4 against 10-13 per view); the glass's
    own depth, which made the far pose win, is left out by the rule above. Measured per view: 0.98 at
    the truth, 11.9 at 30 mm under, 5.7 at 100 mm under (the farther under, the more of the table
    counts as in front: the occluder rule still discounts it, but not below several times the truth)."""
    from autoalign.engine.objective import Level, SilhouetteObjective
    from autoalign.io.bop import read_scene, with_depth
    from autoalign.losses.depth import DepthNoise
    from autoalign.rasterizers.pyramid import MeshPyramid

    ps = table["ps"]
    scene = with_depth(read_scene(ps.folder, 1))
    objective = SilhouetteObjective(MeshPyramid(ps.meshes[1]), scene, depth=DepthNoise())
    level = Level(1.0, 1.0, 0)

    def loss(dz_mm: float) -> float:
        T = ps.poses[1].copy()
        T[2, 3] += dz_mm  # the world's z is up, the table top at z = 0
        ev = objective.evaluate(T, level, with_derivatives=False)
        return ev.value / len(ev.weights)

    right = loss(0.0)
    assert loss(-30.0) > 3 * right and loss(-100.0) > 3 * right


def test_depth_seen_through_at_the_given_pose_costs_one_run(box_with_depth, monkeypatch) -> None:
    """Issue 45, must-show 9: from a given pose whose depth is seen through already there, the engine
    runs once, without the depth (before: once with it, in doubt, then again without it), and the
    result is recognised as seen through; an opaque object's depth is used in its one run."""
    import autoalign.engine.refine as engine
    from autoalign.engine.refine import RefineOptions, refine
    from autoalign.experiments.scenes.synthetic import make_scene
    from autoalign.geometry.se3 import pose_change
    from autoalign.losses.see_through import SeeThrough
    from autoalign.rasterizers.pyramid import MeshPyramid

    mesh, T, cams, depths = box_with_depth
    seed = perturb_pose(T, 5.0, 5.0, np.random.default_rng(1), mesh.centre)
    behind = [np.where(d > 0, d + 150.0, 0.0).astype(np.float32) for d in depths]  # the table through glass
    opts = RefineOptions(region=None)
    runs: list[bool] = []
    one_run = engine._refine_evidence

    def counted_run(scene, *args, **kwargs):
        runs.append(scene.depths is not None)
        return one_run(scene, *args, **kwargs)

    monkeypatch.setattr(engine, "_refine_evidence", counted_run)
    for depth, glass in ((behind, True), (depths, False)):
        runs.clear()
        scene = make_scene(mesh, T, cams)
        result = refine(replace(scene, depths=depth), MeshPyramid(mesh), seed, opts)
        mm, deg = pose_change(T, result.T_wm, mesh.centre)
        assert mm < 1.0 and deg < 1.0, (glass, mm, deg)
        seen = result.measurement(SeeThrough)
        if glass:
            assert runs == [False] and seen is not None and seen.sees_through() and not seen.declared
        else:
            assert runs == [True] and seen is None


@pytest.mark.slow
def test_check_recognises_glass_from_the_depth_unless_declared(table: dict, tmp_path: Path) -> None:
    """Issue 45, must-show 7: ``check`` on the true labels, with the scene's depth, recognises the glass
    (its depth seen through at its labels) and does not report a feature distance for it, which would
    be chance matches on what lies behind it; the opaque object beside it is measured as before. A
    model declared opaque in ``materials.json`` is never recognised."""
    from autoalign.cli.check import format_table
    from autoalign.quality.scene_check import check_scene

    scene = table["root"] / "scene"
    report = check_scene(scene, scene / "scene_gt.json", table["models"], images=4)
    glass, opaque = sorted(report.instances, key=lambda s: s.obj_id)
    assert glass.recognised and glass.material == "transparent" and not glass.features_measurable
    assert glass.through_share >= max(SEES_THROUGH, 0.9) and glass.mean_px is None and glass.edge_px is not None
    assert not opaque.recognised and opaque.material == "opaque" and opaque.features_measurable
    assert opaque.through_share < 0.2
    assert "not measurable (transparent, from the depth)" in format_table(report)
    assert glass.record()["material_recognised"] is True

    models = tmp_path / "models"
    models.mkdir()
    for f in table["models"].iterdir():
        (models / f.name).write_bytes(f.read_bytes())
    (models / "materials.json").write_text(json.dumps({"1": {"material": "opaque"}}))
    declared = check_scene(scene, scene / "scene_gt.json", models, images=4)
    glass = min(declared.instances, key=lambda s: s.obj_id)
    assert not glass.recognised and glass.material == "opaque" and glass.features_measurable


@pytest.mark.slow
def test_a_click_on_glass_on_the_label_page_places_it(table: dict, tmp_path: Path) -> None:
    """Item 5: the label page's click (the session its server drives) on the glass, in the view that
    shows most of it: its depth, seen through, neither pulls the pose nor fails it, as in ``refine``;
    placed within 1 mm / 1 deg, and the page's reasons say that the depth sees through it."""
    import cv2

    from autoalign.experiments.pages.label_page_driver import mask_pixel
    from autoalign.io.models import ModelSet
    from autoalign.label.session import LabelSession

    scene = table["root"] / "scene"
    masks = {int(p.stem.split("_")[0]): cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0
             for p in sorted((scene / "mask_visib").glob("*_000000.png"))}
    image_id = max(masks, key=lambda im: int(masks[im].sum()))
    session = LabelSession(scene, ModelSet.read(table["models"]), tmp_path / "page")
    index = session.place(1, image_id, *mask_pixel(masks[image_id]))
    placed = session.instances[index]
    e = pose_errors(placed.T_wm, table["ps"].poses[0], table["ps"].meshes[0].centre, None, table["symmetries"][0])
    assert index == 0 and e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, (e.pos_err_mm, e.rot_err_deg)
    assert placed.verdict != "failed", placed.reasons
    assert any("sees through this object (recognised" in r for r in placed.reasons), placed.reasons
