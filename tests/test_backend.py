"""drjit finds a usable libLLVM by itself, or says exactly what to install."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from autoalign.errors import BackendError
from autoalign.runtime import backend


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


def test_the_device_is_the_cpu_unless_asked_and_a_wrong_one_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("AUTOALIGN_DEVICE", raising=False)
    assert backend.device() == "cpu" and backend.VARIANTS["cpu"] == "llvm_ad_rgb"
    monkeypatch.setenv("AUTOALIGN_DEVICE", " CUDA ")
    assert backend.device() == "cuda"
    monkeypatch.setenv("AUTOALIGN_DEVICE", "gpu")
    with pytest.raises(BackendError, match="AUTOALIGN_DEVICE=gpu: not a device; set it to cpu or cuda"):
        backend.device()


def test_rendering_on_cuda_without_a_gpu_is_one_line_and_writes_nothing(tmp_path: Path) -> None:
    """``AUTOALIGN_DEVICE=cuda`` renders on an NVIDIA GPU (measured in ``bench_device``); on a machine
    without one the command says so in one line and writes nothing, and with one it refines."""
    ex = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(ex / "scene"), "--model",
                        str(ex / "model.ply"), "--init", str(ex / "init_gt.json"), "--quiet", "--out", str(out)],
                       env={**os.environ, "AUTOALIGN_DEVICE": "cuda"}, capture_output=True, text=True)
    if shutil.which("nvidia-smi") is None:
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("autoalign: error: mitsuba cannot start its CUDA backend")
        assert "unset AUTOALIGN_DEVICE to render on the CPU" in lines[0]
        assert not out.exists()
    else:
        assert p.returncode == 0, p.stderr
        assert (out / "refine.json").is_file()


def test_the_label_page_on_cuda_is_refused_in_one_line(tmp_path: Path) -> None:
    """The label page renders from its request threads, which drjit's CUDA backend refuses."""
    ex = Path(__file__).resolve().parents[1] / "autoalign" / "data" / "example"
    out = tmp_path / "session"
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "label", str(ex / "scene"), "--models",
                        str(tmp_path), "--out", str(out), "--no-browser"],
                       env={**os.environ, "AUTOALIGN_DEVICE": "cuda"}, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip() == ("autoalign: error: AUTOALIGN_DEVICE=cuda: the label page renders on the CPU; "
                                "unset AUTOALIGN_DEVICE for `autoalign label`")
    assert not out.exists()


def test_fresh_process_finds_llvm_without_env() -> None:
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    code = ("from autoalign.runtime.backend import mitsuba; import os; mi = mitsuba(); "
            "print(mi.variant(), os.environ['DRJIT_LIBLLVM_PATH'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    variant, path = out.stdout.split()
    assert variant == "llvm_ad_rgb"
    assert (backend.llvm_major(path) or 0) >= 16


def test_aligned_copy_starts_on_the_boundary_and_keeps_the_values() -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(size=1000)
    for offset in range(8):  # views starting 8 bytes apart
        out = backend.aligned_copy(base[offset:offset + 500], np.float32)
        assert out.ctypes.data % backend.JIT_ALIGN == 0
        assert out.dtype == np.float32 and out.flags.c_contiguous
        np.testing.assert_array_equal(out, base[offset:offset + 500].astype(np.float32))


def test_jit_arrays_compile_one_kernel_whatever_the_numpy_alignment() -> None:
    """drjit specialises a kernel on whether each input starts on a 64-byte boundary; numpy buffers
    16 bytes apart used to give two compiled kernels for one computation (0.1 s each)."""
    mi, dr = backend.mitsuba(), backend.drjit()
    base = np.arange(4096 + 64, dtype=np.float64)
    start = (-base.ctypes.data % 128) // 8  # first element on a 128-byte boundary
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        hashes = []
        for offset in (0, 2, 8, 3):  # 0, 16, 64 and 24 bytes past the boundary
            view = base[start + offset:start + offset + 4096]
            dr.kernel_history()  # clears it
            x = backend.jit_array(mi.Float64, view, np.float64)
            y = x * dr.opaque(mi.Float64, 2.5) + 1.25
            dr.eval(y)
            np.testing.assert_array_equal(np.array(y), view * 2.5 + 1.25)
            hashes += [k["hash"] for k in dr.kernel_history() if str(k["type"]).endswith("JIT")]
        assert len(hashes) == 4 and len(set(hashes)) == 1, hashes
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


@pytest.mark.parametrize("value,threads", [("3", 3), ("1", 1), ("", None)])
def test_autoalign_threads_sets_drjits_thread_count(value: str, threads: int | None) -> None:
    """``AUTOALIGN_THREADS`` is the thread count drjit renders with (a fresh process); unset or
    empty, drjit keeps its own (every core)."""
    env = {k: v for k, v in os.environ.items() if k != "AUTOALIGN_THREADS"}
    if value:
        env["AUTOALIGN_THREADS"] = value
    code = ("from autoalign.runtime.backend import drjit; import os; "
            "print(drjit().thread_count(), os.cpu_count())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    got, cores = map(int, out.stdout.split())
    assert got == (threads if threads is not None else cores)


@pytest.mark.parametrize("value", ["0", "two", "-1", "1.5"])
def test_a_bad_autoalign_threads_is_a_one_line_error(value: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AUTOALIGN_THREADS", value)
    with pytest.raises(BackendError, match=f"AUTOALIGN_THREADS={value}: not a positive whole number"):
        backend.thread_count()


def test_backend_started_by_two_threads_at_once_starts_once() -> None:
    """mitsuba's module is loaded lazily: two threads setting its variant at once made one fail."""
    code = ("import threading; from autoalign.runtime.backend import mitsuba\n"
            "got = []\n"
            "def start(): got.append(mitsuba())\n"
            "ts = [threading.Thread(target=start) for _ in range(4)]\n"
            "[t.start() for t in ts]; [t.join() for t in ts]\n"
            "print(len(got), len({id(m) for m in got}), got[0].variant())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["4", "1", "llvm_ad_rgb"]


def test_numpy_of_runs_the_kernel_once_for_all_and_keeps_the_values() -> None:
    """The arrays of one computation come back from one kernel (run by ``drjit.eval``, without the
    GIL), with the values and dtypes the plain conversion gives."""
    dr, mi = backend.drjit(), backend.mitsuba()
    x = backend.jit_array(mi.Float, np.linspace(0.0, 3.0, 1000), np.float32)
    a, b = dr.sin(x) * 2.0, dr.cos(x) + x
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        got_a, got_b = backend.numpy_of(a, b, dtype=np.float64)
        launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(launched) == 1
    assert got_a.dtype == np.float64 and got_b.dtype == np.float64
    np.testing.assert_array_equal(got_a, np.array(a, dtype=np.float64))
    np.testing.assert_array_equal(got_b, np.array(b, dtype=np.float64))
    t = np.linspace(0.0, 3.0, 1000).astype(np.float32)
    np.testing.assert_allclose(got_a, 2.0 * np.sin(t), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got_b, np.cos(t) + t, rtol=1e-5, atol=1e-6)
