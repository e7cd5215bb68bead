"""Time per stage of a matcher on synthetic pairs of given sizes (prints measured figures).

    python scripts/bench_speed.py --backbone vgg19 --sizes 640x480 1200x900 [--random-weights]

Random weights are fine for timing (the work does not depend on the weight values,
only the match counts do). Each size is matched `--repeats` times after one warm-up.
"""

from __future__ import annotations

import argparse
import resource
import time

import cv2
import numpy as np
import torch

from e3cm_bench.backbones import load_backbone
from e3cm_bench.synth.textures import demo_homography, procedural_scene
from e3cm_bench.matchers.e3cm import E3CMMatcher
from e3cm_bench.matching.pipeline import E3CMSettings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="vgg19")
    parser.add_argument("--sizes", nargs="+", default=["640x480", "1200x900"])
    parser.add_argument("--estimator", default="top8")
    parser.add_argument("--random-weights", action="store_true")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    backbone = load_backbone(args.backbone, pretrained=not args.random_weights, device=args.device)
    print(f"backbone {args.backbone} ({backbone.weights_id}), device {args.device}, torch threads {torch.get_num_threads()}")
    for variant, settings in (("e3cm", E3CMSettings(estimator=args.estimator)), ("direct", E3CMSettings(cascade=False))):
        matcher = E3CMMatcher(backbone, settings)
        for size in args.sizes:
            w, h = (int(v) for v in size.split("x"))
            image0 = procedural_scene((w, h))
            image1 = cv2.warpPerspective(image0, demo_homography((w, h)), (w, h), borderMode=cv2.BORDER_REFLECT)
            matcher.match(image0, image1)  # warm-up
            runs = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                result = matcher.match(image0, image1)
                runs.append((time.perf_counter() - t, result))
            total, result = min(runs, key=lambda r: r[0])
            stages = ", ".join(f"{k} {v:.3f}" for k, v in result.info["timings"].items())
            print(f"{variant:6s} {w}x{h}: {len(result)} matches, total {total:.2f} s (best of {args.repeats}); {stages}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory {peak:.0f} MiB")


if __name__ == "__main__":
    main()
