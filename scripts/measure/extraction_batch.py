"""Feature extraction one image at a time against batches of images, side by side in one process.

    OMP_NUM_THREADS=1 nice python scripts/measure/extraction_batch.py [--matchers xfeat,aliked+lightglue,
        disk+lightglue] [--batch 2 --batch 4] [--side 1200] [--repeat 1] [--csv FILE]

What batching the two-stage matchers' extraction (issue 79's item 3) would buy on this machine,
measured only (the pipeline extracts one image at a time): the 20 KITTI 00 frames of
megadepth_test_1500/scene_info/kitti00_seq.npz (all 1241 x 376), shrunk to `--side` as the
match stage shrinks them (sfm's default 1200), pass through each matcher's extractor network
one by one (what `features` runs) and in batches of each `--batch` (one forward of a B x 3 x H x W
tensor), after a warm-up image, alternating, `--repeat` rounds. Prints seconds per image for each
way, the ratio, and whether each image's batched keypoints and descriptors equal the one-by-one
ones (bit for bit, else the largest absolute difference, each image's points sorted by position; "count" when the keypoint
counts differ) and the share of the one-by-one keypoints the batches found (order aside). SIFT is not here: OpenCV's detector takes one image. Weights: the matchers' own (the
keypoints depend on them).
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import numpy as np
import torch

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.ground.machine import cpu_info, cpu_isa
from e3cm_bench.ground.images import load_image, resize_max_side
from e3cm_bench.matchers.peers.common import rgb
from e3cm_bench.matchers.peers.lightglue import reference_aliked_nms
from e3cm_bench.method.spec import MethodSpec

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def kitti_frames(data: Path, side: int) -> list[np.ndarray]:
    """The sfm KITTI set's distinct images, in pair order, at `side` (the match stage's shrink)."""
    root = data / "megadepth_test_1500"
    pairs = get_benchmark("sfm").load_dataset(root, scene_info=root / "scene_info" / "kitti00_seq.npz",
                                              window="2").pairs
    paths = list(dict.fromkeys(str(p) for pair in pairs for p in (pair.image0, pair.image1)))
    return [resize_max_side(load_image(p), side)[0] for p in paths]


def extractor(name: str):
    """images (B x 3 x H x W, 0-1) -> [(keypoints, descriptors)] per image: the network call that
    the matcher's `features` makes, with its settings, for a batch."""
    matcher = MethodSpec.create(name).build("cpu")
    if name == "xfeat" or name == "xfeat+lighterglue":
        def run(x):
            return [(f["keypoints"], f["descriptors"]) for f in
                    matcher.model.detectAndCompute(x, top_k=matcher.settings.top_k)]
        return run
    kind, model, s = matcher.extractor.kind, matcher.extractor.model, matcher.settings
    if kind == "disk":
        def run(x):
            return [(f.keypoints.float(), f.descriptors) for f in
                    model(x, n=s.max_keypoints, window_size=s.nms_radius, score_threshold=s.detection_threshold,
                          pad_if_not_divisible=True)]
        return run
    if kind == "aliked":
        def run(x):
            with reference_aliked_nms():
                return [(f.keypoints.float(), f.descriptors) for f in model(x)]
        return run
    raise SystemExit(f"--matchers: {name!r} has no batchable extractor here (xfeat, aliked+lightglue, disk+lightglue)")


@torch.inference_mode()
def timed(run, images: list[torch.Tensor], batch: int) -> tuple[float, list]:
    t, out = time.perf_counter(), []
    for i in range(0, len(images), batch):
        out += run(torch.cat(images[i:i + batch]))
    return time.perf_counter() - t, out


def in_point_order(keypoints: torch.Tensor, descriptors: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints and descriptors sorted by (y, x): the batched pass may rank tied points otherwise."""
    k, d = keypoints.float().numpy(), descriptors.float().numpy()
    order = np.lexsort((k[:, 0], k[:, 1]))
    return k[order], d[order]


def difference(one: list, batched: list) -> str:
    """'0' when every image's keypoints and descriptors (in point order) are bit for bit the same,
    'count' when an image's keypoint count differs, else the largest absolute difference."""
    worst = 0.0
    for (k0, d0), (k1, d1) in zip(one, batched):
        if k0.shape != k1.shape or d0.shape != d1.shape:
            return "count"
        for a, b in zip(in_point_order(k0, d0), in_point_order(k1, d1)):
            if a.size:
                worst = max(worst, float(np.abs(a - b).max()))
    return "0" if worst == 0 else f"{worst:.3g}"


def shared_keypoints(one: list, batched: list) -> float:
    """The share of the one-by-one keypoints (to 1/1000 px) that the batched pass also found."""
    found = total = 0
    for (k0, _), (k1, _) in zip(one, batched):
        other = {tuple(p) for p in np.round(k1.float().numpy(), 3).tolist()}
        found += sum(tuple(p) in other for p in np.round(k0.float().numpy(), 3).tolist())
        total += len(k0)
    return found / max(total, 1)


def measure(name: str, images: list[torch.Tensor], batches: list[int], repeat: int) -> list[dict]:
    run = extractor(name)
    timed(run, images[:1], 1)  # warm-up: first-call allocations
    seconds = {b: 0.0 for b in [1, *batches]}
    outputs = {}
    for _ in range(repeat):
        for b in seconds:
            s, outputs[b] = timed(run, images, b)
            seconds[b] += s
    n = len(images) * repeat
    return [{"matcher": name, "batch": b, "images": len(images), "s per image": round(seconds[b] / n, 3),
             "speed-up": round(seconds[1] / seconds[b], 2), "difference": difference(outputs[1], outputs[b]),
             "keypoints shared": round(shared_keypoints(outputs[1], outputs[b]), 4)}
            for b in seconds]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--matchers", default="xfeat,aliked+lightglue,disk+lightglue")
    parser.add_argument("--batch", type=int, action="append", default=None)
    parser.add_argument("--side", type=int, default=1200)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--data", type=Path, default=SHARED)
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()
    frames = kitti_frames(args.data, args.side)
    images = [rgb(f, "cpu") for f in frames]
    print(f"{len(frames)} frames at {frames[0].shape[1]}x{frames[0].shape[0]}; {cpu_info()[0]} ({cpu_isa()}), "
          f"{torch.get_num_threads()} threads; load average before {os.getloadavg()[0]:.1f}", flush=True)
    rows = []
    for name in args.matchers.split(","):
        load = os.getloadavg()[0]
        for row in measure(name, images, args.batch or [2, 4], args.repeat):
            row.update({"size": f"{frames[0].shape[1]}x{frames[0].shape[0]}", "threads": torch.get_num_threads(),
                        "load before": round(load, 1), "load after": round(os.getloadavg()[0], 1)})
            rows.append(row)
            print("  ".join(f"{k} {v}" for k, v in row.items()), flush=True)
        if args.csv:  # after each matcher: a run stopped part way keeps what it measured
            args.csv.parent.mkdir(parents=True, exist_ok=True)
            with open(args.csv, "w", newline="") as f:
                out = csv.DictWriter(f, list(rows[0]))
                out.writeheader()
                out.writerows(rows)


if __name__ == "__main__":
    main()
