"""The undo history of a labelling session: per instance, its states before its last moves (kept
while the server runs, not saved)."""

from __future__ import annotations

from autoalign.errors import AutoalignError
from autoalign.label.records import LabelledInstance

UNDO_STEPS = 50


class UndoHistory:
    """Each instance's last :data:`UNDO_STEPS` states before a move (callers hold the session's lock)."""

    def __init__(self) -> None:
        self._before: dict[int, list[LabelledInstance]] = {}

    def push(self, inst: LabelledInstance) -> None:
        """Remember ``inst`` as it was before a move (the oldest state beyond :data:`UNDO_STEPS` goes)."""
        steps = self._before.setdefault(inst.index, [])
        steps.append(inst)
        del steps[:-UNDO_STEPS]

    def pop(self, index: int) -> LabelledInstance:
        """Instance ``index`` as it was before its last move; raises if there is none."""
        if not self._before.get(index):
            raise AutoalignError(f"instance {index}: nothing to undo")
        return self._before[index].pop()
