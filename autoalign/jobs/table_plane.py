"""The table plane the objects of ``refine --resting`` rest on (:mod:`autoalign.losses.contact`).

``--resting`` alone finds it in the scene: a scene that ``autoalign recon`` wrote is in the table's
frame (``recon.json``'s ``table``: z up, the table at z = 0); otherwise the plane is fitted to the
measured depth of the scene's views (:func:`~autoalign.engine.table_in_depth.table_in_depth`).
``--resting NX,NY,NZ,D`` gives it: the points ``x`` (world frame, mm) with ``NX x + NY y + NZ z + D = 0``,
the normal pointing to the side the objects stand on.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from autoalign.engine.table_in_depth import table_in_depth
from autoalign.errors import AutoalignError
from autoalign.io.bop import Scene
from autoalign.losses.contact import TablePlane

FOUND = "table"
"""``--resting`` without a plane: find it in the scene."""
OFF = "off"
"""``--resting off``: no contact, and none offered to objects whose depth is seen through
(:attr:`~autoalign.engine.options.RefineOptions.offer_table`)."""


def parse_plane(text: str) -> TablePlane:
    """``NX,NY,NZ,D`` (module doc) as a plane; a one-line error naming the option otherwise."""
    try:
        n = np.array([float(v) for v in text.split(",")], dtype=np.float64)
    except ValueError:
        n = np.zeros(0)
    if n.shape != (4,) or not np.all(np.isfinite(n)) or np.linalg.norm(n[:3]) == 0.0:
        raise AutoalignError(f"--resting {text}: expected NX,NY,NZ,D (the table plane NX x + NY y + NZ z + D = 0 in "
                             "the world frame, mm, its normal towards the objects), e.g. 0,0,1,0; or --resting alone "
                             "to find it in the scene")
    return TablePlane.of(n[:3], -n[3] / float(n[:3] @ n[:3]) * n[:3])  # the plane's point nearest the origin


def resting_plane(resting: str | None, scene_dir: str | Path, scenes: Sequence[Scene]) -> TablePlane | None:
    """The plane ``--resting`` asks for (module doc; ``None``: not asked), found in ``scene_dir`` or
    in the measured depth of ``scenes``; a one-line error when the scene has neither."""
    if resting is None or resting == OFF:
        return None
    if resting != FOUND:
        return parse_plane(resting)
    recon = Path(scene_dir) / "recon.json"
    if recon.is_file() and "table" in json.loads(recon.read_text()):
        return TablePlane.of([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    with_depth = [s for s in scenes if s.depths is not None]
    if not with_depth:
        raise AutoalignError(f"--resting: {scene_dir} has neither a recon.json (autoalign recon's table frame) nor "
                             "measured depth to find the table plane in; give it as --resting NX,NY,NZ,D (world "
                             "frame, mm)")
    return table_in_depth(max(with_depth, key=len))
