"""The match stage's pair order (pair_order.reuse_order): every pair once, few images alive,
and, replayed through the feature cache (matchers/feature_cache.py), few backbone passes."""

from __future__ import annotations

import random
from pathlib import Path

import torch

from e3cm_bench.datasets.base import Pair
from e3cm_bench.matchers.feature_cache import FeatureCache
from e3cm_bench.matchers.spill import SpillStore
from e3cm_bench.pipeline.pair_order import most_alive, reuse_order
from helpers import replay_stage


def cache_passes(order: list[Pair], memory: int, spill: Path | None = None, disk: int = 0, planned: bool = True) -> int:
    """Backbone passes (the cache's misses) over `order` of a FeatureCache holding `memory`
    pyramids, and `disk` more in a SpillStore at `spill`, each pyramid a one-byte tensor; told
    the order (planned; else it evicts the least recently used) and after each pair which
    images have no pair left, as the match stage tells it."""
    files_in_order = [(str(pair.image0), str(pair.image1)) for pair in order]
    cache = FeatureCache(memory / 2**20, SpillStore(spill, disk / 2**20) if disk else None)
    replay_stage(cache, files_in_order, lambda image: [torch.zeros(1, dtype=torch.uint8)], plan=planned)
    cache.close()
    return cache.misses


def test_a_shuffled_chain_is_walked_with_two_images_alive():
    """Pairs (i, i+1) of a chain of 30 images, shuffled, plus a pair of an image with itself and
    a second component: the order is a permutation, deterministic, and never has more than
    two images alive (the chain's vertex separation is 1; the list's own order has ~10)."""
    pairs = [Pair(f"c{i}", Path(f"im{i:02d}"), Path(f"im{i + 1:02d}")) for i in range(29)]
    pairs += [Pair("self", Path("im07"), Path("im07")), Pair("other", Path("x"), Path("y"))]
    random.Random(0).shuffle(pairs)
    ordered = reuse_order(pairs)
    assert sorted(p.name for p in ordered) == sorted(p.name for p in pairs)
    assert [p.name for p in reuse_order(pairs)] == [p.name for p in ordered]
    assert most_alive(ordered) <= 2 < most_alive(pairs)
    # two pyramids held are enough: each image through the backbone once
    assert cache_passes(ordered, 2) == 32  # im00..im29, x and y


def test_on_the_yfcc_graph_the_default_budgets_pass_each_image_about_once(shared_data, tmp_path):
    """The real YFCC100M pair graph (4000 pairs, 1455 images): at most 1.2 backbone passes per
    image with what this machine's defaults hold of the largest pyramid of the tables (VGG19
    at 1200x900 in fp32, 509 MiB: 22 in memory, 60 on disk), where the list's own order with
    the least recently used pyramid evicted needs more than three (4555); and fewer images
    alive at once (101) than in the list's order (350)."""
    lines = (shared_data / "yfcc_test_pairs_with_gt.txt").read_text().splitlines()
    pairs = [Pair(str(k), Path(line.split()[0]), Path(line.split()[1])) for k, line in enumerate(lines) if line.strip()]
    images = len({str(p.image0) for p in pairs} | {str(p.image1) for p in pairs})
    ordered = reuse_order(pairs)
    assert sorted(int(p.name) for p in ordered) == list(range(len(pairs)))
    assert most_alive(ordered) < 0.3 * most_alive(pairs)
    planned = cache_passes(ordered, 22, tmp_path / "spill", 60)
    unplanned = cache_passes(pairs, 22, tmp_path / "spill-lru", 60, planned=False)
    assert planned <= 1.2 * images < 3 * images < unplanned
    # memory alone, small and large: fewer passes than the list's order with least-recently-used out
    for held in (4, 64):
        assert cache_passes(ordered, held) < cache_passes(pairs, held, planned=False)
