"""The bundled example (``autoalign/data/example``) and the script that makes it (issue 26):
``make_example`` has a real ``--help``, refuses to replace a folder unless ``--force`` says so
(and then replaces only its own files), and reproduces the bundled files, photos included."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from autoalign.experiments.scenes.make_example import DEFAULT_OUT, PARTS, main

MODULE = [sys.executable, "-m", "autoalign.experiments.scenes.make_example"]


@pytest.mark.slow
def test_help_is_help_not_a_folder(tmp_path: Path) -> None:
    run = subprocess.run([*MODULE, "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("usage:") and "--force" in run.stdout and "DIR" in run.stdout
    assert list(tmp_path.iterdir()) == []  # no folder named --help


@pytest.mark.slow
def test_an_existing_folder_is_refused_without_force(tmp_path: Path) -> None:
    """One line naming the folder and --force, exit 2, and the folder exactly as it was."""
    folder = tmp_path / "mine"
    (folder / "scene").mkdir(parents=True)
    (folder / "scene" / "notes.txt").write_text("keep me")
    run = subprocess.run([*MODULE, str(folder)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and str(folder) in lines[0] and "--force" in lines[0], run.stderr
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == \
        ["mine", "mine/scene", "mine/scene/notes.txt"]
    (tmp_path / "file").write_text("x")
    assert main([str(tmp_path / "file")]) == 2 and (tmp_path / "file").read_text() == "x"


def test_the_default_folder_is_the_bundled_example_and_needs_force(capsys: pytest.CaptureFixture[str]) -> None:
    before = sorted(p.relative_to(DEFAULT_OUT).as_posix() for p in DEFAULT_OUT.rglob("*"))
    assert main([]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert sorted(p.relative_to(DEFAULT_OUT).as_posix() for p in DEFAULT_OUT.rglob("*")) == before


@pytest.mark.slow
def test_force_reproduces_the_bundled_example_and_keeps_other_files(tmp_path: Path) -> None:
    """``--force`` into a folder holding an old example and a file of the user's: the user's file
    stays, and the example's files are those bundled (masks and model to the byte, poses and
    cameras to 1e-9, photos within JPEG noise)."""
    out = tmp_path / "example"
    (out / "scene" / "rgb").mkdir(parents=True)
    (out / "scene" / "rgb" / "stale.png").write_bytes(b"old")
    (out / "mine.txt").write_text("keep me")
    assert main([str(out), "--force"]) == 0
    assert (out / "mine.txt").read_text() == "keep me" and not (out / "scene" / "rgb" / "stale.png").exists()
    assert sorted(p.name for p in out.iterdir()) == sorted([*PARTS, "mine.txt"])
    made = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.name != "mine.txt")
    bundled = sorted(p.relative_to(DEFAULT_OUT).as_posix() for p in DEFAULT_OUT.rglob("*") if p.is_file())
    assert made == bundled
    for name in made:
        a, b = out / name, DEFAULT_OUT / name
        if name.endswith(".json"):
            np.testing.assert_allclose(_numbers(json.loads(a.read_text())), _numbers(json.loads(b.read_text())),
                                       rtol=1e-9, atol=1e-9)
        elif name.endswith(".jpg"):
            diff = np.abs(cv2.imread(str(a)).astype(int) - cv2.imread(str(b)).astype(int))
            assert diff.mean() < 0.5 and np.percentile(diff, 99.9) <= 24, (name, diff.mean())
        else:
            assert a.read_bytes() == b.read_bytes(), name
    assert len(list((out / "scene" / "rgb").glob("*.jpg"))) == 24


def _numbers(data: object) -> list[float]:
    """Every number of a JSON value, in order."""
    if isinstance(data, dict):
        return [x for k in sorted(data) for x in _numbers(data[k])]
    if isinstance(data, list):
        return [x for v in data for x in _numbers(v)]
    return [float(data)] if isinstance(data, (int, float)) else []


def test_the_bundled_example_is_small_and_textured() -> None:
    """Package data stays small (photos a few hundred KB), and the model has vertex colours, so
    ``autoalign check`` has texture to match."""
    from autoalign.io.models import load_coloured_mesh

    photos = sum(p.stat().st_size for p in (DEFAULT_OUT / "scene" / "rgb").iterdir())
    assert photos < 400_000, photos
    assert sum(p.stat().st_size for p in DEFAULT_OUT.rglob("*") if p.is_file()) < 600_000
    mesh = load_coloured_mesh(DEFAULT_OUT / "models" / "obj_000001.ply")
    assert mesh.has_colours and len(np.unique(mesh.colours, axis=0)) >= 4
