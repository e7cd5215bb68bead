"""Backbone passes a pair order needs: FeatureCache's LRU policy replayed over a real pair graph.

    python scripts/pair_order.py [--pairs ../shared/data/yfcc_test_pairs_with_gt.txt] [--resident 16,128,256] [--csv OUT.csv]

For each number of images the cache holds, the passes (misses) of: the list's own order, the
order sorted by (lower, higher) image path (what the match stage used before), and
runner.reuse_order (what it uses now), and passes per distinct image. Counts only: nothing
is matched, so the figures are exact and machine-independent.
"""

from __future__ import annotations

import argparse
from collections import OrderedDict
from pathlib import Path

from e3cm_bench.datasets.base import Pair
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, default=Path("../shared/data/yfcc_test_pairs_with_gt.txt"))
    parser.add_argument("--resident", default="4,16,64,128,256")
    parser.add_argument("--csv", type=Path, help="also write the table here (the docs render results/perf/pair_order_yfcc.csv)")
    args = parser.parse_args()
    rows = []
    pairs = []
    for number, line in enumerate(args.pairs.read_text().splitlines()):
        if line.strip():
            a, b = line.split()[:2]
            pairs.append(Pair(f"{number}", Path(a), Path(b)))
    images = len({str(p.image0) for p in pairs} | {str(p.image1) for p in pairs})
    print(f"{args.pairs}: {len(pairs)} pairs, {images} distinct images")
    print("held | list order | sorted (before) | reuse_order (now) | now per image")
    for resident in (int(v) for v in args.resident.split(",")):
        ordered = reuse_order(pairs, resident)
        assert sorted(p.name for p in ordered) == sorted(p.name for p in pairs)  # every pair, once
        before = sorted(pairs, key=lambda p: (min(str(p.image0), str(p.image1)), max(str(p.image0), str(p.image1))))
        now = passes(ordered, resident)
        rows.append({"images held": resident, "list order": passes(pairs, resident), "sorted (before)": passes(before, resident),
                     "greedy walk (now)": now, "passes per image": round(now / images, 2)})
        print(" | ".join(str(v) for v in rows[-1].values()))
    if args.csv:
        import pandas as pd

        pd.DataFrame(rows).to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
