"""Where the project lead's material is: the ``shared/`` folder beside the checkout (real scenes,
BOP models). ``$AUTOALIGN_SHARED`` names it; otherwise ``shared/`` in or beside the current folder,
then ``/work/shared``."""

from __future__ import annotations

import os
from pathlib import Path


def shared_dir() -> Path:
    """The ``shared/`` folder (it may not exist on a machine without the material)."""
    if "AUTOALIGN_SHARED" in os.environ:
        return Path(os.environ["AUTOALIGN_SHARED"])
    for base in (Path.cwd(), Path.cwd().parent, Path("/work")):
        if (base / "shared").is_dir():
            return base / "shared"
    return Path("/work/shared")


REAL_SCENES = shared_dir() / "real" / "lmo_dev"
"""The real LM-O development scenes."""
YCBV_RGBD = shared_dir() / "real" / "ycbv_rgbd" / "0000"
"""Real YCB-Video RGB-D frames (one viewpoint, sensor depth; the labels agree with it to about 2 mm)."""
