"""Fixtures shared by test files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest


# Each pytest-xdist worker, and the commands it starts, renders on its share of the cores: with a
# thread per core in each of two workers on 2 cores, the refinement tests ran 26% slower (README, Tests).
if "PYTEST_XDIST_WORKER" in os.environ:
    _share = str(max(1, (os.cpu_count() or 1) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))
    os.environ.setdefault("AUTOALIGN_THREADS", _share)
    os.environ.setdefault("OMP_NUM_THREADS", _share)


def pytest_configure(config: pytest.Config) -> None:
    """The Ctrl-C tests send SIGINT to the commands they start, as a terminal does to its foreground
    job. A shell starts a background job (``pytest &``, ``nohup``) with SIGINT ignored, and an ignored
    signal stays ignored across exec, so those commands would never see it; Python's own handler,
    which exec resets to the default, restores a terminal's conditions for them."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Collect the session's garbage now and freeze what is left, before a pytest-xdist worker says
    it is finished. Then pytest's own collections at exit (five in a row, to report unraisable
    exceptions) find nothing to walk. They walked a heap of several test files (meshes, renderers,
    torch and jax) and took over 5 s, after which execnet, which ends a worker that has not returned
    in 5 s, sent the worker SIGINT: the KeyboardInterrupt landed in jax's gc callback, the only
    Python code a collection runs, and the run ended with "Exception ignored in: <function
    _xla_gc_callback> ... KeyboardInterrupt"."""
    import gc

    gc.collect()
    gc.freeze()


@pytest.fixture
def refine_models_command(tmp_path: Path) -> Callable[[Path, Path, list[dict]], dict[str, Any]]:
    """Runs ``autoalign refine SCENE --models MODELS --init INIT`` (the coarse ``scene_gt`` entries
    of image 1) as a user would, asserts it exited 0 or 3 (labels written, some flagged), and
    returns its ``refine.json``."""
    def run(scene: Path, models: Path, coarse: list[dict]) -> dict[str, Any]:
        init, out = tmp_path / "init.json", tmp_path / "out"
        init.write_text(json.dumps({"1": coarse}))
        p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", str(scene), "--models", str(models),
                            "--init", str(init), "--out", str(out), "--quiet"], capture_output=True, text=True,
                           timeout=900)
        assert p.returncode in (0, 3), p.stderr
        return json.loads((out / "refine.json").read_text())
    return run
