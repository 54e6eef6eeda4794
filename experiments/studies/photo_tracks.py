"""The real scenes' photos' own feature tracks (our structure from motion), by which
:func:`~autoalign.experiments.studies.metrics.track_fit` judges a set of cameras without masks or
labels. Its own module so that ``real_scenes`` and ``recon_real`` both use it without importing each other."""

from __future__ import annotations

from pathlib import Path

from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import read_cameras
from autoalign.recon.capture import read_capture
from autoalign.recon.sfm import SfmResult, run_sfm


def photo_tracks(scene: Path, tmp: Path) -> SfmResult:
    """Our structure from motion of the scene's photos (with its ``cam_K``; COLMAP's files in
    ``tmp/tracks``): the photos' own feature tracks, for :func:`~autoalign.experiments.studies.metrics.track_fit`."""
    K = next(iter(read_cameras(scene).values()))[0]
    (tmp / "tracks").mkdir(parents=True, exist_ok=True)
    write_json_atomic(tmp / "tracks" / "K.json", {"cam_K": K.ravel().tolist()})
    return run_sfm(read_capture(scene / "rgb", tmp / "tracks", intrinsics=tmp / "tracks" / "K.json"), tmp / "tracks")
