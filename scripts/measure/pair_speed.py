"""Time per stage of a matcher on synthetic pairs (prints measured figures; never asserted).

    python scripts/measure/pair_speed.py --backbone vgg19 --size 1200x900 --repeat 2 --precision fp32 \
        [--matcher e3cm] [--random-weights | --weights FILE] [--device cpu] [--json] \
        [--compare-release PATH] [--allocator keep|system]

Each size is matched once to warm up, then `--repeat` times; medians are reported. Random
weights cost the same as ImageNet ones (only the match counts differ). With
`--compare-release PATH` (a local checkout of the E3CM authors' release, never a dependency)
the release's `match_large_img` + `refinement_pose_ransac` runs on the same images with the
same weights, alternating with ours in this process. `--json` ends the output with one JSON
object: backbone_s, total_s, overhead_ratio (total_s / backbone_s), release_s, peak_rss_mb,
device, precision and the stage medians of the last size, and the same for every size under
"sizes" (peak_rss_mb is the process's peak over all sizes). `--allocator keep` (the default)
keeps freed memory for reuse as a run does (devices.keep_freed_memory; the release, in the
same process, runs under it too); `system` leaves the C library's default.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from e3cm_bench.backbones.loading import load_backbone
from e3cm_bench.ground.devices import allocator, keep_freed_memory
from e3cm_bench.ground.machine import cpu_info, cpu_isa
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.apps.synth.textures import demo_homography, procedural_scene


def synthetic_pair(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    image0 = procedural_scene((w, h))
    image1 = cv2.warpPerspective(image0, demo_homography((w, h)), (w, h), borderMode=cv2.BORDER_REFLECT)
    return image0, image1


def add_allocator_option(parser: argparse.ArgumentParser) -> None:
    """--allocator keep|system, shared by the speed scripts."""
    parser.add_argument("--allocator", default="keep", choices=("keep", "system"),
                        help="keep: glibc keeps freed memory for reuse, as a run does (devices.keep_freed_memory); "
                             "system: the C library's default")


def use_allocator(choice: str) -> str:
    """Apply --allocator; returns what the process's allocator does (printed beside the figures)."""
    return keep_freed_memory() if choice == "keep" else allocator()


def alternate(ways: dict, repeat: int) -> tuple[dict[str, float], dict]:
    """Call each of `ways` (name -> function of nothing) in turn, repeat + 1 rounds, the first
    a warm-up: each way's median seconds over the later rounds, and its last output."""
    seconds: dict[str, list[float]] = {name: [] for name in ways}
    outputs = {}
    for _ in range(repeat + 1):
        for name, run in ways.items():
            t = time.perf_counter()
            outputs[name] = run()
            seconds[name].append(time.perf_counter() - t)
    return {name: statistics.median(times[1:]) for name, times in seconds.items()}, outputs


def before_after(before, after, repeat: int) -> tuple[float, float, bool]:
    """Alternate two ways of computing one tensor (functions of nothing): the median seconds
    of each and whether their outputs are equal bit for bit."""
    medians, outputs = alternate({"before": before, "after": after}, repeat)
    return medians["before"], medians["after"], torch.equal(outputs["before"], outputs["after"])


def peak_memory_mb(device: str) -> float:
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


class ReleaseRunner:
    """The E3CM release's matcher loaded from a local checkout, with the given VGG19 weights."""

    def __init__(self, path: Path, state_dict: dict, device: str):
        import torchvision

        folder = path / "E3CM_deep_networks" if (path / "E3CM_deep_networks").is_dir() else path
        sys.path.insert(0, str(folder))
        original = torchvision.models.vgg19

        def vgg19_with_our_weights(*args, **kwargs):  # the release asks for pretrained=True (a download)
            model = original(weights=None)
            model.load_state_dict(state_dict)
            return model

        torchvision.models.vgg19 = vgg19_with_our_weights
        import DFM_matcher  # noqa: E402 - from the checkout
        import utils  # noqa: E402

        DFM_matcher.models.vgg19 = vgg19_with_our_weights
        self.utils = utils
        self.matcher = DFM_matcher.DeepFeatureMatcher(model="VGG19", device=torch.device(device), enable_two_stage=False,
                                                      ratio_th=[0.9, 0.9, 0.9, 0.9, 0.95])

    def match(self, image0: np.ndarray, image1: np.ndarray) -> int:
        with torch.no_grad():
            _, _, a, b = self.matcher.match_large_img(image0, image1)
            a, _ = self.utils.refinement_pose_ransac(a, b, 0.01)
        return a.shape[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="vgg19")
    parser.add_argument("--matcher", default="e3cm", help="e3cm, e3cm-ransac, e3cm-release, direct, dfm")
    parser.add_argument("--size", action="append", default=None, help="WxH (repeatable; default 640x480, 1200x900)")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--random-weights", action="store_true")
    parser.add_argument("--weights", default=None)
    parser.add_argument("--compare-release", type=Path, default=None)
    parser.add_argument("--json", action="store_true")
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator_used = use_allocator(args.allocator)
    sizes = args.size or ["640x480", "1200x900"]

    options = {} if args.precision == "fp32" else {"precision": args.precision}
    spec = MethodSpec.create(args.matcher, args.backbone, weights=args.weights, options=options)
    torch.manual_seed(0)  # random weights are the same draw on every run (matches, and so the cascade's work, depend on them)
    matcher = spec.build(args.device, pretrained=not args.random_weights)
    release = None
    if args.compare_release is not None:
        if args.backbone != "vgg19":
            raise SystemExit("--compare-release needs --backbone vgg19 (the release's default network)")
        # The same weights on both sides: rebuild the full torchvision model from our stages' weights.
        import torchvision

        full = torchvision.models.vgg19(weights=None)
        stages = matcher.backbone.stages
        if args.precision != "fp32":  # its weights are stored in that precision: take the float32 ones
            torch.manual_seed(0)
            stages = load_backbone(args.backbone, args.weights, pretrained=not args.random_weights).stages
        ours = {f"features.{k}": v for stage in stages for k, v in stage.state_dict().items()}
        full.load_state_dict({**full.state_dict(), **ours})
        release = ReleaseRunner(args.compare_release, full.state_dict(), args.device)
    cpu = f"{cpu_info()[0]} ({cpu_isa()})"
    print(f"{spec.describe()}; backbone weights {matcher.backbone.weights_id}; precision {args.precision}; "
          f"device {args.device}; CPU {cpu}; torch threads {torch.get_num_threads()}; allocator {allocator_used}")

    result, per_size = {}, []
    for size in sizes:
        w, h = (int(v) for v in size.split("x"))
        image0, image1 = synthetic_pair(w, h)
        matcher.match(image0, image1)  # warm-up
        if release is not None:
            release.match(image0, image1)
        totals, backbones, releases, stages = [], [], [], {}
        for _ in range(args.repeat):
            sync(args.device)
            t = time.perf_counter()
            m = matcher.match(image0, image1)
            sync(args.device)
            totals.append(time.perf_counter() - t)
            for key, value in m.info["timings"].items():
                stages.setdefault(key, []).append(value)
            t = time.perf_counter()
            matcher.pyramids(image0, image1)  # the backbone alone (2 images)
            sync(args.device)
            backbones.append(time.perf_counter() - t)
            if release is not None:
                t = time.perf_counter()
                n_release = release.match(image0, image1)
                releases.append(time.perf_counter() - t)
        result = {
            "size": size, "matcher": args.matcher, "backbone": args.backbone, "matches": len(m),
            "backbone_s": statistics.median(backbones), "total_s": statistics.median(totals),
            "stages_s": {k: statistics.median(v) for k, v in stages.items()},
            "device": args.device, "precision": args.precision, "allocator": allocator_used,
        }
        result["overhead_ratio"] = result["total_s"] / result["backbone_s"]
        line = (f"{args.matcher} {size}: {len(m)} matches; total {result['total_s']:.2f} s, backbone alone "
                f"{result['backbone_s']:.2f} s (x{result['overhead_ratio']:.2f}); stages "
                + ", ".join(f"{k} {v:.3f}" for k, v in result["stages_s"].items()))
        if releases:
            result["release_s"] = statistics.median(releases)
            result["release_matches"] = n_release
            line += f"; release {result['release_s']:.2f} s ({n_release} matches), ours / release " \
                    f"{result['total_s'] / result['release_s']:.2f}"
        print(line + f" (median of {args.repeat})")
        per_size.append(result)
    result["peak_rss_mb"] = peak_memory_mb(args.device)
    print(f"peak memory {result['peak_rss_mb']:.0f} MiB")
    if args.json:  # the last size's figures at the top level, every size's under "sizes"
        print(json.dumps({**result, "cpu": cpu, "sizes": per_size}))


if __name__ == "__main__":
    main()
