"""The typed hand-offs of refining a scene folder (:mod:`autoalign.jobs.refine_folder`): the job
(:class:`FolderJob`, the options of ``autoalign refine``), the run's warnings (:class:`RunLog`),
its progress (:class:`Stages`), what it gave (:class:`FolderOutcome`, with the exit statuses), and
the writing of its outputs. A module of its own so that the one-object and the scene refinement
(:mod:`autoalign.jobs.refine_scene_folder`) and the command line share them without importing each other.

Standard library only at import (the command's start-up stays fast); the rest loads inside.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from autoalign.errors import AutoalignError

if TYPE_CHECKING:
    from autoalign.engine.options import RefineOptions
    from autoalign.jobs.report import RefineReport, SceneReport

OUTPUT_FILES = ("scene_gt.json", "refine.json", "overlay.png", "scene_camera.json")
"""Every file a refinement may write (``scene_camera.json`` only with ``refine_cameras`` or a solved scale)."""
LOSSES = ("l2", "bce", "iou", "dice")
DEPTH_MODES = ("auto", "off")
MASK_MODES = ("auto", "none")
PHOTO_MODES = ("auto", "on", "off")
OPTIMIZERS = ("lm", "gn", "adam")
MESH_UNITS = ("mm", "m")
EXIT_OK = 0
EXIT_FLAGGED = 3
"""The status of a run whose outputs are written but a pose's verdict is ``check`` or ``failed``."""


def one_line(text: str) -> str:
    """``text`` with every run of white space (newlines too) made one space."""
    return " ".join(str(text).split())


@dataclass
class RunLog:
    """The warnings of one run, in order (one line each): written to ``refine.json`` and shown by
    ``show`` as they come (the command prints them on stderr)."""

    warnings: list[str] = field(default_factory=list)
    show: Callable[[str], None] | None = None

    def warning(self, message: str) -> None:
        self.warnings.append(one_line(message))
        if self.show is not None:
            self.show(one_line(message))

    @contextmanager
    def python_warnings(self) -> Iterator[None]:
        """Within the block, Python's warnings are warnings of this run (trimesh's RuntimeWarnings,
        about degenerate faces it handles, dropped)."""
        import warnings

        def show(message: Warning | str, *args: Any, **kwargs: Any) -> None:
            self.warning(str(message))

        with warnings.catch_warnings():
            warnings.showwarning = show
            warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"trimesh(\.|$)")
            yield


class Stages(Protocol):
    """Progress of a run: ``start(desc)`` before the first step, ``(stage, done, total)`` per
    step (it may raise ``KeyboardInterrupt``), ``close()`` at the end."""

    def start(self, desc: str) -> None: ...
    def __call__(self, stage: str, done: int, total: int) -> None: ...
    def close(self) -> None: ...


class NoProgress:
    """:class:`Stages` that shows nothing."""

    def start(self, desc: str) -> None:
        pass

    def __call__(self, stage: str, done: int, total: int) -> None:
        pass

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class FolderJob:
    """One scene folder to refine into ``out``: the options of ``autoalign refine`` (paths as given).

    Exactly one of ``model`` (one object: its mesh, mm) and ``models`` (every instance: a BOP models
    folder); ``init`` (a coarse ``scene_gt.json``) or ``click`` (``IM_ID:U,V``, one object only)
    seeds it; ``units`` of the meshes (``mm``/``m``, default: refuse tiny meshes); ``depth``: ``auto``
    uses the scene's ``depth/`` when it has one (and metric cameras), ``off`` never; ``masks``:
    ``auto`` reads the instance masks, ``none`` withholds them all (the photos place the objects,
    from ``init``); ``photos``: ``auto`` uses the photos as evidence when the folder has ``rgb/``
    (:func:`~autoalign.jobs.refine_folder.refine_folder` goes on with the masks alone, and one
    warning, when a view lacks its photo), ``on`` always (a photo missing is an error), ``off`` never
    (:meth:`uses_photos`); ``resting``: the objects rest on a table plane, found in the scene
    (``table``) or given as ``NX,NY,NZ,D`` (:mod:`autoalign.jobs.table_plane`), ``None``: none declared
    (objects whose depth is seen through are offered the table their depth shows), ``off``: none at all."""

    scene: str
    out: str
    model: str | None = None
    models: str | None = None
    units: str | None = None
    obj_id: int = 1
    instance: int = 0
    instances: str | None = None
    init: str | None = None
    click: str | None = None
    loss: str = "l2"
    optimizer: str = "lm"
    refine_cameras: bool = False
    solve_scale: bool = False
    robust: bool = True
    depth: str = "auto"
    masks: str = "auto"
    photos: str = "auto"
    seed_radius: str | None = None
    resting: str | None = None

    @property
    def seed_radius_mm_deg(self) -> tuple[float, float]:
        """The stated uncertainty of the ``init`` seed (``MM,DEG``; default
        :data:`~autoalign.engine.seed_region.SEED_RADIUS`): a result farther from it is returned only
        when it fits clearly better than the best pose within it, and is flagged either way."""
        from autoalign.engine.seed_region import SEED_RADIUS

        if self.seed_radius is None:
            return SEED_RADIUS
        try:
            mm, deg = (float(x) for x in self.seed_radius.split(","))
        except ValueError:
            raise AutoalignError(f"--seed-radius {self.seed_radius}: expected MM,DEG, e.g. 25,30") from None
        if not (mm > 0 and deg > 0):
            raise AutoalignError(f"--seed-radius {self.seed_radius}: both numbers must be positive")
        return mm, deg

    def refine_options(self) -> RefineOptions:
        """The engine's settings this job asks for: loss, optimiser, robust weights, the seed's radius."""
        from autoalign.engine.options import RefineOptions
        from autoalign.engine.solver import STEP_RULES
        from autoalign.jobs.table_plane import OFF

        return RefineOptions(loss=self.loss, optimizer=STEP_RULES[self.optimizer], robust=self.robust,
                             seed_radius=self.seed_radius_mm_deg, offer_table=self.resting != OFF)

    @property
    def uses_photos(self) -> bool:
        """Whether the photos are evidence: ``photos`` ``on``, or ``auto`` when the scene folder has
        ``rgb/`` (or the masks are withheld)."""
        return self.photos == "on" or (self.photos == "auto" and (self.masks == "none" or (Path(self.scene) / "rgb").is_dir()))

    @property
    def modalities(self) -> tuple[str, ...]:
        """The evidence read for one object (:func:`~autoalign.io.evidence.read_evidence`'s ``modalities``)."""
        return tuple(m for m, used in (("masks", self.masks != "none"), ("photos", self.uses_photos),
                                        ("depth", self.depth == "auto")) if used)

    def check(self) -> None:
        """Refuse combinations of options that cannot work (:class:`AutoalignError`, one line)."""
        if (self.model is None) == (self.models is None):
            raise AutoalignError("give one of --model MESH (one object) and --models MODELS_DIR (every instance)")
        if self.init is not None and self.click is not None:
            raise AutoalignError("give at most one of --init and --click")
        for name, value, allowed in (("--loss", self.loss, LOSSES), ("--optimizer", self.optimizer, OPTIMIZERS),
                                     ("--depth", self.depth, DEPTH_MODES),
                                     ("--masks", self.masks, MASK_MODES), ("--photos", self.photos, PHOTO_MODES),
                                     ("--units", self.units, (None, *MESH_UNITS))):
            if value not in allowed:
                raise AutoalignError(f"{name} {value}: choose one of {', '.join(a for a in allowed if a)}")
        self.seed_radius_mm_deg  # a malformed --seed-radius fails here, before anything is read
        if self.resting is not None:
            from autoalign.jobs.table_plane import FOUND, OFF, parse_plane

            if self.resting not in (FOUND, OFF):
                parse_plane(self.resting)  # so does a malformed --resting plane
        if self.masks == "none" and self.photos == "off":
            raise AutoalignError("--masks none leaves the photos as the only evidence: drop --photos off")
        if self.masks == "none" and self.init is None:
            raise AutoalignError("--masks none refines a coarse pose from the photos: give --init (a coarse scene_gt.json)")
        if self.models is not None and self.click is not None:
            raise AutoalignError("--click seeds one object; with --models give a coarse --init for the scene, or no seed")
        if self.instances is not None and self.models is None:
            raise AutoalignError("--instances needs --models (a models folder for the objects it names)")
        if self.refine_cameras and self.models is None:
            raise AutoalignError("--refine-cameras needs --models: several objects seen together pin a camera down")
        if self.solve_scale and self.models is None:
            raise AutoalignError("--solve-scale needs --models (a models folder whose meshes give the objects' size)")


@dataclass
class FolderOutcome:
    """What a refinement of a folder gave: its status (:data:`EXIT_OK`, or :data:`EXIT_FLAGGED`
    when a verdict is ``check`` or ``failed``), the report written as ``refine.json``, the files
    written (name -> path, in writing order) and the notes to show the person after it."""

    status: int
    report: RefineReport | SceneReport
    paths: dict[str, Path]
    notes: list[str]


def write_json_outputs(out: Path, documents: dict[str, Any], binary: dict[str, bytes],
                       order: Sequence[str] = ()) -> dict[str, Path]:
    """Write the JSON ``documents`` (``refine.json`` without NaN) and ``binary`` files into ``out``,
    all or none (:func:`~autoalign.io.out_folder.write_outputs`); the names in ``order`` first.
    Ctrl-C from here on no longer interrupts the run (:meth:`~autoalign.runtime.interrupts.Interrupts.outputs_written`)."""
    import json

    from autoalign.io.out_folder import write_outputs
    from autoalign.jobs.report import jsonable
    from autoalign.runtime.interrupts import Interrupts

    files = {name: json.dumps(jsonable(doc), indent=1, allow_nan=name != "refine.json").encode()
             for name, doc in documents.items()}
    files.update(binary)
    first = [n for n in order if n in files]
    ordered = {name: files[name] for name in [*first, *[n for n in files if n not in first]]}
    paths = write_outputs(out, ordered)
    Interrupts.outputs_written()
    return paths
