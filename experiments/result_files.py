"""The one way a study or benchmark leaves its results: ``NAME.json`` and ``NAME.md`` in one folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from autoalign.experiments import RESULTS
from autoalign.io.atomic_files import write_json_atomic, write_text_atomic


def write_results(name: str, payload: Any, table: list[str], out: Path = RESULTS,
                  shown: int | None = None) -> None:
    """Write ``out/NAME.json`` (``payload`` as indented JSON) and ``out/NAME.md`` (the lines of
    ``table``, one per line), each atomically, making ``out`` if missing; then print the table's
    first ``shown`` lines (all when None, nothing when 0)."""
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / f"{name}.json", payload)
    write_text_atomic(out / f"{name}.md", "\n".join(table) + "\n")
    if shown != 0:
        print("\n".join(table[:shown]))
