"""Meshes as loaded and prepared, kept on disk between runs: a mesh file read again is not parsed,
welded and decimated again, and trimesh (about 1 s to import, with scipy) is not imported at all.

An entry is keyed by the file's bytes, the units it was read in, the level (the mesh as loaded, or
simplified to at most N triangles, or as the file gives it with its vertex colours) and the versions of the code that made it (:data:`FORMAT`,
numpy, trimesh and fast_simplification), so a changed file or library makes a new entry and never
reads an old one. Entries are ``.npz`` files written atomically; one that cannot be read is made
again. The folder is ``$AUTOALIGN_CACHE_DIR``, else ``$XDG_CACHE_HOME/autoalign/meshes``, else
``~/.cache/autoalign/meshes``; ``AUTOALIGN_CACHE_DIR=off`` turns the cache off. Deleting the folder
is always safe. A folder that cannot be written leaves the cache off, silently: it saves time, it
never changes a result.
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import zipfile
from importlib import metadata
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.io.atomic_files import write_bytes_atomic

FORMAT = 2
"""Bumped whenever what an entry holds, or how it is computed, changes (2: simplified levels made one at
a time; before, two made at once on threads could hold each other's meshes)."""
CACHE_ENV = "AUTOALIGN_CACHE_DIR"
OFF = "off"


def cache_dir() -> Path | None:
    """The cache folder (module doc), or ``None`` when the cache is off."""
    given = os.environ.get(CACHE_ENV, "").strip()
    if given.lower() == OFF:
        return None
    if given:
        return Path(given)
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "autoalign" / "meshes"


@functools.lru_cache(maxsize=1)
def _code_versions() -> str:
    """The versions of everything that shapes an entry (read from the installed packages' metadata)."""
    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "none"

    return f"{FORMAT}/numpy {np.__version__}/trimesh {version('trimesh')}/fs {version('fast_simplification')}"


def file_key(path: Path, units: str | None) -> str:
    """The key of the mesh file ``path`` read in ``units``: a hash of its bytes and of the code's versions."""
    h = hashlib.sha256()
    h.update(_code_versions().encode())
    h.update(f"\0{units}\0".encode())
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def level_key(key: str, max_faces: int) -> str:
    """The key of the mesh of ``key`` simplified to at most ``max_faces`` triangles."""
    return f"{key}-f{int(max_faces)}"


def coloured_key(key: str) -> str:
    """The key of the mesh of ``key`` as its file gives it, with its vertex colours (for the check)."""
    return f"{key}-coloured"


def read_entry(key: str, names: tuple[str, ...]) -> dict[str, NDArray] | None:
    """The arrays ``names`` of entry ``key``; ``None`` when the cache is off, the entry is missing,
    or it cannot be read or lacks one of them (then it is made again)."""
    folder = cache_dir()
    if folder is None:
        return None
    path = folder / f"{key}.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            return {n: z[n] for n in names}
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def write_entry(key: str, arrays: dict[str, NDArray]) -> None:
    """Store ``arrays`` as entry ``key`` (atomically); nothing when the cache is off or unwritable."""
    folder = cache_dir()
    if folder is None:
        return
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(folder / f"{key}.npz", buffer.getvalue())
    except OSError:
        return
