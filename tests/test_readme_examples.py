"""The README's Python examples that need no data files, run as written: the PyTorch loop
(issue 15) must end within 1 mm and 1 degree of the truth."""

from __future__ import annotations

import re
from pathlib import Path


README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks(marker: str) -> list[str]:
    """The README's ```python blocks that contain ``marker``."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    return [b for b in blocks if marker in b]


def run_block(marker: str) -> dict:
    """Execute the one README block containing ``marker``; its variables."""
    (block,) = python_blocks(marker)
    scope: dict = {}
    exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own example
    return scope


def test_pytorch_loop_reaches_1mm_1deg():
    scope = run_block("from autoalign.torch import")
    assert scope["err_mm"] < 1.0 and scope["err_deg"] < 1.0, (scope["err_mm"], scope["err_deg"])


def test_jax_solve_reaches_1mm_1deg():
    scope = run_block("import autoalign.jax as aj")
    assert scope["grad"].shape == (4, 4) and float(abs(scope["grad"]).sum()) > 0
    assert scope["err_mm"] < 1.0 and scope["err_deg"] < 1.0, (scope["err_mm"], scope["err_deg"])
