"""A BOP models folder: ``obj_{obj_id:06d}.ply`` meshes (mm) and ``models_info.json``.

``models_info.json`` gives per object its ``diameter`` (mm) and, for symmetric objects,
``symmetries_discrete`` (model-frame 4x4 transforms, mm) and ``symmetries_continuous``
(``{"axis", "offset"}``), as the bop_toolkit defines them. Meshes load on first use.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError
from autoalign.geometry.mesh import Mesh, load_mesh


@dataclass
class ModelSet:
    """The models of one BOP models folder, by ``obj_id``.

    Attributes:
        folder: the models folder.
        info: ``models_info.json`` entries by ``obj_id`` (``{}`` if the file is absent).
        units: the meshes' units for :func:`~autoalign.geometry.mesh.load_mesh` (``None``: mm, metres refused).
    """

    folder: Path
    info: dict[int, dict[str, Any]]
    units: str | None = None
    _meshes: dict[int, Mesh] = field(default_factory=dict, repr=False)

    @staticmethod
    def read(folder: str | Path, units: str | None = None) -> "ModelSet":
        folder = Path(folder)
        if not folder.is_dir():
            raise AutoalignError(f"{folder}: models folder not found; pass a BOP models folder with "
                                 "obj_XXXXXX.ply files (and models_info.json) to --models")
        info_path = folder / "models_info.json"
        info: dict[int, dict[str, Any]] = {}
        if info_path.is_file():
            try:
                raw = json.loads(info_path.read_text())
                info = {int(k): dict(v) for k, v in raw.items()}
            except (json.JSONDecodeError, UnicodeDecodeError, ValueError, TypeError, AttributeError):
                raise AutoalignError(f"{info_path}: not a BOP models_info.json (object ids mapping to "
                                     "{\"diameter\", ...}); fix it or remove it") from None
        return ModelSet(folder, info, units)

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

    def continuous_axes(self, obj_id: int) -> tuple[NDArray[np.float64], ...]:
        """The unit model-frame axes of ``obj_id``'s continuous symmetries (``models_info.json``)."""
        out = []
        for c in self.info.get(obj_id, {}).get("symmetries_continuous", []):
            a = np.asarray(c["axis"], dtype=np.float64)
            out.append(a / np.linalg.norm(a))
        return tuple(out)

    def symmetric(self, obj_id: int) -> bool:
        """Whether ``models_info.json`` lists symmetries for ``obj_id``."""
        e = self.info.get(obj_id, {})
        return bool(e.get("symmetries_discrete") or e.get("symmetries_continuous"))
