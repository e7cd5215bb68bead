"""The multi-view interval resamples bags, then their pairs (issue 69): a bag's pairs share one
reconstruction, so their luck is shared; resampling only pairs called it signal."""

from __future__ import annotations

import numpy as np
import pytest

from e3cm_bench import stats
from e3cm_bench.sfm import metrics as sfm_metrics
from e3cm_bench.stats.paired import NO_DIFFERENCE
from e3cm_bench.stats.bootstrap import bootstrap_interval, groups_of, nested_resample


def test_groups_of():
    found = groups_of([2, 2, 0, 0, 0, 2])
    assert [g.tolist() for g in found] == [[0, 1, 5], [2, 3, 4]]  # first-seen order
    assert groups_of([1, 1, 1]) is None and groups_of(None) is None


def test_nested_resample_draws_whole_groups_then_rows():
    groups = [np.arange(0, 3), np.arange(3, 10)]
    rng = np.random.default_rng(0)
    sizes = set()
    for _ in range(50):
        drawn = nested_resample(groups, rng)
        # each drawn group contributes its own size: 3+3, 3+7 or 7+7 rows
        sizes.add(len(drawn))
        assert drawn.min() >= 0 and drawn.max() < 10
    assert sizes == {6, 10, 14}


def _two_bags(n: int = 40):
    """Bag 0 reconstructed well (every pair at 1 deg), bag 1 failed (every pair lost)."""
    errors = np.concatenate([np.full(n, 1.0), np.full(n, np.inf)])[:, None]
    return errors, np.full(2 * n, 100.0), np.repeat([0, 1], n)


def test_bags_widen_the_sfm_interval():
    errors, n_matches, bags = _two_bags()
    rows = list(range(len(errors)))
    pairs = bootstrap_interval(rows, sfm_metrics.two_level_summary(errors, n_matches), keys=["auc@10"])["auc@10"]
    nested = bootstrap_interval(rows, sfm_metrics.two_level_summary(errors, n_matches, bags=bags),
                                keys=["auc@10"])["auc@10"]
    # pairs alone: about 45 +- 8; two bags, one lost: anything from none to all of them
    assert pairs[1] - pairs[0] < 25
    assert nested[0] == pytest.approx(0.0) and nested[1] > 85  # all in bag 0: 1 deg each


def test_bags_are_read_from_rows():
    assert sfm_metrics.bags_of([{"bag": 0}, {"bag": "1"}]).tolist() == [0, 1]
    assert sfm_metrics.bags_of([{"pair": "a"}]) is None  # a run written before bags were recorded
    assert sfm_metrics.bags_of([{"bag": float("nan")}]) is None


def test_compare_pairs_bags_together():
    """B beats A by 2 deg in bag 0 and loses by 2 in bag 1: with the bags resampled the verdict
    may not name a winner from a bag's luck."""
    rng = np.random.default_rng(1)
    n = 30
    a = np.concatenate([np.full(n, 5.0), np.full(n, 5.0)]) + rng.normal(0, 0.1, 2 * n)
    b = np.concatenate([np.full(n, 3.0), np.full(n, 6.5)]) + rng.normal(0, 0.1, 2 * n)
    bags = np.repeat([0, 1], n)
    flat = stats.compare_paired(a, b, "err", higher_is_better=False)
    grouped = stats.compare_paired(a, b, "err", higher_is_better=False, resampling=stats.Resampling(groups=bags))
    assert flat.diff == grouped.diff
    assert (grouped.hi - grouped.lo) > 3 * (flat.hi - flat.lo)
    assert grouped.verdict == NO_DIFFERENCE
