"""Tests of the procedural model set: size, determinism, centring, honest symmetry labels, BOP I/O."""

from __future__ import annotations

import itertools
import time

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from autoalign.experiments.scenes.procedural_models import (
    ProceduralModel,
    load_bop_models_info,
    procedural_models,
    write_models,
)
from autoalign.geometry.mesh import load_mesh, mesh_from_trimesh, weld


@pytest.fixture(scope="module")
def models() -> list[ProceduralModel]:
    return procedural_models()


@pytest.fixture(scope="module")
def meshes(models):
    return [mesh_from_trimesh(m.mesh, m.name) for m in models]


def test_count_names_and_labels(models):
    assert len(models) == 44
    assert len({m.name for m in models}) == 44
    none = [m for m in models if m.symmetry == "none"]
    assert len(none) >= 30
    for m in models:
        if m.symmetry == "none":
            assert not m.symmetries_discrete and not m.symmetries_continuous
        else:
            assert m.symmetries_discrete or m.symmetries_continuous


def test_deterministic_and_fast():
    t = time.perf_counter()
    a = procedural_models()
    assert time.perf_counter() - t < 5.0
    b = procedural_models()
    for x, y in zip(a, b):
        assert x.name == y.name
        assert np.array_equal(x.mesh.vertices, y.mesh.vertices)
        assert np.array_equal(x.mesh.faces, y.mesh.faces)


def test_sizes_faces_centring_and_orientation(models, meshes):
    for m, M in zip(models, meshes):
        assert 60.0 <= M.diameter <= 200.0, (m.name, M.diameter)
        assert 200 <= len(m.mesh.faces) <= 5000, (m.name, len(m.mesh.faces))
        assert np.abs(M.centre).max() < 1e-9, m.name
        assert np.all(np.isfinite(M.vertices))
        assert (m.mesh.area_faces > 1e-9).all(), m.name
        # every part is a closed, consistently outward-wound solid
        for part in m.mesh.split(only_watertight=False):
            assert part.is_watertight and part.is_winding_consistent and part.volume > 0, m.name


def _cube_group() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def _axis_rot(axis: int, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _candidates() -> list[np.ndarray]:
    cands = [R for R in _cube_group() if not np.allclose(R, np.eye(3))]
    for axis in range(3):
        for k in (3, 5, 6, 7, 8, 10, 12):
            cands.append(_axis_rot(axis, 360.0 / k))
    cands.append(_axis_rot(2, 23.0))
    return cands


def _declared(m: ProceduralModel, R: np.ndarray) -> bool:
    """Whether rotation R (about the origin) belongs to the model's declared symmetry group."""
    group = [np.eye(3)] + [np.asarray(T)[:3, :3] for T in m.symmetries_discrete]
    for D in group:
        Q = D.T @ R
        if m.symmetries_continuous:
            if any(np.allclose(Q @ np.asarray(c["axis"]), c["axis"], atol=1e-9) for c in m.symmetries_continuous):
                return True
        elif np.allclose(Q, np.eye(3), atol=1e-9):
            return True
    return False


@pytest.mark.slow
def test_symmetry_labels_are_honest(models):
    """For many candidate rotations about the origin (cube group, n-fold turns about the axes):
    the surface maps onto itself (within faceting, < 0.3 mm) exactly when the rotation is in the
    declared symmetry group, and otherwise some point moves > 2 mm off the surface."""
    cands = _candidates()
    for m in models:
        tm = m.mesh
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(tm.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(tm.faces, np.uint32)))
        V = np.asarray(tm.vertices)
        V = V[np.random.default_rng(0).permutation(len(V))[:400]]
        pts = np.concatenate([V, np.asarray(tm.sample(600, seed=1))])
        moved = np.concatenate([pts @ R.T for R in cands]).astype(np.float32)
        dist = scene.compute_distance(o3d.core.Tensor(moved)).numpy().reshape(len(cands), -1).max(axis=1)
        for R, d in zip(cands, dist):
            if _declared(m, R):
                assert d < 0.3, (m.name, R.round(3).tolist(), d)
            else:
                assert d > 2.0, (m.name, R.round(3).tolist(), d)


def test_discrete_symmetries_map_vertices_onto_themselves(models):
    n_sym = 0
    for m in models:
        V = np.asarray(m.mesh.vertices)
        tree = cKDTree(V)
        for T in m.symmetries_discrete:
            T = np.asarray(T)
            assert T.shape == (4, 4)
            assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) > 0
            assert not np.allclose(T, np.eye(4))
            d, _ = tree.query(V @ T[:3, :3].T + T[:3, 3])
            assert d.max() < 1e-3, (m.name, d.max())
            n_sym += 1
        for c in m.symmetries_continuous:
            assert np.linalg.norm(c["axis"]) == pytest.approx(1.0)
            assert np.allclose(c["offset"], 0.0)
    assert n_sym > 0


def test_write_models_and_models_info_round_trip(tmp_path, models, meshes):
    info = write_models(tmp_path / "models", models)
    back = load_bop_models_info(tmp_path / "models")
    assert sorted(back) == list(range(1, 45)) == sorted(info)
    for i, m in enumerate(models, start=1):
        mesh = load_mesh(tmp_path / "models" / f"obj_{i:06d}.ply")
        welded = weld(m.mesh.copy())  # loading merges the vertices of seams (see load_mesh)
        assert mesh.faces.shape == welded.faces.shape
        assert np.abs(mesh.vertices - welded.vertices).max() < 1e-4  # float32 PLY
        e = back[i]
        assert e["diameter"] == pytest.approx(meshes[i - 1].diameter)
        assert mesh.diameter == pytest.approx(e["diameter"], abs=1e-3)
        lo, hi = m.mesh.bounds
        assert [e["min_x"], e["min_y"], e["min_z"]] == pytest.approx(lo.tolist())
        assert [e["size_x"], e["size_y"], e["size_z"]] == pytest.approx((hi - lo).tolist())
        assert len(e["symmetries_discrete"]) == len(m.symmetries_discrete)
        for a, b in zip(e["symmetries_discrete"], m.symmetries_discrete):
            assert a.shape == (4, 4) and np.allclose(a, b)
        assert e["symmetries_continuous"] == m.symmetries_continuous
    # asymmetric objects carry no symmetry keys in the JSON (BOP style)
    import json
    raw = json.loads((tmp_path / "models" / "models_info.json").read_text())
    none_ids = [str(i) for i, m in enumerate(models, start=1) if m.symmetry == "none"]
    assert all("symmetries_discrete" not in raw[k] and "symmetries_continuous" not in raw[k] for k in none_ids)
    # reading the file path directly works too
    assert load_bop_models_info(tmp_path / "models" / "models_info.json").keys() == back.keys()
