"""The peak memory of each pair of an e3cm-plus run (issue 68, item 7), as a run records it
(cost.csv: the matching process's resident high-water mark during the pair, reset before it).

The shared HPatches sequences are small (at most 900 x 680); the pairs where e3cm-plus peaked
near 8 GB were full-resolution HPatches pairs of larger sequences. So the sequences are copied
enlarged by --scale (1.6 by default: 1280 x 1024 to 1440 x 960, the size of many HPatches
images), with their homographies rescaled, and run through `e3cm-bench hpatches` as a user
would. Each variant runs in a fresh process, one after the other.

    python scripts/measure/e3cm_memory.py [--scale 1.6] [--data ../shared/data] [--variant NAME=ARGS ...]
        [--backbone efficientnet_lite0] [--random-weights]

A variant is a name and extra CLI arguments (e.g. 'nocache=--feature-cache-mb 0'), or an
environment setting after '@' ('system=@E3CM_BENCH_ALLOCATOR=system'). Prints each pair's peak
(MiB), the part of it the feature cache held (cost.csv's cache_memory_mb) and the rest, the pair's
working memory, and each variant's highest peak, h_acc@3 and n_matches (which must not change).
--random-weights builds the backbone from a file of random weights (memory does not depend on
their values): how VGG19, the default backbone, is measured where its ImageNet weights cannot be
downloaded; the matches then mean nothing, but stay comparable between variants."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from e3cm_bench.storage import RunFolder


def scaled_copy(source: Path, target: Path, scale: float, sequences: list[str] | None = None) -> Path:
    S = np.diag([scale, scale, 1.0])
    for sequence in sorted(p for p in source.iterdir() if p.is_dir() and (not sequences or p.name in sequences)):
        (target / sequence.name).mkdir(parents=True, exist_ok=True)
        for i in range(1, 7):
            image = cv2.imread(str(sequence / f"{i}.ppm"), cv2.IMREAD_COLOR)
            cv2.imwrite(str(target / sequence.name / f"{i}.ppm"),
                        cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR))
        for i in range(2, 7):
            H = np.loadtxt(sequence / f"H_1_{i}")
            np.savetxt(target / sequence.name / f"H_1_{i}", S @ H @ np.linalg.inv(S))
    return target


def random_weights(backbone: str, folder: Path) -> Path:
    """A state-dict file of the backbone's whole torchvision model with random weights (seed 0)."""
    import torch

    from e3cm_bench.backbones.specs import SPECS

    torch.manual_seed(0)
    path = folder / f"{backbone}-random.pt"
    torch.save(SPECS[backbone].build().state_dict(), path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.6)
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--variant", action="append", default=None)
    parser.add_argument("--sequences", default=None, help="comma-separated sequence names (default: all)")
    parser.add_argument("--backbone", default="efficientnet_lite0")
    parser.add_argument("--random-weights", action="store_true")
    args = parser.parse_args()
    variants = args.variant or ["default="]
    with tempfile.TemporaryDirectory() as folder:
        root = scaled_copy(args.data / "hpatches-sequences-release", Path(folder) / "hpatches", args.scale,
                           args.sequences.split(",") if args.sequences else None)
        results, backbone = [], ["--backbone", args.backbone]
        if args.random_weights:
            backbone += ["--weights", str(random_weights(args.backbone, Path(folder)))]
        for variant in variants:
            name, _, extra = variant.partition("=")
            env = dict(os.environ)
            while extra.startswith("@"):  # @KEY=VALUE settings, separated by spaces, then CLI arguments
                setting, _, extra = extra[1:].partition(" ")
                key, _, value = setting.partition("=")
                env[key] = value
            out = Path(folder) / name
            command = ["e3cm-bench", "hpatches", "--root", str(root), "--out", str(out), "--matcher", "e3cm-plus",
                       *backbone, *shlex.split(extra)]
            subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
            folder = RunFolder(out)
            cost, summary = pd.read_csv(folder.cost_path), pd.read_csv(folder.summary_path).iloc[0]
            print(f"== {name} ({extra or 'default'}): per-pair peak MiB")
            working = cost["peak_memory_mb"] - cost["cache_memory_mb"].fillna(0)
            print("   " + json.dumps({"peak": [round(v) for v in cost["peak_memory_mb"]],
                                      "cache": [round(v) for v in cost["cache_memory_mb"].fillna(0)],
                                      "working": [round(v) for v in working]}))
            results.append((name, cost["peak_memory_mb"].max(), working.max(), summary["h_acc@3"],
                            summary["n_matches"], summary["seconds_per_pair"]))
        for name, peak, work, h3, n, seconds in results:
            print(f"{name}: highest peak {peak:.0f} MiB, highest working (peak - cache) {work:.0f} MiB, "
                  f"h_acc@3 {h3:.4f}, n_matches {n:.1f}, {seconds:.2f} s/pair")


if __name__ == "__main__":
    main()
