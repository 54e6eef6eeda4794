"""The region term: each view's mask fused with its photo's colour posteriors, as the silhouette's target.

Its state is the colour models learned at one pose (:meth:`RegionTerm.learned_at`): per view the
region target they give (:func:`~autoalign.losses.region.region_target`: the posteriors near the
silhouette, their odds multiplied with the mask's), which stays fixed while a pose is descended on
it, so that the solver compares its steps on one objective. Learned again at the pose reached, it
is the alternation PWP3D and RBOT use per frame (the rounds of :mod:`autoalign.engine.photo_evidence`).
It takes the mask term's place: the silhouettes are compared with its targets by the mask term's
loss, and its targets are what the views' overlaps are measured against (the objective's views
as it compares them: :meth:`RegionTerm.targets_in`, a
:class:`~autoalign.losses.compared_views.ComparedViews`). Fused per pixel, not added beside the masks:
added, a pixel that the mask misses but whose colour is clearly the object's would pull nowhere
(measured: ``experiments/results/photo_fusion_additive_*.md``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import Scene
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.mask_term import MaskTerm
from autoalign.losses.region import RegionOptions, RegionTarget, region_target


class RegionTerm(MaskTerm):
    """The silhouettes against the views' region targets learned at one pose (module doc), with one of
    :data:`~autoalign.losses.LOSSES` (``loss``). Named as the mask term, whose place and record it
    takes (``refine.json``'s ``mask_loss``: the silhouette against the view's target).

    Attributes:
        learned: per view what the colour models gave at the pose they were learned at
            (:class:`~autoalign.losses.region.RegionTarget`: the target, the band, the agreement, the
            edge contrast and, where measured, the separation).
        masks_given: whether the instance had masks (``--masks none``: the colours alone make the targets,
            and the edge term reads the photos beside them).
    """

    def __init__(self, learned: Sequence[RegionTarget], masks_given: bool, loss: str = "l2") -> None:
        super().__init__(loss)
        self.learned = tuple(learned)
        self.masks_given = masks_given

    @classmethod
    def learned_at(cls, scene: Scene, silhouettes: list[NDArray[np.bool_]], options: RegionOptions,
                   loss: str = "l2", measure: bool = False) -> "RegionTerm":
        """The colour models of every view of ``scene`` learned around ``silhouettes`` (one hard
        silhouette per view, at the pose they are learned at), fused with the views' masks where it has
        any; with the colour models' separation when ``measure`` (the evidence reported, not the rounds')."""
        if scene.photos is None:
            raise ValueError("the scene has no photos")
        has_mask = scene.has_masks
        return cls([region_target(view.photo, sil, view.mask if has_mask else None, view.ignore, options, measure)
                    for view, sil in zip(scene.views, silhouettes)], has_mask, loss)

    @property
    def targets(self) -> list[NDArray[np.float32]]:
        """Per view the target (H, W) float32 in [0, 1]."""
        return [rt.target for rt in self.learned]

    def covered(self) -> list[int]:
        """The positions of the views whose target shows the object (> 0.5 somewhere): compared as a
        target, an empty one would pull the silhouette out of its view."""
        return [k for k, rt in enumerate(self.learned) if np.any(rt.target > 0.5)]

    def subset(self, idx: Sequence[int]) -> "RegionTerm":
        """The term on the views at positions ``idx``."""
        return RegionTerm([self.learned[int(i)] for i in idx], self.masks_given, self.loss)

    def targets_in(self, scene: Scene) -> ComparedViews:
        """``scene`` (the views this term was learned on) as this term compares it: with its targets,
        and the photos left to the other terms only without masks (the edge term reads them then:
        :mod:`autoalign.losses.edge`); with masks the photos are this term's alone."""
        if len(scene) != len(self.learned):
            raise ValueError(f"{len(scene)} views, but the region term was learned on {len(self.learned)}")
        return ComparedViews(scene, self.targets, None if self.masks_given else scene.photos)
