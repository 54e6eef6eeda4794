"""drjit finds a usable libLLVM by itself, or says exactly what to install."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from autoalign import backend
from autoalign.errors import BackendError


def test_llvm_major_parses_debian_and_generic_names() -> None:
    assert backend.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert backend.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert backend.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1") == 14
    assert backend.llvm_major("/opt/libfoo.so") is None


def test_find_prefers_newest_and_ignores_old(tmp_path: Path) -> None:
    for name in ("libLLVM-14.so.1", "libLLVM-15.so", "libLLVM-17.so", "libLLVM.so.19.1"):
        (tmp_path / name).write_bytes(b"")
    assert backend.find_libllvm((str(tmp_path),)) == str(tmp_path / "libLLVM.so.19.1")
    old = tmp_path / "old"
    old.mkdir()
    (old / "libLLVM-15.so").write_bytes(b"")
    assert backend.find_libllvm((str(old),)) is None


def test_too_old_or_missing_path_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old = tmp_path / "libLLVM-14.so"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    with pytest.raises(BackendError, match="apt-get install libllvm19"):
        backend.configure_libllvm()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "nope.so"))
    with pytest.raises(BackendError, match="no such file"):
        backend.configure_libllvm()


def test_no_llvm_anywhere_names_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(backend, "_SEARCH_DIRS", ("/nonexistent",))
    with pytest.raises(BackendError, match="libllvm19"):
        backend.configure_libllvm()


def test_fresh_process_finds_llvm_without_env() -> None:
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    code = ("from autoalign.backend import mitsuba; import os; mi = mitsuba(); "
            "print(mi.variant(), os.environ['DRJIT_LIBLLVM_PATH'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    variant, path = out.stdout.split()
    assert variant == "llvm_ad_rgb"
    assert (backend.llvm_major(path) or 0) >= 16
