"""The study runner and CLI: task list, resume after a kill, every method end to end, Dask, errors."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from autoalign.batch import read_records, repair_jsonl
from autoalign.errors import AutoalignError
from autoalign.experiments.studies.protocol import ImageSetup
from autoalign.experiments.studies.runner import (
    ALL_METHODS,
    StudyConfig,
    build_tasks,
    run_study,
)
from autoalign.experiments.studies.simulate import main as simulate_main

TINY = ["--width", "160", "--height", "120", "--focal", "150", "--views", "8", "--trials", "1", "--no-progress"]


def _fake(task):
    return {"id": task["id"], "method": task["method"], "condition": task["condition"]}


def test_tasks_cover_conditions_with_unique_ids():
    cfg = StudyConfig(model_ids=(1, 2, 3), trials=2, parts=("main", "views", "noise", "sensitivity"), sweep_trials=1)
    tasks = build_tasks(cfg)
    ids = [t["id"] for t in tasks]
    assert len(ids) == len(set(ids))
    conds = {t["condition"] for t in tasks}
    assert {"main", "views5", "views10", "views20", "noise-erode-0.25", "noise-shift-0.5",
            "sens-sigma31.6", "sens-order-random", "sens-axis-z", "sens-disc-geo4"} <= conds
    main = [t for t in tasks if t["condition"] == "main"]
    assert len(main) == 3 * 2 * len(ALL_METHODS)
    assert {t["method"] for t in tasks if t["condition"] == "sens-axis-z"} == {"paper"}
    assert {t["method"] for t in tasks if t["condition"].startswith("sens-sigma")} == {"paper", "autoalign-seeded"}
    assert all(t["trial"] == 0 for t in tasks if t["part"] != "main")
    json.dumps(tasks)  # tasks are plain JSON


def test_resume_skips_finished_trials_and_repairs_a_torn_line(tmp_path):
    cfg = StudyConfig(model_ids=(1, 2), trials=2, methods=("paper", "init"))
    tasks = build_tasks(cfg)
    path = tmp_path / "trials.jsonl"
    done = [_fake(t) for t in tasks[:3]]
    path.write_text("".join(json.dumps(r) + "\n" for r in done) + '{"id": "main|m2|t1|pa')  # killed mid-write
    ran = []

    def fn(task):
        ran.append(task["id"])
        return _fake(task)

    s = run_study(cfg, tmp_path, progress=False, task_fn=fn)
    assert s.skipped == 3 and s.done == len(tasks) - 3
    assert ran == [t["id"] for t in tasks[3:]]
    recs = read_records(path)
    assert sorted(r["id"] for r in recs) == sorted(t["id"] for t in tasks)
    assert all(json.loads(line) for line in path.read_text().splitlines())  # no torn line left
    assert run_study(cfg, tmp_path, progress=False, task_fn=fn).done == 0  # nothing left to do
    assert repair_jsonl(path) == 0


def test_failed_trials_are_logged_and_retried(tmp_path):
    cfg = StudyConfig(model_ids=(1,), trials=1, methods=("init",))

    def boom(task):
        raise RuntimeError("no luck")

    s = run_study(cfg, tmp_path, progress=False, task_fn=boom)
    assert s.failed == 1 and s.done == 0
    assert "no luck" in (tmp_path / "errors.jsonl").read_text()
    assert run_study(cfg, tmp_path, progress=False, task_fn=_fake).done == 1


@pytest.mark.slow
def test_kill_and_resume(tmp_path):
    script = tmp_path / "slow_study.py"
    script.write_text(textwrap.dedent("""
        import sys, time
        from autoalign.experiments.studies.runner import StudyConfig, run_study
        def slow(task):
            time.sleep(0.4)
            return {"id": task["id"], "method": task["method"], "condition": task["condition"]}
        cfg = StudyConfig(model_ids=(1, 2, 3), trials=3, methods=("paper", "init"))
        run_study(cfg, sys.argv[1], progress=False, task_fn=slow)
    """))
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, str(script), str(out)], env=env)
    path = out / "trials.jsonl"
    t0 = time.time()
    while time.time() - t0 < 30:
        if path.is_file() and len(path.read_text().splitlines()) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = read_records(path)
    assert 3 <= len(first) < 18
    subprocess.run([sys.executable, str(script), str(out)], env=env, check=True, timeout=60)
    recs = read_records(path)
    ids = [r["id"] for r in recs]
    assert len(ids) == len(set(ids)) == 18
    assert recs[: len(first)] == first  # finished trials untouched


@pytest.mark.slow
def test_every_method_end_to_end(tmp_path):
    out = tmp_path / "study"
    code = simulate_main(["--out", str(out), "--model-ids", "1,5", "--method", "all,init", *TINY])
    assert code == 0
    recs = read_records(out / "trials.jsonl")
    assert {r["method"] for r in recs} == set(ALL_METHODS) | {"init"}
    assert len(recs) == 2 * 5
    for mid in (1, 5):  # every method saw the same trial
        rs = [r for r in recs if r["model_id"] == mid]
        assert len({json.dumps(r["T_gt"]) for r in rs}) == 1 and len({json.dumps(r["T_init"]) for r in rs}) == 1
    by = {(r["model_id"], r["method"]): r for r in recs}
    assert by[(5, "paper")]["symmetric"] and not by[(1, "paper")]["symmetric"]
    for r in recs:
        assert np.isfinite(r["pos_err_mm"]) and np.isfinite(r["adds_mm"]) and 0 <= r["iou_mean"] <= 1
        assert r["wall_s"] >= 0 and len(r["traj"]) >= 1
    assert by[(1, "paper")]["stopped"] in ("success", "stall", "max_iters")
    assert by[(1, "init")]["pos_err_mm"] == pytest.approx(by[(1, "init")]["init_pos_err_mm"])
    assert sum(r["success_cols"] for r in recs if r["method"] != "init") >= 4
    with open(out / "trials.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 10 and "success_cols" in rows[0]
    md = (out / "results.md").read_text()
    assert "| paper |" in md and "Speed ratio autoalign:paper" in md and "variance of 10cm" in md
    for name in ("error_vs_iteration", "success_vs_views", "success_vs_initial_error", "success_vs_mask_noise"):
        assert (out / "plots" / f"{name}.png").stat().st_size > 1000
    assert not [p for p in out.rglob("*.tmp")]  # no temporary files left behind
    assert simulate_main(["--out", str(out), "--report-only"]) == 0


@pytest.mark.slow
def test_worker_processes(tmp_path):
    cfg = StudyConfig(model_ids=(1, 5), trials=2, methods=("init",), views=4,
                      setup=ImageSetup(width=160, height=120, focal=150.0))
    s = run_study(cfg, tmp_path, workers=2, progress=False)
    assert s.done == 4 and s.failed == 0
    assert len(read_records(tmp_path / "trials.jsonl")) == 4


@pytest.mark.slow
def test_dask_local_cluster(tmp_path):
    import dask.distributed as distributed  # installed by .ci/install (the [all] extras)
    cfg = StudyConfig(model_ids=(5,), trials=1, methods=("paper", "init"), views=6,
                      setup=ImageSetup(width=160, height=120, focal=150.0))
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        s = run_study(cfg, tmp_path, scheduler=cluster.scheduler_address, progress=False)
    assert s.done == 2 and s.failed == 0, (tmp_path / "errors.jsonl").read_text() if s.failed else ""
    recs = read_records(tmp_path / "trials.jsonl")
    assert {r["method"] for r in recs} == {"paper", "init"}


def test_bad_input_is_one_line_error(tmp_path, capsys):
    assert simulate_main(["--out", str(tmp_path / "o"), "--models", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--models" in err and "\n" not in err
    for argv, opt in ((["--method", "gradient"], "--method"), (["--study", "everything"], "--study"),
                      (["--model-ids", "99"], "--model-ids"), (["--views", "0"], "--views")):
        assert simulate_main(["--out", str(tmp_path / "o"), *argv]) == 2
        assert opt in capsys.readouterr().err
    (tmp_path / "f").write_text("x")
    assert simulate_main(["--out", str(tmp_path / "f")]) == 2
    assert simulate_main(["--out", str(tmp_path / "nothing"), "--report-only"]) == 2


def test_output_folder_of_other_settings_is_refused(tmp_path):
    run_study(StudyConfig(model_ids=(1,), trials=1, methods=("init",), seed=1), tmp_path, progress=False, task_fn=_fake)
    with pytest.raises(AutoalignError, match="other settings"):
        run_study(StudyConfig(model_ids=(1,), trials=1, methods=("init",), seed=2), tmp_path, progress=False,
                  task_fn=_fake)


def test_no_trials_is_a_one_line_error_and_writes_nothing(tmp_path, capsys):
    """``simulate --trials 0``: exit 2, one line naming --trials and the fix, no folder. (Before: an
    empty study written, exit 0.)"""
    out = tmp_path / "study"
    assert simulate_main(["--out", str(out), "--model-ids", "1", *TINY, "--trials", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--trials 0" in err and "--trials 1 or more" in err and "\n" not in err, err
    assert not out.exists()


@pytest.mark.slow
def test_a_study_started_again_with_other_views_is_refused_and_its_report_says_its_views(tmp_path, capsys):
    """``simulate --views 12`` into a folder of 8-view trials: exit 2, one line naming the folder's
    file, what differs and the fix; nothing written. (Before: "already done", exit 0, and
    results.md mixed "views 12", "40 views" and the 8-view trials.) An older folder, whose config
    and trials did not record every setting, is refused by its trials' own views. The report's
    heading gives the trials' number of views."""
    out = tmp_path / "study"
    argv = ["--out", str(out), "--model-ids", "1", "--method", "init", *TINY]
    assert simulate_main(argv) == 0
    md = (out / "results.md").read_text()
    assert "## Main result (8 views," in md and "## Main result (40 views" not in md
    assert "this study's main trials had 8 views, images of 160x120 px with f = 150 px" in md
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert simulate_main([*argv, "--views", "12"]) == 2
    err = capsys.readouterr().err.strip()
    assert str(out / "config.json") in err and "--views 8, now 12" in err and "\n" not in err, err
    assert "another --out" in err and "same options" in err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before

    config = json.loads((out / "config.json").read_text())  # as an older version wrote them
    del config["fingerprint"]["views"]
    (out / "config.json").write_text(json.dumps(config))
    records = [{k: v for k, v in r.items() if k != "settings"} for r in read_records(out / "trials.jsonl")]
    (out / "trials.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    assert simulate_main([*argv, "--views", "12"]) == 2
    err = capsys.readouterr().err.strip()
    assert str(out / "trials.jsonl") in err and "--views 8, now 12" in err and "\n" not in err, err
    assert simulate_main(argv) == 0  # the same options resume it
    assert "0 trials run, 1 already done" in capsys.readouterr().out
