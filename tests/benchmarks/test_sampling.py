"""--sample N [--sample-seed S]: a stratified, seeded sample of a benchmark's pairs;
--limit keeps taking the first N; --viz draws a spread; WxBS and EVD run under
their reference protocol by default."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.datasets.base import Pair, stratified_sample, stratum
from e3cm_bench.drawing.matches import drawn_pairs
from helpers import invoke, one_line_error


def _pairs(groups: dict[str, int], key: str = "category") -> list[Pair]:
    return [Pair(f"{g}/{k}", Path("a"), Path("b"), meta={key: g}) for g, n in groups.items() for k in range(n)]


def test_a_sample_spreads_over_the_strata_and_is_deterministic():
    # As WxBS's test set: six categories of very different sizes, sorted by category.
    pairs = _pairs({"WGABS": 5, "WGALBS": 9, "WGBS": 6, "WGLBS": 9, "WGSBS": 2, "WLABS": 2})
    first3 = {p.category for p in pairs[:3]}
    assert first3 == {"WGABS"}  # what --limit 3 takes: one category
    sample = stratified_sample(pairs, 3, seed=0)
    assert len({p.category for p in sample}) == 3  # three categories, one pair each
    six = stratified_sample(pairs, 6, seed=0)
    assert Counter(p.category for p in six) == Counter({c: 1 for c in ("WGABS", "WGALBS", "WGBS", "WGLBS",
                                                                                "WGSBS", "WLABS")})
    # deterministic given the seed, another seed draws other pairs, and the order is the dataset's
    assert [p.name for p in stratified_sample(pairs, 6, seed=0)] == [p.name for p in six]
    assert any([p.name for p in stratified_sample(pairs, 6, seed=s)] != [p.name for p in six] for s in (1, 2, 3))
    assert [p.name for p in six] == [p.name for p in pairs if p in six]
    # every pair once at most; n past the size is every pair
    assert len({p.name for p in stratified_sample(pairs, 20, 5)}) == 20
    assert stratified_sample(pairs, 99, 0) == pairs


def test_hpatches_strata_put_both_kinds_in_a_sample():
    pairs = [Pair(f"{s}/1-{k}", Path("a"), Path("b"), meta={"sequence": s})
             for s in ("i_ajuntament", "i_boutique", "i_castle", "v_adam", "v_bird") for k in range(2, 7)]
    assert stratum(pairs[0]) == ("i", "i_ajuntament")
    for seed in range(5):
        kinds = sorted(p.sequence[0] for p in stratified_sample(pairs, 2, seed))
        assert kinds == ["i", "v"]
        # 4 pairs: 4 different sequences (two of each kind), not 4 pairs of one
        assert len({p.sequence for p in stratified_sample(pairs, 4, seed)}) == 4
    assert stratum(Pair("x", Path("a"), Path("b"))) == ()  # EVD: one group, a seeded random draw


def test_viz_draws_a_spread_not_the_first_pairs():
    pairs = [Pair(f"{s}/1-{k}", Path("a"), Path("b"), meta={"sequence": s})
             for s in ("i_a", "i_b", "i_c", "v_a", "v_b") for k in range(2, 7)]
    drawn = drawn_pairs(pairs, 3)
    assert {p.sequence[0] for p in drawn} == {"i", "v"} and len({p.sequence for p in drawn}) == 3
    assert drawn == drawn_pairs(pairs, 3) and drawn_pairs(pairs, 0) == []


def test_sampled_pair_list_records_its_sample(wxbs_root):
    bench = get_benchmark("wxbs")
    full = bench.load_dataset(wxbs_root)
    sample = bench.load_dataset(wxbs_root, sample=6, sample_seed=3)
    assert len(sample) == 6 and len({p.category for p in sample}) == 6
    assert sample.describe()["sample"] == {"n": 6, "seed": 3, "from": len(full), "strata": 6}
    assert "sample" not in full.describe()  # an unsampled run's record is unchanged
    assert [p.name for p in bench.load_dataset(wxbs_root, sample=6, sample_seed=3)] == [p.name for p in sample]
    with pytest.raises(ValueError, match="--sample must be a whole number, at least 1"):
        bench.load_dataset(wxbs_root, sample=0)


def test_wxbs_command_samples_and_uses_the_reference_protocol_by_default(wxbs_root, tmp_path):
    out = tmp_path / "run"
    result = invoke("wxbs", "--root", wxbs_root, "--matcher", "sift", "--sample", "3", "--sample-seed", "1",
                    "--out", out, "--viz", "2")
    assert result.exit_code == 0, result.output
    assert "protocol wxbs on wxbs:" in result.output and "PROTOCOLS.md" not in result.output
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["evaluation"]["protocol"] == "wxbs" and config["evaluation"]["opencv_method"] == "magsac"
    assert config["dataset"]["sample"] == {"n": 3, "seed": 1, "from": 31, "strata": 6}
    assert config["dataset_load"]["options"] == {"sample": 3, "sample_seed": 1}
    import pandas as pd

    per_pair = pd.read_csv(out / "per_pair.csv")
    assert len(per_pair) == 3 and per_pair["category"].nunique() == 3
    assert len(list((out / "viz").glob("*.png"))) == 2
    # --protocol default is still there: e3cm-bench's own estimator, named so in the record
    ev = get_benchmark("wxbs").resolve_eval("default")
    assert ev.protocol == "default" and ev.opencv_method == "ransac"
    assert get_benchmark("evd").resolve_eval().protocol == "wxbs"
    assert get_benchmark("hpatches").resolve_eval().protocol == "default"


def test_sample_option_errors_are_one_line(tmp_path, shared_data):
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift",
                                 "--sample", "0", "--out", tmp_path / "r"))
    assert "--sample must be a whole number, at least 1" in line


def test_hpatches_sample_holds_both_kinds(shared_data):
    bench = get_benchmark("hpatches")
    root = shared_data / "hpatches-sequences-release"
    first = bench.load_dataset(root)
    assert {p.sequence[0] for p in list(first)[:3]} == {"i"}  # the first 3: illumination only
    for seed in range(3):
        sample = bench.load_dataset(root, sample=3, sample_seed=seed)
        assert {p.sequence[0] for p in sample} == {"i", "v"}
    assert {p.name for p in sample} <= {p.name for p in first}
