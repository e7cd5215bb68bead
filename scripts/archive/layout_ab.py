"""fp32 backbone passes in NCHW against channels_last memory, side by side in one process.

    python scripts/archive/layout_ab.py [--backbone vgg19 --backbone efficientnet_lite0] [--size 640x480 --size 1200x900] [--repeat 3]

Random weights (the time does not depend on them). For each backbone and size, the passes
alternate between the two layouts; medians, their ratio and the largest difference between
the two layouts' maps are printed. BackboneSpec.fp32_channels_last records the choice made
from these figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from e3cm_bench.backbones.loading import load_backbone
from e3cm_bench.ground.files import cpu_info, cpu_isa


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", action="append", default=None)
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    cpu, isa = cpu_info()[0], cpu_isa()
    print(f"CPU {cpu} ({isa}); torch {torch.__version__}, {torch.get_num_threads()} threads; fp32; median of {args.repeat}")
    for name in args.backbone or ["vgg19", "efficientnet_lite0"]:
        backbone = load_backbone(name, pretrained=False)
        layouts = {"nchw": dataclasses.replace(backbone.spec, fp32_channels_last=False),
                   "channels_last": dataclasses.replace(backbone.spec, fp32_channels_last=True)}
        for size in args.size or ["640x480", "1200x900"]:
            w, h = (int(v) for v in size.split("x"))
            image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
            seconds, maps = {k: [] for k in layouts}, {}
            for _ in range(args.repeat + 1):  # the first round warms up
                for layout, spec in layouts.items():
                    backbone.spec = spec
                    t = time.perf_counter()
                    maps[layout] = backbone(image)
                    seconds[layout].append(time.perf_counter() - t)
            nchw, last = (statistics.median(seconds[k][1:]) for k in layouts)
            diff = max((a - b).abs().max().item() for a, b in zip(maps["nchw"], maps["channels_last"]))
            print(f"{name} {size}: nchw {nchw:.2f} s, channels_last {last:.2f} s, channels_last / nchw {last / nchw:.2f}; "
                  f"maps at most {diff:.1e} apart", flush=True)


if __name__ == "__main__":
    main()
