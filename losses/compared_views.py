"""The views of one instance as its silhouettes are compared with them: the scene as given, and per
view the target each silhouette is compared with.

The target is the view's mask, or, where the photos are evidence, the region term's target learned
on that view (:meth:`~autoalign.losses.region_term.RegionTerm.targets_in`: the mask fused with the
photo's colour posteriors). The scene itself is never rewritten: its masks stay the segmenter's,
and what the evidence made of them is held here beside it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.io.bop import Scene


@dataclass(frozen=True)
class ComparedViews:
    """The views a pose is compared with.

    Attributes:
        scene: the views as given (cameras in the world frame of ``scene_camera.json``, mm; masks,
            depth and photos as read).
        targets: per view (H, W) float32 in [0, 1] (1 = object): what the silhouette is compared with.
        photos: the photos the terms beside the targets read (the edge term's): the scene's, or
            ``None`` where a region term has made them part of its targets.
    """

    scene: Scene
    targets: list[NDArray[np.float32]]
    photos: list[NDArray[np.uint8]] | None

    def __post_init__(self) -> None:
        if len(self.targets) != len(self.scene):
            raise ValueError(f"{len(self.targets)} targets for {len(self.scene)} views")

    @classmethod
    def of(cls, scene: Scene) -> "ComparedViews":
        """``scene``'s views compared with its masks."""
        return cls(scene, scene.masks, scene.photos)

    def __len__(self) -> int:
        return len(self.scene)

    @property
    def cameras(self) -> list[Camera]:
        return self.scene.cameras

    @property
    def image_ids(self) -> list[int]:
        return self.scene.image_ids

    @property
    def ignore(self) -> list[NDArray[np.bool_]] | None:
        """Per view the pixels not compared (another instance's mask claims them), ``None``: none."""
        return self.scene.ignore

    @property
    def depths(self) -> list[NDArray[np.float32]] | None:
        """Per view the measured depth (H, W) float32, mm along the optical axis, 0 = none."""
        return self.scene.depths

    @property
    def has_targets(self) -> bool:
        """Whether any view's target shows the object (> 0.5 somewhere)."""
        return any(np.any(np.asarray(t) > 0.5) for t in self.targets)

    def compared(self, k: int) -> NDArray[np.bool_] | None:
        """View ``k``'s pixels where the silhouette is compared with the target (``None``: all)."""
        return self.scene.compared(k)

    def spread(self, k: int) -> NDArray[np.int64]:
        """Positions of at most ``k`` views evenly spread through the views' order."""
        return self.scene.spread(k)

    def subset(self, idx: Sequence[int] | NDArray[np.int64]) -> "ComparedViews":
        """The views at positions ``idx``."""
        idx = [int(i) for i in idx]
        return ComparedViews(self.scene.subset(idx), [self.targets[i] for i in idx],
                             None if self.photos is None else [self.photos[i] for i in idx])

    def through(self, cameras: Sequence[Camera]) -> "ComparedViews":
        """The same views seen through ``cameras`` (one per view: corrected ones)."""
        return replace(self, scene=replace(self.scene, cameras=list(cameras)))
