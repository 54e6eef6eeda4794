"""A scene's per-view record (:class:`~autoalign.io.bop.View`): each view's camera, mask, image id,
ignored pixels, depth and photo together, in the scene's order, also after taking a subset."""

from __future__ import annotations

import numpy as np

from autoalign.experiments.scenes.synthetic import ring_cameras
from autoalign.io.bop import Scene, View


def _scene(with_extras: bool) -> Scene:
    rng = np.random.default_rng(0)
    cams = ring_cameras(5, rng, (20.0, 40.0), (450.0, 600.0))
    h, w = cams[0].height, cams[0].width
    masks = [rng.random((h, w)).astype(np.float32) for _ in cams]
    if not with_extras:
        return Scene(cams, masks, [10, 11, 12, 13, 14])
    return Scene(cams, masks, [10, 11, 12, 13, 14], ignore=[rng.random((h, w)) > 0.5 for _ in cams],
                 depths=[rng.random((h, w)).astype(np.float32) for _ in cams],
                 photos=[rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in cams])


def test_views_hold_each_views_evidence_in_order() -> None:
    scene = _scene(True)
    views = scene.views
    assert len(views) == len(scene) and all(isinstance(v, View) for v in views)
    for k, v in enumerate(views):
        assert v.camera is scene.cameras[k] and v.mask is scene.masks[k] and v.image_id == scene.image_ids[k]
        assert v.ignore is scene.ignore[k] and v.depth is scene.depths[k] and v.photo is scene.photos[k]
    picked = scene.subset([3, 1])
    assert [v.image_id for v in picked.views] == [13, 11]
    assert all(a.mask is b.mask and a.photo is b.photo for a, b in zip(picked.views, (views[3], views[1])))


def test_views_without_ignore_depth_or_photos_say_none() -> None:
    views = _scene(False).views
    assert all(v.ignore is None and v.depth is None and v.photo is None for v in views)
