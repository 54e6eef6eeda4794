"""The table plane the objects of ``refine --resting`` rest on (:mod:`autoalign.losses.contact`).

``--resting`` alone finds it in the scene: a scene that ``autoalign recon`` wrote is in the table's
frame (``recon.json``'s ``table``: z up, the table at z = 0); otherwise the plane is fitted to the
measured depth of the scene's views (RANSAC, :func:`~autoalign.recon.plane.fit_table_plane`, its
normal towards the cameras). ``--resting NX,NY,NZ,D`` gives it: the points ``x`` (world frame, mm)
with ``NX x + NY y + NZ z + D = 0``, the normal pointing to the side the objects stand on.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from autoalign.errors import AutoalignError
from autoalign.io.bop import Scene
from autoalign.losses.contact import TablePlane

FOUND = "table"
"""``--resting`` without a plane: find it in the scene."""
DEPTH_STEP = 4
"""Every this many pixels, along rows and columns, a depth sample joins the plane's fit."""


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
    if resting is None:
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
    return plane_from_depth(max(with_depth, key=len))


def plane_from_depth(scene: Scene) -> TablePlane:
    """The dominant plane of the points the views of ``scene`` measured (every :data:`DEPTH_STEP`-th
    pixel), its normal towards the cameras."""
    from autoalign.recon.plane import fit_table_plane

    assert scene.depths is not None
    points = []
    for cam, z in zip(scene.cameras, scene.depths):
        rows, cols = np.nonzero(z[::DEPTH_STEP, ::DEPTH_STEP] > 0)
        rows, cols = rows * DEPTH_STEP, cols * DEPTH_STEP
        points.append(cam.centre + z[rows, cols, None] * cam.depth_rays(cols, rows))
    centres = np.array([c.centre for c in scene.cameras])
    plane = fit_table_plane(np.concatenate(points), centres)
    return TablePlane.of(plane.normal, plane.point)
