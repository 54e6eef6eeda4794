"""experiments.result_files: the one writer of a study's or benchmark's NAME.json and NAME.md."""

import json

from autoalign.experiments.result_files import write_results


def test_results_are_indented_json_and_the_table_with_a_final_newline(tmp_path, capsys):
    payload = {"rows": [{"err_mm": 0.25, "verdict": "ok"}], "summary": {"n": 1}}
    table = ["# title", "", "| a | b |", "|---|---|", "| 1 | 2 |"]
    write_results("bench_x", payload, table, tmp_path / "made")
    assert (tmp_path / "made" / "bench_x.json").read_text() == json.dumps(payload, indent=1)
    assert (tmp_path / "made" / "bench_x.md").read_text() == "\n".join(table) + "\n"
    assert capsys.readouterr().out == "\n".join(table) + "\n"


def test_only_the_first_lines_shown_or_none(tmp_path, capsys):
    table = [f"line {i}" for i in range(20)]
    write_results("a", [], table, tmp_path, shown=10)
    assert capsys.readouterr().out == "\n".join(table[:10]) + "\n"
    write_results("b", [], table, tmp_path, shown=0)
    assert capsys.readouterr().out == ""
    assert (tmp_path / "b.md").read_text() == "\n".join(table) + "\n"
