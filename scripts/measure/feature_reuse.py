"""Feature reuse against the pair-by-pair path, side by side in one process: wall time of the
match stage, extractions, and whether the matches agree.

    nice python scripts/measure/feature_reuse.py [--sets kitti,hpatches,yfcc] \
        [--matchers sift,xfeat,xfeat+lighterglue,aliked+lightglue,disk+lightglue] [--device cpu] [--json]
        [--yfcc-pairs N] [--yfcc-size WxH]

Sets (the shared data, ../shared/data):
  kitti:    the 20 KITTI 00 frames of megadepth_test_1500/scene_info/kitti00_seq.npz, pair graph
            `sfm --window 2` (37 pairs), at sfm's default side (1200);
  hpatches: the shared HPatches sequences (3 x 5 pairs over 3 x 6 images), at --hpatches-side
            (default 640; 0: full size, about 1 MP, which takes minutes a matcher on a shared CPU);
  yfcc:     the real YFCC100M pair list (yfcc_test_pairs_with_gt.txt), its first scene
            (buckingham_palace: 1000 pairs over 446 images); its photos are not in the shared data,
            so each image is the synthetic stand-in scripts/measure/benchmark_throughput.py makes
            (one procedural scene per scene folder, each image through its own homography, JPEG, at
            --yfcc-size, default 640x480), at yfcc's default side. --yfcc-pairs N keeps the first N
            pairs of the stage's own order (pipeline.pair_order.reuse_order, which keeps pairs that
            share images together), so a block smaller than the scene still reuses images; 0: the
            whole scene.

For each set and matcher: pipeline.stage.match_stage over the set's pairs twice, with
MatchOptions(feature_reuse=False) (each pair extracts both its images: the path before
two-stage matchers) and then with reuse (each image's features extracted once, kept in the
feature cache at the default budgets); the matcher is built in each stage, and the ratio is of
the seconds spent matching (the stage's match_seconds, build excluded) and of the stage's wall
time. Extractions are counted, and timed, by wrapping the matcher class's `features` (on CPU:
a GPU's queued work is not waited for); the rest of the match seconds is matching the pairs,
so `amdahl bound` = pair-by-pair s / (reused s - extraction s reused) is the speed-up reuse
would give were extraction free. The two runs' matches are compared array for array. Prints measured figures only, with the load average
before and after (the machine may be shared: say so beside the figures).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.datasets.base import Pair
from e3cm_bench.method.protocols import resolve_max_side
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.pair_order import reuse_order
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.pipeline.stage import match_stage
from e3cm_bench.storage import RunFolder
from e3cm_bench.storage.cache import MatchCache

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmark_throughput's YFCC stand-ins
SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MATCHERS = "sift,xfeat,xfeat+lighterglue,aliked+lightglue,disk+lightglue"


def set_pairs(name: str, data: Path, args, work: Path) -> list:
    if name == "kitti":
        root = data / "megadepth_test_1500"
        return get_benchmark("sfm").load_dataset(root, scene_info=root / "scene_info" / "kitti00_seq.npz",
                                                 window="2").pairs  # as the CLI passes it: sfm's --window is text
    if name == "hpatches":
        return get_benchmark("hpatches").load_dataset(data / "hpatches-sequences-release").pairs
    if name == "yfcc":
        return yfcc_pairs(data / "yfcc_test_pairs_with_gt.txt", args.yfcc_pairs, args.yfcc_size, work)
    raise SystemExit(f"--sets: unknown set {name!r} (kitti, hpatches, yfcc)")


def yfcc_pairs(path: Path, keep: int, size: str, work: Path) -> list:
    """The first scene of the real pair graph, on benchmark_throughput.py's stand-ins."""
    from benchmark_throughput import read_pair_graph, stand_in

    graph = read_pair_graph(path)
    scene = graph[0][0].split("/")[0]
    w, h = (int(v) for v in size.split("x"))
    folder = work / "yfcc-stand-ins"
    folder.mkdir(exist_ok=True)
    pairs = [Pair(f"{a} {b}", stand_in(a, (w, h), folder), stand_in(b, (w, h), folder))
             for a, b in graph if a.split("/")[0] == scene]
    return reuse_order(pairs)[:keep] if keep else pairs


def counted(cls) -> dict:
    """Wrap cls.features to count its calls and add up their seconds (once per class)."""
    count = {"n": 0, "s": 0.0}
    if getattr(cls.features, "_counted", None) is None:
        original = cls.features

        def features(self, image):
            features._counted["n"] += 1
            t = time.perf_counter()
            try:
                return original(self, image)
            finally:
                features._counted["s"] += time.perf_counter() - t

        features._counted = count
        cls.features = features
    return cls.features._counted


def same_matches(a: Path, b: Path) -> bool:
    one, two = MatchCache(a), MatchCache(b)
    names = one.names()
    if names != two.names():
        return False
    for name in names:
        x, y = one.read(name), two.read(name)
        if not all(np.array_equal(p, q) for p, q in ((x.keypoints0, y.keypoints0), (x.keypoints1, y.keypoints1),
                                                     (x.scores, y.scores))):
            return False
    return True


def stage(method: MethodSpec, pairs: list, folder: Path, device: str, reuse: bool, count: dict) -> dict:
    count["n"], count["s"] = 0, 0.0
    t = time.perf_counter()
    stats = match_stage(method, pairs, MatchCache(RunFolder(folder).matches_path), device, Console(quiet=True),
                        options=MatchOptions(feature_reuse=reuse))
    return {"wall_s": time.perf_counter() - t, "match_s": stats["match_seconds"], "extractions": count["n"],
            "extraction_s": count["s"], "recorded": stats.get("feature_reuse", {}).get("extractions")}


def measure(set_name: str, pairs: list, matcher: str, side: int | None, device: str, work: Path) -> dict:
    load = os.getloadavg()[0]
    method = MethodSpec.create(matcher, max_side=side)
    count = counted(type(method.build(device)))
    images = {str(p.image0) for p in pairs} | {str(p.image1) for p in pairs}
    plain = stage(method, pairs, work / f"{set_name}-{matcher}-plain", device, False, count)
    reuse = stage(method, pairs, work / f"{set_name}-{matcher}-reuse", device, True, count)
    return {"set": set_name, "matcher": matcher, "pairs": len(pairs), "images": len(images), "side": side,
            "plain": plain, "reuse": reuse, "ratio_match": plain["match_s"] / reuse["match_s"],
            "ratio_wall": plain["wall_s"] / reuse["wall_s"], "load_before": load,
            "amdahl": plain["match_s"] / max(reuse["match_s"] - reuse["extraction_s"], 1e-9),
            "same_matches": same_matches(RunFolder(work / f"{set_name}-{matcher}-plain").matches_path,
                                         RunFolder(work / f"{set_name}-{matcher}-reuse").matches_path)}


COLUMNS = ["set", "matcher", "pairs", "images", "side", "extractions pair by pair", "extractions reused",
           "pair by pair s", "reused s", "speed-up", "wall speed-up", "same matches", "load before", "load after row",
           "extraction s pair by pair", "extraction s reused", "amdahl bound"]


def csv_row(r: dict, after: float) -> dict:
    values = [r["set"], r["matcher"], r["pairs"], r["images"], r["side"] or "full", r["plain"]["extractions"],
              r["reuse"]["extractions"], round(r["plain"]["match_s"], 1), round(r["reuse"]["match_s"], 1),
              round(r["ratio_match"], 2), round(r["ratio_wall"], 2), r["same_matches"], round(r["load_before"], 1),
              round(after, 1), round(r["plain"]["extraction_s"], 1), round(r["reuse"]["extraction_s"], 1),
              round(r["amdahl"], 2)]
    return dict(zip(COLUMNS, [str(v) for v in values]))


def write_csv(path: Path, row: dict) -> None:
    """Put one measured row into path: it replaces the row of the same set and matcher, the
    others stay (an earlier run's, measured another day: docs/speed.md says which is which)."""
    import csv

    path.parent.mkdir(parents=True, exist_ok=True)
    rows = list(csv.DictReader(open(path, newline=""))) if path.exists() else []
    key = (row["set"], row["matcher"])
    at = [i for i, r in enumerate(rows) if (r["set"], r["matcher"]) == key]
    if at:
        rows[at[0]] = row
    else:
        rows.append(row)
    with open(path, "w", newline="") as f:
        out = csv.DictWriter(f, COLUMNS, restval="")
        out.writeheader()
        out.writerows(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sets", default="kitti,hpatches")
    parser.add_argument("--yfcc-pairs", type=int, default=0, help="the first N pairs of the scene's stage order (0: all)")
    parser.add_argument("--yfcc-size", default="640x480", help="the YFCC stand-ins' size")
    parser.add_argument("--matchers", default=MATCHERS)
    parser.add_argument("--hpatches-side", type=int, default=640)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--data", type=Path, default=SHARED)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--csv", type=Path, help="also write the rows here (docs/speed.md reads results/perf/)")
    args = parser.parse_args()
    sides = {"kitti": resolve_max_side(get_benchmark("sfm"), None), "hpatches": args.hpatches_side or None,
             "yfcc": resolve_max_side(get_benchmark("yfcc"), None)}
    rows = []
    before = os.getloadavg()
    print(f"load average before: {before}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for set_name in args.sets.split(","):
            pairs = set_pairs(set_name, args.data, args, Path(tmp))
            for matcher in args.matchers.split(","):
                row = measure(set_name, pairs, matcher, sides[set_name], args.device, Path(tmp))
                rows.append(row)
                print(f"{set_name:9} {matcher:20} pairs {row['pairs']:3} images {row['images']:3}  extractions "
                      f"{row['plain']['extractions']:3} -> {row['reuse']['extractions']:3} (recorded "
                      f"{row['reuse']['recorded']})  match s {row['plain']['match_s']:7.1f} -> "
                      f"{row['reuse']['match_s']:7.1f}  x{row['ratio_match']:.2f}  wall x{row['ratio_wall']:.2f}  "
                      f"extraction s {row['plain']['extraction_s']:.1f} -> {row['reuse']['extraction_s']:.1f}  "
                      f"amdahl bound x{row['amdahl']:.2f}  same matches: {row['same_matches']}  "
                      f"load {row['load_before']:.1f} -> {os.getloadavg()[0]:.1f}", flush=True)
                if args.csv:  # after each row: a run stopped part way keeps what it measured
                    write_csv(args.csv, csv_row(row, os.getloadavg()[0]))
    print(f"load average after: {os.getloadavg()}")
    if args.json:
        print(json.dumps({"rows": rows, "python": sys.version.split()[0]}))


if __name__ == "__main__":
    main()
