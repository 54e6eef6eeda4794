"""Rays cast at meshes (mitsuba, LLVM backend): the product's one ray caster.

:class:`RayCaster` casts at one mesh: hits, depths, and hit counts at many poses. Its mitsuba
scene holds the mesh once, in its model frame; rays are moved into the model frame of a pose
instead of re-building the BVH for each pose. Rays through pixels are formed inside the
ray-casting kernel from per-view tables (double precision, then rounded to the caster's single
precision), never as numpy arrays.

Besides hard hits and depths, :meth:`RayCaster.first_hits` says which triangle each ray hits first
and where on it (barycentric coordinates): the check's colour rendering of several objects.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import invert
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.runtime.backend import drjit, jit_array, mitsuba, numpy_of


class TriangleMesh(Protocol):
    """A triangle mesh in its model frame: vertices (V, 3) in mm and faces (F, 3) vertex indices."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]


@dataclass
class RayHits:
    """The first surface along each of n rays (:meth:`RayCaster.first_hits`).

    ``t``: (n,) float32, the ray parameter of the hit (``origin + t * direction``: a distance in
    units of the direction's length), inf on a miss. ``prim``: (n,) int64, the hit triangle (row of
    the mesh's faces), 0 on a miss. ``bary``: (n, 2) float32, the barycentric weights ``(b1, b2)``
    of the triangle's vertices 1 and 2 at the hit (vertex 0 weighs ``1 - b1 - b2``), 0 on a miss.
    """

    t: NDArray[np.float32]
    prim: NDArray[np.int64]
    bary: NDArray[np.float32]


def _mitsuba_mesh(name: str, vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> Any:
    """A mitsuba ``Mesh`` of ``vertices`` (V, 3; rounded to single precision) and ``faces`` (F, 3)."""
    mi = mitsuba()
    m = mi.Mesh(name, vertex_count=len(vertices), face_count=len(faces), has_vertex_normals=False,
                has_vertex_texcoords=False)
    params = mi.traverse(m)
    params["vertex_positions"] = jit_array(mi.Float, np.asarray(vertices).ravel(), np.float32)
    params["faces"] = jit_array(mi.UInt32, np.asarray(faces).ravel(), np.uint32)
    params.update()
    return m


class RayCaster:
    """Casts rays at ``mesh`` (model frame, mm) placed by world-from-model poses ``T_wm``."""

    def __init__(self, mesh: Mesh | TriangleMesh, watertight: bool = False) -> None:
        """Builds the mesh's BVH (mitsuba's Embree, high quality: about 3 us a triangle).
        ``watertight``: Embree's robust intersections, where no ray slips between two triangles
        that share an edge (without: on LM-O's scanned meshes about one ray in 10^5 that hits sees
        the surface behind instead)."""
        mi = mitsuba()
        self._mi = mi
        self._dr = drjit()
        m = _mitsuba_mesh(getattr(mesh, "name", "mesh"), mesh.vertices, mesh.faces)
        self._scene = mi.load_dict({"type": "scene", "object": m, "embree_use_robust_intersections": watertight})

    def pixel_hits(self, T_wm: NDArray[np.float64], cams: CameraBatch, view: NDArray[np.int64],
                   uv: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Hard hits of the rays through continuous pixel coordinates ``uv`` (N, 2; internal
        convention, pixel centres at +0.5) of views ``view`` (N,)."""
        if len(view) == 0:
            return np.zeros(0, dtype=bool)
        return numpy_of(self._scene.ray_test(self._pixel_rays(T_wm, cams, view, uv)), dtype=bool)[0]

    def pixel_depths(self, T_wm: NDArray[np.float64], cams: CameraBatch, view: NDArray[np.int64],
                     uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (mm) from the camera centre to the first surface along the rays through ``uv``
        (N, 2) of views ``view`` (N,); ``inf`` where the ray misses the object."""
        if len(view) == 0:
            return np.zeros(0)
        hits = self._scene.ray_intersect_preliminary(self._pixel_rays(T_wm, cams, view, uv))
        t = numpy_of(hits.t, dtype=np.float64)[0]
        t[~np.isfinite(t)] = np.inf
        return t

    def first_hits(self, T_wm: NDArray[np.float64], origin: NDArray[np.float64],
                   directions: NDArray[np.float32]) -> RayHits:
        """The first hits of the world rays ``origin + t * directions[i]`` (origin (3,), mm;
        directions (n, 3), any length) at the mesh placed by ``T_wm`` (:meth:`first_hits_from`)."""
        return self.first_hits_from(T_wm, [origin], [directions])[0]

    def first_hits_from(self, T_wm: NDArray[np.float64], origins: Sequence[NDArray[np.float64]],
                        directions: Sequence[NDArray[np.float32]]) -> list[RayHits]:
        """:meth:`first_hits` of several bundles of rays (e.g. one per camera: ``origins[k]`` (3,), mm,
        and ``directions[k]`` (n_k, 3)) in one kernel. The rays are moved into the model frame
        (double precision, then single; each bundle as if cast alone): ``t`` is the same in both frames."""
        mi = self._mi
        counts = [len(d) for d in directions]
        if sum(counts) == 0:
            return [RayHits(np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros((0, 2), np.float32))
                    for _ in counts]
        R, p = np.asarray(T_wm, dtype=np.float64)[:3, :3], np.asarray(T_wm, dtype=np.float64)[:3, 3]
        d_m = np.concatenate([np.asarray(d, dtype=np.float64).reshape(-1, 3) @ R for d in directions])  # rows R^T d
        o_m = np.repeat([(R.T @ (np.asarray(o, dtype=np.float64) - p)).astype(np.float32) for o in origins], counts,
                        axis=0)
        ray = mi.Ray3f(mi.Point3f(*(jit_array(mi.Float, o_m[:, i], np.float32) for i in range(3))),
                       mi.Vector3f(*(jit_array(mi.Float, d_m[:, i], np.float32) for i in range(3))))
        pi = self._scene.ray_intersect_preliminary(ray)
        t, uv, face = numpy_of(pi.t, pi.prim_uv, pi.prim_index, dtype=(np.float32, np.float32, np.int64))
        hit = np.isfinite(t)
        t = np.where(hit, t, np.float32(np.inf))
        face = np.where(hit, face, 0)
        uv = np.where(hit[:, None], uv.T, np.float32(0.0))
        ends = np.cumsum(counts)[:-1]
        return [RayHits(*parts) for parts in zip(np.split(t, ends), np.split(face, ends), np.split(uv, ends))]

    def _pixel_rays(self, T_wm: NDArray[np.float64], cams: CameraBatch, view: NDArray[np.int64],
                    uv: NDArray[np.float64]) -> Any:
        """Model-frame unit rays through ``uv`` of views ``view`` (a mitsuba ``Ray3f``)."""
        dr, mi = self._dr, self._mi
        F64 = mi.Float64
        T_mw = invert(T_wm)
        M = np.einsum("ij,njk,nkl->nil", T_mw[:3, :3], cams.R_c2w, cams.K_inv).reshape(-1, 9)  # pixel -> model dir
        C_m = cams.centres @ T_mw[:3, :3].T + T_mw[:3, 3]  # (V, 3) camera centres, model frame
        v = jit_array(mi.UInt32, view, np.uint32)
        u, w = jit_array(F64, uv[:, 0], np.float64), jit_array(F64, uv[:, 1], np.float64)
        m = [dr.gather(F64, jit_array(F64, M[:, j], np.float64), v) for j in range(9)]
        d = [m[3 * i] * u + m[3 * i + 1] * w + m[3 * i + 2] for i in range(3)]
        inv_norm = dr.rsqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        o = [dr.gather(mi.Float, jit_array(mi.Float, C_m[:, i], np.float32), v) for i in range(3)]
        return mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*(mi.Float(x * inv_norm) for x in d)))

    def posed_hit_sums(self, poses: NDArray[np.float64], centres_w: NDArray[np.float64], dirs_w: NDArray[np.float64],
                       ray_view: NDArray[np.int64], weights: NDArray[np.float64],
                       pairs: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None) -> NDArray[np.float64]:
        """Weighted hit counts of world rays cast at many poses of the mesh, per pose and view, in one drjit kernel.

        Args:
            poses: (K, 4, 4) world-from-model poses of the mesh.
            centres_w: (V, 3) camera centres (the rays' origins), world frame, mm.
            dirs_w: (R, 3) ray directions (any length), world frame.
            ray_view: (R,) the view (row of ``centres_w``) each ray starts from.
            weights: (R, C) per-ray weights.
            pairs: ``(pose_index, ray_index)``, (N,) each: cast just these rays at these poses
                (``None``: every ray at every pose).

        Returns:
            (K, C, V): ``sum of weights[r, c]`` over the rays ``r`` of view ``v`` cast at ``poses[k]``
            that hit the mesh. The model-frame rays are formed, cast and reduced inside the kernel,
            never as arrays (sums in double precision: exact for counts and pixel coordinates).
        """
        dr, mi = self._dr, self._mi
        K, V, R, C = len(poses), len(centres_w), len(dirs_w), weights.shape[1]
        if K == 0 or R == 0 or (pairs is not None and len(pairs[0]) == 0):
            return np.zeros((K, C, V))
        Rt = poses[:, :3, :3].transpose(0, 2, 1)  # model from world
        o_m = np.einsum("kij,kvj->kvi", Rt, centres_w[None] - poses[:, None, :3, 3]).reshape(K * V, 3)
        UInt, Float = mi.UInt32, mi.Float
        if pairs is None:
            flat = dr.arange(UInt, K * R)  # k * R + r: ray r cast at pose k
            k = flat // dr.opaque(UInt, R)  # opaque sizes: one compiled kernel for all of them
            r = flat - k * dr.opaque(UInt, R)
        else:
            k, r = jit_array(UInt, pairs[0], np.uint32), jit_array(UInt, pairs[1], np.uint32)
        kv = k * dr.opaque(UInt, V) + dr.gather(UInt, jit_array(UInt, ray_view, np.uint32), r)
        o = [dr.gather(Float, jit_array(Float, o_m[:, i], np.float32), kv) for i in range(3)]
        rot = [dr.gather(Float, jit_array(Float, Rt[:, i, j], np.float32), k) for i in range(3) for j in range(3)]
        d = [dr.gather(Float, jit_array(Float, dirs_w[:, j], np.float32), r) for j in range(3)]
        d_m = [rot[3 * i] * d[0] + rot[3 * i + 1] * d[1] + rot[3 * i + 2] * d[2] for i in range(3)]
        hit = self._scene.ray_test(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d_m)))
        sums = dr.zeros(mi.Float64, K * V * C)
        for c in range(C):
            w = dr.gather(mi.Float64, jit_array(mi.Float64, weights[:, c], np.float64), r)
            dr.scatter_reduce(dr.ReduceOp.Add, sums, w, kv * dr.opaque(UInt, C) + c, active=hit)
        return numpy_of(sums, dtype=np.float64)[0].reshape(K, V, C).transpose(0, 2, 1)
