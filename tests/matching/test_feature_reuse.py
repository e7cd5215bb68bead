"""Two-stage matchers: each image's features extracted once per run and every pair matched from
them (matchers/two_stage.py, the feature cache) gives per_pair.csv byte for byte as the pair by
pair path (--no-feature-reuse), with one extraction per distinct image; a matcher with only
match() runs as it did."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers import Features, Matcher, MatcherEntry, build_matcher, register, unregister
from e3cm_bench.matchers.base import splits
from e3cm_bench.matchers.feature_cache import FeatureCache
from e3cm_bench.matchers.spill import SpillStore
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.runner import run_benchmark
from e3cm_bench.pipeline.match_options import MatchOptions
from helpers import replay_stage, same_csvs

REPO = Path(__file__).resolve().parents[2]
SEQUENCES = ["i_leuven", "v_boat"]  # 10 pairs over 12 images
CLASSICAL = ["sift", "colmap-sift", "orb"]
PEERS = ["xfeat", "xfeat-star", "xfeat+lighterglue", "aliked+lightglue", "disk+lightglue", "superpoint+lightglue"]


@pytest.fixture
def orb(monkeypatch):
    """The example plugin (examples/plugin), registered from its source."""
    monkeypatch.syspath_prepend(str(REPO / "examples" / "plugin" / "src"))
    importlib.invalidate_caches()
    entry = register(importlib.import_module("e3cm_bench_orb").ENTRY, replace=True)
    yield entry
    unregister("orb")


def two_runs(shared_data, tmp_path, matcher: str, cache_mb: float | None = None) -> dict:
    """The same HPatches pairs with and without feature reuse; per_pair.csv compared byte for
    byte; returns the reuse run's feature_reuse record."""
    hp = get_benchmark("hpatches")
    dataset = hp.load_dataset(shared_data / "hpatches-sequences-release", sequences=SEQUENCES)
    method = MethodSpec.create(matcher, max_side=240)
    run_benchmark(hp, tmp_path / "reuse", method, dataset=dataset, options=MatchOptions(feature_cache_mb=cache_mb))
    run_benchmark(hp, tmp_path / "pairwise", method, dataset=dataset, options=MatchOptions(feature_reuse=False))
    same_csvs(tmp_path / "reuse", tmp_path / "pairwise")
    assert "feature_reuse" not in yaml.safe_load((tmp_path / "pairwise" / "config.yaml").read_text())
    return yaml.safe_load((tmp_path / "reuse" / "config.yaml").read_text())["feature_reuse"]


@pytest.mark.parametrize("matcher", CLASSICAL)
def test_a_classical_two_stage_matcher_extracts_each_image_once_and_matches_as_pair_by_pair(
        matcher, shared_data, tmp_path, orb):
    if matcher == "colmap-sift":
        pytest.importorskip("pycolmap", reason="colmap-sift needs pycolmap (the colmap extra)")
    reuse = two_runs(shared_data, tmp_path, matcher)
    assert reuse["extractions"] == reuse["distinct_images"] == 12 and reuse["reused"] == 8


@pytest.mark.slow  # each: two runs of 10 pairs of a network on the CPU (10-40 s under load)
@pytest.mark.parametrize("matcher", PEERS)
def test_a_peer_extracts_each_image_once_and_matches_as_pair_by_pair(matcher, shared_data, tmp_path):
    pytest.importorskip("kornia")
    try:
        reuse = two_runs(shared_data, tmp_path, matcher)
    except ValueError as error:  # offline without the weights (SuperPoint's come from the Hugging Face hub)
        if "could not be downloaded" not in str(error):
            raise
        pytest.skip(str(error))
    assert reuse["extractions"] == reuse["distinct_images"] == 12


def test_features_memory_cannot_hold_wait_on_disk_and_change_no_match(shared_data, tmp_path):
    """With memory for no image's features, SIFT's numpy features go to the run folder between
    the pairs of their image and come back from it, array for array."""
    reuse = two_runs(shared_data, tmp_path, "sift", cache_mb=0.001)
    assert reuse["extractions"] == 12 and reuse["read_from_disk"] == 8 and reuse["peak_memory_mb"] == 0


def features(seed: int) -> Features:
    gen = np.random.default_rng(seed)
    return Features(points=gen.random((50, 2), dtype=np.float32), descriptors=gen.integers(0, 255, (50, 32), np.uint8),
                    size=(640, 480), none=None)


def test_spilled_features_come_back_as_they_were_and_others_stay_in_memory(tmp_path):
    spill = SpillStore(tmp_path / "spill", 1.0)
    cache = FeatureCache(0.0001, spill)  # holds nothing in memory: everything needed again goes to disk
    files = [("a", "b"), ("b", "c"), ("a", "c")]
    replay_stage(cache, files, lambda file: features(ord(file)))
    assert cache.misses == 3 and cache.hits == 3 and spill.reads == 3
    written = features(7)
    assert spill.write("x", written)
    back = spill.read("x", "cpu")
    assert isinstance(back, Features) and back.keys() == written.keys() and back["size"] == (640, 480)
    assert all(np.array_equal(back[k], written[k]) and back[k].dtype == written[k].dtype for k in ("points", "descriptors"))
    assert not spill.write("y", Features(handle=object()))  # a library's object cannot wait on disk


class OnlyMatch(Matcher):
    """A matcher with one method, match(), as plugins and dense matchers are written."""

    name = "only-match"

    def match(self, image0, image1):
        points = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
        return Matches(points, points, np.ones(2))


def test_a_matcher_with_only_match_runs_pair_by_pair_as_before(shared_data, tmp_path):
    assert not splits(OnlyMatch()) and splits(build_matcher("sift"))
    register(MatcherEntry("only-match", "match() only", build=lambda settings: OnlyMatch()), replace=True)
    try:
        hp = get_benchmark("hpatches")
        dataset = hp.load_dataset(shared_data / "hpatches-sequences-release", sequences=["v_boat"])
        run_benchmark(hp, tmp_path / "run", MethodSpec.create("only-match", max_side=240), dataset=dataset)
    finally:
        unregister("only-match")
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert "feature_reuse" not in config
    assert (tmp_path / "run" / "per_pair.csv").read_text().count("\n") == 6  # a header and 5 pairs
