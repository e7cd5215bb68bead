"""A run's cost beside its accuracy (issue 68, item 5): each pair's time and peak memory in
cost.csv, the summary's seconds_per_pair (with its interval) and peak_memory_mb, the table's
columns, and the report's accuracy-against-time plot with its Pareto front."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from e3cm_bench.drawing.plots import pareto_front
from e3cm_bench.pipeline.evaluate import cost_summary
from e3cm_bench.storage import RunFolder
from helpers import invoke


def test_the_pareto_front_keeps_what_nothing_beats_on_both():
    points = [(1.0, 0.5), (2.0, 0.4), (3.0, 0.9), (0.5, 0.2), (3.0, 0.8), (10.0, 0.9)]
    assert pareto_front(points) == [3, 0, 2]  # by time: 0.5 s / 0.2, 1 s / 0.5, 3 s / 0.9


PEAKS = """
import numpy as np
from e3cm_bench.ground.cost import measured
with measured() as small:
    pass
with measured() as big:
    block = np.ones(64 * 2**20 // 8)  # 64 MiB touched
    del block
with measured() as after:  # the mark was reset: the block freed above is not this block's peak
    pass
print(small.own_peak and big.own_peak, small.peak_mb, big.peak_mb, after.peak_mb)
"""


def test_a_pairs_peak_is_its_own():
    # a fresh process: in this one, an earlier run's kept heap (keep_freed_memory) would serve the
    # block from pages already resident, and the peak would not move
    import subprocess
    import sys

    own, small, big, after = subprocess.run([sys.executable, "-c", PEAKS], capture_output=True, text=True,
                                            check=True).stdout.split()
    if own != "True":
        pytest.skip("the resident high-water mark cannot be reset here (no /proc/self/clear_refs)")
    assert float(big) >= float(small) + 50 and float(after) < float(big) - 50


def test_the_cost_summary_means_seconds_with_an_interval_and_keeps_the_highest_peak():
    costs = [{"match_seconds": s, "peak_memory_mb": p, "gpu_peak_memory_mb": np.nan}
             for s, p in ((1.0, 900.0), (2.0, 1200.0), (3.0, 1000.0))]
    out = cost_summary(costs)
    assert out["seconds_per_pair"] == pytest.approx(2.0) and out["peak_memory_mb"] == 1200.0
    assert 1.0 <= out["seconds_per_pair_lo"] <= 2.0 <= out["seconds_per_pair_hi"] <= 3.0
    assert "gpu_peak_memory_mb" not in out
    assert cost_summary([{"match_seconds": np.nan, "peak_memory_mb": np.nan, "gpu_peak_memory_mb": np.nan}]) == {}


@pytest.fixture(scope="module")
def two_runs(shared_data: Path, tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("cost")
    runs = []
    for matcher in ("sift", "direct"):
        out = root / matcher
        args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", matcher,
                "--max-side", 240, "--limit", 4]
        if matcher == "direct":
            args += ["--backbone", "efficientnet_lite0"]
        result = invoke(*args)
        assert result.exit_code == 0, result.output
        runs.append(out)
    return runs


def test_each_run_writes_its_pairs_cost_and_its_summary_holds_it(two_runs):
    for run in two_runs:
        folder = RunFolder(run)
        cost = pd.read_csv(folder.cost_path)
        assert list(cost.columns[:3]) == ["pair", "match_seconds", "peak_memory_mb"] and len(cost) == 4
        assert (cost["match_seconds"] > 0).all() and (cost["peak_memory_mb"] > 50).all()
        summary = pd.read_csv(folder.summary_path).iloc[0]
        assert summary["seconds_per_pair"] == pytest.approx(cost["match_seconds"].mean(), rel=1e-5)
        assert summary["peak_memory_mb"] == pytest.approx(cost["peak_memory_mb"].max(), rel=1e-5)
        assert "match_seconds" not in pd.read_csv(folder.per_pair_path).columns  # per_pair.csv: accuracy only


def test_the_table_and_the_report_show_the_cost(two_runs, tmp_path):
    result = invoke("table", *two_runs, "--out", tmp_path / "t", "--no-paper")
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "t.csv")
    assert {"seconds_per_pair", "seconds_per_pair_lo", "seconds_per_pair_hi", "peak_memory_mb"} <= set(table.columns)
    result = invoke("report", *two_runs, "--out", tmp_path / "report")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "report" / "img" / "cost_accuracy.png").is_file()
    assert "img/cost_accuracy.png" in (tmp_path / "report" / "index.html").read_text()
