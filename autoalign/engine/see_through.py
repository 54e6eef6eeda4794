"""Objects the measured depth sees through (glass): their depth neither pulls the pose nor fails it.

A model declared transparent (``materials.json``, :meth:`~autoalign.io.models.ModelSet.material`)
is refined without the depth from the start; one declared opaque is refined with it, once, whatever
the depth looks like (the declaration overrides the recognition: depth that disagrees then flags the
result). Any other is refined with it, except from a given pose whose depth is seen through already
there (behind its surface by the seed's stated position uncertainty more than the rule's margin):
then it is refined without the depth first, and with it only if that result is not seen through.
Refined without its depth, such an object is offered the table plane the depth shows
(:func:`~autoalign.engine.table_in_depth.table_in_depth`): it is held there when the other evidence
puts its lowest point on it (:data:`~autoalign.losses.contact.OFFERED_GAP_MM`), since nothing else
fixes it along the viewing rays.
When a result with the depth is in doubt (the depth contradicts it, or its silhouettes miss the
masks), it is refined again without the depth, and where the depth at that pose sees through the object
(:func:`~autoalign.losses.see_through.see_through_shares`: measured behind its surface or missing
inside its masks) that result is kept, the depth recorded as :class:`~autoalign.losses.see_through.SeeThrough`.
An opaque object whose depth agrees runs once, exactly as before. The engine's
:func:`~autoalign.engine.refine.refine` applies these rules with the parts defined here.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.options import RefineOptions
from autoalign.engine.seeding import Click
from autoalign.engine.table_in_depth import table_in_depth
from autoalign.errors import AutoalignError
from autoalign.io.bop import Scene
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.depth import DepthTerms
from autoalign.losses.see_through import SeeThrough, see_through_shares
from autoalign.losses.term import Stance
from autoalign.rasterizers.pyramid import MeshPyramid

LOOSE_IOU = 0.5
"""A result whose median IoU with the masks is below this is in doubt: the verdict's own line for
silhouettes that do not match the masks (:data:`~autoalign.quality.verdict.FAILED_IOU`, a layer above)."""

def measured_see_through(views: ComparedViews, pyramid: MeshPyramid, T_wm: NDArray[np.float64],
                         opts: RefineOptions, declared: bool = False, slack_mm: float = 0.0) -> SeeThrough:
    """The share of the object's depth samples inside its targets (none showing it: its silhouettes at
    ``T_wm``) that lie behind its surface (by more than the occluder margin and ``slack_mm``) or are
    missing, per one of ``views`` (with depth)."""
    assert views.depths is not None and opts.depth is not None
    rast = pyramid.fine(opts.detail)
    masks = views.targets if views.has_targets else rast.hard_masks(T_wm, views.cameras)
    noise = replace(opts.depth, occluder_mm=opts.depth.occluder_mm + slack_mm)
    return SeeThrough(see_through_shares(rast.caster, pyramid.mesh, T_wm, views.cameras, views.depths, masks,
                                         noise), declared)


def offering_table(scene: Scene, opts: RefineOptions) -> RefineOptions:
    """``opts`` for a run without the depth of ``scene``, which sees through the object: the table
    plane that depth shows offered (module doc), unless a resting plane is declared, the offer is
    off, or the depth shows too little of a plane to fit."""
    if opts.resting is not None or not opts.offer_table:
        return opts
    try:
        return replace(opts, table_offered=table_in_depth(scene))
    except AutoalignError:  # too few depth samples for a plane: nothing to offer
        return opts


def seen_through_at_seed(scene: Scene, pyramid: MeshPyramid, seed: NDArray[np.float64] | Click | None,
                         opts: RefineOptions) -> bool:
    """Whether the depth of ``scene`` sees through an object not declared opaque already at a given
    pose ``seed``, beyond how far the seed may be off (``opts.seed_radius``'s millimetres): an opaque
    object's seed nearer the camera than its surface is not mistaken for it."""
    return pyramid.material != "opaque" and isinstance(seed, np.ndarray) and opts.seed_radius is not None and \
        measured_see_through(ComparedViews.of(scene), pyramid, seed, opts, slack_mm=opts.seed_radius[0]).sees_through()


def in_doubt(result: Any) -> bool:
    """Whether a result (:class:`~autoalign.engine.refine.RefineResult`) refined with the depth is
    worth trying without it: the depth contradicts it, or its silhouettes miss the masks (a seed's
    hold let go is not enough: the depth of an opaque object pulls a wrong seed's result away too)."""
    depth = result.measurement(DepthTerms)
    evidence = depth.evidence() if depth is not None else None
    contradicts = evidence is not None and evidence.stance is Stance.CONTRADICTS and evidence.fails
    return contradicts or float(np.median(result.iou_after)) < LOOSE_IOU
