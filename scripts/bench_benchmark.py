"""Pairs per minute over a real pair graph: e3cm-bench's match stage against the release's loop.

    python scripts/bench_benchmark.py --pairs ../shared/data/yfcc_test_pairs_with_gt.txt \
        --size 640x480 --window 24 --precision bf16 --compare-release PATH [--cache-mb 2048] [--json]

The pair graph is the real one (YFCC100M: 4000 pairs over 1455 images); the photos are
replaced by synthetic stand-ins, one procedural scene per image name written as JPEG, so
decoding is paid as with the real files. VGG19 with random weights (seed 0), the same on
both sides; random weights cost what ImageNet ones do.

Measured, on the first --window pairs in the order the match stage uses (runner.reuse_order):
  ours: runner.match_stage as `e3cm-bench yfcc` runs it (feature cache, decoding ahead,
        --precision);
  release: the E3CM release's per-pair loop from --compare-release PATH on the same pairs
        (decode both images, match_large_img + refinement_pose_ransac; it reuses nothing, so
        its cost per pair does not depend on the order).
Projected over the whole graph: the backbone passes the feature cache needs for all pairs
(FeatureCache's own policy replayed over the graph with the measured size of one pyramid)
times the measured seconds per pass, plus the measured seconds per pair after the backbone;
against the release's measured seconds per pair for every pair. Prints measured figures only;
`--json` ends with one JSON object.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torchvision
from rich.console import Console

from e3cm_bench.cache import MatchCache
from e3cm_bench.datasets.base import Pair
from e3cm_bench.images import load_image
from e3cm_bench.matchers.deep import FeatureCache
from e3cm_bench.method import MethodSpec
from e3cm_bench.runner import FEATURE_CACHE_MB, match_stage, reuse_order
from e3cm_bench.synth.textures import procedural_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed import ReleaseRunner  # noqa: E402 - the release loader lives with the per-pair benchmark


def read_pair_graph(path: Path) -> list[tuple[str, str]]:
    """(image0, image1) of each line of a SuperGlue-format pair list."""
    pairs = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if len(fields) < 2:
            raise SystemExit(f"{path}: line {number} has no image pair")
        pairs.append((fields[0], fields[1]))
    return pairs


def _seed(text: str) -> int:
    return int(hashlib.blake2b(text.encode(), digest_size=4).hexdigest(), 16)


def stand_in(name: str, size: tuple[int, int], folder: Path) -> Path:
    """One procedural scene per scene folder of the list (the name's first part), seen by each
    image through its own homography (corners moved up to 8% of the size), as JPEG: the
    two images of a pair overlap, as real views of one place do, so matching does real work."""
    path = folder / (name.replace("/", "__") + ".jpg")
    if not path.is_file():
        w, h = size
        scene = procedural_scene(size, seed=_seed(name.split("/")[0]))
        rng = np.random.default_rng(_seed(name))
        corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
        moved = corners + rng.uniform(-0.08, 0.08, (4, 2)).astype(np.float32) * np.float32([w, h])
        view = cv2.warpPerspective(scene, cv2.getPerspectiveTransform(corners, moved), size, borderMode=cv2.BORDER_REFLECT)
        cv2.imwrite(str(path), cv2.cvtColor(view, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
    return path


class _Sized:
    """Stands in for a pyramid of `nbytes` when replaying the cache policy."""

    def __init__(self, nbytes: int):
        self.nbytes = nbytes

    def numel(self) -> int:
        return self.nbytes

    def element_size(self) -> int:
        return 1


def passes_needed(graph: list[tuple[str, str]], pyramid_bytes: int, cache_mb: float) -> int:
    """Backbone passes FeatureCache needs over the graph in reuse order (every image the same size)."""
    cache = FeatureCache(cache_mb)
    pairs = reuse_order([Pair(f"{a} {b}", Path(a), Path(b)) for a, b in graph])
    for pair in pairs:
        for image in (str(pair.image0), str(pair.image1)):
            if cache.get(image) is None:
                cache.put(image, [_Sized(pyramid_bytes)])
    return cache.misses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True, help="a SuperGlue-format pair list (the graph)")
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--window", type=int, default=24, help="pairs actually matched (from the start of the order)")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--cache-mb", type=float, default=FEATURE_CACHE_MB)
    parser.add_argument("--compare-release", type=Path, default=None)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    graph = read_pair_graph(args.pairs)
    images = {name for pair in graph for name in pair}
    print(f"pair graph {args.pairs}: {len(graph)} pairs, {len(images)} images; stand-ins {w}x{h}; "
          f"VGG19 random weights (seed 0); precision {args.precision}; torch threads {torch.get_num_threads()}")

    work = Path(tempfile.mkdtemp(prefix="bench_benchmark_"))
    try:
        run(args, graph, images, (w, h), work)
    finally:
        shutil.rmtree(work, ignore_errors=True)  # the weights and stand-ins (about 0.6 GB)


def run(args, graph: list[tuple[str, str]], images: set[str], size: tuple[int, int], work: Path) -> None:
    w, h = size
    torch.manual_seed(0)
    full = torchvision.models.vgg19(weights=None)
    weights = work / "vgg19_seed0.pth"
    torch.save(full.state_dict(), weights)
    window = reuse_order([Pair(f"{a} {b}", Path(a), Path(b)) for a, b in graph])[: args.window]
    pairs = [Pair(p.name, stand_in(str(p.image0), (w, h), work), stand_in(str(p.image1), (w, h), work)) for p in window]
    n_images = len({p.image0 for p in pairs} | {p.image1 for p in pairs})

    options = {} if args.precision == "fp32" else {"precision": args.precision}
    method = MethodSpec.create("e3cm", "vgg19", str(weights), options=options)
    matcher = method.build("cpu")
    image = load_image(pairs[0].image0)
    matcher.pyramids(image, image)  # warm-up
    per_pass = []
    for _ in range(3):
        t = time.perf_counter()
        maps = matcher.backbone(matcher.network_input(image))
        per_pass.append(time.perf_counter() - t)
    t_pass = statistics.median(per_pass)
    pyramid_bytes = sum(m.numel() * m.element_size() for m in maps)

    quiet = Console(quiet=True)
    t = time.perf_counter()
    stats = match_stage(method, pairs, MatchCache(work / "ours.h5"), "cpu", quiet, feature_cache_mb=args.cache_mb)
    t_ours = time.perf_counter() - t
    passes = stats["feature_reuse"]["backbone_passes"]
    t_rest = max(0.0, (t_ours - passes * t_pass) / len(pairs))
    result = {
        "pairs_file": str(args.pairs), "graph_pairs": len(graph), "graph_images": len(images), "size": args.size,
        "precision": args.precision, "cache_mb": args.cache_mb, "window_pairs": len(pairs),
        "window_images": n_images, "window_backbone_passes": passes, "ours_window_s": t_ours,
        "ours_pairs_per_min": 60 * len(pairs) / t_ours, "backbone_pass_s": t_pass, "after_backbone_s_per_pair": t_rest,
        "pyramid_mb": pyramid_bytes / 2**20,
    }
    print(f"ours, window of {len(pairs)} pairs ({n_images} images, {passes} backbone passes): {t_ours:.1f} s, "
          f"{result['ours_pairs_per_min']:.1f} pairs/min; one pass {t_pass:.2f} s, after the backbone "
          f"{t_rest:.2f} s per pair; a pyramid is {result['pyramid_mb']:.0f} MiB")
    full_passes = passes_needed(graph, pyramid_bytes, args.cache_mb)
    t_full = full_passes * t_pass + len(graph) * t_rest
    result.update(graph_backbone_passes=full_passes, ours_graph_pairs_per_min=60 * len(graph) / t_full)
    print(f"ours, whole graph (projected): {full_passes} backbone passes for {len(graph)} pairs "
          f"(cache {args.cache_mb:.0f} MiB = {int(args.cache_mb * 2**20 // pyramid_bytes)} pyramids), "
          f"{result['ours_graph_pairs_per_min']:.1f} pairs/min")

    if args.compare_release is not None:
        release = ReleaseRunner(args.compare_release, full.state_dict(), "cpu")
        release.match(image, image)  # warm-up
        t = time.perf_counter()
        for pair in pairs:  # the release's loop: both images decoded and passed for every pair
            release.match(cv2.imread(str(pair.image0)), cv2.imread(str(pair.image1)))
        t_release = time.perf_counter() - t
        per_pair = t_release / len(pairs)
        result.update(release_window_s=t_release, release_pairs_per_min=60 / per_pair,
                      window_speedup=t_release / t_ours, graph_speedup=len(graph) * per_pair / t_full)
        print(f"release loop, same {len(pairs)} pairs: {t_release:.1f} s, {60 / per_pair:.1f} pairs/min")
        print(f"ours / release, pairs per minute: window x{result['window_speedup']:.2f}, whole graph (projected) "
              f"x{result['graph_speedup']:.2f}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
