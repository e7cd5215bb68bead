"""`table` chooses its metrics, leaves out the columns no row fills, captions its LaTeX and takes
a folder as --out like every other command (issue 70, item 6)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from helpers import invoke, one_line_error, sift_hpatches_run


@pytest.fixture(scope="module")
def run(shared_data: Path, tmp_path_factory) -> Path:
    return sift_hpatches_run(shared_data, tmp_path_factory.mktemp("shape") / "sift", max_side=240, limit=2)


def test_metrics_choose_the_columns(run, tmp_path):
    result = invoke("table", run, "--out", tmp_path / "t", "--no-paper", "--metrics", "h_acc@3,mma@3")
    assert result.exit_code == 0, result.output
    columns = list(pd.read_csv(tmp_path / "t.csv").columns)
    assert {"h_acc@3", "h_acc@3_lo", "mma@3", "mma@3_hi"} <= set(columns)
    assert "h_acc@1" not in columns and "h_acc@1_lo" not in columns and "seconds_per_pair" not in columns


def test_an_unknown_metric_names_the_choices(run, tmp_path):
    line = one_line_error(invoke("table", run, "--out", tmp_path / "t", "--metrics", "auc@10"))
    assert "--metrics auc@10: not a column of a hpatches table; choose among" in line and "h_acc@3" in line


def test_columns_no_row_fills_are_left_out(run, tmp_path):
    assert invoke("table", run, "--out", tmp_path / "t", "--no-paper", "--no-compare").exit_code == 0
    columns = list(pd.read_csv(tmp_path / "t.csv").columns)
    assert "vs_paper" not in columns and not any(c.startswith("d_") for c in columns)
    assert "h_acc@1" in columns and "protocol" in columns


def test_latex_has_a_caption(run, tmp_path):
    assert invoke("table", run, "--out", tmp_path / "t", "--latex", "--caption", "HPatches, 2 pairs & SIFT").exit_code == 0
    tex = (tmp_path / "t.tex").read_text()
    assert r"\caption{HPatches, 2 pairs \& SIFT}" in tex and r"\begin{table}" in tex and r"\end{table}" in tex
    assert invoke("table", run, "--out", tmp_path / "u", "--latex").exit_code == 0
    assert r"\caption{[lo, hi]: 95\% bootstrap interval over the pairs" in (tmp_path / "u.tex").read_text()


def test_a_folder_as_out_gets_table_inside(run, tmp_path):
    folder = tmp_path / "tables"
    folder.mkdir()
    assert invoke("table", run, "--out", folder, "--no-paper").exit_code == 0
    assert (folder / "table.csv").is_file() and (folder / "table.md").is_file()
