"""``OUT_DIR/label.lock``: one label server per session folder.

Two servers on one folder would each save their own state over the other's ``session.json`` (a
change on the second erased what the first had placed). The lock is the file's ``fcntl.flock``,
held for the server's life: the kernel drops it when the process ends, however it ends, so a lock
file left by a server that was killed (a dead pid) is simply taken over. The file's content (pid,
host, the page's URL) only says who holds it, for the refusal's message.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError

LOCK_NAME = "label.lock"
_TRIES = 5


def _holder(fd: int) -> dict[str, Any]:
    """What the lock file open at ``fd`` says of its holder (``{}`` if unreadable or half written)."""
    try:
        data = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _is_the_file_at(fd: int, path: Path) -> bool:
    """Whether ``fd`` is still the file at ``path`` (a server that stopped may have just removed it)."""
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def _refusal(out_dir: Path, holder: dict[str, Any]) -> AutoalignError:
    url = holder.get("url") or "still starting"
    who = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}"
    return AutoalignError(f"{out_dir}: another autoalign label server is using this session folder ({url}, {who}); "
                          "use that page, or stop that server (Ctrl-C) first, or pass another --out")


class SessionLock:
    """The lock of ``out_dir`` (see module doc); take it with :meth:`acquire`, give it back with :meth:`release`."""

    def __init__(self, out_dir: Path, fd: int, made_dir: bool) -> None:
        self.out_dir, self._fd, self._made_dir = out_dir, fd, made_dir
        self.path = out_dir / LOCK_NAME

    @classmethod
    def acquire(cls, out_dir: str | os.PathLike[str]) -> SessionLock:
        """Lock ``out_dir`` (made if missing) for this process; raises :class:`AutoalignError` naming the
        server that holds it."""
        out = Path(out_dir)
        made_dir = not out.exists()
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise AutoalignError(f"{out}: cannot make the session folder ({exc.strerror}); pass another --out") from None
        for _ in range(_TRIES):
            try:
                fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise AutoalignError(f"{out / LOCK_NAME}: cannot be opened ({exc.strerror}); make the folder "
                                     "writable, or pass another --out") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _holder(fd)
                os.close(fd)
                raise _refusal(out, holder) from None
            if _is_the_file_at(fd, out / LOCK_NAME):
                lock = cls(out, fd, made_dir)
                lock.announce(None)
                return lock
            os.close(fd)  # locked a file that its server removed as it stopped: take the new one
        raise AutoalignError(f"{out / LOCK_NAME}: could not be locked; try again, or pass another --out")

    def announce(self, url: str | None) -> None:
        """Write who holds the lock: this process, and the page's ``url`` once the server listens."""
        info = {"pid": os.getpid(), "host": socket.gethostname(), "url": url,
                "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, json.dumps(info).encode(), 0)

    def release(self) -> None:
        """Remove the lock file and unlock (the folder too, if the lock made it and nothing else is in it)."""
        if self._fd < 0:
            return
        if _is_the_file_at(self._fd, self.path):
            self.path.unlink()  # while still locked: a server starting now locks a new file
        os.close(self._fd)
        self._fd = -1
        if self._made_dir:
            try:
                self.out_dir.rmdir()
            except OSError:
                pass  # the session's files are there: they stay

    def __enter__(self) -> SessionLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
