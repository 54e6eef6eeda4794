"""A BOP models folder: ``obj_{obj_id:06d}.ply`` meshes (mm) and ``models_info.json``.

``models_info.json`` gives per object its ``diameter`` (mm) and, for symmetric objects,
``symmetries_discrete`` (model-frame 4x4 transforms, mm) and ``symmetries_continuous``
(``{"axis", "offset"}``), as the bop_toolkit defines them. Meshes load on first use, as
:class:`~autoalign.geometry.mesh.Mesh` (welded, for refining) or as :class:`ColouredMesh` (the file's
vertices with their colours, for rendering the labels against photos).

``materials.json`` (optional, beside it; BOP has no such field) declares what the sensors see of an
object: ``{"<obj_id>": {"material": "transparent" | "reflective" | "opaque"}}``. The measured depth of a
transparent object is not evidence about its surface (:mod:`autoalign.engine.see_through`);
an object not listed is recognised from the evidence, and one declared opaque never is (its depth is
always evidence, and disagreeing depth flags it). The photo's features on a transparent or
reflective (mirror-like, polished metal) object are those of its surroundings, refracted or
mirrored, so ``check`` does not measure its feature distance (:data:`FEATURELESS`); a reflective
object's depth is refined as an opaque one's (its holes and specular outliers are per pixel).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.io.bop import read_json_file, whole_number_keys
from autoalign.geometry import mesh_cache
from autoalign.geometry.mesh import ColouredMesh, Mesh, load_mesh, trimesh_module
from autoalign.geometry.se3 import Symmetries
from autoalign.rasterizers.pyramid import MeshPyramid

MATERIALS = ("opaque", "transparent", "reflective")
"""The materials ``materials.json`` may declare."""
FEATURELESS = ("transparent", "reflective")
"""The materials whose photo features are not the object's own (module doc)."""
MATERIALS_FIX = ('materials.json maps object ids to {"material": "transparent"}, {"material": "reflective"} or '
                 '{"material": "opaque"}, e.g. {"3": {"material": "transparent"}}')

GREY = (0.5, 0.5, 0.5)
"""Colour (RGB, 0..1) of a mesh without vertex colours."""


def load_coloured_mesh(path: str | Path) -> ColouredMesh:
    """A mesh file (mm) with its per-vertex colours (``trimesh.load(path, process=False)`` keeps
    them in their vertex order); face colours are spread to the vertices, and a mesh without
    colours is grey (``has_colours`` False). A file read before comes from
    :mod:`~autoalign.geometry.mesh_cache`, without trimesh."""
    path = Path(path)
    try:
        key = mesh_cache.coloured_key(mesh_cache.file_key(path, None))
    except OSError as exc:
        raise AutoalignError(f"{path}: cannot read the mesh ({exc.strerror}); pass a mesh file you can read") from None
    stored = mesh_cache.read_entry(key, _COLOURED)
    if stored is not None:
        return ColouredMesh(stored["vertices"], stored["faces"], stored["colours"], bool(stored["has_colours"]), path)
    mesh = _read_coloured(path)
    mesh_cache.write_entry(key, {"vertices": mesh.vertices, "faces": mesh.faces, "colours": mesh.colours,
                                 "has_colours": np.asarray(mesh.has_colours)})
    return mesh


_COLOURED = ("vertices", "faces", "colours", "has_colours")
"""The arrays of a coloured mesh's cache entry."""


def _read_coloured(path: Path) -> ColouredMesh:
    """:func:`load_coloured_mesh` of a file not in the cache: read by trimesh."""
    trimesh = trimesh_module()
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds
        raise AutoalignError(f"{path}: cannot read the mesh ({exc}); give a PLY/OBJ/GLB mesh in mm") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise AutoalignError(f"{path}: has no triangles; the check renders the object, give a triangle mesh")
    V = np.asarray(loaded.vertices, dtype=np.float64)
    colours = _vertex_colours(loaded.visual, len(V))
    has = colours is not None
    if colours is None:
        colours = np.tile(np.asarray(GREY, dtype=np.float32), (len(V), 1))
    return ColouredMesh(V, np.asarray(loaded.faces, dtype=np.int64), colours, has, path)


def _vertex_colours(visual: Any, n_vertices: int) -> NDArray[np.float32] | None:
    """RGB (0..1) per vertex of a trimesh visual (textures sampled, face colours spread), None without."""
    kind = getattr(visual, "kind", None)
    try:
        if kind == "texture":
            visual = visual.to_color()
            kind = getattr(visual, "kind", None)
        if kind in ("vertex", "face"):
            c = np.asarray(visual.vertex_colors)
            if c.shape[0] == n_vertices:
                return c[:, :3].astype(np.float32) / 255.0
    except Exception:  # a broken texture: fall back to grey
        return None
    return None


INFO_FIX = ('a BOP models_info.json maps object ids to {"diameter": mm, "symmetries_discrete": [16 numbers: a 4x4 '
            'rigid transform, row-major, mm], "symmetries_continuous": [{"axis": 3 numbers, not all 0, "offset": 3 '
            'numbers (mm)}]}')


def read_models_info(path: str | Path) -> dict[int, dict[str, Any]]:
    """A BOP ``models_info.json`` by object id, every entry checked (:func:`check_info_entry`): a
    malformed symmetry is an error naming the file, the object and the fix here, not a traceback
    when the labels are judged."""
    path = Path(path)
    raw = read_json_file(path, INFO_FIX)
    if not isinstance(raw, dict):
        raise AutoalignError(f"{path}: not a BOP models_info.json; {INFO_FIX}")
    info = whole_number_keys(raw, path, "object id")
    for obj, entry in info.items():
        if not isinstance(entry, dict):
            raise AutoalignError(f"{path}: object {obj} is not an object of fields; {INFO_FIX}")
        check_info_entry(entry, f"{path}: object {obj}")
    return {obj: dict(entry) for obj, entry in info.items()}


def check_info_entry(entry: dict[str, Any], where: str) -> None:
    """Raise unless ``entry``'s diameter is a positive number, each discrete symmetry a rigid 4x4
    transform and each continuous one a non-zero axis with an offset (``where`` starts the error)."""
    if "diameter" in entry and not _finite(entry["diameter"], 1, positive=True):
        raise AutoalignError(f"{where} diameter {entry['diameter']!r} is not a positive number (mm); {INFO_FIX}")
    discrete = entry.get("symmetries_discrete", [])
    continuous = entry.get("symmetries_continuous", [])
    if not isinstance(discrete, list) or not isinstance(continuous, list):
        raise AutoalignError(f"{where}: its symmetries must be lists; {INFO_FIX}")
    for k, T in enumerate(discrete):
        if not _finite(T, 16) or not _rigid(np.asarray(T, dtype=np.float64).reshape(4, 4)):
            raise AutoalignError(f"{where} symmetries_discrete[{k}] is not a rigid 4x4 transform (16 numbers, row-major: "
                                 "a rotation with det +1 and a translation in mm, last row 0 0 0 1); fix it or remove it")
    for k, c in enumerate(continuous):
        axis = c.get("axis") if isinstance(c, dict) else None
        if not _finite(axis, 3) or np.linalg.norm(np.asarray(axis, dtype=np.float64)) < 1e-9:
            raise AutoalignError(f"{where} symmetries_continuous[{k}] needs an 'axis' of 3 numbers, not all zero (the "
                                 "axis' direction in the model frame, e.g. [0, 0, 1]); fix it or remove it")
        if "offset" in c and not _finite(c["offset"], 3):
            raise AutoalignError(f"{where} symmetries_continuous[{k}] 'offset' must be 3 numbers (a point on the axis, "
                                 "mm); fix it or remove it")


def _finite(value: Any, n: int, positive: bool = False) -> bool:
    """Whether ``value`` is ``n`` finite numbers (nested lists allowed; one number for ``n`` 1)."""
    if isinstance(value, bool) or value is None or isinstance(value, (str, dict)):
        return False
    try:
        a = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        return False
    return a.size == n and bool(np.all(np.isfinite(a))) and (not positive or bool(np.all(a > 0)))


def _rigid(T: NDArray[np.float64], tol: float = 1e-2) -> bool:
    """Whether ``T`` is a rotation (det +1; BOP files keep few decimals: ``tol``) and a translation."""
    R = T[:3, :3]
    return (np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() < 1e-6 and np.abs(R @ R.T - np.eye(3)).max() < tol
            and abs(np.linalg.det(R) - 1.0) < tol)


def read_materials(path: Path) -> dict[int, str]:
    """``materials.json`` (module doc) by ``obj_id``; an error naming the file and the fix when malformed."""
    raw = read_json_file(path, MATERIALS_FIX)
    if not isinstance(raw, dict):
        raise AutoalignError(f"{path}: not a JSON object; {MATERIALS_FIX}")
    out: dict[int, str] = {}
    for key, entry in whole_number_keys(raw, path, "object id").items():
        material = entry.get("material") if isinstance(entry, dict) else None
        if material not in MATERIALS:
            raise AutoalignError(f"{path}: object {key} has material {material!r}; {MATERIALS_FIX}")
        out[key] = material
    return out


@dataclass
class ModelSet:
    """The models of one BOP models folder, by ``obj_id``.

    Attributes:
        folder: the models folder.
        info: ``models_info.json`` entries by ``obj_id`` (``{}`` if the file is absent).
        units: the meshes' units for :func:`~autoalign.geometry.mesh.load_mesh` (``None``: mm, metres refused).
        materials: ``materials.json``'s declarations by ``obj_id`` (module doc; ``{}`` if the file is absent).
    """

    folder: Path
    info: dict[int, dict[str, Any]]
    units: str | None = None
    materials: dict[int, str] = field(default_factory=dict)
    _meshes: dict[int, Mesh] = field(default_factory=dict, repr=False)
    _coloured: dict[int, ColouredMesh] = field(default_factory=dict, repr=False)
    _pyramids: dict[int, MeshPyramid] = field(default_factory=dict, repr=False)

    @staticmethod
    def read(folder: str | Path, units: str | None = None, with_info: bool = True) -> "ModelSet":
        """The models folder ``folder``; ``with_info`` False leaves ``models_info.json`` unread (``info`` empty)."""
        folder = Path(folder)
        if not folder.is_dir():
            raise AutoalignError(f"{folder}: models folder not found; pass a BOP models folder with "
                                 "obj_XXXXXX.ply files (and models_info.json) to --models")
        info_path = folder / "models_info.json"
        info = read_models_info(info_path) if with_info and info_path.is_file() else {}
        materials_path = folder / "materials.json"
        materials = read_materials(materials_path) if materials_path.is_file() else {}
        return ModelSet(folder, info, units, materials)

    def path(self, obj_id: int) -> Path:
        return self.folder / f"obj_{obj_id:06d}.ply"

    def mesh(self, obj_id: int) -> Mesh:
        """The mesh of ``obj_id`` (mm), loaded once."""
        if obj_id not in self._meshes:
            p = self.path(obj_id)
            if not p.is_file():
                raise AutoalignError(f"{p}: no model for object {obj_id} in {self.folder}; add obj_{obj_id:06d}.ply "
                                     "or leave that instance out of the instances file")
            self._meshes[obj_id] = load_mesh(p, units=self.units)
        return self._meshes[obj_id]

    def pyramid(self, obj_id: int) -> MeshPyramid:
        """The mesh of ``obj_id`` with its simplified versions and their rasterizers, made once: every
        stage that renders the object shares it."""
        if obj_id not in self._pyramids:
            discrete, continuous = self.symmetries(obj_id)
            self._pyramids[obj_id] = MeshPyramid(self.mesh(obj_id), Symmetries(tuple(discrete), tuple(continuous)),
                                                 self.materials.get(obj_id))
        return self._pyramids[obj_id]

    def coloured(self, obj_id: int, named_in: Path | None = None) -> ColouredMesh:
        """The file's mesh of ``obj_id`` with its vertex colours (mm), loaded once; ``named_in``: the
        labels file that names the object, for the error when its mesh is missing."""
        if obj_id not in self._coloured:
            p = self.path(obj_id)
            if not p.is_file():
                named = f" (named in {named_in})" if named_in is not None else ""
                raise AutoalignError(f"{p}: not found; every obj_id of the labels{named} needs its mesh "
                                     f"{p.name} (mm) in --models")
            self._coloured[obj_id] = load_coloured_mesh(p)
        return self._coloured[obj_id]

    def coloured_meshes(self, obj_ids: Sequence[int], named_in: Path | None = None) -> dict[int, ColouredMesh]:
        """:meth:`coloured` of each of ``obj_ids``, by id (in increasing order)."""
        return {obj: self.coloured(obj, named_in) for obj in sorted(set(obj_ids))}

    def continuous_axes(self, obj_id: int) -> tuple[NDArray[np.float64], ...]:
        """The unit model-frame axes of ``obj_id``'s continuous symmetries (``models_info.json``)."""
        return tuple(axis for axis, _ in self.symmetries(obj_id)[1])

    def symmetries(self, obj_id: int) -> tuple[list[NDArray[np.float64]], list[tuple[NDArray[np.float64], NDArray[np.float64]]]]:
        """``obj_id``'s discrete symmetries (4x4, model frame, mm) and continuous ones (unit axis,
        a point on it; model frame, mm), as ``models_info.json`` lists them."""
        e = self.info.get(obj_id, {})
        discrete = [np.asarray(d, dtype=np.float64).reshape(4, 4) for d in e.get("symmetries_discrete", [])]
        continuous = [(np.asarray(c["axis"], dtype=np.float64) / np.linalg.norm(c["axis"]),
                       np.asarray(c.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64))
                      for c in e.get("symmetries_continuous", [])]
        return discrete, continuous

    def symmetric(self, obj_id: int) -> bool:
        """Whether ``models_info.json`` lists symmetries for ``obj_id``."""
        e = self.info.get(obj_id, {})
        return bool(e.get("symmetries_discrete") or e.get("symmetries_continuous"))
