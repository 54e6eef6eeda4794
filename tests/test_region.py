"""The region (colour) term: colour models and posteriors, and refinement on photos with and
without masks, on textured objects on a textured table rendered with mitsuba (masks cast with open3d)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

import autoalign
from autoalign.engine.hypotheses import flips
from autoalign.engine.photo_evidence import PhotoEvidence, best_side, photo_rounds, photo_value
from autoalign.engine.refine import RefineOptions, refine
from autoalign.experiments.scenes.photo_scene import PhotoScene, write_photo_scene
from autoalign.experiments.scenes.procedural_models import procedural_models
from autoalign.experiments.scenes.synthetic import perturb_pose
from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import rotation_angle_deg, transform_points
from autoalign.io.bop import read_cameras, read_scene, scene_gt_of
from autoalign.io.photos import with_photos
from autoalign.losses.region import (
    ColourModel,
    RegionOptions,
    colour_codes,
    colour_counts,
    colour_separation,
    colour_weight,
    region_target,
)
from autoalign.losses.region_term import RegionTerm
from autoalign.rasterizers.pyramid import MeshPyramid

NAMES = ("box_knob", "mug", "l_bracket")


def _errors(T, T_true, centre):
    c = centre[None]
    return (float(np.linalg.norm(transform_points(T, c) - transform_points(T_true, c))),
            rotation_angle_deg(T[:3, :3], T_true[:3, :3]))


@pytest.fixture(scope="module")
def photo_scene(tmp_path_factory) -> PhotoScene:
    pool = {p.name: p for p in procedural_models()}
    meshes = [mesh_from_trimesh(pool[n].mesh, n) for n in NAMES]
    folder = tmp_path_factory.mktemp("photo_scene")
    ps = write_photo_scene(folder / "scene", meshes, 16, seed=3)
    (folder / "models").mkdir()
    for j, n in enumerate(NAMES):
        pool[n].mesh.export(folder / "models" / f"obj_{j + 1:06d}.ply")
    return ps


@pytest.fixture(scope="module")
def starts(photo_scene) -> list[np.ndarray]:
    rng = np.random.default_rng(11)
    return [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(photo_scene.poses, photo_scene.meshes)]


def test_posterior_matches_the_colour_counts():
    """Two colours only on the object, one only around it, one shared half and half: the
    posterior is 1, 0 and 1/2 (equal priors), as counting the pixels by hand gives."""
    rng = np.random.default_rng(0)
    photo = np.zeros((60, 60, 3), np.uint8)
    sil = np.zeros((60, 60), bool)
    sil[15:45, 15:45] = True
    fg_colours = np.array([[200, 30, 30], [30, 200, 30]], np.uint8)
    photo[sil] = fg_colours[rng.integers(0, 2, sil.sum())]
    photo[~sil] = (30, 30, 200)
    shared = (slice(28, 32), slice(10, 50))  # a stripe across the outline, half in and half out
    photo[shared] = (120, 120, 120)
    codes = colour_codes(photo, 16)
    model = ColourModel.learn(codes, sil, ~sil, 16)
    post = model.posterior(codes)
    assert np.allclose(post[20, 20], 1.0, atol=1e-2) and np.allclose(post[5, 5], 0.0, atol=1e-2)
    grey = codes[30, 30]
    n_in, n_out = np.count_nonzero(sil[shared]), np.count_nonzero(~sil[shared])
    expected = (n_in / sil.sum()) / (n_in / sil.sum() + n_out / (~sil).sum())
    assert post[30, 30] == pytest.approx(expected, abs=1e-3) and codes[30, 30] == grey


def test_region_target_completes_a_partial_mask():
    """Where the mask misses half the object the photo's posterior says object; beyond the band
    the target is background; on the mask, with the object's colours, object; a mask pixel on the
    surroundings' colours is in doubt (the mask's and the colour's odds multiply: the colours lower
    it below what this mask, right in 95% of its band against the silhouette, says alone, and the
    mask keeps it from the background's value)."""
    photo = np.full((120, 120, 3), (40, 160, 40), np.uint8)  # green surroundings
    sil = np.zeros((120, 120), bool)
    sil[30:90, 30:90] = True
    photo[sil] = (180, 40, 160)
    mask = np.zeros((120, 120), np.float32)
    mask[30:90, 30:60] = 1.0  # the left half only ...
    mask[40:50, 22:30] = 1.0  # ... and a strip beyond the object
    t = region_target(photo, sil, mask, None, RegionOptions()).target
    assert t[60, 75] > 0.95  # missed by the mask, object by colour
    assert t[60, 45] > 0.99
    assert 0.3 < t[45, 25] < 0.9  # claimed by the mask, surroundings by colour
    assert t[60, 95] < 0.05 and t[5, 5] == 0.0  # surroundings in the band, and beyond it


def test_colour_separation_is_the_leave_one_out_posteriors_contrast():
    """:func:`colour_separation` equals, pixel by pixel, the posterior of models learned again
    without that pixel (:class:`ColourModel`, two sectors), averaged inside less outside; a photo
    whose object shows its background's colours (clear glass) reads near 0, one of distinct colours
    near 1, and too few pixels a side NaN."""
    rng = np.random.default_rng(1)
    bins, groups = 2, 2
    key = rng.integers(0, groups * bins ** 3, 300)
    inside = rng.random(300) < 0.4
    outside = ~inside & (rng.random(300) < 0.8)
    by_hand = []
    for side in (inside, outside):
        for i in np.flatnonzero(side):
            without = np.ones(300, bool)
            without[i] = False
            model = ColourModel.learn_keys(key, inside & without, outside & without, bins, groups)
            by_hand.append((model.posterior_of_keys(key[i:i + 1])[0], side is inside))
    mean_in = np.mean([p for p, is_in in by_hand if is_in])
    mean_out = np.mean([p for p, is_in in by_hand if not is_in])
    assert colour_separation(key, inside, outside, bins, groups) == pytest.approx(mean_in - mean_out, abs=1e-12)

    sil = np.zeros((120, 120), bool)
    sil[30:90, 30:90] = True
    texture = rng.integers(0, 256, (120, 120, 3), dtype=np.uint8)  # the same colours everywhere
    glassy = region_target(texture, sil, None, None, RegionOptions(), separation=True).separation
    distinct = texture.copy()
    distinct[sil] = (180, 40, 160)
    distinct[~sil] = (40, 160, 40)
    assert abs(glassy) < 0.1
    assert region_target(distinct, sil, None, None, RegionOptions(), separation=True).separation > 0.95
    assert np.isnan(region_target(distinct, sil, None, None, RegionOptions()).separation)  # not asked: not measured
    assert np.isnan(colour_separation(key, inside & (np.arange(300) < 30), outside, bins, groups))


def test_colour_weight_is_the_calibrating_temperature_of_the_leave_one_out_log_odds():
    """:func:`colour_weight` is the weight in [0, 1] of the colour models' log-odds that maximises
    the balanced log-likelihood of pixels they were not learned from (models learned again without
    each pixel; scipy's bounded search, to 1e-4). Fused with a mask, a photo whose object shows its
    background's colours gets a weight near 0 and a target that is the mask's evidence alone, and
    distinct colours keep the posteriors as learned (weight exactly 1); without a mask the colours
    are kept as learned."""
    from scipy.optimize import minimize_scalar

    for seed in range(3):
        rng = np.random.default_rng(seed)
        n, bins, groups = 400, 2, 2
        inside = rng.random(n) < 0.45
        outside = ~inside
        own = rng.random(n) < 0.6  # each pixel's colour leans weakly to its own side's half of the codes
        key = rng.integers(0, groups, n) * bins ** 3 + rng.integers(0, 4, n) + np.where(inside == own, 0, 4)
        logits, is_in = [], []
        for i in range(n):
            without = np.ones(n, bool)
            without[i] = False
            p = ColourModel.learn_keys(key, inside & without, outside & without, bins, groups).posterior_of_keys(
                key[i:i + 1])[0]
            logits.append(np.log(p / (1.0 - p)))
            is_in.append(inside[i])
        lg, y = np.array(logits), np.array(is_in)

        def nll(w: float) -> float:
            return float(np.mean(np.log1p(np.exp(-w * lg[y]))) + np.mean(np.log1p(np.exp(w * lg[~y]))))

        best = minimize_scalar(nll, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-8}).x
        assert 0.05 < best < 0.95  # the weight is found inside the range, not at a bound
        assert colour_weight(*colour_counts(key, inside, outside, bins, groups), key, inside, outside) == \
            pytest.approx(best, abs=1e-4)

    rng = np.random.default_rng(1)
    sil = np.zeros((120, 120), bool)
    sil[30:90, 30:90] = True
    texture = rng.integers(0, 256, (120, 120, 3), dtype=np.uint8)  # the same colours everywhere
    mask = np.zeros((120, 120), np.float32)
    mask[34:86, 34:86] = 1.0  # 4 px inside the silhouette all round
    glassy = region_target(texture, sil, mask, None, RegionOptions())
    assert glassy.weight < 0.05
    ring = sil & (mask == 0)
    assert np.all(np.abs(glassy.target[ring] - 0.2) < 0.02)  # the mask's P(object | it says background) alone
    distinct = texture.copy()
    distinct[sil] = (180, 40, 160)
    distinct[~sil] = (40, 160, 40)
    kept = region_target(distinct, sil, mask, None, RegionOptions())
    assert kept.weight == 1.0 and np.all(kept.target[ring] > 0.9)  # the colours complete the mask
    assert region_target(texture, sil, None, None, RegionOptions()).weight == 1.0  # no mask: they draw the outline


def test_the_region_term_takes_the_mask_terms_place_and_leaves_the_scene_as_given():
    """The region term, learned at a pose from half masks and two-coloured photos, completes the masks
    in its targets; the objective of a photo run has it in the mask term's place and compares the views
    with its targets, leaves out the view whose target does not show the object, keeps it on a subset
    of the views, fits the true pose better than the half masks alone do; and the caller's scene keeps
    its masks and photos."""
    from autoalign.engine.schedule import compared_objective
    from autoalign.experiments.scenes.synthetic import default_K, ring_cameras
    from autoalign.io.bop import Scene
    from autoalign.losses.mask_term import MaskTerm

    mesh = mesh_from_trimesh(next(p for p in procedural_models() if p.name == "box_knob").mesh, "box_knob")
    cams = ring_cameras(3, np.random.default_rng(5), dist_range=(380.0, 420.0), K=default_K(160, 120, 190.0),
                        width=160, height=120)
    T = np.eye(4)
    T[:3, 3] = -mesh.centre  # the object at the cameras' target
    pyramid = MeshPyramid(mesh)
    sils = pyramid.fine().hard_masks(T, cams)
    sils[2][:] = False  # the third view does not see it (as if out of frame): its photo is all surroundings
    photos, masks = [], []
    for sil in sils:
        photo = np.full(sil.shape + (3,), (40, 160, 40), np.uint8)
        photo[sil] = (180, 40, 160)
        photos.append(photo)
        half = sil.copy()
        cols = np.nonzero(sil.any(axis=0))[0]
        if len(cols):
            half[:, (cols.min() + cols.max()) // 2:] = False  # the mask misses the right half
        masks.append(half.astype(np.float32))
    scene = Scene(cams, [m.copy() for m in masks], [1, 2, 3], photos=photos)
    term = RegionTerm.learned_at(scene, sils, RegionOptions())
    assert term.covered() == [0, 1]
    for k in (0, 1):
        assert np.mean(term.targets[k][sils[k]] > 0.5) > 0.95  # the right half completed
    opts = RefineOptions()
    obj = compared_objective(pyramid, scene, opts, term)
    assert [t for t in obj.terms if type(t) is MaskTerm] == [] and term.subset([0, 1]).learned == obj.region.learned
    assert obj.compared.image_ids == [1, 2]
    assert obj.compared.photos is None  # with masks the photos are the term's alone
    assert all(np.array_equal(a, b) for a, b in zip(obj.compared.targets, term.targets[:2]))
    assert obj.compared.scene.photos is not None  # the scene it holds is as given: masks and photos
    assert all(np.array_equal(a, b) for a, b in zip(obj.compared.scene.masks, masks[:2]))
    sub = obj.subset([1])
    assert sub.region is not None and sub.region.learned == (term.learned[1],)
    masks_alone = compared_objective(pyramid, scene, opts)
    level = opts.schedule[-1]
    assert obj.evaluate(T, level).value < 0.1 * masks_alone.evaluate(T, level).value  # measured 0.010 against 1.08
    assert scene.photos is photos and all(np.array_equal(a, b) for a, b in zip(scene.masks, masks))


@pytest.mark.slow
def test_photos_alone_refine_every_object(photo_scene, starts):
    """No masks at all: from 10 mm / 15 deg off, each object ends within 1 mm / 1 deg, and more of
    the band's colours agree with its silhouette there than at the start."""
    scene = autoalign.read_evidence(photo_scene.folder, modalities=("photos",))  # the Python API's way to withhold the masks
    assert scene.photos is not None and not any(m.any() for m in scene.masks)
    for T0, T_true, mesh in zip(starts, photo_scene.poses, photo_scene.meshes):
        res = refine(scene, mesh, T0)
        mm, deg = _errors(res.T_wm, T_true, mesh.centre)
        assert mm < 1.0 and deg < 1.0, (mesh.name, mm, deg)
        at_start = RegionTerm.learned_at(scene, MeshPyramid(mesh).fine().hard_masks(T0, scene.cameras), RegionOptions())
        photo = res.measurement(PhotoEvidence)
        assert photo is not None and len(photo.agreement) == len(scene)
        assert np.median(photo.agreement) > np.median([rt.agreement for rt in at_start.learned]) + 0.02


@pytest.mark.slow
def test_with_photos_the_seed_radius_is_measured_from_the_anchor(photo_scene):
    """``refine(..., anchor=A)`` with photos holds the result near ``A``, as without them: seeded at the
    truth with an anchor 20 mm away, the result (at the truth) is 20 mm beyond the anchor's radius."""
    k = 1
    mesh, T_true = photo_scene.meshes[k], photo_scene.poses[k]
    A = T_true.copy()
    A[:3, 3] += [20.0, 0.0, 0.0]
    scene = with_photos(read_scene(photo_scene.folder, k))
    res = refine(scene, mesh, T_true, RefineOptions(seed_radius=(5.0, 5.0)), anchor=A)
    assert res.seed_hold is not None and abs(res.seed_hold.far_move[0] - 20.0) < 2.0, res.seed_hold
    assert res.seed_hold.kept_far and _errors(res.T_wm, T_true, mesh.centre)[0] < 1.0


def _left_halves(scene):
    """``scene`` with every mask cut to the left half of its columns."""
    cut = []
    for m in scene.masks:
        xs = np.nonzero(m.any(0))[0]
        c = m.copy()
        c[:, (xs.min() + xs.max()) // 2:] = 0.0
        cut.append(c)
    return replace(scene, masks=cut)


@pytest.mark.slow
def test_photos_complete_masks_that_miss_half_the_object(photo_scene, starts):
    """Every mask cut to its left half: masks alone end off, with the photos within 2 mm / 2 deg."""
    k = 0
    mesh, T_true = photo_scene.meshes[k], photo_scene.poses[k]
    scene = _left_halves(read_scene(photo_scene.folder, k))
    alone = refine(scene, mesh, starts[k], RefineOptions(region=None))
    both = refine(with_photos(scene), mesh, starts[k])
    mm_a, deg_a = _errors(alone.T_wm, T_true, mesh.centre)
    mm_b, deg_b = _errors(both.T_wm, T_true, mesh.centre)
    print(f"half masks: alone {mm_a:.2f} mm {deg_a:.2f} deg, with the photos {mm_b:.2f} mm {deg_b:.2f} deg")
    assert mm_b < 2.0 and deg_b < 2.0, (mm_b, deg_b)
    assert mm_b < mm_a / 2 and deg_b < deg_a / 4  # half masks pull the silhouette onto the half they show


def _init_file(ps: PhotoScene, starts: list[np.ndarray], path: Path) -> Path:
    cams = read_cameras(ps.folder)
    cameras = [Camera.from_opencv(*v, ps.cameras[0].width, ps.cameras[0].height) for v in cams.values()]
    path.write_text(json.dumps(scene_gt_of([(j + 1, T) for j, T in enumerate(starts)], cameras, list(cams))))
    return path


@pytest.mark.slow
def test_refine_models_without_masks(photo_scene, starts, tmp_path):
    """``autoalign refine --models --masks none --init``: every instance from the photos, the others
    left out of each one's colour models; refine.json records the region term per view."""
    from autoalign.cli.main import main

    init = _init_file(photo_scene, starts, tmp_path / "init.json")
    out = tmp_path / "out"
    rc = main(["refine", str(photo_scene.folder), "--models", str(photo_scene.folder.parent / "models"),
               "--init", str(init), "--masks", "none", "--out", str(out), "--quiet"])
    assert rc in (0, 3)
    labels = json.loads((out / "scene_gt.json").read_text())["0"]
    cam = photo_scene.cameras[0]
    for j, (entry, T_true, mesh) in enumerate(zip(labels, photo_scene.poses, photo_scene.meshes)):
        T_cm = np.eye(4)
        T_cm[:3, :3], T_cm[:3, 3] = np.reshape(entry["cam_R_m2c"], (3, 3)), entry["cam_t_m2c"]
        mm, deg = _errors(np.linalg.inv(cam.T_cw) @ T_cm, T_true, mesh.centre)
        assert mm < 1.0 and deg < 1.0, (NAMES[j], mm, deg)
    rec = json.loads((out / "refine.json").read_text())
    for inst in rec["instances"]:
        assert len(inst["photo"]["agreement"]) == len(inst["image_ids"]) and inst["photo"]["masks_given"] is False


@pytest.mark.parametrize("extra, message", [
    (["--masks", "none"], "give --init"),
    (["--masks", "none", "--photos", "off", "--init", "x.json"], "drop --photos off"),
    (["--seed-radius", "5"], "expected MM,DEG"),
    (["--seed-radius", "5,-1"], "must be positive"),
])
def test_refine_refuses_what_cannot_work(photo_scene, tmp_path, capsys, extra, message):
    from autoalign.cli.main import main

    rc = main(["refine", str(photo_scene.folder), "--model", str(photo_scene.folder.parent / "models" / "obj_000001.ply"),
               "--out", str(tmp_path / "out"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_photo_of_another_size_is_refused(photo_scene, tmp_path):
    """A photo whose size differs from the masks': a one-line error naming the file."""
    import shutil

    from autoalign.errors import AutoalignError

    folder = tmp_path / "scene"
    shutil.copytree(photo_scene.folder, folder)
    cv2.imwrite(str(folder / "rgb" / "000003.png"), np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(AutoalignError, match="000003.png: the photo is 100x100"):
        with_photos(read_scene(folder, 0))


@pytest.mark.parametrize("iou, contrast, status, words", [
    (0.6, 0.5, "ok", "the photo's colours change across the outline"),  # a loose mask, the photo supports
    (0.4, 0.5, "check", "though the photo's colours change across the outline"),  # a mask missing most of it
    (0.9, 0.05, "check", "the photo disagrees"),
    (0.3, 0.2, "check", "neither confirms nor contradicts"),
    (0.3, 0.05, "failed", "silhouettes do not match the masks"),  # masks and photo both against it
    (0.3, None, "failed", "silhouettes do not match the masks"),  # no photo: the masks decide
])
def test_verdict_reads_the_photo(iou, contrast, status, words):
    from autoalign.quality.verdict import PoseEvidence, judge

    n = 10
    photo = None if contrast is None else PhotoEvidence(np.full(n, 20.0), np.full(n, 0.9), np.full(n, contrast), 3)
    said = None if photo is None else photo.evidence()
    v = judge(PoseEvidence(np.full(n, iou), np.ones(n), list(range(n)), terms=() if said is None else (said,)))
    assert v.status == status and any(words in r for r in v.reasons), v


@pytest.mark.slow
def test_a_result_far_from_its_seed_is_flagged_with_the_distance(photo_scene, tmp_path):
    """``refine --init`` whose pose ends farther from the seed than ``--seed-radius``: `check`, with
    the distance in the reason, and refine.json records the radius and the move; within the
    default radius (25 mm / 30 deg) the same run is not flagged for it."""
    from autoalign.cli.main import main

    rng = np.random.default_rng(3)
    T_true, mesh = photo_scene.poses[0], photo_scene.meshes[0]
    start = perturb_pose(T_true, 10.0, 15.0, rng, mesh.centre)
    init = _init_file(photo_scene, [start] + photo_scene.poses[1:], tmp_path / "init.json")
    model = photo_scene.folder.parent / "models" / "obj_000001.ply"
    for radius, flagged in (("5,5", True), (None, False)):
        out = tmp_path / f"out_{radius}"
        args = ["refine", str(photo_scene.folder), "--model", str(model), "--init", str(init), "--out", str(out),
                "--quiet"] + ([] if radius is None else ["--seed-radius", radius])
        rc = main(args)
        rec = json.loads((out / "refine.json").read_text())
        moved = rec["seed"]["moved_mm_deg"]
        assert moved[0] == pytest.approx(10.0, abs=1.5) and moved[1] == pytest.approx(15.0, abs=1.5)
        assert rec["seed"]["radius_mm_deg"] == ([5.0, 5.0] if radius else [25.0, 30.0])
        far = [r for r in rec["reasons"] if "from the given seed" in r]
        assert bool(far) == flagged and (rc == 3 and rec["verdict"] == "check" if flagged else True)


@pytest.mark.slow
def test_without_a_pose_the_photos_choose_the_side_the_masks_cannot(photo_scene):
    """Masks cut to their left half fit an L-bracket turned half over about as well; the photo rounds
    from that turned pose stay turned, and from it and its half turns the one whose own colour targets
    it fits best is the truth (:func:`~autoalign.engine.photo_evidence.best_side`, the no-seed path)."""
    k = 2
    mesh, T_true = photo_scene.meshes[k], photo_scene.poses[k]
    scene = with_photos(_left_halves(read_scene(photo_scene.folder, k)))
    pyramid, options = MeshPyramid(mesh), RefineOptions()
    masks_only = replace(options, region=None, edges=options.region.edge_weight)
    turned = flips(T_true, mesh.principal_axes, mesh.centre)[0]
    stays = photo_rounds(scene, pyramid, turned, masks_only, options.region)
    stages: list[str] = []
    chosen = best_side(scene, pyramid, turned, masks_only, options.region, lambda stage, *_: stages.append(stage))
    assert {f"half turn {k} of 3: photo round 1" for k in (1, 2, 3)} <= set(stages)  # progress names each start
    assert _errors(stays.T_wm, T_true, mesh.centre)[1] > 90.0
    mm, deg = _errors(chosen.T_wm, T_true, mesh.centre)
    assert mm < 1.0 and deg < 1.0, (mm, deg)
    values = [photo_value(scene, pyramid, r.T_wm, masks_only, options.region)[0] for r in (chosen, stays)]
    assert values[0] < values[1] * (1.0 - options.ranking.ambiguity_tol), values
    side = chosen.side  # what refine.json says of it: the half turn that undoes the start's
    assert side is not None and side.chosen == 0, side
    assert side.turn_values[0] < side.masks_value * (1.0 - options.ranking.ambiguity_tol)
    assert PhotoEvidence(np.zeros(1), np.zeros(1), np.zeros(1), 1, True, side).record()["side"]["chosen"].startswith(
        "half turn about model axis")


@pytest.mark.slow
def test_without_a_pose_masks_that_fit_are_not_second_guessed(photo_scene, monkeypatch):
    """No seed and the scene's own masks, which fit: the object is placed as before, the photos'
    half turns (:func:`~autoalign.engine.photo_evidence.best_side`) are not tried."""
    import autoalign.engine.refine as engine  # the engine runs the rounds

    tried = []
    monkeypatch.setattr(engine, "best_side", lambda *args, **kwargs: tried.append(args))
    k = 2
    mesh, T_true = photo_scene.meshes[k], photo_scene.poses[k]
    rounds_alone, counted = engine.photo_rounds, []

    def counting(*args, **kwargs):  # the photo rounds, as they run
        counted.append(rounds_alone(*args, **kwargs))
        return counted[-1]

    monkeypatch.setattr(engine, "photo_rounds", counting)
    result = refine(with_photos(read_scene(photo_scene.folder, k)), mesh, None)
    assert not tried
    mm, deg = _errors(result.T_wm, T_true, mesh.centre)
    assert mm < 1.0 and deg < 1.0, (mm, deg)
    # every render counted: the masks' placement (its orientation search, dozens) besides the rounds and
    # the last refinement (a few)
    (rounds,) = counted
    assert result.renders > rounds.renders + 20 and result.iterations > 0, (result.renders, rounds.renders)
