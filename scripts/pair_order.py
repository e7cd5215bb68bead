"""Backbone passes a pair order needs: the feature cache's policy replayed over a real pair graph.

    python scripts/pair_order.py [--pairs ../shared/data/yfcc_test_pairs_with_gt.txt] [--resident 16,128,256] [--csv OUT.csv]

For each number of images the cache holds in memory, the passes (misses) of a plain LRU cache
in: the list's own order, the order sorted by (lower, higher) image path (what the match stage
used first), runner.reuse_order; then of the cache the match stage uses now
(matchers/feature_cache.py, replayed with stand-in sizes): reuse_order, an image's maps
dropped after its last pair, nothing spilled to disk; and passes per distinct image. With the
spill to disk every image passes once as long as the images alive at once (printed) fit in
memory and disk together. Counts only: nothing is matched, so the figures are exact and
machine-independent.
"""

from __future__ import annotations

import argparse
from collections import OrderedDict
from pathlib import Path

import torch

from e3cm_bench.datasets.base import Pair
from e3cm_bench.matchers.feature_cache import FeatureCache, SpillStore
from e3cm_bench.runner import reuse_order


def passes(order: list[Pair], resident: int) -> int:
    held: OrderedDict[str, None] = OrderedDict()
    misses = 0
    for pair in order:
        for image in dict.fromkeys((str(pair.image0), str(pair.image1))):
            if image in held:
                held.move_to_end(image)
                continue
            misses += 1
            held[image] = None
            if len(held) > resident:
                held.popitem(last=False)
    return misses


class _Sized:
    """Stands in for a pyramid of one byte."""

    dtype = torch.float32

    def numel(self) -> int:
        return 1

    def element_size(self) -> int:
        return 1


class _CountedSpill(SpillStore):
    """A spill store that counts what it would hold (one byte per pyramid) and writes nothing."""

    def __init__(self, pyramids: int):
        super().__init__(Path("unused"), pyramids / 2**20)

    def write(self, key, maps) -> bool:
        if self.bytes + 1 > self.max_bytes:
            self.refused += 1
            return False
        self.sizes[key] = 1
        self.bytes += 1
        self.writes += 1
        return True

    def read(self, key, device):
        self.remove(key)
        self.reads += 1
        return [_Sized()]

    def remove(self, key) -> None:
        if self.sizes.pop(key, None) is not None:
            self.bytes -= 1


def cache_passes(order: list[Pair], memory: int, disk: int = 0) -> int:
    """Misses of FeatureCache holding `memory` pyramids (then `disk` more on disk), told after
    each pair which images have no pair left, as the match stage tells it."""
    last = {image: k for k, pair in enumerate(order) for image in (str(pair.image0), str(pair.image1))}
    cache = FeatureCache(memory / 2**20, _CountedSpill(disk) if disk else None)
    for k, pair in enumerate(order):
        files = (str(pair.image0), str(pair.image1))
        cache.pair_files = files
        for which, image in enumerate(files):
            cache.belongs_to(image, which)
            if cache.get(image) is None:
                cache.put(image, [_Sized()])
        for image in dict.fromkeys(files):
            if last[image] == k:
                cache.done_with(image)
    return cache.misses


def default_budgets(pairs: list[Pair], images: int, spill_folder: Path) -> list[dict]:
    """Passes with this machine's default budgets (memory: auto_cache_mb; disk: auto_spill_mb
    at spill_folder) for the backbones, sizes and precisions of the tables, pyramid sizes
    measured by each backbone (random weights; the size does not depend on them)."""
    from e3cm_bench.backbones import load_backbone
    from e3cm_bench.matchers.feature_cache import auto_cache_mb, auto_spill_mb

    memory_mb, disk_mb = auto_cache_mb("cpu"), auto_spill_mb(spill_folder)
    rows = []
    for name in ("efficientnet_lite0", "vgg19"):
        backbone = load_backbone(name, pretrained=False)
        for w, h in ((640, 480), (1200, 900)):
            for precision, width in (("fp32", 4), ("bf16", 2)):
                one = backbone.pyramid_bytes(h, w) * width / 4 / 2**20
                memory, disk = int(memory_mb // one), int(disk_mb // one)
                passes_now = cache_passes(reuse_order(pairs, memory + disk), memory, disk)
                rows.append({"backbone": name, "size": f"{w}x{h}", "maps held in": precision, "pyramid MiB": round(one, 1),
                             "in memory": memory, "on disk": disk, "passes": passes_now,
                             "passes per image": round(passes_now / images, 2)})
    print(f"defaults on this machine: memory {memory_mb:.0f} MiB, disk {disk_mb:.0f} MiB")
    return rows


def most_alive(order: list[Pair]) -> int:
    """The most images that have had a pair and still have one left, at any point of the order."""
    first, last = {}, {}
    for k, pair in enumerate(order):
        for image in (str(pair.image0), str(pair.image1)):
            first.setdefault(image, k)
            last[image] = k
    events = sorted([(k, 1) for k in first.values()] + [(k, -1) for k in last.values()], key=lambda e: (e[0], -e[1]))
    alive = top = 0
    for _, step in events:
        alive += step
        top = max(top, alive)
    return top


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, default=Path("../shared/data/yfcc_test_pairs_with_gt.txt"))
    parser.add_argument("--resident", default="4,16,64,128,256")
    parser.add_argument("--csv", type=Path, help="also write the table here (the docs render results/perf/pair_order_yfcc.csv)")
    parser.add_argument("--defaults-csv", type=Path, help="also replay this machine's default memory and disk budgets "
                        "for Lite0 and VGG19 at 640x480 and 1200x900, fp32 and bf16, and write that table here")
    args = parser.parse_args()
    rows = []
    pairs = []
    for number, line in enumerate(args.pairs.read_text().splitlines()):
        if line.strip():
            a, b = line.split()[:2]
            pairs.append(Pair(f"{number}", Path(a), Path(b)))
    images = len({str(p.image0) for p in pairs} | {str(p.image1) for p in pairs})
    print(f"{args.pairs}: {len(pairs)} pairs, {images} distinct images")
    print("held | list order | sorted (first) | reuse_order | reuse_order + drop after last pair (now) | now per image")
    alive = None
    for resident in (int(v) for v in args.resident.split(",")):
        ordered = reuse_order(pairs, resident)
        assert sorted(p.name for p in ordered) == sorted(p.name for p in pairs)  # every pair, once
        before = sorted(pairs, key=lambda p: (min(str(p.image0), str(p.image1)), max(str(p.image0), str(p.image1))))
        now = cache_passes(ordered, resident)
        alive = most_alive(ordered)
        rows.append({"images held": resident, "list order": passes(pairs, resident), "sorted (first)": passes(before, resident),
                     "greedy walk": passes(ordered, resident), "greedy walk + drop after last pair (now)": now,
                     "passes per image": round(now / images, 2), "most images alive": alive})
        print(" | ".join(str(v) for v in rows[-1].values()))
    import pandas as pd

    if args.csv:
        pd.DataFrame(rows).to_csv(args.csv, index=False)
    if args.defaults_csv:
        table = pd.DataFrame(default_budgets(pairs, images, args.defaults_csv.parent))
        print(table.to_string(index=False))
        table.to_csv(args.defaults_csv, index=False)


if __name__ == "__main__":
    main()
