"""A weakly observed turn's sigma from the loss along it (:mod:`autoalign.engine.turn_profile`)."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.hypotheses import turns
from autoalign.engine.refine import refine
from autoalign.engine.turn_profile import bootstrap_minima, profile_minimum, shared_shift_minima, view_draws
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
    raised = with_turn_floors(u, [TurnFloor(z, np.radians(3.0) ** 2, np.radians(3.0) ** 2)])
    np.testing.assert_allclose(raised.sigma_deg, [0.2, 0.2, 3.0])
    np.testing.assert_allclose(raised.sigma_mm, u.sigma_mm)
    assert raised.turn_floors and "turn about model z: 3 deg" in raised.weak
    kept = with_turn_floors(u, [TurnFloor(z, np.radians(0.1) ** 2, np.radians(0.1) ** 2)])
    np.testing.assert_allclose(kept.covariance, u.covariance)
    # the covariance takes the floor with the shared outline shift, the views' spread their own
    both = with_turn_floors(u, [TurnFloor(z, np.radians(1.0) ** 2, np.radians(3.0) ** 2)])
    np.testing.assert_allclose(both.sigma_deg, [0.2, 0.2, 3.0])
    np.testing.assert_allclose(np.degrees(np.sqrt(both.spread[5, 5])), 1.0)


def test_a_shared_outline_shift_moves_a_shallow_profiles_minimum_as_its_tilt_says():
    """Twenty views that agree on a shallow minimum at 0 deg (curvatures h_v), whose outline
    shifted by b px tilts each profile by b g_v per degree: the summed minimum sits at
    -b sum g / (2 sum h). Resampling the views alone leaves it at 0; with one shift per draw
    from N(0, s^2) its spread is s |sum g| / (2 sum h) (to the 500 draws' sampling error)."""
    angles = np.array([-24.0, -12.0, -6.0, -3.0, -1.5, 0.0, 1.5, 3.0, 6.0, 12.0, 24.0])
    rng = np.random.default_rng(3)
    h = rng.uniform(0.5, 2.0, 20)[:, None]
    g = rng.uniform(2.0, 6.0, 20)[:, None]  # every view tilted the same way: a shift they share
    s = 1.2
    shifts = s * np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    mid = h * angles[None] ** 2
    shifted = np.stack([mid + b * g * angles[None] for b in shifts])
    counts = view_draws(20, 500, rng)
    assert np.std(bootstrap_minima(angles, mid, 500, rng)) < 1e-9
    spread = np.std(shared_shift_minima(angles, shifted, shifts, s, counts, rng))
    expected = s * np.mean(np.abs(counts @ g[:, 0]) / (2.0 * counts @ h[:, 0]))
    assert spread == pytest.approx(expected, rel=0.1), (spread, expected)


def test_moved_outlines_are_the_masks_moved_by_the_euclidean_distance():
    """:func:`moved_outline` at 0 px is the mask; at whole pixels it agrees with the binary
    Euclidean shift (``shift_outline``, cv2's distance transform thresholded) but on the pixels a
    diagonal outline crosses in part (within 1.5% of the area), and a fraction of a pixel moves
    the area by that fraction of the perimeter."""
    from autoalign.experiments.studies.sam_failures import shift_outline
    from autoalign.losses.silhouette import moved_outline

    yy, xx = np.mgrid[:200, :240]
    disc = (xx - 120.0) ** 2 + (yy - 100.0) ** 2 <= 60.0 ** 2
    np.testing.assert_array_equal(moved_outline(disc, 0.0), disc)
    for px in (-2.0, -1.0, 1.0, 2.0):
        binary = shift_outline(disc, px)
        assert abs(moved_outline(disc, px).sum() - binary.sum()) < 0.015 * disc.sum(), px
    perimeter = 2 * np.pi * 60.0
    grown = moved_outline(disc, 0.4).sum() - disc.sum()
    assert grown == pytest.approx(0.4 * perimeter, rel=0.1), (grown, 0.4 * perimeter)


def _finely_moved(mask: np.ndarray, px: float, factor: int = 4) -> np.ndarray:
    """``mask``'s outline moved ``px`` by the binary Euclidean shift (``shift_outline``) at
    ``factor`` times the resolution, area-averaged back: an independent sub-pixel reference."""
    import cv2

    from autoalign.experiments.studies.sam_failures import shift_outline

    big = cv2.resize((mask > 0.5).astype(np.uint8), None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
    moved = shift_outline(big > 0, px * factor).astype(np.float32)
    return cv2.resize(moved, (mask.shape[1], mask.shape[0]), interpolation=cv2.INTER_AREA)


def test_losses_against_moved_outlines_tilt_a_profile_as_finely_moved_masks_do():
    """The loss between two poses 3 deg apart (the tilt that moves a profile's minimum) changes,
    when every mask's outline moves by half a pixel to two out or in
    (:meth:`SilhouetteObjective.with_moved_outlines`, at the profile's half resolution), as with
    masks moved by the binary Euclidean shift at 4x the resolution (within 15%), and by more than
    a fiftieth of the tilt: the shift matters."""
    from autoalign.engine.objective import Level, SilhouetteObjective
    from autoalign.rasterizers.pyramid import MeshPyramid

    pm = next(m for m in procedural_models() if m.name == "flashlight")
    mesh = mesh_from_trimesh(pm.mesh, pm.name)
    rng = np.random.default_rng(5)
    R = random_rotation(rng)
    T = make_pose(R, -R @ mesh.centre)
    scene = make_scene(mesh, T, ring_cameras(12, rng))
    level = Level(0.5, 1.0, 0)
    turned = turns(T, np.array([1.0, 0.0, 0.0]), mesh.centre, (3.0,))[0]
    obj = SilhouetteObjective(MeshPyramid(mesh), scene, robust=False)
    evs = [obj.evaluate(P, level) for P in (T, turned)]
    tilt = evs[1].terms.loss.sum() - evs[0].terms.loss.sum()
    for px in (-2.0, -1.0, 0.5, 1.0):
        moved = obj.with_moved_outlines(level, px)
        change = obj.loss_against(evs[1], moved).sum() - obj.loss_against(evs[0], moved).sum() - tilt
        fine = Scene(scene.cameras, [_finely_moved(m, px) for m in scene.masks], scene.image_ids)
        ref = SilhouetteObjective(MeshPyramid(mesh), fine, robust=False)
        ref_change = ref.evaluate(turned, level).terms.loss.sum() - ref.evaluate(T, level).terms.loss.sum() - tilt
        assert abs(ref_change) > 0.02 * abs(tilt), (ref_change, tilt)
        assert change == pytest.approx(ref_change, rel=0.15), (px, change, ref_change)
