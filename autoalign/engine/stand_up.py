"""Standing a pose sunk in the table back up: with no seed, glass whose silhouettes do not tell
its base from its rim can come out upside down, its lowest point inside the table that its own
depth shows through it (:data:`~autoalign.losses.contact.OFFERED_GAP_MM`). Nothing stands inside a
table, so the poses that stand it on each of its stable faces (trimesh's stable poses,
:attr:`~autoalign.geometry.mesh.Mesh.resting_downs`), its centre kept above where it was, are
scored against the masks; the best few are polished with the contact held
(:func:`autoalign.engine.refine._resting`), and the masks decide between them. From a given pose
with the masks withheld (the photos alone place it), the pose is stood on its nearest face the
shortest way (:func:`nearest_standing`): the orientation is the person's."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.hypotheses import score_poses
from autoalign.geometry.se3 import make_pose, rotation_angle_deg, so3_exp
from autoalign.losses.compared_views import ComparedViews
from autoalign.losses.contact import CONTACT_MAX_LEAN_DEG, RestingContact
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

STAND_UP_YAWS_DEG = tuple(range(0, 360, 45))
"""The turns about the table's normal tried on each stable face (degrees): standing a pose up turns
it by up to half a turn, and which way round it then stands (a mug's handle) the masks say."""
STAND_UP_POLISHED = 2
"""How many standings are polished with the contact held: the best of each of the best-scoring faces."""


def standings(T_wm: NDArray[np.float64], term: RestingContact) -> NDArray[np.float64]:
    """``T_wm`` (world from model, mm) stood on each of ``term``'s stable faces, turned about the
    plane's normal by each of :data:`STAND_UP_YAWS_DEG`: the face's downward direction turned onto
    the plane's downward normal the shortest way, the object centre (``term.centre_m``) kept on the
    same line along the normal and the lowest point put on the plane; (K, 4, 4)."""
    from scipy.spatial.transform import Rotation  # only here: scipy.spatial costs ~0.4 s to import

    n = term.plane.normal
    R = T_wm[:3, :3]
    centre_w = R @ term.centre_m + T_wm[:3, 3]
    out = []
    for down_m in term.downs_m:
        onto, _ = Rotation.align_vectors(-n[None], (R @ down_m)[None])
        for yaw in STAND_UP_YAWS_DEG:
            R_new = so3_exp(n * np.radians(yaw)) @ onto.as_matrix() @ R
            T = make_pose(R_new, centre_w - R_new @ term.centre_m)
            T[:3, 3] -= term.gap_mm(T) * n  # the plane's heights are linear: this puts the lowest point on it
            out.append(T)
    return np.array(out).reshape(-1, 4, 4)


def nearest_standing(T_wm: NDArray[np.float64], term: RestingContact) -> NDArray[np.float64] | None:
    """``T_wm`` (world from model, mm) stood on the stable face nearest the plane's downward normal,
    turned the shortest way and not about the normal (of :func:`standings`, the one that turns it
    least: a given orientation kept as far as the table allows), (4, 4); ``None`` without stable faces."""
    cands = standings(T_wm, term)
    if not len(cands):
        return None
    return cands[int(np.argmin([rotation_angle_deg(T[:3, :3], T_wm[:3, :3]) for T in cands]))]


def best_standings(rast: SoftSilhouetteRasterizer, views: ComparedViews, T_wm: NDArray[np.float64],
                   term: RestingContact) -> NDArray[np.float64]:
    """The best standings of ``T_wm`` (:func:`standings`) on :data:`STAND_UP_POLISHED` different
    faces (their downward directions more than
    :data:`~autoalign.losses.contact.CONTACT_MAX_LEAN_DEG` apart), by how well their silhouettes fit
    ``views``' targets (robust hard IoU at 1/4 resolution, each moved across the views to the masks'
    centroids and put back on the plane), best first; (k, 4, 4)."""
    cands = standings(T_wm, term)
    if not len(cands):
        return cands
    scores, moved = score_poses(rast, views, cands, scale=0.25, recentre=True)
    # the best yaw of each of the best distinct faces: two yaws of one face (or of two faces a mesh's
    # facets split from one) would leave the other way up untried where the masks barely tell them apart
    downs = np.repeat(term.downs_m, len(STAND_UP_YAWS_DEG), axis=0)
    same_face = np.cos(np.radians(CONTACT_MAX_LEAN_DEG))
    kept: list[int] = []
    for k in np.argsort(-scores):
        if all(downs[k] @ downs[j] < same_face for j in kept):
            kept.append(int(k))
        if len(kept) == STAND_UP_POLISHED:
            break
    best = moved[kept]
    for T in best:
        T[:3, 3] -= term.gap_mm(T) * term.plane.normal
    return best
