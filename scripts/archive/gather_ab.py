"""Gathering normalised level-0 pixels from bf16 rows: dividing the bf16 rows by the float32 norms
against widening them first and dividing in place (cascade.UnitPixels.gather), side by side.

    python scripts/archive/gather_ab.py [--size 640x480 --size 1200x900] [--patches 474] [--repeat 7]

The confidence score of the top-8 and PROSAC cascades gathers patches of level 0 from the
backbone's own channels-last rows (bf16 where the backbone ran in bf16) and divides each row by
its pixel's norm. For each size: random ReLU'd rows of 64 channels stored in bf16, their norms,
and the pixels of `--patches` random 16 x 16 patches (level 4's; pair_speed.py's 640x480 pair
scores 474 of them), gathered both ways; medians, their ratio, and whether the two are equal
bit for bit.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from e3cm_bench.ground.files import cpu_info, cpu_isa
from e3cm_bench.matching.cascade import UnitPixels

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import add_allocator_option, before_after, use_allocator  # noqa: E402 - the speed scripts' helpers


def mixed(rows: torch.Tensor, norms: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """bf16 rows divided by float32 norms: torch widens element by element as it divides."""
    return torch.div(rows.index_select(0, index), norms.index_select(0, index)[:, None])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--patches", type=int, default=474)
    parser.add_argument("--repeat", type=int, default=7)
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator = use_allocator(args.allocator)
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"64 channels, bf16 rows, float32 norms, {args.patches} patches of 16 x 16 pixels; median of {args.repeat}; allocator {allocator}")
    gen = torch.Generator().manual_seed(0)
    for size in args.size or ["640x480", "1200x900"]:
        w, h = (int(v) for v in size.split("x"))
        rows = (torch.randn(h * w, 64, generator=gen).relu_() * 3).bfloat16()
        norms = rows.float().norm(dim=1).clamp_min_(1e-12)
        cells = torch.stack([torch.randint(0, w // 16, (args.patches,), generator=gen),
                             torch.randint(0, h // 16, (args.patches,), generator=gen)], 1)
        unit = UnitPixels(rows, norms, w)  # widens before it divides, in place
        index = unit.patch_index(cells, 16)
        old, new, same = before_after(lambda: mixed(rows, norms, index), lambda: unit.gather(index), args.repeat)
        print(f"{size}: bf16 / float32 {old * 1000:.2f} ms, widened then divided {new * 1000:.2f} ms, "
              f"ratio {new / old:.2f}; bit for bit equal: {same}", flush=True)


if __name__ == "__main__":
    main()
