"""The match stage's pair order (pair_order.reuse_order): every pair once, few images alive."""

from __future__ import annotations

import importlib.util
import random
from pathlib import Path

from e3cm_bench.datasets.base import Pair
from e3cm_bench.pair_order import most_alive, reuse_order


def _script():
    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_pair_order.py"
    spec = importlib.util.spec_from_file_location("pair_order_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


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


def test_on_the_yfcc_graph_the_default_budgets_pass_each_image_about_once(shared_data):
    """The real YFCC100M pair graph (4000 pairs, 1455 images): at most 1.2 backbone passes per
    image with what this machine's defaults hold of the largest pyramid of the tables (VGG19
    at 1200x900 in fp32, 509 MiB: 22 in memory, 60 on disk), replaying the cache's policy,
    where the greedy walk it replaced needed 1.83; and far fewer images alive at once."""
    script = _script()
    lines = (shared_data / "yfcc_test_pairs_with_gt.txt").read_text().splitlines()
    pairs = [Pair(str(k), Path(line.split()[0]), Path(line.split()[1])) for k, line in enumerate(lines) if line.strip()]
    images = len({str(p.image0) for p in pairs} | {str(p.image1) for p in pairs})
    ordered = reuse_order(pairs)
    assert sorted(int(p.name) for p in ordered) == list(range(len(pairs)))
    walk = script.walk_order(pairs, 82)
    assert most_alive(ordered) < 0.3 * most_alive(walk)
    assert script.cache_passes(ordered, 22, 60) <= 1.2 * images < script.cache_passes(walk, 22, 60, planned=False)
    # memory alone, small and large: fewer passes than the walk with least-recently-used out
    for held in (4, 64):
        assert script.cache_passes(ordered, held) < script.cache_passes(script.walk_order(pairs, held), held, planned=False)
