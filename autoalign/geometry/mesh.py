"""Object meshes: loading with validation, and the edge/face topology the renderer needs.

Models are in millimetres (BOP). Any format trimesh reads works; multi-part scenes are
concatenated, non-watertight meshes are fine (open boundary edges count as contour edges). A mesh
file read before comes from :mod:`autoalign.geometry.mesh_cache`, with its simplified levels; trimesh
is imported only to read or process one that is not there.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry import mesh_cache
from autoalign.runtime.interrupts import Interrupts

if TYPE_CHECKING:
    import trimesh

_DECIMATING = threading.Lock()
"""One decimation at a time: fast_simplification keeps the mesh it works on in global state and lets go
of the GIL, so two at once (instances refined side by side) came back with each other's meshes."""
LEVEL_EXTENT = 0.05
"""How far (a share of the diameter) a simplified level's box may lie from the mesh's (:meth:`Mesh.simplified`)."""
_CACHED = ("vertices", "faces", "face_normals", "edges", "edge_faces", "hull")
"""What a cache entry of a mesh holds; the mesh as loaded also its :data:`_CACHED_LOADED`."""
ROUND_MOMENTS = 0.1
"""A surface is nearly round about an axis when its two other second moments differ by at most this
share: YCB-Video's tuna and soup cans 0.004 and 0.014, a flashlight 0.061; a spray bottle 0.15."""
_CACHED_LOADED = ("diameter", "principal_axes")
SURFACE_PARTS = 12
"""The pieces :attr:`Mesh.parts` splits a surface into: a handle, a spout or a ladle's bowl is one or
two of them."""


def trimesh_module() -> ModuleType:
    """trimesh, imported on first use with Ctrl-C deferred (an extension module's import must not be
    cut in two): a mesh read from the cache needs none of it."""
    with Interrupts.deferred():
        import trimesh
    return trimesh


@dataclass
class Mesh:
    """A triangle mesh in the model frame (mm) with the adjacency used for contour extraction.

    Attributes:
        vertices: (V, 3) float64, mm.
        faces: (F, 3) int64 vertex indices.
        edges: (E, 2) unique undirected edges.
        edge_faces: (E, 2) indices of the faces on either side; second ``-1`` for an open boundary
            or non-manifold edge.
        centre: (3,) centre of the axis-aligned bounding box, mm (the BOP model origin convention).
        diameter: largest distance between two vertices, mm.
        name: file stem or a given label.
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    name: str = "mesh"
    edges: NDArray[np.int64] = field(init=False)
    edge_faces: NDArray[np.int64] = field(init=False)
    face_normals: NDArray[np.float64] = field(init=False)
    centre: NDArray[np.float64] = field(init=False)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self.face_normals = np.asarray(self.trimesh.face_normals, dtype=np.float64)
        self.edges, self.edge_faces = _edge_faces(self.faces)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.centre = (lo + hi) / 2.0
        self._cache_key: str | None = None

    @classmethod
    def _restored(cls, arrays: dict[str, NDArray], name: str, key: str | None) -> "Mesh":
        """The mesh of a cache entry (:mod:`~autoalign.geometry.mesh_cache`), as :meth:`__post_init__` and
        its properties made it; ``key``: the entry's, for the simplified levels (``None`` for a level)."""
        m = cls.__new__(cls)
        m.vertices, m.faces, m.name = arrays["vertices"], arrays["faces"], name
        m.face_normals, m.edges, m.edge_faces = arrays["face_normals"], arrays["edges"], arrays["edge_faces"]
        lo, hi = m.vertices.min(0), m.vertices.max(0)
        m.centre = (lo + hi) / 2.0
        m.__dict__["hull"] = arrays["hull"]
        if "diameter" in arrays:
            m.__dict__["diameter"] = float(arrays["diameter"])
            m.__dict__["principal_axes"] = arrays["principal_axes"]
        m._cache_key = key
        return m

    def _cache_arrays(self, loaded: bool) -> dict[str, NDArray]:
        """What a cache entry of this mesh holds (``loaded``: the mesh as loaded, with its diameter and axes)."""
        arrays = {n: np.asarray(getattr(self, n)) for n in _CACHED}
        if loaded:
            arrays.update(diameter=np.float64(self.diameter), principal_axes=self.principal_axes)
        return arrays

    @functools.cached_property
    def diameter(self) -> float:
        """Largest distance between two vertices, mm (computed on first use)."""
        return _diameter(self.vertices)

    @functools.cached_property
    def hull(self) -> NDArray[np.float64]:
        """(H, 3) vertices of the convex hull (model frame, mm), for projected bounds and crops."""
        hull = self.trimesh.convex_hull.vertices if len(self.vertices) > 4 else self.vertices
        return np.asarray(hull, dtype=np.float64)

    @functools.cached_property
    def resting_downs(self) -> NDArray[np.float64]:
        """(K, 3) unit directions (model frame) that point down, onto a table, in the poses the
        object can rest in: trimesh's stable poses (faces of the convex hull over which the centre
        of mass lies: the mesh's own when it is watertight, else its hull's), most probable first;
        none for a flat mesh. Computed on first use."""
        tm = self.trimesh
        with np.errstate(invalid="ignore", divide="ignore"):  # a flat hull's centre of mass divides by 0
            hull = tm.convex_hull
            volume = float(hull.volume)
        if not volume > 1e-9 * self.diameter ** 3:  # flat: no face to rest on (trimesh would not return)
            return np.zeros((0, 3))
        centre_of_mass = tm.center_mass if tm.is_watertight else hull.center_mass
        transforms, _ = trimesh_module().poses.compute_stable_poses(tm, center_mass=centre_of_mass)
        return np.array([-np.asarray(T)[2, :3] for T in transforms], dtype=np.float64).reshape(-1, 3)

    @functools.cached_property
    def principal_axes(self) -> NDArray[np.float64]:
        """(3, 3) rows: unit principal axes of the surface (second moments of surface samples
        about ``centre``), major first; model frame."""
        d = self.sample_points(2000) - self.centre
        return np.linalg.eigh(d.T @ d)[1][:, ::-1].T.copy()

    @functools.cached_property
    def round_axes(self) -> NDArray[np.float64]:
        """(K, 3) rows: the unit axes (model frame) about which the surface is nearly round, the only
        ones a turn of a few degrees can leave looking alike: principal axes of its second moments
        about ``centre``, exact over the triangles (a triangle's is area / 12 (the sum of v v^T over
        its corners plus s s^T, s their sum)), whose other two moments lie within
        :data:`ROUND_MOMENTS` of each other. An axis of symmetry is exactly one of them, where
        :attr:`principal_axes` (2,000 samples, what the search turns about) put a can's 1.8 deg off."""
        V = self.vertices[self.faces] - self.centre  # (F, 3 corners, 3)
        area = 0.5 * np.linalg.norm(np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0]), axis=1)
        s = V.sum(axis=1)
        values, axes = np.linalg.eigh(np.einsum("f,fki,fkj->ij", area, V, V) + np.einsum("f,fi,fj->ij", area, s, s))
        others = [np.delete(values, i) for i in range(3)]
        round_ = [abs(o[1] - o[0]) <= ROUND_MOMENTS * max(abs(o[1]), 1e-12) for o in others]
        return axes.T[np.array(round_, dtype=bool)].reshape(-1, 3).copy()

    @functools.cached_property
    def parts(self) -> NDArray[np.int64]:
        """(F,) each face's piece of the surface, ``0 .. SURFACE_PARTS - 1``: the face centres are
        split about :data:`SURFACE_PARTS` of them picked farthest first (the first the farthest
        from their mean), each face to the nearest, so that the pieces are compact and cover the
        whole object. What the measured depth says is read piece by piece (:mod:`autoalign.losses.depth`)."""
        c = self.vertices[self.faces].mean(axis=1)
        k = min(SURFACE_PARTS, len(c))
        picked = [int(np.argmax(np.sum((c - c.mean(axis=0)) ** 2, axis=1)))]
        d2 = np.sum((c - c[picked[0]]) ** 2, axis=1)
        for _ in range(k - 1):
            picked.append(int(np.argmax(d2)))
            d2 = np.minimum(d2, np.sum((c - c[picked[-1]]) ** 2, axis=1))
        seeds = c[picked]
        return np.argmin(np.sum(seeds ** 2, axis=1) - 2.0 * c @ seeds.T, axis=1).astype(np.int64)  # |c - s|^2 - |c|^2

    @property
    def trimesh(self) -> "trimesh.Trimesh":
        """A trimesh view of the same geometry (no processing)."""
        return trimesh_module().Trimesh(self.vertices, self.faces, process=False)

    def simplified(self, max_faces: int) -> "Mesh":
        """This mesh with at most about ``max_faces`` triangles (quadric decimation), same frame and centre.

        Used for the coarse, low-resolution levels, where a pixel spans millimetres; returns
        ``self`` when the mesh is already small enough. Each size is computed once per mesh.
        """
        if len(self.faces) <= max_faces:
            return self
        cache = self.__dict__.setdefault("_simplified", {})
        if max_faces not in cache:
            key = getattr(self, "_cache_key", None)
            level = None if key is None else mesh_cache.level_key(key, max_faces)
            stored = None if level is None else mesh_cache.read_entry(level, _CACHED)
            if stored is not None and not self._same_extent(stored["vertices"]):
                stored = None  # another mesh's level (made before the decimation was serialised): made again
            if stored is not None:
                out = Mesh._restored(stored, self.name, None)
            else:
                vertices, faces = self._decimated(max_faces)
                if not self._same_extent(vertices):  # a decimation gone wrong: render the mesh as it is
                    cache[max_faces] = self
                    return self
                out = Mesh(vertices, faces)
            out.name = f"{self.name}@{len(out.faces)}"
            out.centre = self.centre.copy()  # twists turn about the same point at every level
            out.diameter, out.principal_axes = self.diameter, self.principal_axes
            if stored is None and level is not None:
                mesh_cache.write_entry(level, out._cache_arrays(loaded=False))
            cache[max_faces] = out
        return cache[max_faces]

    def _same_extent(self, vertices: NDArray[np.float64]) -> bool:
        """Whether ``vertices`` (a simplified level's) span this mesh's box to within
        :data:`LEVEL_EXTENT` of its diameter (a right decimation of the LM-O, YCB-Video and T-LESS
        models moved it by at most 0.35%; another object's level by 10% and more)."""
        v = np.asarray(vertices, dtype=np.float64)
        if len(v) == 0:
            return False
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        moved = max(float(np.abs(v.min(0) - lo).max()), float(np.abs(v.max(0) - hi).max()))
        return moved <= LEVEL_EXTENT * self.diameter

    def _decimated(self, max_faces: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The vertices and faces of this mesh decimated to at most about ``max_faces`` triangles."""
        with _DECIMATING:
            tm = self.trimesh.simplify_quadric_decimation(face_count=int(max_faces))
        # the decimator leaves collapsed triangles behind as duplicates: drop them and unused vertices
        tm.update_faces(tm.unique_faces() & tm.nondegenerate_faces())
        tm.remove_unreferenced_vertices()
        return np.asarray(tm.vertices), np.asarray(tm.faces)

    def sample_points(self, n: int, seed: int = 0) -> NDArray[np.float64]:
        """``n`` points sampled uniformly on the surface (mm, model frame), reproducibly."""
        pts, _ = trimesh_module().sample.sample_surface(self.trimesh, n, seed=seed)
        return np.asarray(pts, dtype=np.float64)


@dataclass
class ColouredMesh:
    """A triangle mesh in its model frame (mm) with one RGB colour (0..1) per vertex, as its file
    gives them (for rendering labels against photos; :class:`Mesh` is the welded one for refining)."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    colours: NDArray[np.float32]
    has_colours: bool
    path: Path | None = None


def _diameter(V: NDArray[np.float64], max_points: int = 2500) -> float:
    """Largest vertex-to-vertex distance (exact on up to ``max_points`` convex-hull vertices)."""
    try:
        pts = np.asarray(trimesh_module().convex.convex_hull(V).vertices)
    except Exception:  # degenerate (flat) point sets have no 3-D hull
        pts = V
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    return float(max(np.linalg.norm(pts - p, axis=1).max() for p in pts))


def _edge_faces(faces: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unique edges and the two faces beside each.

    The second face is ``-1`` for an open boundary edge *and* for a non-manifold edge (three or
    more faces): the renderer then treats the edge as a possible contour in every view and lets
    its ray test decide, instead of trusting an arbitrary pair of its faces.
    """
    F = len(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fid = np.tile(np.arange(F), 3)
    e_sorted = np.sort(e, axis=1)
    uniq, inv = np.unique(e_sorted, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    inv_s, fid_s = inv[order], fid[order]
    first = np.r_[True, inv_s[1:] != inv_s[:-1]]
    starts = np.flatnonzero(first)
    counts = np.diff(np.r_[starts, len(inv_s)])
    ef = np.full((len(uniq), 2), -1, dtype=np.int64)
    ef[inv_s[starts], 0] = fid_s[starts]
    two = counts == 2
    ef[inv_s[starts[two]], 1] = fid_s[starts[two] + 1]
    return uniq.astype(np.int64), ef


UNITS_MM = {"mm": 1.0, "m": 1000.0}
"""Millimetres per unit of a mesh file, for ``--units``."""
METRES_SUSPECT = 2.0
"""A mesh less than this many units across is taken for metres unless its units are given."""


def weld(tm: "trimesh.Trimesh") -> "trimesh.Trimesh":
    """``tm`` with vertices at the same position merged (in place) and the faces that this makes
    duplicate (the same three vertices, either winding) or degenerate dropped.

    Positions only: texture seams and split normals must not keep a surface apart, or every seam
    edge would be an open boundary, a contour candidate in every view.
    """
    tm.merge_vertices(merge_tex=True, merge_norm=True)
    tm.update_faces(tm.unique_faces() & tm.nondegenerate_faces())
    tm.remove_unreferenced_vertices()
    return tm


def load_mesh(path: str | Path, name: str | None = None, units: str | None = None) -> Mesh:
    """Read a mesh file with trimesh and return it in millimetres; raise :class:`AutoalignError`
    naming the file on failure.

    ``units``: ``"mm"`` or ``"m"`` (scaled by 1000); ``None`` means millimetres, but a mesh under
    :data:`METRES_SUSPECT` units across is then refused as probably metres (pass the units to
    go on). Duplicate vertices are merged (an STL file stores each triangle's corners apart) and
    the faces they make duplicate or degenerate are dropped, so every format gives the same mesh.
    """
    path = Path(path)
    if path.is_dir():
        raise AutoalignError(f"{path}: is a folder, not a mesh file; pass the mesh file itself to --model")
    if not path.is_file():
        raise AutoalignError(f"{path}: mesh file not found; pass an existing file to --model")
    if units is not None and units not in UNITS_MM:
        raise AutoalignError(f"{path}: unknown units {units!r}; use one of {', '.join(UNITS_MM)}")
    try:
        key = mesh_cache.file_key(path, units)
    except OSError as exc:
        raise AutoalignError(f"{path}: cannot read the mesh ({exc.strerror}); pass a mesh file you can read") from None
    stored = mesh_cache.read_entry(key, _CACHED + _CACHED_LOADED)
    if stored is not None:
        return Mesh._restored(stored, name or path.stem, key)
    mesh = Mesh(*_read_welded(path, units), name=name or path.stem)
    try:
        arrays = mesh._cache_arrays(loaded=True)
    except (ValueError, IndexError, RuntimeError):  # no hull or axes (a flat mesh): computed again when asked
        return mesh
    mesh_cache.write_entry(key, arrays)
    mesh._cache_key = key
    return mesh


def _read_welded(path: Path, units: str | None) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The vertices (mm) and faces of the mesh file ``path``, welded (:func:`load_mesh`)."""
    trimesh = trimesh_module()
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False, skip_materials=True)  # geometry only
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        raise AutoalignError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc}); "
                             "pass a mesh file trimesh reads (PLY, OBJ, STL, GLB, OFF)") from None
    if isinstance(loaded, trimesh.Scene):  # pragma: no cover - force='mesh' normally concatenates
        loaded = loaded.dump(concatenate=True)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) < 3:
        raise AutoalignError(f"{path}: the mesh has no triangles; pass a mesh with faces (not a point cloud)")
    if not np.all(np.isfinite(np.asarray(loaded.vertices))):
        raise AutoalignError(f"{path}: the mesh has non-finite vertex coordinates; repair the file")
    tm = weld(trimesh.Trimesh(np.asarray(loaded.vertices, dtype=np.float64),
                              np.asarray(loaded.faces, dtype=np.int64), process=False))
    V = np.asarray(tm.vertices, dtype=np.float64)
    extent = float(np.linalg.norm(V.max(0) - V.min(0)))
    if units is None and extent < METRES_SUSPECT:
        raise AutoalignError(f"{path}: the model is only {extent:.3g} units across, so it is probably in metres "
                             "(autoalign works in millimetres); pass --units m to scale it by 1000, or --units mm "
                             "if it really is that small")
    return V * UNITS_MM[units or "mm"], np.asarray(tm.faces, dtype=np.int64)


def mesh_from_trimesh(tm: "trimesh.Trimesh", name: str = "mesh") -> Mesh:
    """Wrap an in-memory trimesh (mm) as it is (:func:`load_mesh` also welds it, see :func:`weld`)."""
    return Mesh(np.asarray(tm.vertices), np.asarray(tm.faces), name=name)
