"""One model's mesh at the detail of each image resolution, each with its rasterizer: the one owner
of mesh detail. The refinement, the joint solve, the scale's guess, the overlay and the label page
all render a model through its pyramid, so every IoU they report comes from the same triangles.

A pixel at 1/8 resolution spans 10-15 mm, where a mesh of 1,500 triangles draws the same
silhouette as the scan; at full resolution the LINEMOD scans' silhouettes at 20,000 triangles
agree with the originals' at IoU >= 0.999 in every view (quadric decimation,
:meth:`~autoalign.geometry.mesh.Mesh.simplified`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from autoalign.geometry.mesh import Mesh
from autoalign.geometry.se3 import Symmetries
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

SEARCH_SCALE = 0.125
"""At this fraction of the image size or less the mesh is drawn at :attr:`MeshDetail.search`."""


@dataclass(frozen=True)
class MeshDetail:
    """At most how many triangles the mesh is drawn with at each resolution (``None``: as given).

    Attributes:
        fine: at full resolution: the silhouettes every reported IoU is measured on.
        coarse: below full resolution and above 1/8 (a pixel there spans millimetres).
        search: at 1/8 resolution or less: the orientation search and its scoring.
    """

    fine: int | None = 20000
    coarse: int | None = 5000
    search: int | None = 1500

    def at_scale(self, scale: float) -> int | None:
        """The triangle budget at ``scale`` (fraction of the image size)."""
        return self.fine if scale >= 1.0 else self.coarse if scale > SEARCH_SCALE else self.search


AS_GIVEN = MeshDetail(None, None, None)
"""The mesh as given at every resolution."""


class MeshPyramid:
    """``mesh`` (model frame, mm) and its simplified versions, each with its rasterizer, made on
    first use and kept: one per model (:meth:`~autoalign.io.models.ModelSet.pyramid`), shared by
    every stage that renders it, also from several threads (the instances of a scene refined side by
    side, :mod:`autoalign.runtime.parallel`).
    ``symmetries``: the model's (:class:`~autoalign.geometry.se3.Symmetries`), for what measures
    how far a pose moved (a turn about an axis of continuous symmetry is no move); ``material``:
    what the model is declared to be to the sensors (``"opaque"``, ``"transparent"``, ``"reflective"``;
    ``materials.json``, :mod:`autoalign.io.models`), ``None`` where nothing is declared."""

    def __init__(self, mesh: Mesh, symmetries: Symmetries = Symmetries(), material: str | None = None) -> None:
        self.mesh = mesh
        self.symmetries = symmetries
        self.material = material
        self._rasterizers: dict[int | None, SoftSilhouetteRasterizer] = {}
        self._making = threading.Lock()  # each level made once, by the first thread to ask

    @property
    def transparent(self) -> bool:
        """Whether the model is declared transparent to depth sensors."""
        return self.material == "transparent"

    def with_faces(self, max_faces: int | None) -> SoftSilhouetteRasterizer:
        """The rasterizer of the mesh simplified to at most ``max_faces`` triangles (``None``: as given)."""
        if max_faces is not None and len(self.mesh.faces) <= max_faces:
            max_faces = None  # already small enough: share the mesh as given
        with self._making:
            if max_faces not in self._rasterizers:
                mesh = self.mesh if max_faces is None else self.mesh.simplified(max_faces)
                self._rasterizers[max_faces] = SoftSilhouetteRasterizer(mesh)
            return self._rasterizers[max_faces]

    def at(self, scale: float, detail: MeshDetail = MeshDetail()) -> SoftSilhouetteRasterizer:
        """The rasterizer for images at ``scale`` of the full size, at ``detail``."""
        return self.with_faces(detail.at_scale(scale))

    def fine(self, detail: MeshDetail = MeshDetail()) -> SoftSilhouetteRasterizer:
        """The rasterizer at full resolution: the one every reported IoU is measured with."""
        return self.at(1.0, detail)
