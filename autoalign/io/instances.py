"""The instances of a multi-object BOP scene folder: which object each mask shows, and one
:class:`~autoalign.io.bop.Scene` per instance whose ignored pixels are those other masks claim.

Instance ``k`` is the ``k`` of ``mask_visib/{im_id:06d}_{k:06d}.png``. Its object comes from

* an instances file, for a fresh capture whose segmenter keeps instance ids across views::

      {"instances": {"0": 5, "3": 8}}

  (instance number -> BOP ``obj_id``). Instances not listed are objects without a model: they are
  not posed, but their masks still claim pixels (see below);
* or else the scene's own ``scene_gt.json`` (BOP: entry ``k`` of an image's list is the mask
  ``..._{k:06d}.png``); an instance's ``obj_id`` must be the same in every image that lists it.

An instance may be missing in some views (no file, or an empty mask: treated as missing). In each
view, the pixels of the other instances' masks (modelled or not) that its own mask does not
cover are ignored for it: the object may be hidden behind that one there, or that mask may have
strayed onto it. Its silhouette is compared with its own mask everywhere else.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.camera import Camera
from autoalign.geometry.se3 import invert
from autoalign.io.bop import (
    INIT_FIX,
    MAX_IMAGE_PIXELS,
    Scene,
    check_masks_have_cameras,
    check_scene_dir,
    init_images_without_camera,
    mask_files,
    pose_of_entry,
    read_cameras,
    read_init_file,
    read_json_file,
    read_masks,
    scene_cameras,
    whole_number_keys,
    with_depth,
)

INSTANCES_FIX = 'an instances file is JSON {"instances": {"0": 5, "3": 8}}: instance number -> BOP obj_id'


@dataclass(frozen=True)
class Instance:
    """One object instance: its mask number ``index`` (``..._{index:06d}.png``) and BOP ``obj_id``."""

    index: int
    obj_id: int


@dataclass
class InstanceScenes:
    """What :func:`read_instance_scenes` returns.

    Attributes:
        instances: the posed instances, by mask number.
        scenes: one :class:`Scene` per posed instance (its non-empty views only, other masks ignored).
        cameras: every image of ``scene_camera.json`` (at the masks' scale), with ``image_ids``.
        unmodelled: mask numbers seen in ``mask_visib/`` that no model is given for.
    """

    instances: list[Instance]
    scenes: list[Scene]
    cameras: list[Camera]
    image_ids: list[int]
    unmodelled: list[int]

    def through(self, cameras: dict[int, Camera]) -> "InstanceScenes":
        """The same scene seen through ``cameras`` (by image id; images not in it keep theirs), e.g.
        corrected or rescaled ones."""
        return replace(self, scenes=[replace(sc, cameras=[cameras.get(im, c) for im, c in zip(sc.image_ids, sc.cameras)])
                                     for sc in self.scenes],
                       cameras=[cameras.get(im, c) for im, c in zip(self.image_ids, self.cameras)])

    def with_depth(self) -> "InstanceScenes":
        """Every instance's scene with the folder's measured depth (:func:`~autoalign.io.bop.with_depth`,
        each image read once)."""
        read: dict[int, NDArray[np.float32] | None] = {}
        return replace(self, scenes=[with_depth(sc, read) for sc in self.scenes])

    def views(self, image_ids: list[int]) -> "InstanceScenes":
        """The same instances seen only in the images ``image_ids`` (each instance's views among
        them, :meth:`Scene.subset`; its empty masks and skipped images among them too), e.g. one
        half of the views. An instance with no view there keeps an empty scene."""
        keep = set(int(i) for i in image_ids)
        scenes = [replace(sc.subset([k for k, im in enumerate(sc.image_ids) if im in keep]),
                          empty=tuple(im for im in sc.empty if im in keep),
                          skipped=tuple(im for im in sc.skipped if im in keep)) for sc in self.scenes]
        pos = [k for k, im in enumerate(self.image_ids) if im in keep]
        return replace(self, scenes=scenes, cameras=[self.cameras[k] for k in pos],
                       image_ids=[self.image_ids[k] for k in pos])

    @property
    def camera_by_id(self) -> dict[int, Camera]:
        """Every image's camera by image id."""
        return dict(zip(self.image_ids, self.cameras))


def read_instances(scene_dir: str | os.PathLike[str],
                   instances_file: str | os.PathLike[str] | None = None) -> list[Instance]:
    """The instances to pose, from ``instances_file`` or else ``scene_dir/scene_gt.json``."""
    if instances_file is not None:
        return _from_instances_file(Path(instances_file))
    path = Path(scene_dir) / "scene_gt.json"
    if not path.is_file():
        raise AutoalignError(f"{path}: not found, and no --instances file was given; say which object each "
                             f"instance is ({INSTANCES_FIX}), or add the scene's scene_gt.json")
    return instances_of_scene_gt(path)


def instances_of_scene_gt(path: str | os.PathLike[str],
                          fix: str = f"pass an --instances file ({INSTANCES_FIX})") -> list[Instance]:
    """The instances a BOP ``scene_gt.json`` lists: entry ``k`` of an image is instance ``k``, whose
    ``obj_id`` must be the same in every image that lists it; ``fix`` ends the error when it lists none."""
    path = Path(path)
    data = read_json_file(path, fix)
    seen: dict[int, tuple[int, str]] = {}
    if not isinstance(data, dict):
        raise AutoalignError(f"{path}: expected image ids mapping to lists of {{\"obj_id\", ...}}; fix the file")
    for im, entries in whole_number_keys(data, path, "image id").items():
        if not isinstance(entries, list) or not all(isinstance(e, dict) and isinstance(e.get("obj_id"), int)
                                                    for e in entries):
            raise AutoalignError(f"{path}: image {im} must hold a list of entries with an integer obj_id; fix the file")
        for k, e in enumerate(entries):
            if k in seen and seen[k][0] != e["obj_id"]:
                raise AutoalignError(f"{path}: entry {k} is obj_id {seen[k][0]} in image {seen[k][1]} but "
                                     f"{e['obj_id']} in image {im}; BOP instance k must be the same object in "
                                     f"every image, or pass an --instances file")
            seen.setdefault(k, (e["obj_id"], im))
    if not seen:
        raise AutoalignError(f"{path}: lists no objects; {fix}")
    return [Instance(k, obj) for k, (obj, _) in sorted(seen.items())]


def _from_instances_file(path: Path) -> list[Instance]:
    data = read_json_file(path, f"pass an existing instances file ({INSTANCES_FIX})")
    table = data.get("instances") if isinstance(data, dict) else None
    if not isinstance(table, dict) or not table:
        raise AutoalignError(f"{path}: no \"instances\" table; {INSTANCES_FIX}")
    out = []
    for index, obj in whole_number_keys(table, path, "instance number").items():
        if isinstance(obj, bool) or not isinstance(obj, int) or obj < 0 or index < 0:
            raise AutoalignError(f"{path}: instance {index} -> {obj!r}; {INSTANCES_FIX}")
        out.append(Instance(index, obj))
    return sorted(out, key=lambda i: i.index)


def read_instance_scenes(scene_dir: str | os.PathLike[str], instances: list[Instance] | None,
                         max_pixels: int | None = MAX_IMAGE_PIXELS) -> InstanceScenes:
    """Cameras and every mask of ``scene_dir``, as one :class:`Scene` per instance (see module doc).
    ``instances=None``: every instance number with a non-empty mask, its object not known yet
    (``obj_id`` 0, for ``autoalign label``, where a person says which object it is)."""
    scene_dir = check_scene_dir(scene_dir)
    cams = read_cameras(scene_dir)
    check_masks_have_cameras(scene_dir, set(cams))
    read = read_masks(mask_files(scene_dir), max_pixels)
    if read.size is None:
        raise AutoalignError(f"{scene_dir / 'mask_visib'}: no mask files named {{im_id:06d}}_{{instance:06d}}.png; "
                             "write the instance masks there")
    ids = list(cams)
    cameras = scene_cameras(cams, ids, read)
    claimed = {}  # im -> union of every mask of that image
    for (im, _), m in read.masks.items():
        claimed[im] = m | claimed[im] if im in claimed else m.copy()
    pos = {im: i for i, im in enumerate(ids)}
    if instances is None:
        instances = [Instance(k, 0) for k in sorted({k for _, k in read.masks})]
    views_of = {inst.index: [im for im in ids if (im, inst.index) in read.masks] for inst in instances}
    for inst in instances:
        if not views_of[inst.index]:
            raise AutoalignError(f"{scene_dir / 'mask_visib'}: instance {inst.index} (obj {inst.obj_id}) has no "
                                 f"non-empty mask ..._{inst.index:06d}.png in any image; remove it from the "
                                 "instances or add its masks")

    def targets(inst: Instance) -> tuple[list[NDArray[np.float32]], list[NDArray[np.bool_]]]:
        """The instance's masks as float targets, and the pixels the other instances' masks claim."""
        own = [read.masks[(im, inst.index)] for im in views_of[inst.index]]
        return [m.astype(np.float32) for m in own], [claimed[im] & ~m for im, m in zip(views_of[inst.index], own)]

    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:  # numpy lets go of the GIL here
        made = list(pool.map(targets, instances))
    scenes = []
    for inst, (masks, ignore) in zip(instances, made):
        views = views_of[inst.index]
        scenes.append(Scene([cameras[pos[im]] for im in views], masks, views,
                            scene_dir, tuple(im for im in ids if (im, inst.index) not in read.masks and
                                             (im, inst.index) not in read.empty),
                            tuple(im for im, k in read.empty if k == inst.index), 1.0 / read.factor,
                            ignore=ignore))
    posed = {i.index for i in instances}
    unmodelled = sorted({k for _, k in read.masks} - posed)
    return InstanceScenes(list(instances), scenes, cameras, ids, unmodelled)


def read_init_poses(path: str | os.PathLike[str], found: InstanceScenes) -> dict[int, NDArray[np.float64]]:
    """World-from-model poses (4x4, mm) of the instances from a coarse BOP ``scene_gt.json``.

    Instance ``k``'s pose is entry ``k`` of the lowest image id that has a camera and lists it with
    the instance's ``obj_id``; instances it does not give are left out. A file none of whose images
    has a camera in the scene is an error (:func:`~autoalign.io.bop.read_init_file` checks its shape).
    """
    path = Path(path)
    images = read_init_file(path)
    cams = dict(zip(found.image_ids, found.cameras))
    if not any(im in cams for im in images):
        raise init_images_without_camera(path, images, cams)
    out: dict[int, NDArray[np.float64]] = {}
    for inst in found.instances:
        for im, entries in images.items():
            if im not in cams or len(entries) <= inst.index or entries[inst.index].get("obj_id") != inst.obj_id:
                continue
            T_cm = pose_of_entry(entries[inst.index], path, f"image {im} entry {inst.index}", INIT_FIX)
            out[inst.index] = invert(cams[im].T_cw) @ T_cm
            break
    return out
