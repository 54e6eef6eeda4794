"""Start drjit/mitsuba on the LLVM (CPU) backend, finding a usable libLLVM by itself.

drjit's LLVM backend needs a *shared* libLLVM of version 16 or newer; versions 14/15 crash.
When ``DRJIT_LIBLLVM_PATH`` is unset we look for the newest ``libLLVM*.so*`` in the usual
library folders and set it before drjit is imported. Import this module (never ``drjit``
directly) from the rest of the package.
"""

from __future__ import annotations

import glob
import os
import re
from types import ModuleType

from autoalign.errors import BackendError

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


def mitsuba() -> ModuleType:
    """The ``mitsuba`` module with the ``llvm_ad_rgb`` variant set (imported once)."""
    global _mi
    if _mi is None:
        configure_libllvm()
        import drjit as dr  # noqa: F401  (imported after the libLLVM path is set)
        import mitsuba as mi

        try:
            mi.set_variant("llvm_ad_rgb")
        except Exception as exc:  # pragma: no cover - depends on the machine
            raise BackendError(f"mitsuba cannot start its LLVM backend ({exc}); {_FIX}") from None
        _mi = mi
    return _mi


def drjit() -> ModuleType:
    """The ``drjit`` module, configured for the LLVM backend."""
    mitsuba()
    import drjit as dr

    return dr
