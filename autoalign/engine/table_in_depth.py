"""The table plane in a scene's measured depth: the plane most of its points lie on (RANSAC,
:func:`~autoalign.recon.plane.fit_table_plane`), its normal towards the cameras.

``refine --resting`` finds its plane here when the scene has no ``recon.json``, and an object whose
depth is seen through (:mod:`autoalign.engine.see_through`) is offered it. The fit costs about 0.1 s
(10 views of 640x480), so a scene's plane is fitted once and kept for the scenes that share its
depth images (the instances of one ``--models`` scene); two instances that ask at once may each fit
it, and get the same plane.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from autoalign.io.bop import Scene
from autoalign.losses.contact import TablePlane

DEPTH_STEP = 4
"""Every this many pixels, along rows and columns, a depth sample joins the plane's fit."""
KEPT = 4
"""Planes kept, the most recently used: the scenes of one run."""
_kept: OrderedDict[tuple[int, ...], tuple[list, TablePlane]] = OrderedDict()
_KEPT_LOCK = threading.Lock()  # instances refined side by side ask at once; the fit itself runs outside it


def plane_from_depth(scene: Scene) -> TablePlane:
    """The dominant plane of the points the views of ``scene`` measured (every :data:`DEPTH_STEP`-th
    pixel), its normal towards the cameras."""
    from autoalign.recon.plane import fit_table_plane

    assert scene.depths is not None
    points = []
    for view in scene.views:
        cam, z = view.camera, view.depth
        assert z is not None
        rows, cols = np.nonzero(z[::DEPTH_STEP, ::DEPTH_STEP] > 0)
        rows, cols = rows * DEPTH_STEP, cols * DEPTH_STEP
        points.append(cam.centre + z[rows, cols, None] * cam.depth_rays(cols, rows))
    centres = np.array([c.centre for c in scene.cameras])
    plane = fit_table_plane(np.concatenate(points), centres)
    return TablePlane.of(plane.normal, plane.point)


def table_in_depth(scene: Scene) -> TablePlane:
    """:func:`plane_from_depth` of ``scene``, fitted once for the same depth images and cameras."""
    assert scene.depths is not None
    key = tuple(id(d) for d in scene.depths) + tuple(id(c) for c in scene.cameras)
    with _KEPT_LOCK:
        if key in _kept:
            _kept.move_to_end(key)
            return _kept[key][1]
    plane = plane_from_depth(scene)
    with _KEPT_LOCK:
        _kept[key] = ([*scene.depths, *scene.cameras], plane)  # the arrays held: their ids stay theirs
        while len(_kept) > KEPT:
            _kept.popitem(last=False)
    return plane
