"""One mesh-detail pyramid per model (issue 27): the model set keeps one per object, each image
resolution gets the detail its :class:`MeshDetail` gives, and every IoU that is reported of a pose
(``refine``'s before and after, what the overlay prints, what the label page shows) is one number:
:func:`~autoalign.losses.overlap.view_ious` of the pyramid's full-resolution silhouettes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from autoalign.engine.refine import RefineOptions, refine
from autoalign.experiments.scenes.procedural_models import procedural_models, write_models
from autoalign.experiments.scenes.synthetic import (
    default_K,
    perturb_pose,
    random_rotation,
    ring_cameras,
    write_multi_scene,
)
from autoalign.geometry.se3 import make_pose
from autoalign.io.instances import read_instance_scenes, read_instances
from autoalign.io.models import ModelSet
from autoalign.label.page_geometry import SilhouetteRenderer, fit
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.overlap import view_ious
from autoalign.rasterizers.pyramid import MeshDetail

W, H, VIEWS = 320, 240, 6


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, ModelSet, list[np.ndarray]]:
    """Two procedural objects side by side, each hiding part of the other in some views."""
    root = tmp_path_factory.mktemp("pyramid")
    write_models(root / "models", procedural_models()[1:3])  # box_plain, mug
    models = ModelSet.read(root / "models")
    rng = np.random.default_rng(7)
    truth = []
    for k in range(2):
        R = random_rotation(rng)
        truth.append(make_pose(R, np.array([40.0 * k - 20.0, 0.0, 30.0]) - R @ models.mesh(k + 1).centre))
    cams = ring_cameras(VIEWS, rng, dist_range=(350.0, 450.0), target=(0.0, 0.0, 30.0),
                        K=default_K(W, H, 380.0), width=W, height=H, elev_range_deg=(10.0, 25.0))
    write_multi_scene(root / "scene", [models.mesh(1), models.mesh(2)], [1, 2], truth, cams)
    return root, models, truth


def test_a_model_has_one_pyramid_and_each_resolution_its_detail(pair) -> None:
    _, models, _ = pair
    pyramid = models.pyramid(2)
    assert pyramid is models.pyramid(2) and pyramid.mesh is models.mesh(2)
    n = len(pyramid.mesh.faces)
    detail = MeshDetail(fine=n // 2, coarse=n // 4, search=n // 8)
    fine, coarse, search = pyramid.fine(detail), pyramid.at(0.25, detail), pyramid.at(0.125, detail)
    assert fine is pyramid.at(1.0, detail) and coarse is pyramid.at(0.5, detail) and search is pyramid.at(0.05, detail)
    assert n // 4 < len(fine.mesh.faces) <= n // 2 and n // 8 < len(coarse.mesh.faces) <= n // 4
    assert len(search.mesh.faces) <= n // 8
    assert pyramid.fine(detail) is fine  # made once
    # a budget above the mesh's own size draws the mesh as given, shared with an unlimited budget
    assert pyramid.with_faces(10 * n) is pyramid.with_faces(None) and pyramid.with_faces(None).mesh is pyramid.mesh


def test_every_reported_iou_is_one_number(pair) -> None:
    root, models, truth = pair
    found = read_instance_scenes(root / "scene", read_instances(root / "scene"))
    k, obj_id = 1, found.instances[1].obj_id
    scene = found.scenes[k]
    assert scene.ignore is not None and any(g.any() for g in scene.ignore)  # the other object's pixels are left out
    n = len(models.mesh(obj_id).faces)
    detail = MeshDetail(fine=n // 2, coarse=n // 4, search=n // 8)  # the full-resolution mesh is not the file's
    T0 = perturb_pose(truth[k], 3.0, 3.0, np.random.default_rng(1), models.mesh(obj_id).centre)
    result = refine(scene, models.pyramid(obj_id), T0, RefineOptions(detail=detail))

    drawn = models.pyramid(obj_id).fine(detail)
    after = view_ious(drawn.hard_masks(result.T_wm, scene.cameras), ComparedViews.of(scene))
    before = view_ious(drawn.hard_masks(result.T_init, scene.cameras), ComparedViews.of(scene))
    np.testing.assert_allclose(result.iou_after, after, rtol=0, atol=1e-12)  # from the last evaluation, not cast again
    np.testing.assert_allclose(result.iou_before, before, rtol=0, atol=1e-12)
    assert after.mean() > before.mean() and after.min() > 0.9

    page = SilhouetteRenderer(models, found.image_ids, found.cameras, detail)
    shown = fit(scene, page.silhouettes(obj_id, result.T_wm))
    np.testing.assert_allclose([shown[im] for im in scene.image_ids], after, rtol=0, atol=1e-12)

    # the file's own mesh gives other numbers: the pyramid's detail is what makes them one
    as_file = view_ious(models.pyramid(obj_id).with_faces(None).hard_masks(result.T_wm, scene.cameras),
                        ComparedViews.of(scene))
    assert np.abs(as_file - after).max() > 1e-6
