"""The label page's "refine all together" and ``autoalign refine --models`` are one pipeline (issue
44): on a scene with depth and photos, from the same poses, they give the same poses, sigmas and
verdicts. The page used to pass no depth, skip what the command does after the joint stage (the
outline prior, the photos' disagreement) and judge each pose without them."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.experiments.studies.rgbd_depth import eroded_folder, starts_along_rays
from autoalign.experiments.studies.shared_data import YCBV_RGBD
from autoalign.geometry.se3 import make_pose, pose_change
from autoalign.io.models import ModelSet


@pytest.mark.slow
@pytest.mark.skipif(not YCBV_RGBD.is_dir(), reason=f"no real RGB-D scene at {YCBV_RGBD}")
def test_refine_together_on_the_page_is_the_commands_refine(tmp_path, refine_models_command) -> None:
    """The YCB-Video frames (depth, photos, masks eroded by 4 px), every object 20 mm along its
    ray and a few degrees off: the page's session, its instances placed there (a session saved with
    them, as after a restart), refined together, against ``refine --models --init`` from the same
    poses: every pose within 0.01 mm / 0.01 deg, every sigma within 1%, the same verdicts."""
    from autoalign.label.records import LabelledInstance
    from autoalign.label.session import LabelSession
    from autoalign.label.session_file import SessionFile

    scene = eroded_folder(YCBV_RGBD, tmp_path / "scene", ("scene_camera.json", "scene_gt.json", "rgb", "depth"))
    models = ModelSet.read(YCBV_RGBD / "models")
    _, coarse = starts_along_rays(YCBV_RGBD, models, 20.0, np.radians([3.0, -2.0, 2.0]))
    report = refine_models_command(scene, YCBV_RGBD / "models", coarse)  # world = the camera of image 1

    out = tmp_path / "page"
    placed = [LabelledInstance(k, int(e["obj_id"]), make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), e["cam_t_m2c"]))
              for k, e in enumerate(coarse)]
    SessionFile(out, scene, models.folder).write(1, placed)
    session = LabelSession(scene, models, out)
    session.refine_together()

    assert len(report["instances"]) == len(placed) == 3
    for rec in report["instances"]:
        inst = session.instances[rec["instance"]]
        mm, deg = pose_change(np.asarray(rec["pose"]["T_wm"]), inst.T_wm, models.mesh(inst.obj_id).centre)
        assert mm < 0.01 and deg < 0.01, (inst.obj_id, mm, deg)
        assert inst.source == "together" and inst.verdict == rec["verdict"], (inst.verdict, rec["verdict"])
        assert inst.reasons == rec["reasons"]
        np.testing.assert_allclose(inst.sigma_mm, rec["uncertainty"]["sigma_mm"], rtol=0.01)
        np.testing.assert_allclose(inst.sigma_deg, rec["uncertainty"]["sigma_deg"], rtol=0.01)
