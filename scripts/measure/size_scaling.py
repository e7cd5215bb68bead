"""How time and peak memory grow with image size: scripts/measure/pair_speed.py at several sizes.

    python scripts/measure/size_scaling.py [--backbone vgg19 --backbone efficientnet_lite0] \
        [--megapixels 0.25 0.5 1 2] [--precision fp32] [--out results/perf]

Each (backbone, size) runs `pair_speed.py --json` in its own process, so that each peak
memory figure (the process's peak RSS) belongs to one size. Sizes are 4:3. Writes
OUT/scaling.csv (one row per backbone and size) and OUT/scaling.png (seconds per pair and
peak memory against megapixels), and prints the rows. VGG19 runs with random weights (the
same cost as ImageNet ones); EfficientNet-Lite0 with its packaged ImageNet weights.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

HERE = Path(__file__).resolve().parent


def size_of(megapixels: float) -> tuple[int, int]:
    """4:3 width x height of about this many megapixels (multiples of 16)."""
    h = math.sqrt(megapixels * 1e6 * 3 / 4)
    return int(round(h * 4 / 3 / 16)) * 16, int(round(h / 16)) * 16


def measure(backbone: str, size: tuple[int, int], precision: str, repeat: int) -> dict:
    command = [sys.executable, str(HERE / "pair_speed.py"), "--backbone", backbone, "--size", f"{size[0]}x{size[1]}",
               "--repeat", str(repeat), "--precision", precision, "--json"]
    if backbone == "vgg19":
        command.append("--random-weights")
    done = subprocess.run(command, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", action="append", default=None)
    parser.add_argument("--megapixels", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0])
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("results/perf"))
    args = parser.parse_args()
    rows = []
    for backbone in args.backbone or ["vgg19", "efficientnet_lite0"]:
        for mp in args.megapixels:
            w, h = size_of(mp)
            r = measure(backbone, (w, h), args.precision, args.repeat)
            rows.append({"backbone": backbone, "megapixels": round(w * h / 1e6, 3), "size": f"{w}x{h}",
                         "precision": args.precision, "backbone_s": round(r["backbone_s"], 3),
                         "total_s": round(r["total_s"], 3), "overhead_ratio": round(r["overhead_ratio"], 3),
                         "peak_rss_mb": round(r["peak_rss_mb"]), "matches": r["matches"]})
            print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "scaling.csv", index=False)
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    for backbone, part in table.groupby("backbone", sort=False):
        ax_t.plot(part["megapixels"], part["total_s"], "o-", label=f"{backbone}: pair")
        ax_t.plot(part["megapixels"], part["backbone_s"], "x--", label=f"{backbone}: backbone only")
        ax_m.plot(part["megapixels"], part["peak_rss_mb"] / 1024, "o-", label=backbone)
    ax_t.set(xlabel="megapixels per image", ylabel="seconds per pair", title=f"time ({args.precision}, CPU)")
    ax_m.set(xlabel="megapixels per image", ylabel="peak RSS (GiB)", title="peak memory")
    for ax in (ax_t, ax_m):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "scaling.png", dpi=120)
    print(f"wrote {args.out / 'scaling.csv'} and {args.out / 'scaling.png'}")


if __name__ == "__main__":
    main()
