"""The photo as evidence for several objects: each instance's region targets with the pixels that
another modelled object, at its pose, covers left out (occlusion-aware colour models and targets).

The alone stage (:func:`~autoalign.scene.refine.refine_instances`) refines each instance on its
photos with the others at their seeds left out (:func:`others_left_out`); the joint stage then
compares every instance with its region term learned at the alone stage's poses (:func:`region_terms`),
the others at theirs left out.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.options import RefineOptions
from autoalign.engine.photo_evidence import PhotoEvidence, region_term_at
from autoalign.io.instances import InstanceScenes
from autoalign.io.models import ModelSet
from autoalign.losses.region import RegionOptions
from autoalign.losses.region_term import RegionTerm
from autoalign.rasterizers.label_rendering import PlacedMesh, cast_labels


def nearest_instance(found: InstanceScenes, models: ModelSet, poses: dict[int, NDArray[np.float64]]
                     ) -> dict[int, NDArray[np.int32]]:
    """Per image id, the position in ``found.instances`` of the posed instance seen at each pixel
    (-1: none), by ray casting every instance of ``poses`` (instance index -> world from model, mm)."""
    out = {}
    pos = {inst.index: k for k, inst in enumerate(found.instances)}
    for im, cam in zip(found.image_ids, found.cameras):
        placed = []
        for index, T in poses.items():
            T_cm = cam.T_cw @ T
            mesh = models.mesh(found.instances[pos[index]].obj_id)
            placed.append(PlacedMesh(pos[index], mesh, T_cm[:3, :3], T_cm[:3, 3]))
        seen = np.full((cam.height, cam.width), -1, np.int32)
        cast = cast_labels(placed, cam.K_opencv, cam.width, cam.height)
        if cast is not None:
            u0, v0, u1, v1 = cast.box
            index = np.where(cast.index >= 0, np.array([p.instance for p in placed])[np.maximum(cast.index, 0)], -1)
            seen[v0:v1, u0:u1] = index.reshape(v1 - v0, u1 - u0)
        out[im] = seen
    return out


def others_left_out(found: InstanceScenes, models: ModelSet, poses: dict[int, NDArray[np.float64]]) -> InstanceScenes:
    """Every instance's scene with the pixels where another instance of ``poses`` is the nearest
    surface added to its ignored ones (:attr:`~autoalign.io.bop.Scene.ignore`)."""
    seen = nearest_instance(found, models, poses)
    scenes = []
    for k, sc in enumerate(found.scenes):
        others = [(seen[im] >= 0) & (seen[im] != k) for im in sc.image_ids]
        ignore = others if sc.ignore is None else [a | b for a, b in zip(sc.ignore, others)]
        scenes.append(replace(sc, ignore=ignore))
    return replace(found, scenes=scenes)


def region_terms(found: InstanceScenes, models: ModelSet, poses: list[NDArray[np.float64]], options: RefineOptions,
                 region: RegionOptions) -> tuple[list[RegionTerm | None], list[PhotoEvidence | None]]:
    """Every instance's region term (``region``, with ``options``' loss and detail) learned at its pose of
    ``poses`` (one per instance, in order) on its views in ``found``, which has the other instances left
    out already (:func:`others_left_out`), and each one's photo evidence there (its colour models'
    separation measured); ``None`` for the instances without photos."""
    terms: list[RegionTerm | None] = []
    evidence: list[PhotoEvidence | None] = []
    for inst, sc, T in zip(found.instances, found.scenes, poses):
        if sc.photos is None:
            terms.append(None)
            evidence.append(None)
            continue
        term = region_term_at(sc, models.pyramid(inst.obj_id), T, options, region, measure=True)
        terms.append(term)
        evidence.append(PhotoEvidence.of(term.learned, 0, term.masks_given))
    return terms, evidence
