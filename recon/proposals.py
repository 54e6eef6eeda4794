"""Object instances proposed from a fused RGB-D reconstruction (``autoalign recon --propose``): what
stands on the table, clustered, and its visible mask in every view, with ids that agree across
views, so that a user with depth and meshes needs no segmenter.

The fused surface (:mod:`autoalign.recon.fusion`, world frame with the table at z = 0, z up) above
:data:`ABOVE_TABLE_MM` is clustered with open3d's DBSCAN (:data:`EPS_MM`: the fusion's voxels are
3 mm, so the points of one surface are closer than that; objects a few centimetres apart stay
apart; objects that touch are one cluster). Clusters of fewer than :data:`MIN_POINTS` points
(specks, fusion noise) or wider than :data:`MAX_EXTENT_MM` (a wall, an arm) are dropped. Each
view's mask of proposal ``k`` is where a ray through the pixel centre first hits one of its
triangles (one with a vertex of the cluster and none of another; open3d ray casting of the whole
fused surface, so what another proposal or the table hides is not in it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera

ABOVE_TABLE_MM = 4.0
EPS_MM = 8.0
MIN_POINTS = 300
MAX_EXTENT_MM = 400.0

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Proposal:
    """One proposed instance: its number ``index`` (mask ``..._{index:06d}.png``), the centre and
    size of its fused points' bounding box (world, mm; only what the cameras saw, so its underside
    is missing) and how many points it has."""

    index: int
    centre_mm: NDArray[np.float64]
    size_mm: NDArray[np.float64]
    points: int


def cluster_above_table(mesh: Any) -> tuple[list[Proposal], NDArray[np.int64]]:
    """The proposals among ``mesh``'s vertices (an open3d ``TriangleMesh`` in the table frame, mm)
    and each vertex's proposal index (-1: none), largest cluster first."""
    import open3d as o3d

    V = np.asarray(mesh.vertices, dtype=np.float64)
    above = np.flatnonzero(V[:, 2] > ABOVE_TABLE_MM)
    labels = np.full(len(V), -1, dtype=np.int64)
    if len(above) == 0:
        return [], labels
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(V[above]))
    raw = np.asarray(pcd.cluster_dbscan(eps=EPS_MM, min_points=10))
    found = []
    for c in range(int(raw.max()) + 1 if len(raw) else 0):
        members = above[raw == c]
        lo, hi = V[members].min(0), V[members].max(0)
        if len(members) >= MIN_POINTS and np.all(hi - lo <= MAX_EXTENT_MM):
            found.append((members, (lo + hi) / 2.0, hi - lo))
    found.sort(key=lambda f: -len(f[0]))
    proposals = []
    for k, (members, centre, size) in enumerate(found):
        labels[members] = k
        proposals.append(Proposal(k, centre, size, len(members)))
    return proposals, labels


def proposal_masks(mesh: Any, vertex_labels: NDArray[np.int64], n: int, cameras: dict[int, Camera],
                   progress: Progress | None = None) -> dict[int, list[NDArray[np.bool_]]]:
    """Per image id, the visible mask (H, W) of each of the ``n`` proposals: a pixel is proposal
    ``k``'s where the ray through its centre first hits a triangle with a vertex of ``k``'s and none
    of another's."""
    import open3d as o3d

    F = np.asarray(mesh.triangles, dtype=np.int64)
    tri = vertex_labels[F]
    top = tri.max(1)  # a triangle is k's if one of its vertices is and none is another's: DBSCAN leaves
    tri_label = np.where(((tri == top[:, None]) | (tri < 0)).all(1), top, -1)  # a few noise points on surfaces
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(F.astype(np.uint32)))
    out = {}
    for m, (im, cam) in enumerate(cameras.items()):
        j, i = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        d = cam.pixel_rays(j, i)
        rays = np.column_stack([np.broadcast_to(cam.centre, d.shape), d]).astype(np.float32)
        prim = scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().astype(np.int64)
        hit = prim != scene.INVALID_ID
        label = np.full(len(prim), -1, dtype=np.int64)
        label[hit] = tri_label[prim[hit]]
        label = label.reshape(cam.height, cam.width)
        out[im] = [label == k for k in range(n)]
        if progress is not None:
            progress("proposing instances", m + 1, len(cameras))
    return out
