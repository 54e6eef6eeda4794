"""experiments.commands: the autoalign command run in a child process for studies and benchmarks."""

import sys

import pytest

from autoalign.experiments.commands import autoalign_command, run_autoalign
from autoalign.jobs.job import EXIT_FLAGGED


def test_the_command_line_is_this_interpreter_running_the_cli_module():
    assert autoalign_command("refine", "scene") == [sys.executable, "-m", "autoalign.cli.main", "refine", "scene"]


def test_a_run_is_timed_and_ok_on_exit_0(tmp_path):
    run = run_autoalign("--help")
    assert run.returncode == 0 and run.ok and run.check() is run and run.wall_s > 0


def test_a_failed_run_says_its_command_and_its_stderr(tmp_path):
    run = run_autoalign("refine", str(tmp_path / "no_scene"), "--model", str(tmp_path / "no.ply"))
    assert run.returncode not in (0, EXIT_FLAGGED) and not run.ok and run.stderr
    with pytest.raises(RuntimeError, match=r"autoalign\.cli\.main refine .*no_scene.* failed \(\d+\): "):
        run.check()
