"""The check's rendering (mitsuba) against open3d's ``RaycastingScene``, an independent ray caster
(open3d is allowed in tests only): instance maps, depths, hit triangles and colours of posed meshes,
with rays formed here from the OpenCV ``cam_K`` (``K^-1 [j, i, 1]``), not from ``pixel_rays``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import pytest
import trimesh
from numpy.typing import NDArray

from autoalign.experiments.scenes.synthetic import random_rotation
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_cameras, read_labels
from autoalign.io.models import ColouredMesh, ModelSet
from autoalign.rasterizers.label_rendering import PlacedMesh, cast_labels, render_labels
from autoalign.rasterizers.ray_casting import RayCaster

REAL = REAL_SCENES / "lmo_im0480_0695"
needs_real = pytest.mark.skipif(not (REAL / "scene_gt.json").is_file(), reason=f"real scene {REAL} not present")


@dataclass
class Reference:
    """open3d's rendering, per pixel (H, W): placed-mesh index (-1: none), triangle, depth z (mm), colour."""

    index: NDArray[np.int64]
    prim: NDArray[np.int64]
    depth: NDArray[np.float64]
    rgb: NDArray[np.float64]


def _open3d_render(placed: list[PlacedMesh], K: NDArray[np.float64], W: int, H: int) -> Reference:
    """Every pixel's ray ``K^-1 [j, i, 1]`` (OpenCV pixel centres; unit z, so the hit parameter is
    the depth z) cast with open3d; colour the barycentric blend of the vertex colours (0..255)."""
    scene = o3d.t.geometry.RaycastingScene()
    for p in placed:
        V = p.mesh.vertices @ p.R_m2c.T + p.t_m2c
        scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(p.mesh.faces.astype(np.uint32)))
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    d = np.column_stack([jj.ravel(), ii.ravel(), np.ones(W * H)]) @ np.linalg.inv(K).T
    rays = np.hstack([np.zeros((W * H, 3)), d / d[:, 2:3]]).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    t = hits["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    index = np.where(hit, hits["geometry_ids"].numpy().astype(np.int64), -1)
    prim = np.where(hit, hits["primitive_ids"].numpy().astype(np.int64), -1)
    uv = hits["primitive_uvs"].numpy().astype(np.float64)
    rgb = np.zeros((W * H, 3))
    for k, p in enumerate(placed):
        sel = index == k
        tri = p.mesh.faces[prim[sel]]
        w = np.column_stack([1.0 - uv[sel].sum(1), uv[sel]])
        rgb[sel] = np.einsum("nk,nkc->nc", w, p.mesh.colours[tri].astype(np.float64)) * 255.0
    return Reference(index.reshape(H, W), prim.reshape(H, W), np.where(hit, t, np.inf).reshape(H, W),
                     rgb.reshape(H, W, 3))


def _compare(placed: list[PlacedMesh], K: NDArray[np.float64], W: int, H: int) -> tuple[float, int]:
    """Assert render_labels agrees with open3d; return the share of pixels with the same instance and
    the number of pixels both hit."""
    ref = _open3d_render(placed, K, W, H)
    r = render_labels(placed, K, W, H)
    numbers = np.array([-1] + [p.instance for p in placed])
    ref_instance = numbers[ref.index + 1]
    same = float(np.mean(r.instance == ref_instance))
    assert same >= 0.995
    both = (r.instance >= 0) & (ref_instance >= 0)
    assert np.all(np.isfinite(r.depth) == (r.instance >= 0)) and np.all(r.rgb[r.instance < 0] == 0)
    assert np.abs(r.depth[both] - ref.depth[both]).max() <= 0.01  # mm
    # the triangle each pixel hits, as render_labels found it
    cast = cast_labels(placed, K, W, H)
    assert cast is not None
    u0, v0, u1, v1 = cast.box
    index, prim = np.full((H, W), -1), np.full((H, W), -1)
    index[v0:v1, u0:u1] = cast.index.reshape(v1 - v0, u1 - u0)
    prim[v0:v1, u0:u1] = np.where(cast.index >= 0, cast.hits.prim, -1).reshape(v1 - v0, u1 - u0)
    assert np.array_equal(numbers[index + 1], r.instance)
    same_tri = both & (index == ref.index) & (prim == ref.prim)
    assert same_tri.sum() >= 0.99 * both.sum()
    assert np.abs(r.rgb[same_tri].astype(np.float64) - ref.rgb[same_tri]).max() <= 1.0  # 1/255
    return same, int(both.sum())


def _coloured(mesh: trimesh.Trimesh, rng: np.random.Generator) -> ColouredMesh:
    """``mesh`` with random vertex colours."""
    V = np.asarray(mesh.vertices, dtype=np.float64)
    return ColouredMesh(V, np.asarray(mesh.faces, dtype=np.int64), rng.uniform(0, 1, (len(V), 3)).astype(np.float32), True)


@pytest.mark.parametrize("seed", range(3))
def test_overlapping_primitives_agree_with_open3d(seed: int) -> None:
    """A box, a sphere and a cylinder at random poses overlapping in a 320x240 image."""
    rng = np.random.default_rng(seed)
    W, H = 320, 240
    K = np.array([[420.0, 0.0, 161.7], [0.0, 430.0, 118.2], [0.0, 0.0, 1.0]])
    shapes = [trimesh.creation.box((60.0, 40.0, 30.0)), trimesh.creation.icosphere(3, radius=30.0),
              trimesh.creation.cylinder(radius=20.0, height=70.0, sections=48)]
    placed = [PlacedMesh(5 + k, _coloured(s, rng), random_rotation(rng),
                         np.array([rng.uniform(-25, 25), rng.uniform(-20, 20), rng.uniform(280, 340)]))
              for k, s in enumerate(shapes)]
    same, both = _compare(placed, K, W, H)
    # measured: 0 pixels differ in instance, 11461 / 10056 / 7870 both hit, all on the same triangle,
    # depths within 7.4e-4 mm, colours within 0.502 of open3d's unrounded blend (float32)
    assert both > 5000 and same >= 0.999


@needs_real
def test_real_lmo_image_agrees_with_open3d() -> None:
    """The first LM-O image with the most labelled objects (scanned meshes occluding each other) at
    its ground-truth poses, 640x480."""
    labels = read_labels(REAL / "scene_gt.json")
    im = max(sorted(labels), key=lambda i: len(labels[i]))
    K = read_cameras(REAL)[im][0]
    meshes = ModelSet.read(REAL / "models").coloured_meshes([lab.obj_id for lab in labels[im]])
    placed = [PlacedMesh(lab.instance, meshes[lab.obj_id], lab.R_m2c, lab.t_m2c) for lab in labels[im]]
    assert len(placed) >= 5
    same, both = _compare(placed, K, 640, 480)
    # measured (image 480, 8 objects): 0 of 307200 pixels differ in instance, 21529 both hit, 21528
    # on the same triangle, depths within 0.002 mm, colours within 0.5004 of open3d's unrounded blend
    # (without watertight casting one ray slipped between two triangles: 7.5 mm deeper)
    assert both > 20000 and same >= 0.999


def test_first_hits_give_triangle_barycentrics_and_ray_parameter() -> None:
    """A triangle placed 50 mm in front of the origin and turned: ``t`` is the ray parameter (the
    distance in units of the direction's length, the same in the model and world frames), the
    barycentrics rebuild the world hit point, and a ray that misses gives inf."""
    V = np.array([[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [0.0, 10.0, 0.0]])
    caster = RayCaster(ColouredMesh(V, np.array([[0, 1, 2]]), np.zeros((3, 3), np.float32), False))
    T = make_pose(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([0.0, 0.0, 50.0]))  # 90 deg about z
    d = np.array([[0.0, 0.0, 1.0], [0.02, 0.01, 1.0], [0.0, 0.0, 2.0], [1.0, 0.0, 1.0]], dtype=np.float32)
    h = caster.first_hits(T, np.zeros(3), d)
    assert h.prim.tolist() == [0, 0, 0, 0]
    assert np.allclose(h.t[:3], [50.0, 50.0, 25.0], atol=1e-4) and np.isinf(h.t[3])
    w = np.column_stack([1.0 - h.bary[:3].sum(1), h.bary[:3]])
    assert np.allclose(w @ (V @ T[:3, :3].T + T[:3, 3]), h.t[:3, None] * d[:3], atol=1e-4)
    assert np.all(h.bary[3] == 0)


def test_bundles_of_rays_cast_in_one_kernel_hit_what_open3d_hits() -> None:
    """``first_hits_from``: three cameras' rays (one camera with none) cast together give, bundle by
    bundle, the hits each bundle gets cast alone, to the bit, and the depths and triangles open3d's
    caster finds for the same world rays."""
    rng = np.random.default_rng(5)
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    mesh = ColouredMesh(np.asarray(box.vertices, float), np.asarray(box.faces, np.int64),
                        np.zeros((len(box.vertices), 3), np.float32), False)
    caster = RayCaster(mesh)
    T = make_pose(random_rotation(rng), np.array([5.0, -3.0, 2.0]))
    origins = [np.array([0.0, 0.0, -300.0]), np.array([250.0, 40.0, -120.0]), np.array([-200.0, 150.0, 90.0])]
    bundles = []
    for o, n in zip(origins, (500, 0, 700)):  # aimed at the box's middle, some rays past its edges
        aim = rng.normal(scale=25.0, size=(n, 3)) - o
        bundles.append((aim / np.linalg.norm(aim, axis=1, keepdims=True)).astype(np.float32))
    together = caster.first_hits_from(T, origins, bundles)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((mesh.vertices @ T[:3, :3].T + T[:3, 3]).astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    for o, d, h in zip(origins, bundles, together, strict=True):
        alone = caster.first_hits(T, o, d)
        assert np.array_equal(h.t, alone.t) and np.array_equal(h.prim, alone.prim)
        assert np.array_equal(h.bary, alone.bary)
        if len(d) == 0:
            assert len(h.t) == 0
            continue
        ref = scene.cast_rays(o3d.core.Tensor(np.hstack([np.tile(o, (len(d), 1)), d]).astype(np.float32)))
        t_ref = ref["t_hit"].numpy()
        hit = np.isfinite(t_ref)
        assert 0.2 < hit.mean() < 1.0  # some rays hit, some pass the box
        assert np.array_equal(np.isfinite(h.t), hit)
        assert np.allclose(h.t[hit], t_ref[hit], atol=1e-3)
        assert np.mean(h.prim[hit] == ref["primitive_ids"].numpy()[hit].astype(np.int64)) > 0.99  # edges may differ
