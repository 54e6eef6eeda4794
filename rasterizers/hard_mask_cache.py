"""The hard masks of the last few poses a rasterizer drew, per camera: a refinement asks for the
same pose's full-image masks several times (the IoUs its report reads, the outline prior, the
overlay's before and after), and each is a ray cast of every pixel in the object's crop."""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera

HELD_POSES = 2
"""How many poses' masks are held: the last pose refined, and the one before it (the seed's, which
the overlay draws beside it)."""

CropHits = tuple[tuple[int, int, int, int], NDArray[np.bool_]]
"""A view's crop box ``(x0, y0, w, h)`` (px) and its hard mask within the box."""


def camera_key(cam: Camera) -> tuple[bytes, bytes, bytes, int, int]:
    """A camera's identity by value: its intrinsics, pose and image size."""
    return (np.asarray(cam.K, np.float64).tobytes(), np.asarray(cam.R_w2c, np.float64).tobytes(),
            np.asarray(cam.t_w2c, np.float64).tobytes(), cam.width, cam.height)


class HardMaskCache:
    """Crops of hard masks keyed by the pose (its exact bytes) and the camera (:func:`camera_key`), for
    the last :data:`HELD_POSES` poses; a crop holds only the object's box, so the memory held is
    small. Safe to share between threads (the label server renders from more than one)."""

    def __init__(self) -> None:
        self._poses: OrderedDict[bytes, dict[tuple, CropHits]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, T_wm: NDArray[np.float64], cams: list[Camera]) -> list[CropHits | None]:
        """The held crop of each camera at ``T_wm`` (``None`` where it is not held)."""
        key = np.asarray(T_wm, np.float64).tobytes()
        with self._lock:
            held = self._poses.get(key)
            if held is None:
                return [None] * len(cams)
            self._poses.move_to_end(key)
            return [held.get(camera_key(c)) for c in cams]

    def put(self, T_wm: NDArray[np.float64], cams: list[Camera], crops: list[CropHits]) -> None:
        """Hold ``crops`` (one per camera) for ``T_wm``, letting go of the least recently used pose."""
        key = np.asarray(T_wm, np.float64).tobytes()
        with self._lock:
            held = self._poses.setdefault(key, {})
            self._poses.move_to_end(key)
            for cam, crop in zip(cams, crops):
                held[camera_key(cam)] = crop
            while len(self._poses) > HELD_POSES:
                self._poses.popitem(last=False)
