"""Start drjit/mitsuba on the LLVM (CPU) backend, finding a usable libLLVM by itself.

drjit's LLVM backend needs a *shared* libLLVM of version 16 or newer; versions 14/15 crash.
When ``DRJIT_LIBLLVM_PATH`` is unset we look for the newest ``libLLVM*.so*`` in the usual
library folders and set it before drjit is imported. Import this module (never ``drjit``
directly) from the rest of the package.

``AUTOALIGN_DEVICE`` picks what renders: ``cpu`` (the default: drjit's LLVM backend) or ``cuda``
(mitsuba's ``cuda_ad_rgb`` variant: drjit's CUDA backend, rays traced by OptiX; it needs an NVIDIA
GPU and driver). Everything else runs on the CPU either way; CI and the tests use the CPU.

``AUTOALIGN_THREADS`` (a positive integer), if set, is how many threads drjit renders with; by
default it takes every core. Processes that share the cores (a test runner's workers, jobs on one
node) should each take their share: two processes with a thread per core each ran the test
suite's refinements 26% slower than with one thread each, on 2 cores.
"""

from __future__ import annotations

import glob
import os
import re
import threading
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from autoalign.errors import BackendError
from autoalign.runtime.interrupts import Interrupts

MIN_LLVM_MAJOR = 16
_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)
_FIX = ("install a shared libLLVM >= 16, e.g. `apt-get install libllvm19` on Debian/Ubuntu, "
        "or set DRJIT_LIBLLVM_PATH to its libLLVM*.so")

_mi: ModuleType | None = None
_MI_LOCK = threading.Lock()
JIT_ALIGN = 128  # bytes; drjit calls a buffer aligned at 64 and then loads it with `align 128`


def llvm_major(path: str) -> int | None:
    """Major LLVM version encoded in a library file name (``libLLVM-19.so``, ``libLLVM.so.19.1``)."""
    name = os.path.basename(path)
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", name)
    return int(m.group(1)) if m else None


def find_libllvm(search_dirs: tuple[str, ...] | None = None) -> str | None:
    """Newest shared libLLVM of version >= 16 found in ``search_dirs`` (default: the usual folders), or None."""
    found: list[tuple[int, str]] = []
    for d in _SEARCH_DIRS if search_dirs is None else search_dirs:
        for p in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(os.path.join(d, "libLLVM*.dylib")):
            major = llvm_major(p)
            if major is not None and major >= MIN_LLVM_MAJOR and os.path.isfile(p):
                found.append((major, p))
    if not found:
        return None
    return sorted(found)[-1][1]


def configure_libllvm() -> str:
    """Make sure ``DRJIT_LIBLLVM_PATH`` points at a usable libLLVM; return that path."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path:
        if not os.path.isfile(path):
            raise BackendError(f"DRJIT_LIBLLVM_PATH={path}: no such file; {_FIX}")
        major = llvm_major(path)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise BackendError(f"DRJIT_LIBLLVM_PATH={path} is LLVM {major}, too old (drjit crashes); {_FIX}")
        return path
    path = find_libllvm()
    if path is None:
        raise BackendError(f"no shared libLLVM >= {MIN_LLVM_MAJOR} found in {', '.join(_SEARCH_DIRS[:3])}; {_FIX}")
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


VARIANTS = {"cpu": "llvm_ad_rgb", "cuda": "cuda_ad_rgb"}
"""mitsuba's variant for each ``AUTOALIGN_DEVICE``."""


def device() -> str:
    """What renders, from ``AUTOALIGN_DEVICE`` (``cpu`` when unset): a key of :data:`VARIANTS`."""
    value = os.environ.get("AUTOALIGN_DEVICE", "").strip().lower() or "cpu"
    if value not in VARIANTS:
        raise BackendError(f"AUTOALIGN_DEVICE={value}: not a device; set it to {' or '.join(VARIANTS)}, "
                           "or unset it to render on the CPU")
    return value


def mitsuba() -> ModuleType:
    """The ``mitsuba`` module with the variant of :func:`device` set (imported once)."""
    global _mi
    with _MI_LOCK:  # two threads starting the backend at once: mitsuba's lazy module races
        if _mi is None:
            _mi = _started_mitsuba()
    return _mi


def _started_mitsuba() -> ModuleType:
    """Import mitsuba (on the CPU with drjit's libLLVM found), set its variant and drjit's thread count."""
    on = device()
    if on == "cpu":
        configure_libllvm()
    with Interrupts.deferred():  # Ctrl-C inside drjit's module init aborts the process
        import drjit as dr  # noqa: F401  (imported after the libLLVM path is set)
        import mitsuba as mi

        try:
            mi.set_variant(VARIANTS[on])
            if on == "cuda":
                dr.eval(mi.Float(0.0))  # drjit finds the GPU (or fails) at its first kernel
        except Exception as exc:  # depends on the machine
            fix = _FIX if on == "cpu" else "unset AUTOALIGN_DEVICE to render on the CPU, or install an NVIDIA driver"
            raise BackendError(f"mitsuba cannot start its {on.upper()} backend "
                               f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); {fix}") from None
        threads = thread_count()
        if threads is not None:
            dr.set_thread_count(threads)
    return mi


def thread_count() -> int | None:
    """The threads ``AUTOALIGN_THREADS`` asks drjit for; ``None`` when unset (every core)."""
    value = os.environ.get("AUTOALIGN_THREADS", "").strip()
    if not value:
        return None
    if not value.isdigit() or int(value) < 1:
        raise BackendError(f"AUTOALIGN_THREADS={value}: not a positive whole number; set it to the threads "
                           "to render with (e.g. 1), or unset it to use every core")
    return int(value)


def drjit() -> ModuleType:
    """The ``drjit`` module, configured for the LLVM backend."""
    mitsuba()
    import drjit as dr

    return dr


def aligned_copy(a: ArrayLike, dtype: DTypeLike) -> NDArray[Any]:
    """A C-contiguous copy of ``a`` as ``dtype`` whose data starts on a ``JIT_ALIGN``-byte boundary."""
    a = np.asarray(a, dtype=dtype)
    buf = np.empty(a.nbytes + JIT_ALIGN, dtype=np.uint8)
    start = -buf.ctypes.data % JIT_ALIGN
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def numpy_of(*arrays: Any, dtype: DTypeLike | tuple[DTypeLike, ...]) -> list[NDArray[Any]]:
    """The drjit ``arrays`` as numpy arrays of ``dtype`` (one, or one per array), their kernel launched
    first by ``drjit.eval`` (one kernel for all of them). ``drjit.eval`` launches it without the GIL
    and returns before it ends; the first read waits for it, without the GIL too. A conversion that
    evaluates by itself holds the GIL while the kernel runs, and another thread's Python (an instance
    refined side by side, :mod:`autoalign.runtime.parallel`) then waits for the kernel too."""
    drjit().eval(*arrays)
    dtypes = dtype if isinstance(dtype, tuple) else (dtype,) * len(arrays)
    return [np.array(a, dtype=d) for a, d in zip(arrays, dtypes, strict=True)]


def jit_array(array_type: Any, a: ArrayLike, dtype: DTypeLike) -> Any:
    """``array_type(a)`` for a drjit array type (``mi.Float``, ``mi.UInt32``, ...), built from an aligned copy.

    drjit's LLVM backend takes a numpy buffer without copying and compiles every kernel for the
    alignment of its inputs (whether each starts on a 64-byte boundary). numpy only promises 16
    bytes, so the same kernel was compiled again (about 0.1 s each) for every new pattern of input
    alignments: 5-22 times per refinement of the simulation study, and more on a machine whose
    kernel cache is empty. Inputs that are all aligned give one kernel per computation.
    """
    return array_type(aligned_copy(a, dtype))
