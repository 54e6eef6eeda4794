"""Atomic writes: all files or none, and the permissions of an ordinary file."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from autoalign.io.atomic_files import write_files_atomic, write_json_atomic


def _umask() -> int:
    old = os.umask(0o022)
    os.umask(old)
    return old


def test_files_get_ordinary_permissions_not_those_of_a_temporary_file(tmp_path: Path) -> None:
    write_json_atomic(tmp_path / "scene_gt.json", {"0": []})
    mode = stat.S_IMODE((tmp_path / "scene_gt.json").stat().st_mode)
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert mode == stat.S_IMODE(plain.stat().st_mode) == 0o666 & ~_umask()


def test_a_failed_write_leaves_no_file_and_no_temporary(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_bytes(b"old")
    with pytest.raises(OSError):
        write_files_atomic({tmp_path / "a.json": b"new", tmp_path / "missing" / "b.json": b"x"})
    assert (tmp_path / "a.json").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]
