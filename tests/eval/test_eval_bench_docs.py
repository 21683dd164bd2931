"""bench_docs: the benchmarks' shared writers (markdown table, JSON and docs section)."""

from __future__ import annotations

import argparse
import json

from mogs_node.eval.bench_docs import add_output_options, markdown_table, write_results


def test_markdown_table_lines():
    assert markdown_table(["a", "b"], [("1", 2), ["x", "y"]]) == [
        "| a | b |",
        "| --- | --- |",
        "| 1 | 2 |",
        "| x | y |",
    ]
    assert markdown_table(["only"]) == ["| only |", "| --- |"]


def test_write_results_prints_writes_json_and_the_docs_section(tmp_path, capsys, monkeypatch):
    written = {}
    monkeypatch.setattr(
        "mogs_node.eval.bench_docs.update_markdown_section",
        lambda name, body: written.setdefault(name, body),
    )
    write_results("sec", "## md", {"x": 1.5}, tmp_path / "f.json", docs=False)
    assert capsys.readouterr().out == "## md\n"
    assert json.loads((tmp_path / "f.json").read_text()) == {"x": 1.5}
    assert written == {}
    write_results("sec", "## md", {}, None, docs=True)
    assert written == {"sec": "## md"}


def test_output_options():
    ap = argparse.ArgumentParser()
    add_output_options(ap, docs_from="DIR")
    a = ap.parse_args(["--json", "p.json", "--no-docs", "--docs-from", "run"])
    assert (a.json, a.no_docs, a.docs_from) == ("p.json", True, "run")
    a = argparse.ArgumentParser()
    add_output_options(a)
    assert vars(a.parse_args([])) == {"json": None, "no_docs": False}
