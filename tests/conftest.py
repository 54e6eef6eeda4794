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

import numpy as np
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
    _session_mesh_cache(config)


def _session_mesh_cache(config: pytest.Config) -> None:
    """One mesh cache (:mod:`autoalign.geometry.mesh_cache`) for the whole run, new each run: the
    workers and the commands they start share it (they inherit the environment), and no run reads
    what an earlier one left in the user's cache."""
    if "PYTEST_XDIST_WORKER" in os.environ or os.environ.get("AUTOALIGN_CACHE_DIR"):
        return
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="autoalign-test-mesh-cache-")
    os.environ["AUTOALIGN_CACHE_DIR"] = folder
    config.add_cleanup(lambda: shutil.rmtree(folder, ignore_errors=True))


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


def at_once(calls: list[Callable[[], Any]]) -> list[Any]:
    """Each of ``calls`` on a thread of its own, all let go at once (a barrier), and their results in
    order; the first call's error that failed, if any, raised after all have ended."""
    import threading

    start = threading.Barrier(len(calls), timeout=60)
    results: list[Any] = [None] * len(calls)
    errors: list[BaseException | None] = [None] * len(calls)

    def run(k: int) -> None:
        start.wait()
        try:
            results[k] = calls[k]()
        except BaseException as exc:  # handed to the caller's thread
            errors[k] = exc

    threads = [threading.Thread(target=run, args=(k,)) for k in range(len(calls))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    failed = next((e for e in errors if e is not None), None)
    if failed is not None:
        raise failed
    return results


def open3d_depth(mesh: Any, T_wm: np.ndarray, cam: Any) -> np.ndarray:
    """Depth (mm along the optical axis, 0: no hit) of pixel (i, j) through OpenCV's (u, v) = (j, i),
    ray-cast by open3d (independent of our caster and of our pixel convention)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    V = mesh.vertices @ T_wm[:3, :3].T + T_wm[:3, 3]
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    j, i = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    d_cam = np.stack([j.ravel(), i.ravel(), np.ones(j.size)], 1) @ np.linalg.inv(cam.K_opencv).T  # unit z
    rays = np.concatenate([np.tile(cam.centre, (len(d_cam), 1)), d_cam @ cam.R_w2c], 1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(cam.height, cam.width)
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32)


@pytest.fixture
def depth_caster() -> Any:
    """:func:`open3d_depth`, for the tests that cast the depth of their own scenes."""
    return open3d_depth


@pytest.fixture(scope="module")
def box_with_depth() -> tuple[Any, np.ndarray, list, list[np.ndarray]]:
    """A box (mesh, world-from-model pose) in 4 views of 320x240 at about 400 mm, and its depth in
    each (:func:`open3d_depth`)."""
    from autoalign.experiments.scenes.procedural_models import procedural_models
    from autoalign.experiments.scenes.synthetic import default_K, ring_cameras
    from autoalign.geometry.mesh import mesh_from_trimesh
    from autoalign.geometry.se3 import make_pose, so3_exp

    mesh = mesh_from_trimesh(procedural_models()[1].mesh, "box")
    cams = ring_cameras(4, np.random.default_rng(3), dist_range=(380.0, 420.0), K=default_K(320, 240, 380.0),
                        width=320, height=240)
    T = make_pose(so3_exp(np.array([0.3, -0.2, 0.5])), -mesh.centre)
    return mesh, T, cams, [open3d_depth(mesh, T, c) for c in cams]


@pytest.fixture
def pool_of_two() -> Any:
    """drjit's pool at two threads (the test workers run with one each), as on a 2-core machine: work
    run side by side (:mod:`autoalign.runtime.parallel`) then runs on two threads."""
    from autoalign.runtime.backend import drjit

    dr = drjit()
    before = dr.thread_count()
    dr.set_thread_count(2)
    try:
        yield
    finally:
        dr.set_thread_count(before)
