"""The joint stage of ``refine --models`` honours ``--optimizer`` and ``--loss`` or refuses them
(issue 44, "No silent skip"): it hard-wired Levenberg-Marquardt and the L2 loss, so ``--optimizer
gn`` and ``--loss iou`` were silently not what solved the objects together."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from autoalign.engine.refine import RefineOptions
from autoalign.engine.solver import Adam, GaussNewton
from autoalign.errors import AutoalignError
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.io.instances import read_init_poses, read_instance_scenes, read_instances
from autoalign.io.models import ModelSet
from autoalign.scene import refine as scene_refine

EXAMPLE = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"


@pytest.mark.parametrize("option", [["--loss", "iou"], ["--loss", "bce"], ["--optimizer", "adam"]])
def test_an_option_the_joint_stage_cannot_honour_is_a_one_line_error(tmp_path: Path, option: list[str]) -> None:
    """``--solve-scale`` makes the bundled example's one object go through the joint stage: ``--loss
    iou`` (or bce, or ``--optimizer adam``) stops at once with exit 2, one line naming the option
    and the fix, no traceback, and no ``--out``."""
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(EXAMPLE / "scene"), "--models",
                        str(EXAMPLE / "models"), "--init", str(EXAMPLE / "init_gt.json"), "--solve-scale", *option,
                        "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    lines = [s for s in p.stderr.splitlines() if s.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"autoalign: error: {option[0]} {option[1]}:"), p.stderr
    assert "--model" in lines[0] and "Traceback" not in p.stderr
    assert not out.exists()


def test_the_joint_rule_follows_the_optimizer() -> None:
    assert scene_refine.joint_rule(RefineOptions()) is None  # the stage's own Levenberg-Marquardt
    assert isinstance(scene_refine.joint_rule(RefineOptions(optimizer=GaussNewton())), GaussNewton)
    with pytest.raises(AutoalignError, match="--optimizer adam"):
        scene_refine.joint_rule(RefineOptions(optimizer=Adam()))
    with pytest.raises(AutoalignError, match="--loss dice"):
        scene_refine.joint_rule(RefineOptions(loss="dice"))


@pytest.mark.slow
def test_optimizer_gn_solves_the_joint_stage_with_gauss_newton(monkeypatch: pytest.MonkeyPatch) -> None:
    """``optimizer=GaussNewton()`` with the scale solved: every joint solve is given Gauss-Newton steps, and the
    label ends within 1 mm / 1 deg of the bundled example's truth with the scale within 0.002 of 1."""
    given = []
    joint = scene_refine.refine_jointly

    def spy(*args, **kwargs):
        given.append(kwargs.get("rule"))
        return joint(*args, **kwargs)

    monkeypatch.setattr(scene_refine, "refine_jointly", spy)
    found = read_instance_scenes(EXAMPLE / "scene", read_instances(EXAMPLE / "scene"))
    models = ModelSet.read(EXAMPLE / "models")
    seeds = read_init_poses(EXAMPLE / "init_gt.json", found)
    done = scene_refine.refine_scene(found, models, seeds, RefineOptions(optimizer=GaussNewton()), solve_scale=True)
    assert given and all(isinstance(r, GaussNewton) for r in given), given
    truth = read_init_poses(EXAMPLE / "scene" / "scene_gt.json", found)
    for r in done.results:
        k = r.instance.index
        e = pose_errors(r.result.T_wm, truth[k], models.mesh(r.instance.obj_id).centre, None, Symmetries())
        assert e.pos_err_mm < 1.0 and e.rot_err_deg < 1.0, e
    assert abs(done.scale - 1.0) < 0.002, done.scale
