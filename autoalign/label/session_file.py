"""``OUT_DIR/session.json``: a labelling session saved after every change (atomically, so a crash
leaves the previous one whole) and read back when the server starts again.

Format: ``{"kind": SESSION_KIND, "autoalign_version", "scene_dir", "models", "revision", "units",
"instances": [LabelledInstance.record(), ...]}``; poses are world-from-model 4x4 in mm, world =
the frame of ``scene_camera.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from autoalign import __version__
from autoalign.errors import AutoalignError
from autoalign.io.atomic_files import write_bytes_atomic
from autoalign.io.bop import read_json_file
from autoalign.label.records import LabelledInstance

SESSION_KIND = "autoalign label session"


@dataclass(frozen=True)
class SavedSession:
    """What a ``session.json`` held: its revision and its instances (objects checked against the models)."""

    revision: int
    instances: list[LabelledInstance]


@dataclass(frozen=True)
class SessionFile:
    """The ``session.json`` of a session on ``scene_dir`` with the models of ``models_dir``, in ``out_dir``."""

    out_dir: Path
    scene_dir: Path
    models_dir: Path

    @property
    def path(self) -> Path:
        return self.out_dir / "session.json"

    def read(self, object_ids: list[int]) -> SavedSession | None:
        """The saved session (``None`` if there is none yet); raises if it is not one of this scene's,
        is unreadable, holds a malformed entry (a null, non-finite or non-rigid pose among them), or
        names an object not in ``object_ids``."""
        path = self.path
        if not path.is_file():
            return None
        fix = f"delete {path} to start a new session, or pass another --out"
        try:
            data = read_json_file(path, fix)
        except RecursionError:
            raise AutoalignError(f"{path}: nested too deeply to be a session; {fix}") from None
        if not isinstance(data, dict) or data.get("kind") != SESSION_KIND:
            raise AutoalignError(f"{path}: not an autoalign label session; {fix}")
        if Path(data.get("scene_dir", "")).resolve() != self.scene_dir.resolve():
            raise AutoalignError(f"{path}: belongs to the scene {data.get('scene_dir')}, not {self.scene_dir}; {fix}")
        revision = data.get("revision", 0)
        if not isinstance(revision, int) or isinstance(revision, bool) or revision < 0:
            raise AutoalignError(f"{path}: revision {revision!r} is not a whole number; {fix}")
        if not isinstance(data.get("instances"), list):
            raise AutoalignError(f"{path}: no list of instances; {fix}")
        return SavedSession(revision, [self._instance(rec, k, object_ids) for k, rec in enumerate(data["instances"])])

    def _instance(self, rec: object, k: int, object_ids: list[int]) -> LabelledInstance:
        """Entry ``k`` of the saved instances, checked (raises naming the file, the entry and the fix)."""
        path = self.path
        name = f"instance {rec.get('index')}" if isinstance(rec, dict) else f"entry {k} of the instances"
        fix = f"correct or remove that entry (or delete {path} to start a new session), or pass another --out"
        try:
            if not isinstance(rec, dict):
                raise TypeError("not an object")
            inst = LabelledInstance.from_record(rec)
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            why = f"no {exc.args[0]}" if isinstance(exc, KeyError) else " ".join(str(exc).split())
            raise AutoalignError(f"{path}: {name} is malformed ({why}); {fix}") from None
        if inst.obj_id is not None and inst.obj_id not in object_ids:
            raise AutoalignError(f"{path}: instance {inst.index} is object {inst.obj_id}, which has no model "
                                 f"in {self.models_dir}; pass the models the session was made with")
        return inst

    def write(self, revision: int, instances: list[LabelledInstance]) -> None:
        """Write ``session.json`` atomically."""
        data = {"kind": SESSION_KIND, "autoalign_version": __version__, "scene_dir": str(self.scene_dir.absolute()),
                "models": str(self.models_dir.absolute()), "revision": revision,
                "units": "mm; T_wm is world-from-model, world = the frame of scene_camera.json",
                "instances": [i.record() for i in instances]}
        self.out_dir.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(self.path, json.dumps(data, indent=1).encode())
