"""Many scenes at once (issue 15): ``autoalign.batch.refine_many`` on a local Dask cluster started
by the test, and ``autoalign refine --batch`` resuming an interrupted batch without redoing the
finished scenes. Scenes: one procedural object each, 8 views of 160x120, masks by open3d ray
casting, a coarse --init 5 mm / 5 deg off given per scene in the list."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from autoalign.batch import BATCH_RECORDS, read_records, refine_many
from autoalign.bop import scene_gt_of
from autoalign.atomic_files import write_json_atomic
from autoalign.experiments.procedural_models import procedural_models, write_models
from autoalign.experiments.synthetic import default_K, perturb_pose, random_rotation, ring_cameras, write_multi_scene
from autoalign.models import ModelSet
from autoalign.se3 import make_pose

N_SCENES = 20


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """``root/models``, ``root/scene_XX`` and ``root/list.txt`` (each line: a scene and its --init)."""
    root = tmp_path_factory.mktemp("batch")
    write_models(root / "models", procedural_models()[:4])
    models = ModelSet.read(root / "models")
    lines = []
    for k in range(N_SCENES):
        rng = np.random.default_rng([5, k])
        obj = 1 + k % 4
        mesh = models.mesh(obj)
        R = random_rotation(rng)
        T = make_pose(R, -R @ mesh.centre)
        cams = ring_cameras(8, rng, dist_range=(350, 450), K=default_K(160, 120, 150.0), width=160, height=120)
        scene = root / f"scene_{k:02d}"
        write_multi_scene(scene, [mesh], [obj], [T], cams)
        write_json_atomic(scene / "init_gt.json", scene_gt_of([(obj, perturb_pose(T, 5.0, 5.0, rng, mesh.centre))],
                                                              cams[:1], [0]))
        lines.append(f"{scene.name} --init {scene / 'init_gt.json'}")
    (root / "list.txt").write_text("# one scene per line\n" + "\n".join(lines) + "\n")
    return root


def test_batch_on_a_local_dask_cluster(batch, tmp_path):
    import dask.distributed as distributed  # installed by the test command: a missing one must fail
    from autoalign.batch import read_scene_list

    scenes = read_scene_list(batch / "list.txt")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        summary = refine_many([s for s, _ in scenes], ["--models", str(batch / "models")], tmp_path / "out",
                              scheduler=client, progress=False, extra={str(s): e for s, e in scenes})
    assert (summary.total, summary.done, summary.failed) == (N_SCENES, N_SCENES, 0)
    records = read_records(tmp_path / "out" / BATCH_RECORDS)
    assert sorted(Path(r["scene"]).name for r in records) == [f"scene_{k:02d}" for k in range(N_SCENES)]
    assert all(r["status"] == 0 for r in records), [r for r in records if r["status"]]
    for k in range(N_SCENES):
        rec = json.loads((tmp_path / "out" / f"scene_{k:02d}" / "refine.json").read_text())
        assert rec["instances"][0]["verdict"] == "ok"


def test_interrupted_batch_resumes_without_redoing(batch, tmp_path):
    """The first 12 scenes done (as an interrupted run leaves them), then the command on all 20:
    only the other 8 run, the first 12's outputs are untouched."""
    from autoalign.batch import read_scene_list

    scenes = read_scene_list(batch / "list.txt")
    out = tmp_path / "out"
    first = refine_many([s for s, _ in scenes[:12]], ["--models", str(batch / "models")], out, progress=False,
                        extra={str(s): e for s, e in scenes})
    assert first.done == 12
    stamps = {k: (out / f"scene_{k:02d}" / "refine.json").stat().st_mtime_ns for k in range(12)}
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", "--batch", str(batch / "list.txt"),
                        "--models", str(batch / "models"), "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "8 scene(s) refined, 12 already done, 0 failed" in p.stdout
    assert all((out / f"scene_{k:02d}" / "refine.json").stat().st_mtime_ns == stamps[k] for k in range(12))
    assert len(read_records(out / BATCH_RECORDS)) == N_SCENES


def test_bad_batch_lists_are_one_line_errors(batch, tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("scene_that_is_not_there\n")

    def run(*extra):
        return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", *extra, "--models",
                               str(batch / "models"), "--out", str(tmp_path / "out")], capture_output=True, text=True)

    p = run("--batch", str(bad))
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "is not a folder" in p.stderr
    p = run(str(batch / "scene_00"), "--batch", str(batch / "list.txt"))
    assert p.returncode == 2 and "not both" in p.stderr
    assert not (tmp_path / "out").exists()
