"""The path-traced test scenes (issue 45): their camera convention against open3d's ray-cast masks,
and what their materials look like."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from autoalign.experiments.scenes.path_traced import (
    PathTracing,
    coverage_images,
    mitsuba_sensor,
    path_traced_photos,
)
from autoalign.experiments.scenes.synthetic import raycast_visible_masks
from autoalign.geometry.camera import Camera, look_at
from autoalign.geometry.mesh import mesh_from_trimesh
from autoalign.geometry.se3 import make_pose


def _l_block() -> trimesh.Trimesh:
    """A non-symmetric block (an L of two boxes), resting on z = 0."""
    a = trimesh.creation.box((60.0, 20.0, 30.0))
    a.apply_translation((0.0, 0.0, 15.0))
    b = trimesh.creation.box((20.0, 50.0, 30.0))
    b.apply_translation((20.0, 25.0, 15.0))
    return trimesh.util.concatenate([a, b])


def _scene() -> tuple[list, list[np.ndarray], list[Camera]]:
    """Two objects on the table, seen by three cameras whose principal points are off the image
    centre in different directions (a wrong sign or half-pixel shows in the centroids)."""
    meshes = [mesh_from_trimesh(_l_block(), "l_block"),
              mesh_from_trimesh(trimesh.creation.cylinder(radius=25.0, height=70.0, sections=48), "can")]
    poses = [make_pose(np.eye(3), np.array([-40.0, -20.0, 0.0])), make_pose(np.eye(3), np.array([50.0, 30.0, 35.0]))]
    cams = []
    for (cx, cy), eye in zip([(342.6, 219.2), (296.4, 263.8), (320.0, 240.0)],
                             [(380.0, -150.0, 260.0), (-200.0, -340.0, 300.0), (60.0, 420.0, 200.0)]):
        K = np.array([[600.0, 0.0, cx], [0.0, 600.0, cy], [0.0, 0.0, 1.0]])
        cams.append(look_at(np.array(eye), np.array([0.0, 0.0, 30.0]), K, 640, 480, up=np.array([0.0, 0.0, 1.0])))
    return meshes, poses, cams


def test_path_traced_cameras_see_what_open3d_ray_casting_sees() -> None:
    """The mitsuba sensor's pixel coverage of each object, thresholded at a half, against open3d's
    masks cast through the pixel centres: IoU > 0.99 and centroids within 0.2 px in every view.
    A principal point half a pixel off moves the centroids by 0.5 px; one mirrored, by 20-40 px."""
    meshes, poses, cams = _scene()
    masks = raycast_visible_masks(meshes, poses, cams)
    cover = coverage_images(meshes, poses, cams, spp=64)
    for i in range(len(cams)):
        for j in range(len(meshes)):
            m, c = masks[i][j], cover[i][j]
            assert m.sum() > 2000
            iou = (m & (c > 0.5)).sum() / (m | (c > 0.5)).sum()
            assert iou > 0.99, (i, j, iou)
            rows, cols = np.mgrid[0:m.shape[0], 0:m.shape[1]]
            centroid_mask = np.array([cols[m].mean(), rows[m].mean()])
            centroid_cover = np.array([(cols * c).sum(), (rows * c).sum()]) / c.sum()
            assert np.linalg.norm(centroid_mask - centroid_cover) < 0.2, (i, j, centroid_mask, centroid_cover)


def test_each_material_renders_as_it_should() -> None:
    """Glass shows the table through it (its pixels vary as the texture behind it does, unlike a
    uniform patch), polished metal mirrors its surroundings, and the opaque object is textured;
    a wrong material name or non-square pixels are refused before anything is rendered."""
    meshes, poses, cams = _scene()
    cam = cams[0].scaled(0.5)
    masks = raycast_visible_masks(meshes, poses, [cam])[0]
    photos = {}
    for material in ("opaque", "glass", "metal"):
        photos[material] = path_traced_photos(meshes, poses, ["opaque", material], [cam], np.random.default_rng(0),
                                              PathTracing(spp=16), noise=0.0)[0]
    inner = masks[1] & np.roll(masks[1], 4, 0) & np.roll(masks[1], -4, 0) & np.roll(masks[1], 4, 1) & np.roll(masks[1], -4, 1)  # 4 px in
    assert inner.sum() > 300
    diff = {k: np.abs(photos[k].astype(float) - photos["opaque"].astype(float))[inner].mean() for k in ("glass", "metal")}
    assert diff["glass"] > 10.0 and diff["metal"] > 10.0, diff
    # outside the object the three photos are the same scene (noise off): the table is not the object
    outside = ~np.any(masks, axis=0)
    assert np.abs(photos["glass"].astype(float) - photos["opaque"].astype(float))[outside].mean() < 6.0
    with pytest.raises(ValueError, match="unknown material"):
        path_traced_photos(meshes, poses, ["opaque", "gold"], [cam], np.random.default_rng(0))
    skewed = Camera(np.array([[300.0, 0.0, 160.0], [0.0, 310.0, 120.0], [0.0, 0.0, 1.0]]), cam.R_w2c, cam.t_w2c, 320, 240)
    with pytest.raises(ValueError, match="square pixels"):
        mitsuba_sensor(skewed, 4)
