"""Level 0 normalised for the confidence score: torch's norm against the banded sum, side by side.

    python scripts/bench_norm.py [--size 640x480 --size 1200x900] [--channels 64] [--repeat 5]

`unit_pixel_major` (matching/cascade.py) is what the top-8 and PROSAC cascades pay per
image before their confidence score. It computes the channel norm either with torch's
`Tensor.norm` (the fallback) or with `_channel_norm_by_rows` (the default where it gives
torch's bits). For each size, the two alternate on the same random map (ReLU'd, as a
backbone's map is); medians, their ratio, and whether the outputs are equal bit for bit are
printed.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from e3cm_bench.files import cpu_info, cpu_isa
from e3cm_bench.matching import cascade


def torch_norm(feat: torch.Tensor) -> torch.Tensor:
    return feat.norm(2, 0, keepdim=True).clamp_min(1e-12)


def banded_norm(feat: torch.Tensor) -> torch.Tensor:
    return cascade._channel_norm_by_rows(feat).clamp_min_(1e-12)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--channels", type=int, default=64, help="64: VGG19's level 0")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"{args.channels} channels, fp32; median of {args.repeat}")
    for size in args.size or ["640x480", "1200x900"]:
        w, h = (int(v) for v in size.split("x"))
        feat = torch.randn(args.channels, h, w, generator=torch.Generator().manual_seed(0)).relu_()
        ways = {"torch norm": torch_norm, "banded": banded_norm}
        seconds = {k: [] for k in ways}
        norms = {k: [] for k in ways}
        for _ in range(args.repeat + 1):  # the first round warms up (and runs the bit check)
            for name, norm in ways.items():
                t = time.perf_counter()
                norms[name] = norm(feat)
                seconds[name].append(time.perf_counter() - t)
        old, new = (statistics.median(seconds[k][1:]) for k in ways)
        same = torch.equal(norms["torch norm"], norms["banded"])
        print(f"{size}: torch norm {old * 1000:.1f} ms, banded {new * 1000:.1f} ms, banded / torch {new / old:.2f}; "
              f"bit for bit equal: {same}; fast path taken: {cascade._row_block_norm_exact(feat)}", flush=True)


if __name__ == "__main__":
    main()
