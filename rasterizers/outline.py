"""The visible outline of a mesh in many views: contour edges split into sub-pixel segments.

Contour edges are the mesh edges whose two faces point to opposite sides of the camera, plus
open boundary edges. Each is projected, split into segments of about ``segment_px`` pixels, and
a segment is kept when two rays just either side of it disagree (one hits, one misses): that is
the outline a viewer sees, without the contour parts the mesh itself hides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import invert, transform_points
from autoalign.rasterizers.camera_batch import CameraBatch, per_view_matvec
from autoalign.rasterizers.ray_casting import RayCaster

NEAR_MM = 1.0
"""Points closer than this to a camera plane are not projected."""
_SIDE_PX = 0.3  # how far either side of a segment its two test rays pass


@dataclass
class Outline:
    """The outline segments of all views (S of them), in image pixels (internal convention).

    Attributes:
        view: (S,) view of each segment.
        edge: (S,) its mesh edge (row of ``Mesh.edges``).
        mid: (S, 2) its midpoint.
        t0, t1: (S,) the visible interval of its edge, as fractions from the edge's first end
            (from the first to the last outline segment of that edge in that view).
        a, b: (S, 2) the end points of that interval: distances are taken to the whole interval,
            so the nearest outline point moves continuously while the pose changes.
    """

    view: NDArray[np.int64]
    edge: NDArray[np.int64]
    mid: NDArray[np.float64]
    t0: NDArray[np.float64]
    t1: NDArray[np.float64]
    a: NDArray[np.float64]
    b: NDArray[np.float64]

    @staticmethod
    def empty() -> "Outline":
        return Outline(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0),
                       np.zeros((0, 2)), np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.view)

    def per_view(self, n_views: int) -> NDArray[np.int64]:
        """(n_views,) segments found per view."""
        return np.bincount(self.view, minlength=n_views).astype(np.int64)


class OutlineFinder:
    """Finds the visible outline of ``mesh`` (model frame, mm), using ``caster`` for the side rays.

    Args:
        segment_px: length of the segments contour edges are split into, pixels.
    """

    def __init__(self, mesh: Mesh, caster: RayCaster, segment_px: float = 0.75) -> None:
        self.mesh = mesh
        self.caster = caster
        self.segment_px = float(segment_px)
        # per-face constants of the facing test n.(c - v0) > 0  <=>  n.c > n.v0
        self._n = mesh.face_normals
        self._nv0 = np.einsum("ij,ij->i", mesh.face_normals, mesh.vertices[mesh.faces[:, 0]])
        ef = mesh.edge_faces
        self._interior = ef[:, 1] >= 0
        self._ef0, self._ef1 = ef[:, 0], np.where(ef[:, 1] >= 0, ef[:, 1], ef[:, 0])

    def contour_matrix(self, T_wm: NDArray[np.float64], cams: CameraBatch) -> NDArray[np.bool_]:
        """(E, N) whether edge e is a contour-generator edge in view n."""
        T_mw = invert(T_wm)
        C_m = cams.centres @ T_mw[:3, :3].T + T_mw[:3, 3]  # (N, 3) camera centres, model frame
        facing = (self._n @ C_m.T) > self._nv0[:, None]  # (F, N)
        flip = facing[self._ef0] != facing[self._ef1]  # (E, N)
        flip |= ~self._interior[:, None]
        return flip

    def find(self, T_wm: NDArray[np.float64], cams: CameraBatch, crops: NDArray[np.int64]) -> Outline:
        """The outline at pose ``T_wm`` in every view whose crop (N, 4: x0, y0, w, h) is not empty."""
        flip = self.contour_matrix(T_wm, cams)  # (E, N)
        flip[:, crops[:, 2] * crops[:, 3] == 0] = False
        view, edge = np.nonzero(flip.T)  # grouped by view
        if len(edge) == 0:
            return Outline.empty()
        is_used = np.zeros(len(self.mesh.vertices), dtype=bool)
        is_used[self.mesh.edges[edge]] = True
        used = np.flatnonzero(is_used)  # the contour edges' vertices, sorted, unique
        V_w = np.zeros_like(self.mesh.vertices)
        V_w[used] = transform_points(T_wm, self.mesh.vertices[used])
        ends = self.mesh.edges[edge]
        t = cams.t_w2c[view]
        Xa = per_view_matvec(cams.R_w2c, view, V_w[ends[:, 0]]) + t
        Xb = per_view_matvec(cams.R_w2c, view, V_w[ends[:, 1]]) + t
        ok = (Xa[:, 2] > NEAR_MM) & (Xb[:, 2] > NEAR_MM)
        view, edge, Xa, Xb = view[ok], edge[ok], Xa[ok], Xb[ok]
        ua, ub = per_view_matvec(cams.K, view, Xa), per_view_matvec(cams.K, view, Xb)
        A, B = ua[:, :2] / ua[:, 2:3], ub[:, :2] / ub[:, 2:3]
        d = B - A
        L = np.linalg.norm(d, axis=1)
        good = L > 1e-9
        view, edge, A, d, L = view[good], edge[good], A[good], d[good], L[good]
        n_sub = np.maximum(1, np.ceil(L / self.segment_px).astype(np.int64))
        rep = np.repeat(np.arange(len(L)), n_sub)
        k = np.arange(len(rep)) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)
        t = (k + 0.5) / n_sub[rep]
        mid = A[rep] + t[:, None] * d[rep]
        nrm = np.column_stack([-d[:, 1], d[:, 0]]) / L[:, None]
        side = _SIDE_PX * nrm[rep]
        n = len(rep)
        uv = np.empty((2 * n, 2))  # the test points either side: mid + side, then mid - side
        np.add(mid, side, out=uv[:n])
        np.subtract(mid, side, out=uv[n:])
        sv = view[rep]
        hits = self.caster.pixel_hits(T_wm, cams, np.concatenate([sv, sv]), uv)
        pair = np.flatnonzero(hits[:n] != hits[n:])
        owner = rep[pair]  # non-decreasing, and k[pair] increasing within each owner
        # An edge's visible interval runs from its first outline segment to its last: its pairs
        # are consecutive here, and k / n_sub grows with k.
        bounds = np.append(np.flatnonzero(np.diff(owner, prepend=-1)), len(owner))
        first, last, count = bounds[:-1], bounds[1:] - 1, np.diff(bounds)
        t0 = np.repeat(k[pair[first]] / n_sub[owner[first]], count)
        t1 = np.repeat((k[pair[last]] + 1.0) / n_sub[owner[last]], count)
        A_o, d_o = A[owner], d[owner]
        a, b = A_o + t0[:, None] * d_o, A_o + t1[:, None] * d_o
        return Outline(sv[pair], edge[owner], mid[pair], t0, t1, a, b)
