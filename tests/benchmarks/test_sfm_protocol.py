"""The sfm benchmark's protocol (sfm/protocol.py): the mapper, its seeds in the interval, the
keypoint merge's per-matcher default and hloc's quantization, COLMAP's verification, the
largest-model rule, bags, and `compare` over pairs and seeds. On the synthetic room
(e3cm_bench/apps/synth/multiview.py) with SIFT: 6 views, a window of 2 (9 pairs), seconds per
reconstruction."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.interchange import tracks
from e3cm_bench.sfm import metrics as sfm_metrics
from e3cm_bench.sfm.benchmark import SFM
from e3cm_bench.sfm.protocol import DENSE_MERGE_PX, ReconstructionProtocol, keypoints_are_detections, protocol_of
from e3cm_bench.stats import compare_paired
from helpers import invoke

pycolmap = pytest.importorskip("pycolmap", reason="the sfm benchmark needs pycolmap (the colmap extra)")


# ----------------------------------------------------------------------------- pure parts


def test_merge_default_follows_the_matchers_kind():
    assert keypoints_are_detections("sift") is True
    for dense in ("e3cm", "e3cm-ransac", "e3cm-plus", "e3cm-release", "direct", "dfm"):
        assert keypoints_are_detections(dense) is False, dense
    assert keypoints_are_detections("no-such-matcher") is None
    auto = ReconstructionProtocol()
    assert auto.resolved(True).merge == "exact" and auto.resolved(True).merge_px == 0
    assert auto.resolved(False).merge == "radius" and auto.resolved(False).merge_px == DENSE_MERGE_PX
    assert auto.resolved(None).merge_px == DENSE_MERGE_PX  # unknown kind: the dense default
    # --merge-px overrides the default, for either kind (the evaluation's settings, as sfm resolves them)
    ev = SFM.resolve_eval(None, 0, {"merge_px": 1.5})
    assert protocol_of(ev).resolved(True).merge_px == 1.5
    assert protocol_of(SFM.resolve_eval(None, 0, {"merge_px": 0})).resolved(False).merge == "exact"
    assert protocol_of(SFM.resolve_eval(None, 0, {"merge": "quantize"})).resolved(True).merge == "quantize"


@pytest.mark.parametrize("option, value, flag", [("mapper", "sequential", "--mapper"), ("mapper_seeds", 0, "--mapper-seeds"),
                                                 ("merge", "near", "--merge"), ("verification", "magsac", "--verification"),
                                                 ("score_model", "best", "--score-model"), ("merge_px", -2, "--merge-px")])
def test_bad_protocol_values_are_one_line(option, value, flag):
    with pytest.raises(ValueError, match=flag):
        SFM.resolve_eval(None, 0, {option: value})


def test_quantize_merges_within_a_cell_and_the_max_error():
    # image a: (1, 1) then (3.5, 3.5) share the cell [0, 4)^2 and are 3.5 px apart: merged;
    # (4.2, 1) is in the next cell: its own; with max error 2 the second stays apart
    k0 = np.array([[1.0, 1.0], [3.5, 3.5], [4.2, 1.0]])
    k1 = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]])
    keypoints, pairs = tracks.merge_keypoints([("a", "b", k0, k1)], cell=4.0, max_error=4.0)
    assert keypoints["a"].tolist() == [[1.0, 1.0], [4.2, 1.0]] and pairs[0][:, 0].tolist() == [0, 0, 1]
    keypoints, _ = tracks.merge_keypoints([("a", "b", k0, k1)], cell=4.0, max_error=2.0)
    assert len(keypoints["a"]) == 3
    moved = tracks.merge_displacement([("a", "b", k0, k1)], *tracks.merge_keypoints([("a", "b", k0, k1)], cell=4.0))
    assert moved == pytest.approx(np.hypot(2.5, 2.5) / 6)


def test_repeat_share_counts_locations_another_pair_also_matched():
    a_with_b = np.array([[0.0, 0.0], [10.0, 10.0]])
    a_with_c = np.array([[0.0, 0.0], [11.5, 10.0]])
    items = [("a", "b", a_with_b, a_with_b + 50), ("a", "c", a_with_c, a_with_c + 80)]
    # image a: 4 locations, (0, 0) repeated twice exactly; b and c have one pair each
    assert tracks.repeat_share(items, 0.0) == pytest.approx(2 / 8)
    assert tracks.repeat_share(items, 2.0) == pytest.approx(4 / 8)


def test_two_level_interval_holds_the_seeds_spread():
    """30 pairs all right in two seeds, all failed in the third: resampling pairs only gives a
    point; resampling the seeds too gives the seeds' spread."""
    errors = np.tile([1.0, 1.0, np.inf], (30, 1))
    n_matches = np.full(30, 100.0)
    from e3cm_bench.stats import bootstrap_interval

    pairs_only = bootstrap_interval(list(range(30)), lambda idx: sfm_metrics.summarize_seeds(errors[idx], n_matches),
                                    keys=["auc@10"])
    both = bootstrap_interval(list(range(30)), sfm_metrics.two_level_summary(errors, n_matches), keys=["auc@10"])
    assert pairs_only["auc@10"][0] == pairs_only["auc@10"][1]
    assert both["auc@10"][0] < 40 and both["auc@10"][1] > 80


def test_compare_over_pairs_and_seeds():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 5, (40, 3))
    same = compare_paired(a, a.copy(), "err_pose", higher_is_better=False, statistic="median")
    assert same.diff == 0 and same.verdict == "no difference detectable"
    worse = compare_paired(a, a + 3.0, "err_pose", higher_is_better=False, statistic="median")
    assert worse.verdict == "A better" and worse.n == 40
    # a method whose one seed in three fails everywhere is not called better on its good seeds
    flaky = a.copy()
    flaky[:, 2] = np.inf
    passes_a, passes_b = (a < 10).astype(float), (flaky < 10).astype(float)
    result = compare_paired(passes_a, passes_b, "err_pose<10", statistic="mean")
    assert result.diff == pytest.approx(-1 / 3) and result.hi >= result.lo


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> tuple[Path, Path]:
    from e3cm_bench.apps.synth.multiview import write_multiview

    root = tmp_path_factory.mktemp("room")
    return root, write_multiview(root, n_views=6)


def room_args(room) -> list:
    root, scene_info = room
    return ["sfm", "--root", root, "--scene-info", scene_info, "--window", "2", "--matcher", "sift"]


@pytest.fixture(scope="module")
def incremental_run(room, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sfm-protocol") / "sift"
    result = invoke(*room_args(room), "--mapper", "incremental", "--mapper-seeds", "2", "--out", out)
    assert result.exit_code == 0, result.output
    assert "mapper.log" in result.output  # says where COLMAP's log went
    return out


def test_mapper_and_seeds_recorded_and_used(incremental_run):
    config = yaml.safe_load((incremental_run / "config.yaml").read_text())
    assert config["evaluation"]["mapper"] == "incremental" and config["given"]["evaluation"]["mapper"] == "incremental"
    assert config["evaluation"]["mapper_seeds"] == 2 and "protocol" not in config["dataset"]
    assert config["dataset"]["reconstruction"]["global"]["method"] == "pycolmap.global_mapping"
    summary = pd.read_csv(incremental_run / "summary.csv").iloc[0]
    assert summary["mapper"] == "incremental" and summary["mapper_seeds"] == 2
    assert summary["merge"] == "exact"  # sift's keypoints are detections
    assert summary["registered_images"] >= 5 and summary["repeat_share"] > 0.3
    per_seed = pd.read_csv(incremental_run / "sfm" / "per_seed.csv")
    assert per_seed["seed"].tolist() == [0, 1]
    # the headline is the mean over the seeds of each seed's numbers
    assert summary["auc@10"] == pytest.approx(per_seed["auc@10"].mean(), abs=1e-4)
    assert summary["auc@10_lo"] <= summary["auc@10"] <= summary["auc@10_hi"]
    per_pair = pd.read_csv(incremental_run / "per_pair.csv")
    assert {"err_pose_s0", "err_pose_s1", "model_s1"} <= set(per_pair.columns)
    assert (incremental_run / "sfm" / "models").is_dir() and (incremental_run / "sfm" / "seed-1" / "models").is_dir()
    assert per_pair["bag"].eq(0).all()  # one bag: the graph is connected
    # each seed verified the pairs with its own draw (evaluate.py): seed 1's database differs
    def inliers(database):
        with pycolmap.Database.open(str(database)) as db:
            return sorted(len(g.inlier_matches) for g in db.read_two_view_geometries()[1])
    assert inliers(incremental_run / "sfm" / "database.db") != inliers(incremental_run / "sfm" / "seed-1" / "database.db")
    log = (incremental_run / "sfm" / "mapper.log").read_text()
    assert "Registering image" in log or "registered" in log.lower(), log[:500]
    assert "Could not read image" not in log  # the mapper is given the images' folder (evaluate.image_root)


def test_eval_only_with_another_protocol_on_the_same_matches(room, incremental_run, tmp_path):
    copy = tmp_path / "global"
    shutil.copytree(incremental_run, copy)
    result = invoke(*room_args(room), "--out", copy, "--eval-only", "--mapper", "global", "--mapper-seeds", "1",
                    "--verification", "colmap", "--merge", "quantize", "--score-model", "largest")
    assert result.exit_code == 0, result.output
    summary = pd.read_csv(copy / "summary.csv").iloc[0]
    assert summary["mapper"] == "global" and summary["verification"] == "colmap"
    assert summary["merge"].startswith("quantize") and summary["score_model"] == "largest"
    assert summary["registered_images"] >= 5
    per_pair = pd.read_csv(copy / "per_pair.csv")
    assert "err_pose_s1" not in per_pair.columns
    # COLMAP's verification, not the estimator's: inlier counts differ from the first run's
    before = pd.read_csv(incremental_run / "per_pair.csv")
    assert not per_pair["n_inliers"].equals(before["n_inliers"])
    with pycolmap.Database.open(str(copy / "sfm" / "database.db")) as db:
        assert db.num_verified_image_pairs() >= 8
    # compare pairs the two runs over pairs and seeds
    result = invoke("compare", incremental_run, copy)
    assert result.exit_code == 0, result.output
    assert "err_pose" in result.output and "seeds" in result.output


def test_bags_are_reconstructed_apart(room, tmp_path):
    """Two bags (pair.bag, set where the graph splits): one folder and one database each,
    every pair scored in its own bag's reconstruction."""
    from e3cm_bench.ground.images import load_image
    from e3cm_bench.matchers.sift import SiftMatcher

    root, scene_info = room
    dataset = get_benchmark("sfm").load_dataset(root, scene_info=scene_info, window="1")
    chosen = [p for p in dataset if not p.view0.endswith("02.png")]  # 0-1-2 | 3-4-5: no pair 2-3
    for pair in chosen:
        pair.bag = 0 if pair.view0 < "images/view02.png" else 1
    matcher = SiftMatcher(4000, 0.8, False)
    matches = [matcher.match(load_image(p.image0), load_image(p.image1)) for p in chosen]
    ev = get_benchmark("sfm").resolve_eval(given={"mapper_seeds": 1})
    rows, numbers = get_benchmark("sfm").evaluate_set(chosen, matches, ev, tmp_path)
    assert (tmp_path / "sfm" / "bag-0" / "database.db").is_file() and (tmp_path / "sfm" / "bag-1" / "database.db").is_file()
    with pycolmap.Database.open(str(tmp_path / "sfm" / "bag-0" / "database.db")) as db:
        assert db.num_images() == 3
    assert all(np.isfinite(r["err_pose"]) for r in rows), rows
    assert numbers["n_images"] == 6 and numbers["registered_images"] == 6


def test_one_mapper_table_for_sfm_and_reconstruct():
    """sfm (a set's ground-truth K) and reconstruct (a folder's own images) take the incremental
    mapper's options from one table (sfm/mapper.py): the same choices for both, the
    intrinsics fixed and the colours skipped only where the set is calibrated."""
    pytest.importorskip("pycolmap")
    from e3cm_bench.sfm.mapper import mapper_options

    calibrated, own = mapper_options(7), mapper_options(7, calibrated=False)
    for options in (calibrated, own):
        assert options.min_model_size == 3 and options.num_threads == 1 and options.mapper.num_threads == 1
        assert options.mapper.init_min_tri_angle == 4.0
        assert options.random_seed == options.mapper.random_seed == options.triangulation.random_seed == 7
    assert not calibrated.ba_refine_focal_length and not calibrated.mapper.abs_pose_refine_focal_length
    assert not calibrated.extract_colors
    assert own.ba_refine_focal_length and own.ba_refine_extra_params and own.extract_colors
    # the global mapper too: sfm's choices, but reconstruct's unknown intrinsics refined (pycolmap's default)
    fixed, free = mapper_options(7, "global"), mapper_options(7, "global", calibrated=False)
    assert not fixed.mapper.bundle_adjustment.refine_focal_length and free.mapper.bundle_adjustment.refine_focal_length
    assert free.num_threads == free.mapper.num_threads == 1 and free.mapper.random_seed == 7
