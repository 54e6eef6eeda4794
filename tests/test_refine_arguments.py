"""One parser for ``autoalign refine`` (issue 44, item 3): a batch's scene lines are parsed by the
command's own argparse parser, into the same typed job the command builds; the options a batch
shares reach every scene unchanged; a mistake in a line is one line naming it."""

from __future__ import annotations

import pytest

from autoalign.cli.main import build_parser
from autoalign.errors import AutoalignError
from autoalign.jobs.refine_arguments import job_of, scene_job, shared_argv

COMMANDS = [
    ["--models", "models"],
    ["--model", "m.ply", "--obj-id", "5", "--instance", "2", "--units", "m"],
    ["--models", "models", "--refine-cameras", "--solve-scale", "--no-robust", "--depth", "off", "--photos", "on",
     "--masks", "auto", "--optimizer", "gn", "--seed-radius", "10,5", "--quiet"],
    ["--models", "models", "--instances", "inst.json", "--loss", "l2", "--photos", "off", "--json"],
]


@pytest.mark.parametrize("command", COMMANDS)
def test_a_scene_of_a_batch_gets_the_job_the_command_would_build(command: list[str]) -> None:
    """``refine --batch LIST OPTIONS``: each scene's job (its line adds ``--init``) is the job of
    ``refine SCENE OPTIONS --init ...`` as the command line builds it."""
    args = build_parser().parse_args(["refine", *command, "--batch", "list.txt", "--workers", "2", "--out", "out"])
    line = ["--init", "coarse.json"]
    job = scene_job("scene_a", [*shared_argv(args), *line], "out/scene_a")
    direct = build_parser().parse_args(["refine", "scene_a", *command, *line, "--out", "out/scene_a"])
    assert job == job_of(direct)


def test_the_line_may_use_any_spelling_the_command_takes() -> None:
    """``--photos=off`` and an option's unambiguous prefix, as on the command line."""
    job = scene_job("s", ["--models", "m", "--photos=off", "--seed-rad", "5,5"], "o")
    assert job.photos == "off" and job.seed_radius == "5,5"


@pytest.mark.parametrize("line, words", [
    (["--models", "m", "--workers", "2"], "--workers: an option of the whole batch"),
    (["--models", "m", "--work", "2"], "--workers: an option of the whole batch, not of one scene's line"),
    (["--models", "m", "--out", "x"], "--out: an option of the whole batch"),
    (["--models", "m", "--loss", "huber"], "invalid choice: 'huber'"),
    (["--models", "m", "--obj-id", "0"], "'0' must be 1 or more"),
    (["--models", "m", "--inti", "c.json"], "unrecognized arguments: --inti"),
    (["--models", "m", "--init"], "expected one argument"),
    (["--models", "m", "--model", "x.ply"], "not allowed with argument"),
])
def test_a_mistake_in_a_line_is_one_line(line: list[str], words: str) -> None:
    with pytest.raises(AutoalignError) as err:
        scene_job("s", line, "o")
    message = str(err.value)
    assert words in message and "\n" not in message and "autoalign refine --help" in message, message
