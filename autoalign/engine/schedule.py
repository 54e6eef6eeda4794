"""Descending a pose through resolution levels: the step of the engine every stage repeats."""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Evaluation, Level, SilhouetteObjective
from autoalign.engine.options import RefineOptions
from autoalign.engine.solver import StepRule, Trace, solve_pose
from autoalign.io.bop import Scene
from autoalign.losses.region_term import RegionTerm
from autoalign.rasterizers.pyramid import MeshPyramid

Progress = Callable[[str, int, int], None]


def run_schedule(obj: SilhouetteObjective, T: NDArray[np.float64], levels: tuple[Level, ...], rule: StepRule,
                  progress: Progress | None = None, label: str = "refine",
                  give_up: Callable[[int, Evaluation], bool] | None = None) -> tuple[NDArray[np.float64], list[Trace]]:
    """Run ``levels`` in turn from ``T`` with the step ``rule``; ``give_up(iteration, evaluation)``
    returning True ends a level early."""
    traces = []
    total = sum(lv.max_iters for lv in levels)
    done = 0
    for lv in levels:
        base = done

        def cb(it: int, ev: Evaluation, base: int = base) -> bool:
            if progress is not None:
                progress(label, base + it + 1, total)
            return give_up is not None and give_up(it, ev)

        T, tr = solve_pose(obj, T, lv, rule, callback=cb)
        traces.append(tr)
        done += lv.max_iters
        if progress is not None:
            progress(label, done, total)
    return T, traces


def polish(scene: Scene, pyramid: MeshPyramid, T: NDArray[np.float64], levels: tuple[Level, ...],
           options: RefineOptions, progress: Progress | None = None, label: str = "refine",
           region: RegionTerm | None = None) -> tuple[NDArray[np.float64], int, int]:
    """``T`` descended through ``levels`` on the masks of ``scene`` (its depth too), or on the
    ``region`` term's targets learned on its views, and nothing else: no search, no disambiguation,
    no report. Returns the pose, the iterations and the renders."""
    obj = compared_objective(pyramid, scene, options, region)
    T, traces = run_schedule(obj, T, levels, options.optimizer, progress, label)
    return T, sum(tr.iterations for tr in traces), obj.renders


def compared_objective(pyramid: MeshPyramid, scene: Scene, options: RefineOptions,
                       region: RegionTerm | None = None) -> SilhouetteObjective:
    """The objective of ``options`` on the views of ``scene`` whose target shows the object: its
    masks, or the ``region`` term's targets learned on its views (which then takes the mask term's
    place). The others are left out: compared, an empty target would pull the silhouette out of its view."""
    if region is None:
        return SilhouetteObjective(pyramid, scene.without_empty_masks(), options.loss, options.robust, options.detail,
                                   options.depth, options.edges)
    keep = region.covered()
    return SilhouetteObjective(pyramid, scene.subset(keep), options.loss, options.robust, options.detail,
                               options.depth, options.edges, region.subset(keep))
