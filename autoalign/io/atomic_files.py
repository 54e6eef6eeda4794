"""Writing files so that nobody ever reads half of one.

Each file is written to a temporary file beside its target, flushed to disk, and renamed over
the target (``os.replace``, atomic on POSIX). The files get the permissions a plain
``open(path, "w")`` would give them (0666 less the umask), not the 0600 of a temporary file.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from autoalign.runtime.interrupts import STOP_SIGNALS, held_signals

_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read once at import: os.umask can only be read by setting it


def write_files_atomic(files: dict[Path, bytes]) -> None:
    """Write every ``path -> bytes``; the targets are replaced only once all of them are written.

    If any write fails (a full disk, a missing folder) no temporary file is left behind, no target
    is touched, and the ``OSError`` propagates.
    """
    temps: list[tuple[Path, str]] = []
    try:
        for path, data in files.items():
            path = Path(path)
            with held_signals(*STOP_SIGNALS):  # a stop between creating and recording it would leak the file
                fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
                temps.append((path, tmp))
            with os.fdopen(fd, "wb") as f:
                os.fchmod(f.fileno(), 0o666 & ~_UMASK)
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        with held_signals(*STOP_SIGNALS):  # all the targets replaced, or none
            for path, tmp in temps:
                os.replace(tmp, path)
    except BaseException:
        for _, tmp in temps:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    write_files_atomic({Path(path): data})


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes_atomic(path, text.encode())


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    write_text_atomic(path, json.dumps(data, indent=1))
