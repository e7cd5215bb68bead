"""Reduced-precision passes with the weights cast once against cast at every pass, side by side.

    python scripts/archive/weight_cast_ab.py [--backbone vgg19 --backbone efficientnet_lite0]
        [--precision bf16] [--size 640x480 --size 1200x900] [--repeat 5] [--allocator keep|system]

Under bf16 or fp16 the convolutions run under autocast, which casts their float32 weights
at every call. `backbones.cast_weights` stores them in that precision once, when the backbone
is built. For each backbone (random weights, seed 0) and size, two backbones are built from
the same draw, one with its weights left in float32 (as before), and they pass the same
synthetic image in turn: medians of the passes after a warm-up, their ratio, and whether
the maps are equal bit for bit.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import torch

from e3cm_bench.backbones import loading as backbones
from e3cm_bench.ground.files import cpu_info, cpu_isa
from e3cm_bench.matchers.deep import image_to_tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import add_allocator_option, alternate, synthetic_pair, use_allocator  # noqa: E402


def build(name: str, precision: str, cast: bool) -> backbones.Backbone:
    torch.manual_seed(0)  # the same random draw for both
    real = backbones.cast_weights
    if not cast:
        backbones.cast_weights = lambda module, dtype: None
    try:
        return backbones.load_backbone(name, pretrained=False, precision=precision)
    finally:
        backbones.cast_weights = real


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", action="append", default=None)
    parser.add_argument("--precision", action="append", default=None, choices=("bf16", "fp16"))
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--repeat", type=int, default=5)
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator = use_allocator(args.allocator)
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"random weights (seed 0); median of {args.repeat}; allocator {allocator}")
    for name in args.backbone or ["vgg19", "efficientnet_lite0"]:
        for precision in args.precision or ["bf16"]:
            ways = {"each pass": build(name, precision, False), "once": build(name, precision, True)}
            dtype = backbones.REDUCED_DTYPES[precision]
            cast = sum(p.numel() for p in ways["once"].parameters() if p.dtype == dtype)
            for size in args.size or ["640x480", "1200x900"]:
                w, h = (int(v) for v in size.split("x"))
                image = image_to_tensor(synthetic_pair(w, h)[0], "cpu")
                medians, maps = alternate({way: functools.partial(backbone, image) for way, backbone in ways.items()},
                                          args.repeat)
                each, once = (1000 * medians[way] for way in ways)
                same = all(torch.equal(a, b) for a, b in zip(maps["each pass"], maps["once"]))
                print(f"{name} {precision} {size} ({cast / 1e6:.1f}M values cast): cast at each pass {each:.0f} ms, "
                      f"once {once:.0f} ms, once / each {once / each:.3f}; bit for bit equal: {same}", flush=True)


if __name__ == "__main__":
    main()
