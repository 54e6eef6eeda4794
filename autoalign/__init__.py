"""autoalign: label the 6-DoF pose of a known object from calibrated multi-view masks.

Quick use::

    import autoalign
    scene = autoalign.read_scene("scene_dir")
    mesh = autoalign.load_mesh("obj_000001.ply")
    result = autoalign.refine(scene, mesh, seed=None)   # or a 4x4 pose, or autoalign.Click(...)
    print(result.T_wm)

Heavy modules (mitsuba/drjit) load on first use, so ``import autoalign`` stays fast.
"""

from __future__ import annotations

import os
import signal
import threading
from typing import TYPE_CHECKING, Any

from autoalign.runtime.interrupts import Interrupts, is_command_process

# Until the command's main() takes over; a process that ignores Ctrl-C (a batch worker, nohup) keeps ignoring it.
if (is_command_process() and threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
    signal.signal(signal.SIGINT, Interrupts.remember)

__version__ = "0.1.0"

# In a source checkout the subpackages (losses/, rasterizers/, recon/, cli/, experiments/) sit
# beside this folder and pyproject.toml maps them to autoalign.*; let the checkout import them the
# same way (e.g. `python -m autoalign.cli.main` run from the repository root). No-op when installed.
_checkout = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if os.path.isfile(os.path.join(_checkout, "pyproject.toml")) and os.path.isdir(os.path.join(_checkout, "losses")):
    __path__.append(_checkout)  # noqa: F821 - the package's own __path__

_LAZY = {
    "refine": "autoalign.engine.refine", "RefineOptions": "autoalign.engine.options", "RefineResult": "autoalign.engine.refine",
    "read_scene": "autoalign.io.bop", "Scene": "autoalign.io.bop", "read_init_pose": "autoalign.io.bop",
    "read_evidence": "autoalign.io.evidence", "check": "autoalign.jobs.check",
    "load_mesh": "autoalign.geometry.mesh", "Mesh": "autoalign.geometry.mesh", "mesh_from_trimesh": "autoalign.geometry.mesh",
    "Camera": "autoalign.geometry.camera", "Click": "autoalign.engine.seeding", "AutoalignError": "autoalign.errors",
    "Level": "autoalign.engine.objective", "SearchOptions": "autoalign.engine.options",
    "RankingOptions": "autoalign.engine.options", "DisambiguationOptions": "autoalign.engine.options",
    "MeshDetail": "autoalign.rasterizers.pyramid", "MeshPyramid": "autoalign.rasterizers.pyramid",
    "LevenbergMarquardt": "autoalign.engine.solver", "GaussNewton": "autoalign.engine.solver",
    "Adam": "autoalign.engine.solver", "TablePlane": "autoalign.losses.contact",
}

# ``check`` (autoalign.jobs.check) is left out below: it reaches autoalign.jobs.report, which imports
# __version__ from this package, a cycle for type checkers and tests/test_layers.
if TYPE_CHECKING:  # pragma: no cover
    from autoalign.engine.objective import Level  # noqa: F401
    from autoalign.engine.options import (  # noqa: F401
        DisambiguationOptions,
        RankingOptions,
        RefineOptions,
        SearchOptions,
    )
    from autoalign.engine.refine import RefineResult, refine  # noqa: F401
    from autoalign.engine.seeding import Click  # noqa: F401
    from autoalign.engine.solver import Adam, GaussNewton, LevenbergMarquardt  # noqa: F401
    from autoalign.errors import AutoalignError  # noqa: F401
    from autoalign.geometry.camera import Camera  # noqa: F401
    from autoalign.geometry.mesh import Mesh, load_mesh, mesh_from_trimesh  # noqa: F401
    from autoalign.io.bop import Scene, read_init_pose, read_scene  # noqa: F401
    from autoalign.io.evidence import read_evidence  # noqa: F401
    from autoalign.losses.contact import TablePlane  # noqa: F401
    from autoalign.rasterizers.pyramid import MeshDetail, MeshPyramid  # noqa: F401


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'autoalign' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's own names and the lazily loaded ones (``refine``, ``read_scene``, ...), for
    ``dir(autoalign)`` and tab completion."""
    return sorted(set(globals()) | set(_LAZY))


__all__ = sorted(_LAZY)
