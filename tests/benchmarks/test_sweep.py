"""The two-view protocol sweep (issue 69, item 4): cached matches scored again under each
estimator x threshold, rankings with intervals, Kendall's tau against the runs' own cell, flips
with paired intervals, thresholds tuned on a half of the pairs disjoint from the reported one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.pipeline import sweep as sweeping
from helpers import invoke, one_line_error

pytestmark = pytest.mark.slow  # two matched runs and a 7-cell sweep: about 30 s

pytest.importorskip("poselib")
pytest.importorskip("pycolmap")
pytest.importorskip("scipy")


@pytest.fixture(scope="module")
def kitti_runs(shared_data: Path, tmp_path_factory) -> tuple[Path, Path]:
    where = tmp_path_factory.mktemp("sweep")
    root = shared_data / "megadepth_test_1500"
    runs = []
    for name, extra in (("sift", []), ("sift-weak", ["--label", "sift-weak", "--set", "max_keypoints=300"])):
        out = where / name
        result = invoke("megadepth", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz",
                        "--matcher", "sift", "--limit", 6, "--max-side", 640, "--out", out, *extra)
        assert result.exit_code == 0, result.output
        runs.append(out)
    return tuple(runs)


@pytest.fixture(scope="module")
def swept(kitti_runs, tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("swept") / "sweep"
    result = invoke("sweep", *kitti_runs, "--out", out, "--estimators", "opencv-ransac,opencv-magsac,poselib,pycolmap",
                    "--thresholds", "0.5px,2px", "--seeds", 2, "--tune")
    assert result.exit_code == 0, result.output
    return out, result


def test_the_default_cell_reproduces_each_runs_own_numbers(kitti_runs, swept):
    out, _ = swept
    cells = pd.read_csv(out / "cells" / "opencv-ransac_0.5px.csv")
    keys = {Path(r["folder"]).name: r["key"] for r in yaml.safe_load((out / "sweep.yaml").read_text())["runs"]}
    for run in kitti_runs:
        own = pd.read_csv(run / "per_pair.csv")
        # seed 0 of the runs' own cell is the run's own evaluation, pair for pair (a run's columns
        # are named by its key: identity, fingerprint and folder, issue 81)
        assert np.allclose(cells[f"{keys[run.name]}_s0"].to_numpy(), own["err_pose"].to_numpy(), equal_nan=True)


def test_the_sweep_writes_rankings_taus_and_flips(swept):
    out, result = swept
    table = pd.read_csv(out / "sweep.csv")
    cells = set(table["cell"])
    assert {"opencv-ransac 0.5px", "opencv-magsac 2px", "poselib 0.5px", "pycolmap 2px"} <= cells
    assert {"opencv-ransac tuned", "poselib tuned", "pycolmap tuned"} <= cells
    assert (table["auc@10_lo"] <= table["auc@10"] + 1e-9).all() and (table["auc@10"] <= table["auc@10_hi"] + 1e-9).all()
    taus = pd.read_csv(out / "tau.csv")
    assert taus.loc[taus["cell"] == "opencv-ransac 0.5px", "kendall_tau"].iloc[0] == pytest.approx(1.0)
    flips = pd.read_csv(out / "flips.csv")
    assert list(flips.columns[:3]) == ["cell", "a", "b"]
    assert (out / "ranks.png").stat().st_size > 1000 and "Kendall tau" in (out / "sweep.md").read_text()
    record = (out / "sweep.yaml").read_text()
    assert "fingerprint" in record and "sha256 is even" in record


def test_tuned_thresholds_are_chosen_on_the_other_half(swept):
    out, _ = swept
    table = pd.read_csv(out / "sweep.csv")
    names = pd.read_csv(out / "cells" / "opencv-ransac_0.5px.csv")["pair"].tolist()
    tune, report = sweeping.split_pairs(names)
    assert tune.any() and report.any() and not (tune & report).any()
    # with --tune every cell is reported on the report half only
    assert set(table["n_pairs"]) == {int(report.sum())}
    chosen = (out / "cells" / "opencv-ransac_tuned.yaml").read_text()
    assert "thresholds_px" in chosen


def test_a_sweep_resumes_from_its_cells(kitti_runs, swept):
    out, _ = swept
    again = invoke("sweep", *kitti_runs, "--out", out, "--estimators", "opencv-ransac,opencv-magsac,poselib,pycolmap",
                   "--thresholds", "0.5px,2px", "--seeds", 2, "--tune")
    assert again.exit_code == 0 and "pairs x 2 seed(s)" not in again.output  # nothing scored again


def test_kendall_tau_and_ranks():
    assert sweeping.ranks({"a": 3.0, "b": 5.0, "c": 3.0}) == {"a": 2, "b": 1, "c": 2}
    tau, _ = sweeping.kendall_tau({"a": 1, "b": 2, "c": 3}, {"a": 3, "b": 2, "c": 1})
    assert tau == pytest.approx(-1.0)


@pytest.mark.parametrize("option, value, words", [
    ("--estimators", "opencv-lmeds", "unknown estimator 'opencv-lmeds'"),
    ("--estimators", "poselib-magsac", "unknown estimator 'poselib-magsac'"),
    ("--thresholds", "-1px", "'-1px' is no threshold"),
    ("--thresholds", "1cm", "'1cm' is no threshold"),
    ("--seeds", "0", "--seeds 0: give 1 to 20"),
    ("--metric", "maa", "--metric 'maa'"),
])
def test_bad_options_get_one_line(kitti_runs, tmp_path, option, value, words):
    line = one_line_error(invoke("sweep", *kitti_runs, "--out", tmp_path / "s", option, value))
    assert words in line


def test_sweep_refuses_other_benchmarks_and_one_run(kitti_runs, shared_data, tmp_path):
    assert "at least two runs" in one_line_error(invoke("sweep", kitti_runs[0], "--out", tmp_path / "s"))
    homography = tmp_path / "h"
    assert invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift", "--limit", 1,
                  "--max-side", 240, "--out", homography).exit_code == 0
    line = one_line_error(invoke("sweep", kitti_runs[0], homography, "--out", tmp_path / "s"))
    assert "hpatches run; the sweep re-scores two-view pose runs" in line
