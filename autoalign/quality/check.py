"""Ground-truth-free quality check of 6-DoF pose labels: the "feature distance" of ProgressLabeller.

For every image and every labelled instance the object's vertex-coloured mesh is rendered at the
label's pose (on black, occluded by the other labelled instances of the image), SIFT keypoints
are detected in the rendering and in the photo, matched (brute force, Lowe's ratio test 0.8), and
the matches whose keypoints lie within ``MAX_MATCH_PX`` (10 px) of each other are kept. The mean
image distance of the kept matches is the feature distance: a label that puts the object where
the photo shows it gives a small one (ProgressLabeller reports 1.95 px for its labels against
2.28 px for the dataset's own on HOPE). Objects without texture give few matches and are flagged
``too_few_matches`` instead of getting a number. Transparent and reflective objects
(``materials.json``, :data:`~autoalign.io.models.FEATURELESS`) are not matched at all: the features
the photo shows on them are their surroundings', refracted or mirrored, and would match by chance a
few px away. With the scene's depth, an object whose depth is seen through at its labels (glass:
most of its samples missing or behind its rendered surface, :mod:`autoalign.losses.see_through`'s
rule) is recognised as transparent and its feature distance is not reported either, unless
``materials.json`` declares it. Every view also gets the outline-to-edge distance
(:mod:`autoalign.quality.edge_distance`), which needs no texture.

Large photos: a photo of more than :data:`autoalign.io.bop.MAX_IMAGE_PIXELS` is read downscaled by the
same whole factor as ``autoalign refine`` reads its masks (area-averaged over whole blocks, its
masks and ``cam_K`` with it, so the pixel grid stays exact), and SIFT and the edge maps see only the
region around the labels' renderings, SIFT at most :data:`~autoalign.quality.sift.MAX_SIFT_PIXELS`:
24 views of 12-megapixel photos are checked in well under 2 GB (README, "Large images"). Every distance, coordinate and px
parameter is then in the pixels of the photo as checked (``image_scale`` times the file's); a
photo the size of LM-O's (640 x 480) is checked whole and at full size, as before.

Conventions (as the BOP files):

* millimetres; OpenCV camera frame (x right, y down, z forward);
* ``scene_camera.json``: per image ``cam_K`` (9, px), ``cam_R_w2c`` (9, row-major), ``cam_t_w2c``
  (3, mm) with ``x_cam = R_w2c x_world + t_w2c`` (only ``cam_K`` is needed here);
* labels (a BOP ``scene_gt.json``): per image id a list of ``{"obj_id", "cam_R_m2c", "cam_t_m2c"}``,
  the model-to-camera pose ``x_cam = R_m2c x_model + t_m2c``; entry ``k`` of an image's list is
  instance ``k``, whose visible mask (optional) is ``mask_visib/{im_id:06d}_{k:06d}.png``;
* pixels: ``cam_K`` in the OpenCV / BOP convention, the centre of pixel (row i, col j) is at
  continuous coordinate ``(u, v) = (j, i)``; the ray of pixel (i, j) goes through ``K^-1 [j, i, 1]``.
  Keypoint positions (OpenCV) use the same convention.

The check is split by job: the photos read at a scale (:mod:`~autoalign.io.photos`), the labels'
rendering (:mod:`~autoalign.rasterizers.label_rendering`), SIFT (:mod:`~autoalign.quality.sift`), the
bootstrap intervals (:mod:`~autoalign.quality.stats`), the records (:mod:`~autoalign.quality.check_report`),
the scene's inputs and loop (:mod:`~autoalign.quality.scene_check`) and the figure
(:mod:`~autoalign.quality.figures`); this module checks one image and summarises the instances.

Nothing here imports torch or jax.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.io.bop import Label
from autoalign.io.models import FEATURELESS
from autoalign.losses.see_through import SEES_THROUGH, through_share
from autoalign.geometry.mesh import ColouredMesh
from autoalign.quality.check_report import (
    BBOX_MARGIN_PX,
    CONTEXT_PX,
    MIN_MATCHES,
    SILHOUETTE_MARGIN_PX,
    InstanceSummary,
    ViewInstanceCheck,
)
from autoalign.quality.edge_distance import (
    MIN_OUTLINE_PX,
    PhotoEdges,
    outline_edge_distances,
    outline_pixels,
    photo_edges,
)
from autoalign.rasterizers.label_rendering import PlacedMesh, Rendering, render_labels
from autoalign.losses.overlap import iou_from_counts
from autoalign.quality.sift import (
    MAX_SIFT_PIXELS,
    UPSAMPLE,
    Features,
    at_pixels,
    in_box,
    match_features,
    sift_features,
    sift_scale,
)
from autoalign.quality.stats import bootstrap_mean_ci, pooled_mean_ci


def check_image(image_id: int, photo_bgr: NDArray[np.uint8], K: NDArray[np.float64], labels: Sequence[Label],
                meshes: Mapping[int, ColouredMesh], masks: Mapping[int, NDArray[np.bool_]] | None = None,
                seed: int = 0, photo_features: Features | None = None, edges: PhotoEdges | None = None,
                featureless: Collection[int] = (), depth_mm: NDArray[np.floating] | None = None
                ) -> tuple[Rendering, list[ViewInstanceCheck]]:
    """Check every label of one image against its photo (BGR, OpenCV ``cam_K`` in px, poses in mm).

    ``masks``: instance -> visible mask (H, W) bool, for the IoU (instances without one get None).
    ``photo_features``: the photo's :func:`sift_features` (photo pixels), when already computed
    (several label sets checked against one photo); ``edges``: its
    :func:`autoalign.quality.edge_distance.photo_edges`, likewise (covering the labels' outlines). A photo
    of 640 x 480 or less is searched whole; a larger one only in the box of the labels' rendered
    pixels dilated by ``CONTEXT_PX`` (:func:`sift_scale` sets SIFT's resolution there). The objects
    of ``featureless`` (obj_ids: transparent, reflective) get no matches. ``depth_mm``: the image's
    measured depth (mm, 0 = none; the photo's size), for the share of each label's visible pixels
    (inside its mask, where it has one) whose depth is seen through. Returns the rendering of all
    labels together and one :class:`ViewInstanceCheck` per label.
    """
    H, W = photo_bgr.shape[:2]
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    objects = [PlacedMesh(lab.instance, meshes[lab.obj_id], lab.R_m2c, lab.t_m2c) for lab in labels]
    rendering = render_labels(objects, K, W, H)
    region = _search_region(rendering.instance)
    u0, v0, u1, v1 = region if region is not None else (0, 0, 0, 0)
    inst_map = rendering.instance[v0:v1, u0:u1]  # the labels' pixels all lie in the region
    render_feats = photo_feats = Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    if region is not None:
        scale = sift_scale(u1 - u0, v1 - v0)
        crop = np.ascontiguousarray(rendering.rgb[v0:v1, u0:u1])
        render_feats = sift_features(cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY), scale).moved(u0, v0)
        if photo_features is None:
            crop = np.ascontiguousarray(photo_bgr[v0:v1, u0:u1])
            photo_feats = sift_features(cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY), scale).moved(u0, v0)
        if edges is None:
            edges = photo_edges(photo_bgr[v0:v1, u0:u1], (v0, u0))
        del crop
    if photo_features is not None:
        photo_feats = photo_features
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SILHOUETTE_MARGIN_PX + 1,) * 2)
    out = []
    for lab in labels:
        sil = inst_map == lab.instance
        visible = int(np.count_nonzero(sil))
        iou = None
        if masks is not None and lab.instance in masks:
            m = np.asarray(masks[lab.instance], dtype=bool)
            area = int(np.count_nonzero(m))
            if area or visible:
                iou = float(iou_from_counts(np.count_nonzero(m[v0:v1, u0:u1] & sil), area, visible))
        check = ViewInstanceCheck(lab.image_id, lab.instance, lab.obj_id, iou, 0, None, visible_px=visible)
        if depth_mm is not None and visible:
            seen = sil if masks is None or lab.instance not in masks else \
                sil & np.asarray(masks[lab.instance], dtype=bool)[v0:v1, u0:u1]
            check.through_share = through_share(depth_mm[v0:v1, u0:u1][seen], rendering.depth[v0:v1, u0:u1][seen])
        if visible:
            rc = outline_pixels(inst_map, lab.instance)  # the region's border is the photo's or off the labels
            check.edge_distances = outline_edge_distances(edges, inst_map, lab.instance, rc, (v0, u0))
            check.outline_rc = rc + [v0, u0]
        if len(check.edge_distances) >= MIN_OUTLINE_PX:
            check.edge_px = float(check.edge_distances.mean())
        if visible and lab.obj_id not in featureless:
            rows, cols = np.flatnonzero(sil.any(axis=1)) + v0, np.flatnonzero(sil.any(axis=0)) + u0
            box = (max(int(cols[0]) - BBOX_MARGIN_PX, 0), max(int(rows[0]) - BBOX_MARGIN_PX, 0),
                   min(int(cols[-1]) + 1 + BBOX_MARGIN_PX, W), min(int(rows[-1]) + 1 + BBOX_MARGIN_PX, H))
            near = cv2.dilate(sil.astype(np.uint8), kernel).astype(bool)
            r = render_feats.subset(in_box(render_feats.uv, box))
            r = r.subset(at_pixels(r.uv - [u0, v0], near))
            p = photo_feats.subset(in_box(photo_feats.uv, box))
            matches = match_features(r, p)
            check.bbox, check.n_render_keypoints, check.n_photo_keypoints = box, len(r.uv), len(p.uv)
            check.matches, check.n_matches = matches, len(matches)
            if len(matches):
                d = check.distances_px
                check.mean_px = float(d.mean())
                check.offset_px = (float((matches[:, 2] - matches[:, 0]).mean()),
                                   float((matches[:, 3] - matches[:, 1]).mean()))
                check.ci95 = bootstrap_mean_ci(d, np.random.default_rng([seed, image_id, lab.instance]))
        out.append(check)
    return rendering, out


def _search_region(instance_map: NDArray[np.int32]) -> tuple[int, int, int, int] | None:
    """The region (u0, v0, u1, v1), end exclusive, of a photo that SIFT and the edge maps see: all of
    a photo of at most 640 x 480 (``MAX_SIFT_PIXELS / UPSAMPLE**2``); of a larger one, the box of the
    labels' rendered pixels dilated by ``CONTEXT_PX``, None when no label is in view."""
    H, W = instance_map.shape
    if W * H * UPSAMPLE ** 2 <= MAX_SIFT_PIXELS:
        return 0, 0, W, H
    seen = instance_map >= 0
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if rows.size == 0:
        return None
    return (max(int(cols[0]) - CONTEXT_PX, 0), max(int(rows[0]) - CONTEXT_PX, 0),
            min(int(cols[-1]) + 1 + CONTEXT_PX, W), min(int(rows[-1]) + 1 + CONTEXT_PX, H))


def summarize(views: Sequence[ViewInstanceCheck], seed: int = 0,
              materials: Mapping[int, str] | None = None) -> list[InstanceSummary]:
    """Per-instance summaries (sorted by instance, then obj_id) of per-view checks; ``materials``:
    the declared ones by obj_id (``materials.json``). An object not declared whose depth is seen
    through in most views that measured it (median share at least
    :data:`~autoalign.losses.see_through.SEES_THROUGH`) is recognised as transparent: its feature
    distance is not reported; any other is opaque."""
    materials = materials or {}
    keys = sorted({(v.instance, v.obj_id) for v in views})
    out = []
    for inst, obj in keys:
        mine = [v for v in views if v.instance == inst and v.obj_id == obj]
        groups = [v.distances_px for v in mine if v.n_matches]
        n = int(sum(v.n_matches for v in mine))
        ious = [v.iou for v in mine if v.iou is not None]
        shares = [v.through_share for v in mine if v.through_share is not None and np.isfinite(v.through_share)]
        recognised = obj not in materials and bool(shares) and float(np.median(shares)) >= SEES_THROUGH
        material = "transparent" if recognised else materials.get(obj, "opaque")
        too_few = n < MIN_MATCHES and material not in FEATURELESS
        mean = ci = offset = None
        if n >= MIN_MATCHES and material not in FEATURELESS:
            allm = np.concatenate([v.matches for v in mine if v.n_matches])
            mean, ci = pooled_mean_ci(groups, np.random.default_rng([seed, 1_000_003, inst, obj]))
            offset = (float((allm[:, 2] - allm[:, 0]).mean()), float((allm[:, 3] - allm[:, 1]).mean()))
        edges = [v.edge_distances for v in mine if v.edge_px is not None]
        edge, edge_ci = pooled_mean_ci(edges, np.random.default_rng([seed, 3_000_017, inst, obj]))
        out.append(InstanceSummary(inst, obj, mean, ci, n, len(mine), float(np.median(ious)) if ious else None,
                                   too_few, len(groups), offset, edge, edge_ci, len(edges), material,
                                   float(np.median(shares)) if shares else None, recognised))
    return out
