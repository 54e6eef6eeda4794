"""The changing state of a labelling session: its instances, the instance a page selected, and a
revision counting the changes, under one lock, with a wait for the next change (the page's long
poll and the 3D view follow it)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from autoalign.label.records import LabelledInstance

Save = Callable[[int, list[LabelledInstance]], None]
"""``save(revision, instances)``: keep a change (:meth:`autoalign.label.session_file.SessionFile.write`)."""


class SessionState:
    """Instances by mask number, the focus and the revision; change them with :attr:`lock` held
    (short: no rendering under it), then call :meth:`changed`."""

    def __init__(self, instances: dict[int, LabelledInstance], revision: int, save: Save) -> None:
        self.instances = instances
        self.revision = revision
        self.focus: int | None = None  # the instance last selected on a page (the 3D view's gizmo goes to it)
        self.lock = threading.RLock()
        self._changed = threading.Condition(self.lock)
        self._save = save

    def changed(self, save: bool = True) -> None:
        """Count a change, save it (lock held) and wake everyone waiting in :meth:`wait`."""
        with self.lock:
            self.revision += 1
            if save:
                self._save(self.revision, list(self.instances.values()))
            self._changed.notify_all()

    def wait(self, since: int, timeout_s: float) -> int:
        """Block until the revision differs from ``since`` or ``timeout_s`` passed; the revision.

        A ``since`` above the revision comes from a page that saw this session before the server
        restarted (progress counts revisions that are not saved): it is answered at once."""
        with self._changed:
            self._changed.wait_for(lambda: self.revision != since, timeout=timeout_s)
            return self.revision

    def put_back(self, before: LabelledInstance) -> bool:
        """Its instance as ``before`` again (not saved: as ``session.json`` still has it) if its pose
        changed since; whether it did."""
        with self.lock:
            now = self.instances[before.index]
            if now.pose_revision == before.pose_revision:
                return False
            self.instances[before.index] = replace(before, pose_revision=now.pose_revision + 1)
            self.changed(save=False)
            return True

    def decisions(self) -> dict[str, Any]:
        """Every placed instance's record and the accepted ones' numbers (``labels.json`` of the export)."""
        with self.lock:
            return {"instances": [i.record() for i in self.instances.values() if i.placed],
                    "accepted": [i.index for i in self.instances.values() if i.decision == "accepted" and i.placed],
                    "labels": "scene_gt.json lists the accepted instances, in this order"}
