"""No command writes over a run's own files (issue 70, item 3): `table --out RUN/summary` exited 0
and replaced the run's summary.csv; `--out RUN/per_pair.csv` left a run that could not be read."""

from __future__ import annotations

from pathlib import Path

import pytest

from e3cm_bench.storage import RunFolder
from helpers import invoke, one_line_error, sift_hpatches_run


@pytest.fixture(scope="module")
def run(shared_data: Path, tmp_path_factory) -> Path:
    return sift_hpatches_run(shared_data, tmp_path_factory.mktemp("own") / "sift", max_side=240, limit=2)


@pytest.mark.parametrize("target", ["summary", "per_pair.csv", "cost", "failures"])
def test_table_refuses_an_out_over_the_runs_files(run, target):
    files = {name: (run / name).read_bytes() for name in ("summary.csv", "per_pair.csv", "config.yaml", "cost.csv")}
    line = one_line_error(invoke("table", run, "--out", run / target))
    assert str(run) in line and "never writes over" in line
    assert {name: (run / name).read_bytes() for name in files} == files


def test_table_may_write_beside_the_runs_files(run):
    result = invoke("table", run, "--out", run / "my_table", "--no-paper")
    assert result.exit_code == 0, result.output
    assert (run / "my_table.csv").is_file()


def test_own_file_needs_a_run_folder(tmp_path):
    assert not RunFolder.own_file(tmp_path / "summary.csv")  # not a run folder: any name is free
    (tmp_path / RunFolder.CONFIG).write_text("benchmark: hpatches\n")
    assert RunFolder.own_file(tmp_path / "summary.csv") and RunFolder.own_file(tmp_path / "matches.003.h5")
    assert not RunFolder.own_file(tmp_path / "table.csv")
