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
    (short: no rendering under it), then call :meth:`changed`.

    An instance can be shown at a pose that is not a label yet (:meth:`put` ``shown_only``: a click's
    poses before its result): the pages see it, ``session.json`` keeps it as it was."""

    def __init__(self, instances: dict[int, LabelledInstance], revision: int, save: Save) -> None:
        self.instances = instances
        self.revision = revision
        self.focus: int | None = None  # the instance last selected on a page (the 3D view's gizmo goes to it)
        self.lock = threading.RLock()
        self._changed = threading.Condition(self.lock)
        self._save = save
        self._kept: dict[int, LabelledInstance] = {}  # instance -> as saved, while it is shown elsewhere

    def changed(self, save: bool = True) -> None:
        """Count a change, save it (lock held) and wake everyone waiting in :meth:`wait`."""
        with self.lock:
            self.revision += 1
            if save:
                self._save(self.revision, [self._kept.get(i.index, i) for i in self.instances.values()])
            self._changed.notify_all()

    def put(self, inst: LabelledInstance, shown_only: bool = False) -> None:
        """Set ``inst`` and count the change: saved, or with ``shown_only`` only shown (every save
        writes the instance as it was before, until a ``put`` that is not ``shown_only`` or :meth:`put_back`)."""
        with self.lock:
            if shown_only:
                self._kept.setdefault(inst.index, self.instances[inst.index])
            else:
                self._kept.pop(inst.index, None)
            self.instances[inst.index] = inst
            self.changed(save=not shown_only)

    def wait(self, since: int, timeout_s: float) -> int:
        """Block until the revision differs from ``since`` or ``timeout_s`` passed; the revision.

        A ``since`` above the revision comes from a page that saw this session before the server
        restarted (progress counts revisions that are not saved): it is answered at once."""
        with self._changed:
            self._changed.wait_for(lambda: self.revision != since, timeout=timeout_s)
            return self.revision

    def put_back(self, index: int) -> bool:
        """Instance ``index`` as saved again if it is shown elsewhere (:meth:`put` ``shown_only``);
        whether it was."""
        with self.lock:
            kept = self._kept.pop(index, None)
            if kept is None:
                return False
            self.instances[index] = replace(kept, pose_revision=self.instances[index].pose_revision + 1)
            self.changed(save=False)
            return True

    def decisions(self) -> dict[str, Any]:
        """Every placed instance's record and the accepted ones' numbers (``labels.json`` of the export)."""
        with self.lock:
            return {"instances": [i.record() for i in self.instances.values() if i.placed],
                    "accepted": [i.index for i in self.instances.values() if i.decision == "accepted" and i.placed],
                    "labels": "scene_gt.json lists the accepted instances, in this order"}
