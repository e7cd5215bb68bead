"""The backbone's maps made C-contiguous float32: torch's copy against the banded copy, side by side.

    python scripts/archive/maps_copy_ab.py [--backbone vgg19 --backbone efficientnet_lite0]
        [--precision bf16 --precision fp32] [--size 640x480 --size 1200x900] [--repeat 3]

Under channels_last (every backbone in bf16 or fp16, Lite0 in fp32) the convolutions give
channels-last maps; the matching steps index C-contiguous float32 ones (`backbones._maps`).
`backbones.channel_first_float` makes that copy a band of rows at a time. For each level of
each backbone (random weights, a random image), the stage's real output is copied both ways,
alternating: medians, their ratio and whether the two copies are equal bit for bit. Then
whole passes of one image with the plain copy and with the banded one, alternating.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import time
from pathlib import Path

import torch

from e3cm_bench.backbones import loading as backbones
from e3cm_bench.ground.files import cpu_info, cpu_isa
from e3cm_bench.method.spec import MethodSpec

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import alternate  # noqa: E402 - the speed scripts' side-by-side timing


def plain(x: torch.Tensor) -> torch.Tensor:
    return x.float().contiguous()


def plain_maps(x: torch.Tensor) -> list[torch.Tensor]:
    return [plain(x[i]) for i in range(len(x))]


def median_ms(seconds: list[float]) -> float:
    return 1000 * statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", action="append", default=None)
    parser.add_argument("--precision", action="append", default=None, choices=("fp32", "bf16"))
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"random weights (seed 0); median of {args.repeat}")
    banded_maps = backbones._maps
    for name in args.backbone or ["vgg19", "efficientnet_lite0"]:
        for precision in args.precision or ["bf16", "fp32"]:
            torch.manual_seed(0)
            options = {} if precision == "fp32" else {"precision": precision}
            backbone = MethodSpec.create("e3cm", name, options=options).build("cpu", pretrained=False).backbone
            if backbone.memory_format != "channels_last":
                print(f"{name} {precision}: NCHW convolutions, its maps are already C-contiguous (no copy)")
                continue
            for size in args.size or ["640x480", "1200x900"]:
                w, h = (int(v) for v in size.split("x"))
                image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
                outputs = []
                backbones._maps = lambda x: outputs.append(x[0]) or banded_maps(x)
                try:
                    backbone.forward(image)
                finally:
                    backbones._maps = banded_maps
                total = {"plain": 0.0, "banded": 0.0}
                for level, x in enumerate(outputs):
                    medians, copies = alternate({"plain": functools.partial(plain, x),
                                                 "banded": functools.partial(backbones.channel_first_float, x)}, args.repeat)
                    old, new = 1000 * medians["plain"], 1000 * medians["banded"]
                    total["plain"] += old
                    total["banded"] += new
                    print(f"{name} {precision} {size} level {level} {tuple(x.shape)} {str(x.dtype)[6:]}: "
                          f"plain {old:.1f} ms, banded {new:.1f} ms, banded / plain {new / old:.2f}; "
                          f"bit for bit equal: {torch.equal(copies['plain'], copies['banded'])}", flush=True)
                print(f"{name} {precision} {size} all levels: plain {total['plain']:.0f} ms, "
                      f"banded {total['banded']:.0f} ms per image", flush=True)
                passes = {"plain": [], "banded": []}
                for _ in range(args.repeat + 1):
                    for way, maps in (("plain", plain_maps), ("banded", banded_maps)):
                        backbones._maps = maps
                        try:
                            t = time.perf_counter()
                            backbone.forward(image)
                            passes[way].append(time.perf_counter() - t)
                        finally:
                            backbones._maps = banded_maps
                old, new = median_ms(passes["plain"][1:]), median_ms(passes["banded"][1:])
                print(f"{name} {precision} {size} whole pass of one image: plain copy {old:.0f} ms, "
                      f"banded {new:.0f} ms, banded / plain {new / old:.2f}", flush=True)


if __name__ == "__main__":
    main()
