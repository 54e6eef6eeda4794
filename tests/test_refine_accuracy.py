"""Refinement accuracy on synthetic scenes whose masks come from open3d ray casting (issue #2, 1-3).

The full-size study (20+ scenes per seed, with timings) is ``experiments/studies/refine_study.py``; these
tests run a smaller sample of the same scenes with the same thresholds.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import autoalign
from autoalign.engine.refine import refine
from autoalign.experiments.benchmarks.bench_refine import blob_mesh
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import (
    make_scene,
    perturb_pose,
    random_rotation,
    sphere_cameras,
)
from autoalign.experiments.studies.refine_study import (
    TOLERANCES,
    make_study_scene,
    pose_errors,
    run_in_process,
    study_meshes,
    summarise,
)
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose


@pytest.fixture(scope="module")
def meshes():
    return study_meshes()


def _study(meshes, kind: str, n: int) -> dict:
    rows = [run_in_process(make_study_scene(k, kind, meshes), kind) for k in range(n)]
    for r in rows:
        print(r)
    return summarise(rows, *TOLERANCES[kind])


@pytest.mark.slow
def test_init_seed_reaches_1mm_1deg(meshes) -> None:
    s = _study(meshes, "init", 12)
    assert s["success"] >= 0.95, s


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["click", "none"])
def test_click_and_no_seed_reach_1mm_1deg(meshes, kind: str) -> None:
    s = _study(meshes, kind, 4)
    assert s["success"] >= 0.9, s


@pytest.mark.slow
def test_a_click_previews_the_searchs_first_pose_and_ends_as_without(meshes) -> None:
    """``preview`` is called first before any descent, with a pose at the click's position (its
    centre within a tenth of the diameter of the truth's), then with the refined pose before its
    uncertainty is worked out (on masks alone nothing moves it after: the result's pose); the result
    is the same to the bit."""
    from autoalign.engine.seeding import Click

    s = make_study_scene(1, "click", meshes)
    shown: list[np.ndarray] = []
    seen = refine(s.scene, s.mesh, Click(*s.click), preview=shown.append)
    plain = refine(s.scene, s.mesh, Click(*s.click))
    assert len(shown) == 2 and np.array_equal(shown[1], seen.T_wm)
    centre = lambda T: T[:3, :3] @ s.mesh.centre + T[:3, 3]  # noqa: E731
    assert np.linalg.norm(centre(shown[0]) - centre(s.T_gt)) < 0.1 * s.mesh.diameter
    assert np.array_equal(seen.T_wm, plain.T_wm) and seen.iterations == plain.iterations
    e_mm, e_deg = pose_errors(seen.T_wm, s.T_gt, s.mesh.centre)
    assert e_mm < TOLERANCES["click"][0] and e_deg < TOLERANCES["click"][1], (e_mm, e_deg)


@pytest.mark.slow
def test_thirty_percent_corrupted_masks_stay_within_2mm_2deg(meshes) -> None:
    s = _study(meshes, "corrupt", 4)
    assert s["success"] >= 0.9, s


@pytest.mark.slow
def test_the_full_resolution_budget_lets_a_slow_roll_converge(meshes) -> None:
    """The pen of the study's corrupted scene 19 turns slowly about its long axis at full
    resolution (the roll barely shows in the silhouettes): with a budget of 15 iterations there
    it stopped unconverged at 8.2 degrees; within 30 it converges (17 iterations)."""
    s = make_study_scene(19, "corrupt", meshes)
    res = autoalign.refine(s.scene, s.mesh, seed=s.T_init)
    e_mm, e_deg = pose_errors(res.T_wm, s.T_gt, s.mesh.centre)
    assert res.history[-1]["converged"], [(h["scale"], h["iterations"]) for h in res.history]
    assert e_mm < TOLERANCES["corrupt"][0] and e_deg < TOLERANCES["corrupt"][1], (e_mm, e_deg)


def _refine_synthetic(mesh, seed: int = 3) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    cams = sphere_cameras(20, rng)
    R = random_rotation(rng)
    T_gt = make_pose(R, -R @ mesh.centre)
    scene = make_scene(mesh, T_gt, cams)
    T0 = perturb_pose(T_gt, 8.0, 15.0, rng, mesh.centre)
    res = autoalign.refine(scene, mesh, seed=T0)
    return pose_errors(res.T_wm, T_gt, mesh.centre)


def test_open_non_watertight_mesh() -> None:
    tm = trimesh.creation.annulus(r_min=25.0, r_max=40.0, height=60.0, sections=48)
    keep = np.ones(len(tm.faces), dtype=bool)
    keep[np.flatnonzero(tm.triangles_center[:, 2] > 29.0)[::2]] = False  # punch holes in the top rim
    handle = trimesh.creation.box((30.0, 10.0, 40.0), transform=make_pose(np.eye(3), [50.0, 0.0, 5.0]))
    open_mesh = trimesh.util.concatenate([trimesh.Trimesh(tm.vertices, tm.faces[keep], process=False), handle])
    mesh = mesh_from_trimesh(open_mesh, "open_cup")
    assert (mesh.edge_faces[:, 1] < 0).sum() > 0  # really has open boundary edges
    e_mm, e_deg = _refine_synthetic(mesh)
    assert e_mm < 1.0 and e_deg < 1.0, (e_mm, e_deg)


@pytest.mark.slow
def test_dense_50k_face_mesh() -> None:
    mesh = blob_mesh(50000)
    assert len(mesh.faces) >= 50000
    e_mm, e_deg = _refine_synthetic(mesh)
    assert e_mm < 1.0 and e_deg < 1.0, (e_mm, e_deg)


@pytest.mark.slow
def test_search_keeps_a_slowly_descending_hypothesis_under_eroded_masks() -> None:
    """The simulated mug (trial 0) with a quarter of its masks eroded: the only hypothesis near
    the true orientation starts 37 degrees off and descends by 1-2% per step at the search level.
    With the search stopping at ``FTOL / scale`` (0.8% predicted gain) it was dropped and the
    answer was the upside-down mug (180 degrees off); with the full-resolution ``FTOL`` it is
    found to 1 mm and 1 degree."""
    from autoalign.experiments.scenes.synthetic import corrupt_views
    from autoalign.experiments.studies.protocol import ImageSetup, make_trial, noise_rng
    from autoalign.experiments.studies.runner import get_model

    entry = get_model("procedural44", 3)
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, 0, 3, 0, 40, 100.0, ImageSetup())
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    scene.masks, _ = corrupt_views(scene.masks, 0.25, noise_rng(0, 3, 0), kinds=("erode",))
    result = autoalign.refine(scene, entry.mesh)
    e_t, e_r = pose_errors(result.T_wm, geo.T_gt, entry.mesh.centre)
    assert e_t < 1.0 and e_r < 1.0, (e_t, e_r)


def test_empty_masks_in_memory_are_left_out_not_targets() -> None:
    """A segmentation dropout (2 of 24 masks empty) through the Python API: the views are left out.

    Compared as "object absent" targets they pulled this mug 50 degrees off."""
    from autoalign.experiments.scenes.synthetic import ring_cameras
    from autoalign.io.bop import Scene

    rng = np.random.default_rng(3)
    pm = next(m for m in procedural_models() if m.name == "mug")
    mesh = mesh_from_trimesh(pm.mesh, "mug")
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    scene = make_scene(mesh, T, ring_cameras(24, rng))
    masks = [np.zeros_like(m) if k in (3, 15) else m for k, m in enumerate(scene.masks)]
    result = refine(Scene(scene.cameras, masks, scene.image_ids), mesh, perturb_pose(T, 10.0, 15.0, rng, mesh.centre))
    assert result.image_ids == [i for i in scene.image_ids if i not in (3, 15)]
    e_t, e_r = pose_errors(result.T_wm, T, mesh.centre)
    assert e_t < 1.0 and e_r < 1.0
