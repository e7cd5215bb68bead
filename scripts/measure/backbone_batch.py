"""Backbone passes one image at a time against batches of images, side by side in one process.

    python scripts/measure/backbone_batch.py [--backbone vgg19] [--size 640x480] [--precision fp32 --precision bf16]
                                  [--batch 4] [--images 8] [--repeat 2] [--device cuda] [--csv FILE]

What `--backbone-batch` (match_jobs, DeepMatcher.prefetch) buys on a device: the same
`--images` images go through the network one by one and in batches of `--batch`,
alternating, after a warm-up round. Prints seconds per image for each, their ratio, and the
largest difference between the two ways' maps (0 where the kernels do not depend on the
batch size, as on this project's CPU). Random weights: the time does not depend on them.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import torch

from e3cm_bench.backbones.loading import load_backbone
from e3cm_bench.ground.machine import cpu_info, cpu_isa


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{cpu_info()[0]} ({cpu_isa()}), {torch.get_num_threads()} threads"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", action="append", default=None)
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--precision", action="append", default=None)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--csv", type=Path, default=None, help="also write the figures here, a row each")
    args = parser.parse_args()
    rows = []
    device = torch.device(args.device)
    print(f"{device_name(device)}; torch {torch.__version__}; {args.images} images, batches of {args.batch}; "
          f"median of {args.repeat}")
    for name in args.backbone or ["vgg19"]:
        for precision in args.precision or ["fp32"]:
            backbone = load_backbone(name, pretrained=False, precision=precision, device=device)
            for size in args.size or ["640x480"]:
                w, h = (int(v) for v in size.split("x"))
                images = torch.rand(args.images, 3, h, w, generator=torch.Generator().manual_seed(0)).to(device)
                seconds = {"one by one": [], "batched": []}
                for round_ in range(args.repeat + 1):  # the first round warms up
                    sync(device)
                    t = time.perf_counter()
                    alone = [backbone(images[i:i + 1]) for i in range(len(images))]
                    sync(device)
                    one = time.perf_counter() - t
                    t = time.perf_counter()
                    together = [maps for start in range(0, len(images), args.batch)
                                for maps in backbone.forward_batch(images[start:start + args.batch])]
                    sync(device)
                    batched = time.perf_counter() - t
                    if round_:
                        seconds["one by one"].append(one / len(images))
                        seconds["batched"].append(batched / len(images))
                diff = max((a - b).abs().max().item() for x, y in zip(alone, together) for a, b in zip(x, y))
                one, batched = (statistics.median(seconds[k]) for k in ("one by one", "batched"))
                print(f"{name} {size} {precision}: one by one {one:.3f} s/image, batches of {args.batch} "
                      f"{batched:.3f} s/image, batched / one by one {batched / one:.2f}; maps at most {diff:.1e} apart",
                      flush=True)
                rows.append({"device": device_name(device), "backbone": name, "size": size, "precision": precision,
                             "batch": args.batch, "one by one s/image": round(one, 3),
                             "batched s/image": round(batched, 3), "batched / one by one": round(batched / one, 2),
                             "largest difference": f"{diff:.1e}"})
    if args.csv is not None:
        with args.csv.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
