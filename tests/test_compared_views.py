"""The views as compared (``losses/compared_views.py``): the scene as given beside each view's target."""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.geometry.camera import Camera
from autoalign.io.bop import Scene
from autoalign.losses.compared_views import ComparedViews


def _scene(n: int) -> Scene:
    K = np.array([[100.0, 0, 20], [0, 100.0, 15], [0, 0, 1]])
    cams = [Camera.from_opencv(K, np.eye(3), np.array([float(k), 0.0, 0.0]), 40, 30) for k in range(n)]
    masks = [np.full((30, 40), k % 2, np.float32) for k in range(n)]
    photos = [np.full((30, 40, 3), k, np.uint8) for k in range(n)]
    ignore = [np.eye(30, 40, dtype=bool) for _ in range(n)]
    return Scene(cams, masks, [10 + k for k in range(n)], ignore=ignore, photos=photos)


def test_a_scene_compared_as_given_is_compared_with_its_masks():
    scene = _scene(3)
    views = ComparedViews.of(scene)
    assert views.targets is scene.masks and views.photos is scene.photos and len(views) == 3
    assert views.image_ids == [10, 11, 12] and views.cameras is scene.cameras
    assert np.array_equal(views.compared(1), ~scene.ignore[1])
    assert views.has_targets and not ComparedViews.of(Scene(scene.cameras[:1], scene.masks[:1], [10])).has_targets


def test_subsets_and_other_cameras_keep_each_target_with_its_view():
    scene = _scene(4)
    targets = [np.full((30, 40), 0.25 * k, np.float32) for k in range(4)]
    views = ComparedViews(scene, targets, None)
    sub = views.subset([3, 1])
    assert sub.image_ids == [13, 11] and sub.photos is None
    assert [float(t[0, 0]) for t in sub.targets] == [0.75, 0.25]
    assert [float(m[0, 0]) for m in sub.scene.masks] == [1.0, 1.0]  # the scene's own masks, not the targets
    moved = [c.scaled(0.5) for c in scene.cameras]
    seen = views.through(moved)
    assert seen.cameras == moved and seen.targets is views.targets and views.cameras is scene.cameras
    assert seen.scene.masks is scene.masks


def test_targets_must_be_one_per_view():
    with pytest.raises(ValueError, match="2 targets for 3 views"):
        ComparedViews(_scene(3), [np.zeros((30, 40), np.float32)] * 2, None)
