"""The mask term: each view's soft silhouette against its target mask (:data:`~autoalign.losses.LOSSES`)."""

from __future__ import annotations

from autoalign.losses.silhouette import LOSSES, targets_in_crops
from autoalign.losses.term import Fragments, TermValues


class MaskTerm:
    """The silhouettes against the level's targets with one of :data:`~autoalign.losses.LOSSES` (``loss``);
    its soft IoU is what the views' robust weights read."""

    name = "mask"

    def __init__(self, loss: str = "l2") -> None:
        if loss not in LOSSES:
            raise ValueError(f"unknown loss {loss!r}; choose one of {sorted(LOSSES)}")
        self.loss = loss

    def residuals(self, fragments: Fragments) -> TermValues:
        sil = fragments.silhouettes
        return TermValues(self.name, LOSSES[self.loss](sil, targets_in_crops(fragments.views.targets, sil),
                                                       fragments.views.totals))
