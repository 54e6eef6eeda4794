"""The scene a labelling session works on, read once: its views, its instance masks, the objects
that can be chosen and those an instances file suggests. Read-only, so any thread may ask it.

Pixel coordinates are OpenCV's (the centre of the top-left pixel at 0, 0), in the masks'
resolution (the views' ``width`` x ``height``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera
from autoalign.io.bop import Scene
from autoalign.io.instances import InstanceScenes, read_instance_scenes, read_instances
from autoalign.io.models import ModelSet
from autoalign.scene.scale import cameras_up_to_scale

NEAR_MASK_PX = 40
"""With the photos as evidence, a click off every mask this close (px) to an instance's mask means
that instance: the part a segmenter mask misses (a dark handle) adjoins what it found. A click
farther from every mask is refused rather than guessed."""


class SessionScene:
    """A BOP scene folder's views and instance masks, with the models to choose from.

    Args:
        scene_dir: a BOP scene folder with ``scene_camera.json`` and instance masks in ``mask_visib/``.
        models: the objects that can be chosen.
        instances_file: an instances file (``{"instances": {"0": 5}}``) whose objects are offered first.
    """

    def __init__(self, scene_dir: str | os.PathLike[str], models: ModelSet,
                 instances_file: str | os.PathLike[str] | None = None) -> None:
        self.scene_dir, self.models = Path(scene_dir), models
        self.found: InstanceScenes = read_instance_scenes(self.scene_dir, None)
        if not cameras_up_to_scale(self.scene_dir):  # measured depth joins the masks (as in refine)
            self.found = self.found.with_depth()
        if (self.scene_dir / "rgb").is_dir():  # and the photos (as refine's --photos auto)
            from autoalign.io.evidence import instance_scenes_with_photos

            self.found = instance_scenes_with_photos(self.found)
        self.indices = [i.index for i in self.found.instances]
        if not self.indices:
            raise AutoalignError(f"{self.scene_dir / 'mask_visib'}: no non-empty instance mask; label a scene with "
                                 "masks (a segmenter's, or 'autoalign recon --propose')")
        self.suggested = self._suggested_objects(None if instances_file is None else Path(instances_file))
        self.object_ids = sorted(int(p.stem[4:]) for p in models.folder.glob("obj_*.ply") if p.stem[4:].isdigit())
        if not self.object_ids:
            raise AutoalignError(f"{models.folder}: no obj_XXXXXX.ply; pass a BOP models folder to --models")

    @property
    def views(self) -> list[Camera]:
        return self.found.cameras

    @property
    def image_ids(self) -> list[int]:
        return self.found.image_ids

    def _suggested_objects(self, instances_file: Path | None) -> dict[int, int]:
        """instance -> obj_id from an instances file or the scene's own ``scene_gt.json`` (if any)."""
        if instances_file is None and not (self.scene_dir / "scene_gt.json").is_file():
            return {}
        return {i.index: i.obj_id for i in read_instances(self.scene_dir, instances_file)}

    def scene_of(self, index: int) -> Scene:
        """The views and masks of instance ``index`` (other masks' pixels ignored)."""
        return self.found.scenes[self.indices.index(index)]

    def view(self, image_id: int) -> Camera:
        """The camera of image ``image_id``; raises if the scene has no such view."""
        if image_id not in self.image_ids:
            raise AutoalignError(f"image {image_id} is not a view of {self.scene_dir}")
        return self.views[self.image_ids.index(image_id)]

    def masks_in_view(self, image_id: int) -> dict[int, NDArray[np.bool_]]:
        """Every instance's mask in image ``image_id`` (at the views' resolution), by instance."""
        out = {}
        for inst, sc in zip(self.found.instances, self.found.scenes):
            if image_id in sc.image_ids:
                out[inst.index] = np.asarray(sc.masks[sc.image_ids.index(image_id)]) > 0.5
        return out

    @property
    def has_photos(self) -> bool:
        """Whether the photos are evidence (the scene has ``rgb/``)."""
        return any(sc.photos is not None for sc in self.found.scenes)

    def instance_at(self, image_id: int, u: float, v: float) -> int:
        """The instance a click at OpenCV pixel ``(u, v)`` of image ``image_id`` means (:meth:`click_target`)."""
        return self.click_target(image_id, u, v)[0]

    def click_target(self, image_id: int, u: float, v: float) -> tuple[int, float, float]:
        """The instance a click means and the OpenCV pixel to seed it from: the instance whose mask
        covers the pixel (the smallest, where masks overlap), seeded there; with the photos as
        evidence, a click off every mask within :data:`NEAR_MASK_PX` of one means that instance
        (its mask missed the part clicked, the photo completes it), seeded from its mask's nearest
        pixel. Raises :class:`AutoalignError` if neither."""
        cam = self.view(image_id)
        col, row = int(round(u)), int(round(v))
        if not (0 <= col < cam.width and 0 <= row < cam.height):
            raise AutoalignError(f"pixel {u:.0f},{v:.0f} is outside the {cam.width}x{cam.height} image {image_id}")
        masks = self.masks_in_view(image_id)
        under = [(int(m.sum()), k) for k, m in masks.items() if m[row, col]]
        if under:
            return min(under)[1], float(u), float(v)
        if self.has_photos:
            near = []
            for k, m in masks.items():
                ys, xs = np.nonzero(m)
                if len(ys):
                    j = int(np.argmin((xs - col) ** 2 + (ys - row) ** 2))
                    near.append((float(np.hypot(xs[j] - col, ys[j] - row)), k, float(xs[j]), float(ys[j])))
            if near and min(near)[0] <= NEAR_MASK_PX:
                _, k, x, y = min(near)
                return k, x, y
            raise AutoalignError(f"no instance mask under pixel {col},{row} of image {image_id}, nor within "
                                 f"{NEAR_MASK_PX} px of it; click on an object that has a mask in some part of it")
        raise AutoalignError(f"no instance mask under pixel {col},{row} of image {image_id}; click inside a tinted "
                             "region (autoalign aligns a model with a mask; with photos in rgb/, also next to one)")

    def check_object(self, obj_id: int) -> None:
        """Raise unless ``obj_id`` has a model."""
        if obj_id not in self.object_ids:
            raise AutoalignError(f"object {obj_id} has no model in {self.models.folder}; choose one of "
                                 f"{', '.join(map(str, self.object_ids))}")

    def check_instance(self, index: int) -> None:
        """Raise unless ``index`` is one of the scene's instance masks."""
        if index not in self.indices:
            raise AutoalignError(f"instance {index} has no mask in {self.scene_dir / 'mask_visib'}")
