"""Pairs per minute over a real pair graph, measured end to end: e3cm-bench's match stage
against the E3CM release's per-pair loop.

    python scripts/measure/benchmark_throughput.py --pairs ../shared/data/yfcc_test_pairs_with_gt.txt \
        --scenes 1 --size 640x480 --precision fp32 --compare-release PATH [--release-sample 24] [--json]
        [--device cuda --backbone-batch 8] [--allocator keep|system]

The block: the first --scenes scenes of the list, whole (YFCC100M: 1000 pairs per scene,
buckingham_palace first), in the list's order. The photos are replaced by synthetic
stand-ins, one procedural scene per scene folder seen by each image through its own
homography, written as JPEG, so decoding is paid as with the real files and matching does
real work. VGG19 with random weights (seed 0), the same on both sides; random weights cost
what ImageNet ones do.

  ours: pipeline.stage.match_stage over the whole block as `e3cm-bench yfcc` runs it: pairs in
        reuse_order, the feature cache with this machine's default memory and disk budgets,
        decoding ahead, --precision, --device, --backbone-batch (default: the run's, 8 on a
        GPU and 1 on a CPU). Backbone passes and passes per image are its own counts.
  release: the release's loop (decode both images, match_large_img + refinement_pose_ransac,
        fp32: it has no other precision) from --compare-release PATH, timed on
        --release-sample pairs spread evenly over the block, half before ours and half
        after (load on a shared machine then weighs on both alike); it reuses nothing, so
        its seconds per pair times the block's pairs is its time for the block.

Prints measured figures only, with the CPU model and its instruction set (and the GPU's name
with --device cuda); `--json` ends with
one JSON object (pairs, distinct_images, passes, passes_per_image, ours_pairs_per_min,
release_pairs_per_min, speedup, precision, cpu, cpu_isa, allocator, peak_rss_mb, ...).
`--allocator keep` (the default) keeps freed memory for reuse as `e3cm-bench yfcc` does
(devices.keep_freed_memory), for the release's loop in the same process too.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
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

from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.images import load_image
from e3cm_bench.ground.machine import cpu_info, cpu_isa
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.pipeline.stage import match_stage
from e3cm_bench.storage import RunFolder
from e3cm_bench.apps.synth.textures import procedural_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pair_speed import ReleaseRunner, add_allocator_option, use_allocator  # noqa: E402 - the release loader lives with the per-pair benchmark


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True, help="a SuperGlue-format pair list (the graph)")
    parser.add_argument("--scenes", type=int, default=1, help="whole scenes matched, from the top of the list")
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--cache-mb", type=float, default=None, help="feature cache memory (default: the run's default)")
    parser.add_argument("--compare-release", type=Path, default=None)
    parser.add_argument("--release-sample", type=int, default=24, help="pairs the release's loop is timed on")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backbone-batch", type=int, default=None, help="images per backbone pass (default: the run's)")
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator = use_allocator(args.allocator)
    w, h = (int(v) for v in args.size.split("x"))
    graph = read_pair_graph(args.pairs)
    scenes = list(dict.fromkeys(a.split("/")[0] for a, _ in graph))[: args.scenes]
    block = [(a, b) for a, b in graph if a.split("/")[0] in scenes]
    images = {name for pair in block for name in pair}
    cpu, isa = cpu_info()[0], cpu_isa()
    print(f"block: {', '.join(scenes)} of {args.pairs}: {len(block)} pairs, {len(images)} images; stand-ins {w}x{h}; "
          f"VGG19 random weights (seed 0); precision {args.precision}; CPU {cpu} ({isa}); torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads; allocator {allocator}" + (f"; device {args.device}: {gpu_name(args.device)}"
                                                  if args.device != "cpu" else ""))
    work = Path(tempfile.mkdtemp(prefix="benchmark_throughput_"))
    try:
        result = run(args, block, (w, h), work)
    finally:
        shutil.rmtree(work, ignore_errors=True)  # the weights and stand-ins
    result.update(pairs_file=str(args.pairs), scenes=scenes, cpu=cpu, cpu_isa=isa, torch=torch.__version__, allocator=allocator,
                  peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  threads=torch.get_num_threads(), device=args.device,
                  gpu=gpu_name(args.device) if args.device != "cpu" else None)
    if args.json:
        print(json.dumps(result))


def gpu_name(device: str) -> str:
    return torch.cuda.get_device_name(torch.device(device)) if torch.device(device).type == "cuda" else device


def run(args, block: list[tuple[str, str]], size: tuple[int, int], work: Path) -> dict:
    torch.manual_seed(0)
    full = torchvision.models.vgg19(weights=None)
    weights = work / "vgg19_seed0.pth"
    torch.save(full.state_dict(), weights)
    pairs = [Pair(f"{a} {b}", stand_in(a, size, work), stand_in(b, size, work)) for a, b in block]

    release = None
    sample = pairs[:: max(1, len(pairs) // max(1, args.release_sample))][: args.release_sample]
    release_s: list[float] = []
    if args.compare_release is not None:
        release = ReleaseRunner(args.compare_release, full.state_dict(), args.device)
        warm = cv2.imread(str(sample[0].image0))
        release.match(warm, warm)

    def time_release(part: list[Pair]) -> None:
        for pair in part:  # the release's loop: both images decoded and passed for every pair
            t = time.perf_counter()
            release.match(cv2.imread(str(pair.image0)), cv2.imread(str(pair.image1)))
            release_s.append(time.perf_counter() - t)

    if release is not None:
        time_release(sample[::2])

    options = {} if args.precision == "fp32" else {"precision": args.precision}
    method = MethodSpec.create("e3cm", "vgg19", weights=str(weights), options=options)
    quiet = Console(quiet=True)
    warm = load_image(pairs[0].image0)
    method.build(args.device).pyramids(warm, warm)  # warm-up (its own matcher: nothing cached carries over)
    t = time.perf_counter()
    stats = match_stage(method, pairs, RunFolder(work / "ours").cache(), args.device, quiet,
                        options=MatchOptions(feature_cache_mb=args.cache_mb, backbone_batch=args.backbone_batch))
    t_ours = time.perf_counter() - t
    reuse = stats["feature_reuse"]
    result = {
        "size": args.size, "precision": args.precision, "pairs": len(pairs), "distinct_images": reuse["distinct_images"],
        "passes": reuse["backbone_passes"], "passes_per_image": reuse["passes_per_image"],
        "read_from_disk": reuse.get("read_from_disk", 0), "cache_mb": reuse["cache_mb"], "spill_mb": reuse["spill_mb"],
        "peak_cache_mb": reuse["peak_memory_mb"], "backbone_batch": reuse["backbone_batch"],
        "batches_run": reuse["batches_run"], "ours_s": t_ours, "ours_pairs_per_min": 60 * len(pairs) / t_ours,
    }
    print(f"ours: {len(pairs)} pairs in {t_ours:.0f} s = {result['ours_pairs_per_min']:.1f} pairs/min; "
          f"{result['passes']} backbone passes for {result['distinct_images']} images "
          f"({result['passes_per_image']:.2f} per image), {result['read_from_disk']} read back from disk; "
          f"cache {result['cache_mb']} MiB (peak {result['peak_cache_mb']:.0f}), disk {result['spill_mb']} MiB")
    if release is not None:
        time_release(sample[1::2])
        per_pair = statistics.mean(release_s)
        result.update(release_sample=len(release_s), release_s_per_pair=per_pair, release_pairs_per_min=60 / per_pair,
                      speedup=(60 * len(pairs) / t_ours) / (60 / per_pair))
        print(f"release loop: {len(release_s)} of the same pairs, {per_pair:.2f} s per pair (half before ours, half "
              f"after: {statistics.mean(release_s[: len(sample[::2])]):.2f} / {statistics.mean(release_s[len(sample[::2]):]):.2f})"
              f" = {60 / per_pair:.1f} pairs/min, so {len(pairs) * per_pair:.0f} s for the block")
        print(f"ours / release, pairs per minute: x{result['speedup']:.2f}")
    return result


if __name__ == "__main__":
    main()
