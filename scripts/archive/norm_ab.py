"""Channel norms of a feature map: torch's norm against the ordered sum (matching/norms.py), side by side.

    python scripts/archive/norm_ab.py [--size 640x480 --size 1200x900] [--channels 64] [--repeat 5]

The top-8 and PROSAC cascades take the channel norms of level 0 whole for their confidence
score (`cascade.pixel_norms`); the deepest level and the children read by refinement are
normalised too. `norms.channel_norm` computes the norm with `norms.ordered_norm` where that gives torch's
bits, else with torch's `Tensor.norm`. For each size, the two alternate on the same random
map (ReLU'd, as a backbone's map is); medians, their ratio, and whether the outputs are
equal bit for bit are printed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from e3cm_bench.ground.files import cpu_info, cpu_isa
from e3cm_bench.matching import norms

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import add_allocator_option, before_after, use_allocator  # noqa: E402 - the speed scripts' helpers


def torch_norm(feat: torch.Tensor) -> torch.Tensor:
    return feat.norm(2, 0, keepdim=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--channels", type=int, default=64, help="64: VGG19's level 0")
    parser.add_argument("--repeat", type=int, default=5)
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator = use_allocator(args.allocator)
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"{args.channels} channels, fp32; median of {args.repeat}; allocator {allocator}")
    for size in args.size or ["640x480", "1200x900"]:
        w, h = (int(v) for v in size.split("x"))
        feat = torch.randn(args.channels, h, w, generator=torch.Generator().manual_seed(0)).relu_()
        old, new, same = before_after(lambda: torch_norm(feat), lambda: norms.ordered_norm(feat), args.repeat)
        print(f"{size}: torch norm {old * 1000:.1f} ms, ordered {new * 1000:.1f} ms, ordered / torch {new / old:.2f}; "
              f"bit for bit equal: {same}; fast path taken: {norms.ordered_is_exact(feat)}", flush=True)


if __name__ == "__main__":
    main()
