"""A weakly observed turn's sigma from the loss along it (:mod:`autoalign.engine.turn_profile`)."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.hypotheses import turns
from autoalign.engine.refine import refine
from autoalign.engine.turn_profile import bootstrap_minima, profile_minimum
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import make_scene, random_rotation, ring_cameras, wiggle_mask
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose, so3_log
from autoalign.io.bop import Scene


def test_profile_minimum_is_the_parabola_vertex():
    """On samples of a parabola (uneven spacing) the three-point vertex is exact; at the end of
    the samples it is the end."""
    angles = np.array([-24.0, -12.0, -6.0, -3.0, -1.5, 0.0, 1.5, 3.0, 6.0, 12.0, 24.0])
    assert profile_minimum(angles, (angles - 0.7) ** 2 + 3.0) == pytest.approx(0.7)
    assert profile_minimum(angles, (angles - 4.2) ** 2) == pytest.approx(4.2)
    assert profile_minimum(angles, -angles) == 24.0


def test_bootstrap_spread_is_small_where_the_views_agree_and_large_where_they_split():
    """Twenty views each with its minimum at 0 deg (curvatures from 1 to 20: only a few see the
    turn well): every draw's minimum stays at 0. Sixteen at 0 and four, the ones that see the
    turn best, at 12 deg: the summed minimum lies between, and moves with how many of the four a
    draw holds, degrees either way."""
    angles = np.array([-24.0, -12.0, -6.0, -3.0, -1.5, 0.0, 1.5, 3.0, 6.0, 12.0, 24.0])
    h = np.linspace(1.0, 20.0, 20)[:, None]
    agree = h * angles[None] ** 2
    rng = np.random.default_rng(1)
    assert np.std(bootstrap_minima(angles, agree, 500, rng)) < 1e-9
    split = agree.copy()
    split[-4:] = 5.0 * h[-4:] * (angles[None] - 12.0) ** 2
    spread = np.std(bootstrap_minima(angles, split, 500, rng))
    assert spread > 1.0, spread


@pytest.mark.slow
@pytest.mark.parametrize("k", range(4))
def test_roll_sigma_covers_a_roll_the_masks_disagree_on(k):
    """A flashlight (its button the only sign of its roll), outlines wiggled by about 1 px, whose
    masks in every other view show it rolled 30 degrees: its roll is named as weakly observed, the
    loss profile raises its sigma (the views disagree on it), and the sigma covers the roll's error
    within 3 sigma."""
    pm = next(m for m in procedural_models() if m.name == "flashlight")
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    rng = np.random.default_rng([11, k])
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    cams = ring_cameras(24, rng)
    rolled = turns(T, np.array([0.0, 0.0, 1.0]), mesh.centre, (30.0,))[0]
    true, pulled = make_scene(mesh, T, cams), make_scene(mesh, rolled, cams)
    masks = [wiggle_mask((p if v % 2 == 0 else t) > 0.5, rng).astype(np.float32)
             for v, (t, p) in enumerate(zip(true.masks, pulled.masks))]
    r = refine(Scene(true.cameras, masks, true.image_ids), mesh, T)
    roll = float(np.degrees(so3_log(T[:3, :3].T @ r.T_wm[:3, :3]))[2])
    u = r.uncertainty
    assert any(w.startswith("turn about model z") for w in u.weak), u.weak
    assert len(u.turn_floors) >= 1 and abs(u.turn_floors[0].axis_m[2]) > 0.9  # the roll's profile
    assert abs(roll) < 3.0 * u.sigma_deg[2], (roll, u.sigma_deg)


def test_a_floor_raises_its_turn_alone():
    """A floor above the turn's variance raises it to the floor along that turn alone; one below
    leaves the covariance as it was."""
    from autoalign.engine.uncertainty import TurnFloor, uncertainty_of, with_turn_floors

    cov = np.diag([0.04, 0.04, 0.09, np.radians(0.2), np.radians(0.2), np.radians(0.5)]) ** 2
    u = uncertainty_of(cov, cov, np.eye(3))
    z = np.array([0.0, 0.0, 1.0])
    raised = with_turn_floors(u, [TurnFloor(z, np.radians(3.0) ** 2)])
    np.testing.assert_allclose(raised.sigma_deg, [0.2, 0.2, 3.0])
    np.testing.assert_allclose(raised.sigma_mm, u.sigma_mm)
    assert raised.turn_floors and "turn about model z: 3 deg" in raised.weak
    kept = with_turn_floors(u, [TurnFloor(z, np.radians(0.1) ** 2)])
    np.testing.assert_allclose(kept.covariance, u.covariance)


def test_a_free_spin_is_neither_profiled_nor_searched():
    """A can whose spin about its axis the covariance calls weak: declared as the model's continuous
    symmetry, that spin is not among the turns left to measure, and its profile renders nothing and
    leaves the uncertainty as it was; undeclared, the same spin is profiled (13 renders) and floored."""
    from autoalign.engine.objective import SilhouetteObjective
    from autoalign.engine.turn_profile import with_turn_profiles
    from autoalign.engine.uncertainty import uncertainty_of
    from autoalign.geometry.se3 import Symmetries
    from autoalign.rasterizers.pyramid import MeshPyramid

    pm = next(m for m in procedural_models() if m.name == "can_plain")
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    T = make_pose(np.eye(3), -mesh.centre)
    scene = make_scene(mesh, T, ring_cameras(6, np.random.default_rng(3)))
    z = np.array([0.0, 0.0, 1.0])
    cov = np.diag([0.05, 0.05, 0.05, np.radians(0.1), np.radians(0.1), np.radians(5.0)]) ** 2
    u = uncertainty_of(cov, cov, np.eye(3))
    assert len(u.weak_turn_axes) == 1 and abs(u.weak_turn_axes[0] @ z) > 0.99
    declared = SilhouetteObjective(MeshPyramid(mesh, Symmetries(continuous=((z, np.zeros(3)),))), scene)
    assert u.weak_turns_not_free(declared.pyramid.symmetries.axes) == []
    kept = with_turn_profiles(declared, T, u, np.ones(len(scene)), 0.5)
    assert kept is u and declared.renders == 0
    plain = SilhouetteObjective(MeshPyramid(mesh), scene)
    profiled = with_turn_profiles(plain, T, u, np.ones(len(scene)), 0.5)
    assert plain.renders == 1 + 2 * 6 and len(profiled.turn_floors) == 1
