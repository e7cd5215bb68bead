"""Backbone passes a pair order needs: the feature cache's policy replayed over a real pair graph.

    python scripts/measure/pair_order_passes.py [--pairs ../shared/data/yfcc_test_pairs_with_gt.txt] [--resident 16,128,256] [--csv OUT.csv]

For each number of images the cache holds in memory, the passes (misses) of a plain LRU cache
in: the list's own order, the order sorted by (lower, higher) image path (what the match stage
used first), the greedy walk that followed (`walk_order` below: the most recently used image's
pairs next); then of the cache the match stage uses now (matchers/feature_cache.py, replayed
with stand-in sizes) in pair_order.reuse_order: told the order (the pyramid needed last goes
out first), an image's maps dropped after its last pair, nothing spilled to disk; and passes
per distinct image, and the most images alive at once in each order: with the spill to disk
every image passes once as long as those fit in memory and disk together. Counts only:
nothing is matched, so the figures are exact and machine-independent.
"""

from __future__ import annotations

import argparse
from collections import OrderedDict
from pathlib import Path

import torch

from e3cm_bench.datasets.base import Pair
from e3cm_bench.matchers.feature_cache import FeatureCache
from e3cm_bench.matchers.spill import SpillStore
from e3cm_bench.pipeline.pair_order import most_alive, reuse_order


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

    def read(self, key, device, keep=False):
        if not keep:
            self.remove(key)
        self.reads += 1
        return [_Sized()]

    def remove(self, key) -> None:
        if self.sizes.pop(key, None) is not None:
            self.bytes -= 1


def walk_order(pairs: list[Pair], resident: int = 16) -> list[Pair]:
    """The order the match stage used before pair_order.reuse_order: a greedy walk keeping an
    LRU list of `resident` images, taking next a pair whose two images are held (the most
    recently used first), else one whose image is held (with the partner that has the most
    pairs left), else starting at the image with the most pairs left."""
    names = [(str(p.image0), str(p.image1)) for p in pairs]
    incident: dict[str, list[int]] = {}
    for i, (a, b) in enumerate(names):
        incident.setdefault(a, []).append(i)
        if b != a:
            incident.setdefault(b, []).append(i)
    left = {image: len(items) for image, items in incident.items()}
    done = [False] * len(pairs)
    held: OrderedDict[str, None] = OrderedDict()
    order: list[int] = []

    def remaining(image: str):
        return (i for i in incident[image] if not done[i])

    def other(i: int, image: str) -> str:
        a, b = names[i]
        return b if a == image else a

    while len(order) < len(pairs):
        chosen = None
        recent = list(reversed(held))
        for image in recent:
            chosen = next((i for i in remaining(image) if other(i, image) in held), None)
            if chosen is not None:
                break
        if chosen is None:
            for image in recent:
                candidates = list(remaining(image))
                if candidates:
                    chosen = max(candidates, key=lambda i: (left[other(i, image)], -i))
                    break
        if chosen is None:
            start = max((image for image in incident if left[image]), key=lambda image: (left[image], image))
            chosen = next(remaining(start))
        done[chosen] = True
        order.append(chosen)
        for image in dict.fromkeys(names[chosen]):
            left[image] -= 1
            held[image] = None
            held.move_to_end(image)
            if len(held) > max(1, resident):
                held.popitem(last=False)
    return [pairs[i] for i in order]


def cache_passes(order: list[Pair], memory: int, disk: int = 0, planned: bool = True) -> int:
    """Misses of FeatureCache holding `memory` pyramids (then `disk` more on disk), told the
    order (planned; else it evicts the least recently used) and after each pair which images
    have no pair left, as the match stage tells it."""
    files_in_order = [(str(pair.image0), str(pair.image1)) for pair in order]
    last = {image: k for k, files in enumerate(files_in_order) for image in files}
    cache = FeatureCache(memory / 2**20, _CountedSpill(disk) if disk else None)
    if planned:
        cache.plan(files_in_order)
    for k, pair in enumerate(order):
        files = files_in_order[k]
        cache.at(k, files)
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
    from e3cm_bench.backbones.loading import load_backbone
    from e3cm_bench.matchers.feature_cache import auto_cache_mb
    from e3cm_bench.matchers.spill import auto_spill_mb

    memory_mb, disk_mb = auto_cache_mb("cpu"), auto_spill_mb(spill_folder)
    ordered = reuse_order(pairs)
    rows = []
    for name in ("efficientnet_lite0", "vgg19"):
        backbone = load_backbone(name, pretrained=False)
        for w, h in ((640, 480), (1200, 900)):
            for precision, width in (("fp32", 4), ("bf16", 2)):
                one = backbone.pyramid_bytes(h, w) * width / 4 / 2**20
                memory, disk = int(memory_mb // one), int(disk_mb // one)
                walk = cache_passes(walk_order(pairs, memory + disk), memory, disk, planned=False)
                passes_now = cache_passes(ordered, memory, disk)
                rows.append({"backbone": name, "size": f"{w}x{h}", "maps held in": precision, "pyramid MiB": round(one, 1),
                             "in memory": memory, "on disk": disk, "passes (walk, LRU: before)": walk,
                             "walk per image": round(walk / images, 2), "passes": passes_now,
                             "passes per image": round(passes_now / images, 2)})
    print(f"defaults on this machine: memory {memory_mb:.0f} MiB, disk {disk_mb:.0f} MiB")
    return rows


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
    ordered = reuse_order(pairs)
    assert sorted(p.name for p in ordered) == sorted(p.name for p in pairs)  # every pair, once
    before = sorted(pairs, key=lambda p: (min(str(p.image0), str(p.image1)), max(str(p.image0), str(p.image1))))
    print(f"most images alive at once: {most_alive(ordered)} in reuse_order")
    for resident in (int(v) for v in args.resident.split(",")):
        walk = walk_order(pairs, resident)
        now = cache_passes(ordered, resident)
        rows.append({"images held": resident, "list order": passes(pairs, resident), "sorted (first)": passes(before, resident),
                     "greedy walk": passes(walk, resident),
                     "greedy walk + drop after last pair (before)": cache_passes(walk, resident, planned=False),
                     "reuse_order + planned cache (now)": now, "passes per image": round(now / images, 2),
                     "most alive (walk)": most_alive(walk), "most alive (now)": most_alive(ordered)})
        print(" | ".join(f"{k}: {v}" for k, v in rows[-1].items()))
    import pandas as pd

    if args.csv:
        pd.DataFrame(rows).to_csv(args.csv, index=False)
    if args.defaults_csv:
        table = pd.DataFrame(default_budgets(pairs, images, args.defaults_csv.parent))
        print(table.to_string(index=False))
        table.to_csv(args.defaults_csv, index=False)


if __name__ == "__main__":
    main()
