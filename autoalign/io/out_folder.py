"""The output folder of a run (``--out``): created when needed and removed again if the run fails,
its files written all or none (:mod:`autoalign.io.atomic_files`), and no input file replaced; or,
for an output that is a whole folder (``autoalign export``'s dataset), replaced as a whole
(:func:`replace_folder`).

Error messages name ``--out``, the option through which every command and the batch runner
(:mod:`autoalign.batch`, whose scenes take the command's options) choose this folder.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import tempfile
from collections.abc import Iterable
from pathlib import Path

from autoalign.errors import AutoalignError
from autoalign.io.atomic_files import write_files_atomic
from autoalign.runtime.interrupts import STOP_SIGNALS, Interrupts, held_signals


def prepare_out_dir(out: Path) -> list[Path]:
    """Create ``out`` if needed and check a file can be written there.

    Returns the folders that were created (outermost first) so that a failed run can remove them.
    Raises :class:`AutoalignError` naming ``--out`` when that is impossible.
    """
    fix = "choose a folder you can write to with --out"
    if out.exists() and not out.is_dir():
        raise AutoalignError(f"--out {out}: exists and is not a folder; {fix}")
    missing: list[Path] = []
    p = out.absolute()
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    if not p.is_dir():
        raise AutoalignError(f"--out {out}: cannot create it because {p} is a file, not a folder; {fix}")
    created = list(reversed(missing))
    try:
        out.mkdir(parents=True, exist_ok=True)
        # Held: a stop arriving between the probe's creation and its removal (a worker's SIGTERM raises
        # in whatever line it lands on) would otherwise leave the probe in the user's folder.
        with held_signals(*STOP_SIGNALS):
            fd, probe = tempfile.mkstemp(prefix=".autoalign-probe-", suffix=".tmp", dir=out)
            try:
                os.write(fd, b"autoalign")
            finally:
                os.close(fd)
                os.unlink(probe)
    except OSError as exc:
        remove_empty_dirs(created)
        raise AutoalignError(f"--out {out}: cannot create or write to the folder ({exc.strerror or exc}); {fix}") from None
    except BaseException:  # Ctrl-C half-way: leave nothing behind
        remove_empty_dirs(created)
        raise
    return created


def remove_empty_dirs(created: list[Path]) -> None:
    """Remove the folders this run created (innermost first), if they are still empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            break


def write_outputs(out: Path, files: dict[str, bytes]) -> dict[str, Path]:
    """Write every ``name -> bytes`` into ``out`` atomically (:mod:`autoalign.io.atomic_files`): all or none.

    If any write fails no temporary file is left behind and no target file is touched. Nothing is
    written after Ctrl-C (see :class:`Interrupts`).
    """
    Interrupts.check()
    try:
        write_files_atomic({out / name: data for name, data in files.items()})
    except OSError as exc:
        raise AutoalignError(f"--out {out}: cannot write the outputs ({exc.strerror or exc}); "
                             "free some space or choose another --out") from None
    return {name: out / name for name in files}


def write_folder(out: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` (names relative to ``out``, subfolders allowed) with :func:`write_outputs`;
    the folders this creates are removed again if the writing fails."""
    created = prepare_out_dir(out)
    for sub in sorted({name.rsplit("/", 1)[0] for name in files if "/" in name}):
        if not (out / sub).is_dir():
            (out / sub).mkdir(parents=True)
            created.append(out / sub)
    try:
        write_outputs(out, files)
    except BaseException:
        remove_empty_dirs(created)
        raise


def check_outputs_spare_inputs(out: Path, scene_dir: Path, inputs: list[Path], outputs: Iterable[str]) -> None:
    """Refuse an ``--out`` that is the scene folder, or where one of the files ``outputs`` would
    replace an input file."""
    fix = "choose another folder with --out"
    if out.resolve() == scene_dir.resolve():
        raise AutoalignError(f"--out {out}: is the scene folder itself, whose scene_gt.json would be replaced; {fix}")
    taken = {p.resolve() for p in inputs}
    for name in outputs:
        if (out / name).resolve() in taken:
            raise AutoalignError(f"--out {out}: writing {name} there would replace the input file {out / name}; {fix}")


def replace_folder(out: Path, files: dict[str, bytes], marker: str) -> None:
    """Make ``out`` hold exactly ``files`` (names relative to it, subfolders allowed), all or none:
    they are written into a new folder beside it, which then takes its place, the old one removed.
    No file of an earlier, larger output is left beside the new ones, and a run that fails or is
    interrupted leaves the old folder as it was. ``marker``, a file every such output has, tells
    an earlier output from anything else: a non-empty ``out`` without it is refused."""
    out = out.absolute()
    check_replaceable(out, marker)
    created = prepare_out_dir(out.parent)
    new = _sibling(out, "new")
    try:
        new.mkdir()
        for sub in sorted({name.rsplit("/", 1)[0] for name in files if "/" in name}):
            (new / sub).mkdir(parents=True, exist_ok=True)
        write_outputs(new, files)
        _swap_in(new, out)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        remove_empty_dirs(created)
        raise


def check_replaceable(out: Path, marker: str) -> None:
    """Refuse an ``out`` that :func:`replace_folder` may not replace: a file, or a non-empty folder
    without ``marker`` (not an earlier output of the command)."""
    if out.exists() and not out.is_dir():
        raise AutoalignError(f"--out {out}: exists and is not a folder; choose a folder with --out")
    if out.is_dir() and any(out.iterdir()) and not (out / marker).is_file():
        raise AutoalignError(f"--out {out}: is not empty and has no {marker}, so it is not an earlier output of this "
                             "command, which replaces the whole folder; choose a new or empty folder with --out")


def _sibling(out: Path, what: str) -> Path:
    """A name beside ``out`` that nothing has: hidden, ending in ``.tmp`` like the temporary files."""
    return out.parent / f".{out.name}.{what}-{os.getpid()}-{secrets.token_hex(4)}.tmp"


def _swap_in(new: Path, out: Path) -> None:
    """Put the folder ``new`` in the place of ``out`` (if any), then remove the old one. The two renames
    are not cut apart by Ctrl-C or SIGTERM; if the second fails, the old folder goes back."""
    old = _sibling(out, "old") if out.exists() else None
    with held_signals(signal.SIGINT, signal.SIGTERM):
        try:
            if old is not None:
                os.rename(out, old)
            try:
                os.rename(new, out)
            except OSError:
                if old is not None:
                    os.rename(old, out)
                raise
        except OSError as exc:
            raise AutoalignError(f"--out {out}: cannot put the new folder in place ({exc.strerror or exc}); "
                                 "choose another --out") from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
