"""The mesh cache (:mod:`autoalign.geometry.mesh_cache`): a mesh read again comes from disk exactly as
it was made, without trimesh, and a changed file, other units, a broken entry or an unusable folder
never give a wrong mesh."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from autoalign.geometry.mesh import Mesh, load_mesh
from autoalign.geometry.mesh_cache import CACHE_ENV
from tests.conftest import at_once

EXAMPLE_MODEL = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example" / "model.ply"
ARRAYS = ("vertices", "faces", "face_normals", "edges", "edge_faces", "centre", "hull", "principal_axes")
LEVELS = (20000, 5000, 1500)


def _same(a: Mesh, b: Mesh) -> bool:
    return (all(np.array_equal(getattr(a, n), getattr(b, n)) for n in ARRAYS) and a.diameter == b.diameter
            and a.name == b.name)


def _fine_mesh(path: Path, scale: float = 1.0) -> Path:
    """An icosphere of 20,480 triangles (radius 40 mm x ``scale``): big enough for every level to simplify it."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=40.0 * scale)
    sphere.export(path)
    return path


def _load_with_levels(path: Path, units: str | None = None) -> tuple[Mesh, list[Mesh]]:
    m = load_mesh(path, units=units)
    return m, [m.simplified(n) for n in LEVELS]


def test_a_mesh_read_again_is_the_mesh_made_without_the_cache(tmp_path, monkeypatch):
    model = _fine_mesh(tmp_path / "sphere.ply")
    monkeypatch.setenv(CACHE_ENV, "off")
    made, made_levels = _load_with_levels(model)
    assert not any(tmp_path.glob("cache/*"))
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    first, first_levels = _load_with_levels(model)
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1 + 3  # the mesh and its three simplified levels
    again, again_levels = _load_with_levels(model)
    for got in ((first, *first_levels), (again, *again_levels)):
        assert all(_same(a, b) for a, b in zip(got, (made, *made_levels)))
    assert len(made.faces) == 20480 and all(1000 < len(m.faces) <= n for m, n in zip(made_levels, LEVELS))


def test_a_second_command_reads_the_mesh_without_importing_trimesh(tmp_path):
    env = {**os.environ, CACHE_ENV: str(tmp_path / "cache")}
    code = ("import sys; from autoalign.geometry.mesh import load_mesh; "
            f"m = load_mesh({str(EXAMPLE_MODEL)!r}); h = m.hull, m.diameter, m.principal_axes; "
            "print(len(m.faces), 'trimesh' in sys.modules, 'scipy' in sys.modules)")
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
            for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    assert runs[0].stdout.split() == ["1176", "True", "True"]  # made: trimesh read and welded it
    assert runs[1].stdout.split() == ["1176", "False", "False"]  # read again: no trimesh, no scipy


def test_a_coloured_mesh_read_again_is_the_file_as_trimesh_reads_it(tmp_path, monkeypatch):
    """The check's meshes (the file's vertices and colours): equal to trimesh's reading, array for
    array, from a new process that imports neither trimesh nor scipy."""
    env = {**os.environ, CACHE_ENV: str(tmp_path / "cache")}
    code = ("import sys; import numpy as np; from autoalign.io.models import load_coloured_mesh; "
            f"m = load_coloured_mesh({str(EXAMPLE_MODEL)!r}); "
            f"np.savez({str(tmp_path)!r} + f'/got{{sys.argv[1]}}.npz', v=m.vertices, f=m.faces, c=m.colours); "
            "print(m.has_colours, 'trimesh' in sys.modules, 'scipy' in sys.modules)")
    runs = [subprocess.run([sys.executable, "-c", code, str(k)], env=env, capture_output=True, text=True, timeout=120)
            for k in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    assert [r.stdout.split() for r in runs] == [["True", "True", "True"], ["True", "False", "False"]]
    ref = trimesh.load(EXAMPLE_MODEL, process=False)  # independent: trimesh's own reading of the file
    for k in range(2):
        with np.load(tmp_path / f"got{k}.npz") as got:
            assert np.array_equal(got["v"], np.asarray(ref.vertices)) and np.array_equal(got["f"], ref.faces)
            assert np.array_equal(got["c"], np.asarray(ref.visual.vertex_colors)[:, :3].astype(np.float32) / 255)


def test_a_changed_file_or_other_units_is_never_read_from_an_old_entry(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    model = _fine_mesh(tmp_path / "sphere.ply")
    small = load_mesh(model)
    _fine_mesh(model, scale=1.5)  # the same name, other bytes
    big = load_mesh(model)
    assert big.diameter == pytest.approx(1.5 * small.diameter, rel=1e-6)  # the file holds single precision
    in_metres = load_mesh(model, units="m")
    assert in_metres.diameter == pytest.approx(1000 * big.diameter, rel=1e-9)
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 3


def test_a_broken_entry_is_made_again(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    model = _fine_mesh(tmp_path / "sphere.ply")
    made = load_mesh(model)
    (entry,) = (tmp_path / "cache").glob("*.npz")
    entry.write_bytes(entry.read_bytes()[:100])  # cut short, as a full disk would leave it
    again = load_mesh(model)
    assert _same(again, made)
    assert load_mesh(model).diameter == made.diameter  # and written whole again
    assert entry.stat().st_size > 1000


def test_a_folder_that_cannot_be_written_leaves_the_cache_off(tmp_path, monkeypatch):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv(CACHE_ENV, str(blocker / "cache"))
    model = _fine_mesh(tmp_path / "sphere.ply")
    monkeypatch.setenv(CACHE_ENV, "off")
    made = load_mesh(model)
    monkeypatch.setenv(CACHE_ENV, str(blocker / "cache"))
    assert _same(load_mesh(model), made)
    assert blocker.read_text().startswith("a file")


def test_meshes_simplified_on_threads_at_once_are_each_their_own(tmp_path, monkeypatch):
    """fast_simplification keeps the mesh it decimates in global state and lets go of the GIL: two
    decimations at once (instances refined side by side) mixed their meshes, and a YCB-Video box was
    refined, and cached on disk, as the mug's simplified silhouette at the coarse levels (7 of 20 such
    pairs came back wrong before the decimation was serialised)."""
    monkeypatch.setenv(CACHE_ENV, "off")
    meshes = [Mesh(np.asarray(s.vertices) * scale, np.asarray(s.faces), name=f"m{k}")
              for k, (s, scale) in enumerate([(trimesh.creation.icosphere(5), (40.0, 30.0, 20.0)),
                                              (trimesh.creation.capsule(60.0, 15.0, count=[96, 96]), (1.0, 1.0, 1.0)),
                                              (trimesh.creation.icosphere(5), (10.0, 50.0, 25.0)),
                                              (trimesh.creation.cylinder(30.0, 80.0, sections=2048), (1.0, 1.0, 1.0))])]
    assert all(len(m.faces) > 8000 for m in meshes)
    alone = [m._decimated(2000) for m in meshes]
    for _ in range(5):
        got = at_once([lambda m=m: m._decimated(2000) for m in meshes])
        for k, (v, f) in enumerate(alone):
            assert np.array_equal(got[k][0], v) and np.array_equal(got[k][1], f), f"mesh {k} came back as another's"


def test_another_meshs_level_in_the_cache_is_made_again(tmp_path, monkeypatch):
    """A cached level whose box is not its mesh's (another object's, as the race above left them) is
    never used: the level is decimated again and the entry written over."""
    from autoalign.geometry import mesh_cache

    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    sphere = _fine_mesh(tmp_path / "sphere.ply")
    box = tmp_path / "box.ply"
    trimesh.creation.box((120.0, 40.0, 20.0)).subdivide().subdivide().subdivide().subdivide().subdivide().export(box)
    right, right_levels = _load_with_levels(sphere)
    _, box_levels = _load_with_levels(box)
    assert not np.allclose(box_levels[1].vertices.max(0), right_levels[1].vertices.max(0), atol=1.0)
    key = mesh_cache.file_key(sphere, None)
    poisoned = tmp_path / "cache" / f"{mesh_cache.level_key(key, LEVELS[1])}.npz"
    poisoned.write_bytes((tmp_path / "cache" / f"{mesh_cache.level_key(mesh_cache.file_key(box, None), LEVELS[1])}.npz")
                         .read_bytes())
    again = load_mesh(sphere).simplified(LEVELS[1])
    assert _same(again, right_levels[1])
    assert np.array_equal(np.load(poisoned)["vertices"], right_levels[1].vertices)  # the entry is the sphere's again


def test_a_decimation_that_comes_back_as_another_shape_leaves_the_mesh_as_it_is(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    m = load_mesh(_fine_mesh(tmp_path / "sphere.ply"))
    small = trimesh.creation.icosphere(subdivisions=3, radius=20.0)  # half the size: not this mesh simplified
    monkeypatch.setattr(Mesh, "_decimated", lambda self, n: (np.asarray(small.vertices), np.asarray(small.faces)))
    assert m.simplified(LEVELS[1]) is m
    assert len(list((tmp_path / "cache").glob("*-f*.npz"))) == 0  # and nothing wrong is kept
