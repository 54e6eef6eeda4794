"""Studies, benchmarks and page drivers built on autoalign (not part of the labelling command).

* ``studies/``: the simulated convergence study behind ``autoalign simulate`` (runner, protocol,
  report, the paper's method) and the studies on real and synthetic scenes (``python -m
  autoalign.experiments.studies.NAME``).
* ``benchmarks/``: speed and memory (``python -m autoalign.experiments.benchmarks.bench_NAME``),
  each writing its table to ``results/``.
* ``result_files``: how a study or benchmark writes ``NAME.json`` and ``NAME.md`` there;
  ``commands``: how it runs the ``autoalign`` command in a child process, timed.
* ``pages/``: the label page driven in a real browser (Playwright), for its tests and benchmarks.
* ``scenes/``: synthetic scenes and models (open3d ray-cast masks, procedural meshes, a
  simulated RGB-D stream, the bundled example).

May import anything in autoalign; nothing in ``autoalign/`` imports it.
"""

from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
"""Where the studies and benchmarks write their tables and figures (committed)."""
