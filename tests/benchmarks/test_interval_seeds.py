"""RANSAC's spread in the two-view interval by default (issue 69, item 5): the interval holds
several RANSAC seeds (each bootstrap resample of the pairs takes one), the run's numbers stay its
own seed's, a reference's protocol keeps one evaluation, and the fingerprint does not move."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.benchmarks.base import Benchmark
from e3cm_bench.datasets.base import Pair, PairList
from e3cm_bench.ground.matches import Matches
from e3cm_bench.pipeline.evaluate import evaluate_stage
from helpers import invoke, one_line_error


@dataclass(frozen=True)
class SeedEcho(Benchmark):
    """A benchmark whose every pair scores its evaluation's seed: what each seed contributes to
    the interval is then known exactly."""

    def pair_columns(self, ev):
        return ["pair", "x"]

    def evaluate_pair(self, pair, matches, ev):
        return {"pair": pair.name, "x": float(ev.seed)}

    def summarize(self, rows, ev):
        return {"n_pairs": len(rows), "x": float(np.mean([r["x"] for r in rows]))}


class Cache:
    def read(self, name):
        return Matches(np.zeros((1, 2), np.float32), np.zeros((1, 2), np.float32), np.ones(1, np.float32), {})


@pytest.mark.parametrize("seeds, bounds", [(1, (0.0, 0.0)), (3, (0.0, 2.0))])
def test_the_interval_holds_the_seeds_and_the_number_is_the_runs_own(seeds, bounds):
    bench = SeedEcho(name="echo", dataset=PairList)
    pairs = [Pair(f"p{k}", Path("a"), Path("b")) for k in range(8)]
    _, summary, _ = evaluate_stage(bench, pairs, Cache(), EvalSettings(seed=0, interval_seeds=seeds))
    assert summary["x"] == 0.0  # seed 0's, whatever the interval holds
    assert (summary["x_lo"], summary["x_hi"]) == bounds
    assert summary.get("interval_seeds", 1) == seeds


def test_defaults_follow_the_protocol():
    assert get_benchmark("hpatches").resolve_eval().interval_seeds == 3
    assert get_benchmark("megadepth").resolve_eval().interval_seeds == 3
    assert get_benchmark("yfcc").resolve_eval("superglue").interval_seeds == 1  # the reference evaluates once
    assert get_benchmark("wxbs").resolve_eval().interval_seeds == 1  # its default protocol is wxbs-benchmark's
    assert get_benchmark("sfm").resolve_eval().interval_seeds == 1  # its mapper seeds are its interval's
    assert get_benchmark("hpatches").resolve_eval(interval_seeds=5).interval_seeds == 5
    with pytest.raises(ValueError, match="--interval-seeds must be 1 to 20"):
        EvalSettings(interval_seeds=0)


def test_a_run_keeps_its_numbers_and_fingerprint_whatever_its_interval_holds(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    args = ["hpatches", "--root", root, "--matcher", "sift", "--limit", 4]
    assert invoke(*args, "--out", tmp_path / "three").exit_code == 0
    assert invoke(*args, "--out", tmp_path / "one", "--interval-seeds", 1).exit_code == 0
    three, one = (pd.read_csv(tmp_path / name / "summary.csv").iloc[0] for name in ("three", "one"))
    assert three["interval_seeds"] == 3 and "interval_seeds" not in one
    for metric in ("h_acc@1", "h_acc@3", "mma@3"):
        assert three[metric] == one[metric]
    assert three["fingerprint"] == one["fingerprint"]
    line = one_line_error(invoke(*args, "--out", tmp_path / "bad", "--interval-seeds", 21))
    assert "--interval-seeds must be 1 to 20" in line
