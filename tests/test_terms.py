"""Evidence terms (issue 44, item 1): one render feeds every term, the terms are summed in one place,
a term that finds hidden pixels takes them off for the terms after it, and a term on the pose joins
an objective without changing the one it came from."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.engine.objective import Level, SilhouetteObjective
from autoalign.engine.seed_region import SeedRegion
from autoalign.experiments.scenes.synthetic import raycast_masks
from autoalign.geometry.se3 import apply_twist, transform_points
from autoalign.io.bop import Scene
from autoalign.losses import l2, targets_in_crops
from autoalign.losses.depth import DepthNoise, depth_terms
from autoalign.losses.mask_term import MaskTerm
from autoalign.losses.term import Fragments, TermValues, evaluate_terms
from autoalign.rasterizers.pyramid import MeshPyramid

@pytest.fixture(scope="module")
def posed(box_with_depth):
    """The box with exact masks and depth, and a pose 3 mm / 3 deg off."""
    mesh, T, cams, depths = box_with_depth
    masks = [m.astype(np.float32) for m in raycast_masks(mesh, T, cams)]
    off = apply_twist(T, np.array([3.0, -1.0, 2.0, 0.03, -0.02, 0.04]), transform_points(T, mesh.centre[None])[0])
    return mesh, Scene(cams, masks, list(range(4)), depths=depths), off


def test_the_objective_is_the_weighted_sum_of_each_term_computed_alone(posed) -> None:
    """The objective with depth: its value, gradient and Gauss-Newton matrix are the robust-weighted
    sums of the L2 mask term and the depth term, each computed here by the losses' own functions."""
    mesh, scene, T = posed
    obj = SilhouetteObjective(MeshPyramid(mesh), scene, depth=DepthNoise())
    level = Level(1.0, 1.0, 0)
    ev = obj.evaluate(T, level)
    assert [v.name for v in ev.values] == ["depth", "mask"] and obj.renders == 1

    rast = obj.pyramid.at(1.0, obj.detail)
    centre = transform_points(T, mesh.centre[None])[0]
    d = depth_terms(rast.caster, rast.mesh, T, scene.cameras, scene.depths, centre, DepthNoise(), masks=scene.masks)
    assert not d.hidden.any()  # exact depth: nothing hides the box, every pixel is compared
    sil = rast.render(T, scene.cameras, 1.0)
    m = l2(sil, targets_in_crops(scene.masks, sil), np.array([float(t.sum()) for t in scene.masks]))
    w = ev.weights
    np.testing.assert_allclose(ev.value, w @ (m.loss + d.loss), rtol=1e-12)
    np.testing.assert_allclose(ev.grad, w @ (m.grad + d.grad), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ev.gn, np.einsum("i,ijk->jk", w, m.gn + d.gn), rtol=1e-10, atol=1e-14)
    rec = ev.record()
    np.testing.assert_allclose(rec.losses["depth"], d.loss, rtol=1e-12)
    np.testing.assert_allclose(rec.shares()["depth"] + rec.shares()["mask"], 1.0)


class _HidesLeftHalf:
    """A stand-in for a term that finds pixels hidden by something unmodelled (the left half of every view)."""

    name = "left half hidden"

    def residuals(self, fragments: Fragments) -> TermValues:
        hidden = []
        for c in fragments.views.cameras:
            h = np.zeros((c.height, c.width), bool)
            h[:, : c.width // 2] = True
            hidden.append(h)
        return TermValues(self.name, hidden=hidden)


def test_pixels_a_term_finds_hidden_are_off_for_the_terms_after_it(posed) -> None:
    """A term that hides the left half runs before the mask term: the mask term's loss is that of the
    silhouettes with those pixels off (and differs from the whole image's); a mask term before it
    sees the whole image."""
    mesh, scene, T = posed
    obj = SilhouetteObjective(MeshPyramid(mesh), scene)
    frags = obj.fragments(T, Level(0.5, 1.0, 0))
    _, (_, after) = evaluate_terms((_HidesLeftHalf(), MaskTerm()), frags)
    _, (before, _) = evaluate_terms((MaskTerm(), _HidesLeftHalf()), frags)
    hidden = _HidesLeftHalf().residuals(frags).hidden
    alone = MaskTerm().residuals(frags.hiding(hidden))
    np.testing.assert_array_equal(after.views.loss, alone.views.loss)
    np.testing.assert_array_equal(before.views.loss, MaskTerm().residuals(frags).views.loss)
    assert np.all(np.abs(after.views.loss - before.views.loss) > 1e-6)


def test_a_pose_term_joins_a_copy_and_shares_its_renders(posed) -> None:
    """``with_pose_term``: the held objective's value is the original's plus the seed region's
    penalty at that pose; the original has no such term; renders are counted once, in common."""
    mesh, scene, T = posed
    obj = SilhouetteObjective(MeshPyramid(mesh), scene)
    region = SeedRegion(apply_twist(T, np.array([0, 0, 0, 0.0, 0.0, 0.6]), mesh.centre), mesh.centre,
                        (1.0, 5.0), 1e3 * len(scene))
    held = obj.with_pose_term(region)
    level = Level(0.5, 1.0, 0)
    a, b = obj.evaluate(T, level), held.evaluate(T, level)
    penalty = region.term(T)
    assert penalty.value > 0
    np.testing.assert_allclose(b.value, a.value + penalty.value, rtol=1e-12)
    np.testing.assert_allclose(b.grad, a.grad + penalty.grad, rtol=1e-12)
    assert [v.name for v in a.values] == ["mask"] and [v.name for v in b.values] == ["mask", "seed"]
    assert obj.renders == held.renders == 2


def test_an_objective_without_its_depth_is_the_one_built_without_it(posed) -> None:
    """The seed's hold also starts from where the terms other than the depth lead (issue 45): that
    objective, the seed region kept, gives what one built without depth gives, shares the views and
    render count, and leaves the one it came from as it was; an objective with no depth has none to drop."""
    mesh, scene, T = posed
    pyramid, level = MeshPyramid(mesh), Level(1.0, 1.0, 0)
    region = SeedRegion(T, mesh.centre, (1.0, 1.0), 100.0)
    with_depth = SilhouetteObjective(pyramid, scene, depth=DepthNoise()).with_pose_term(region)
    alone = with_depth.without_depth()
    assert alone is not None and [t.name for t in alone.terms] == ["mask", region.name]
    built = SilhouetteObjective(pyramid, scene).with_pose_term(region)
    off = apply_twist(T, np.array([4.0, 1.0, -2.0, 0.05, 0.0, -0.03]), transform_points(T, mesh.centre[None])[0])
    got, want = alone.evaluate(off, level), built.evaluate(off, level)
    np.testing.assert_allclose(got.value, want.value, rtol=1e-12)
    np.testing.assert_allclose(got.grad, want.grad, rtol=1e-10, atol=1e-14)
    assert with_depth.renders == alone.renders and [t.name for t in with_depth.terms] == ["depth", "mask", region.name]
    assert built.without_depth() is None
