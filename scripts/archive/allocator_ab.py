"""glibc's malloc keeping freed memory (what a run does) against its default, side by side in one process.

    python scripts/archive/allocator_ab.py [--backbone vgg19] [--precision bf16] [--size 640x480 --size 1200x900] \
        [--repeat 3]

torch's CPU tensors come from malloc. By default glibc serves a block over its mmap threshold
(which grows to at most 32 MiB) with a fresh mmap and unmaps it when freed, so each backbone
pass touches new pages, which the kernel zeroes on a page fault. `devices.keep_freed_memory`
(called by every run) turns mmap off and never trims the heap, so one pass's pages serve the
next. This script alternates the two settings in one process on the same synthetic pair
(`e3cm`, random weights, seed 0): "default" is glibc's behaviour once its threshold has grown
to its 32 MiB ceiling (mmap on, a 32 MiB threshold, trimming, the heap trimmed before each
timing); "keep" is keep_freed_memory's. After each switch one untimed match lets the heap
grow back (as a run's first pair does), then a pair's match and its two backbone passes are
timed. It prints medians of a pair's match and of its two
backbone passes alone, the ratio keep / default, whether the matches are equal bit for bit,
and the process's peak resident memory (`--csv FILE` appends a row per size). Needs glibc
(Linux).
"""

from __future__ import annotations

import argparse
import csv
import ctypes
import hashlib
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import synthetic_pair  # noqa: E402 - the same pair as the per-pair figures

from e3cm_bench.ground.files import cpu_info, cpu_isa  # noqa: E402
from e3cm_bench.method.spec import MethodSpec  # noqa: E402

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_MMAP_MAX = -1, -3, -4


def set_allocator(libc, mode: str) -> None:
    if mode == "keep":  # devices.keep_freed_memory's settings
        libc.mallopt(M_MMAP_MAX, 0)
        libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    else:  # glibc's default behaviour at its grown threshold
        libc.mallopt(M_MMAP_MAX, 65536)
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 64 << 20)
        libc.malloc_trim(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="vgg19")
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16"))
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--csv", type=Path, default=None, help="append a row per size to this CSV (for docs/speed.md)")
    args = parser.parse_args()
    if platform.libc_ver()[0] != "glibc":
        raise SystemExit("allocator_ab.py compares glibc's settings; this C library is not glibc")
    libc = ctypes.CDLL("libc.so.6")
    options = {} if args.precision == "fp32" else {"precision": args.precision}
    torch.manual_seed(0)
    matcher = MethodSpec.create("e3cm", args.backbone, options=options).build("cpu", pretrained=False)
    print(f"e3cm, {args.backbone} random weights, {args.precision}; CPU {cpu_info()[0]} ({cpu_isa()}); torch "
          f"{torch.__version__}, {torch.get_num_threads()} threads; median of {args.repeat}, alternating", flush=True)
    for size in args.size or ["640x480", "1200x900"]:
        w, h = (int(v) for v in size.split("x"))
        image0, image1 = synthetic_pair(w, h)
        times = {mode: {"pair": [], "backbone": []} for mode in ("default", "keep")}
        digests = {}
        for round_ in range(args.repeat + 1):  # round 0 warms up both
            for mode in ("default", "keep"):
                set_allocator(libc, mode)
                matcher.match(image0, image1)  # untimed: the heap the default trimmed grows back under keep
                t = time.perf_counter()
                m = matcher.match(image0, image1)
                pair_s = time.perf_counter() - t
                t = time.perf_counter()
                matcher.pyramids(image0, image1)
                backbone_s = time.perf_counter() - t
                digests.setdefault(mode, set()).add(hashlib.sha256(
                    m.keypoints0.tobytes() + m.keypoints1.tobytes() + m.scores.tobytes()).hexdigest())
                if round_:
                    times[mode]["pair"].append(pair_s)
                    times[mode]["backbone"].append(backbone_s)
        med = {mode: {k: statistics.median(v) for k, v in parts.items()} for mode, parts in times.items()}
        same = len(digests["default"] | digests["keep"]) == 1
        print(f"{size}: pair default {med['default']['pair']:.2f} s, keep {med['keep']['pair']:.2f} s "
              f"(keep / default {med['keep']['pair'] / med['default']['pair']:.2f}); backbone alone default "
              f"{med['default']['backbone']:.2f} s, keep {med['keep']['backbone']:.2f} s "
              f"({med['keep']['backbone'] / med['default']['backbone']:.2f}); {len(m)} matches, bit for bit equal: "
              f"{same}", flush=True)
        if args.csv is not None:
            new = not args.csv.exists()
            with args.csv.open("a", newline="") as f:
                out = csv.writer(f)
                if new:
                    out.writerow(["backbone, precision", "size", "pair, default s", "pair, keep s",
                                  "pair, keep / default", "backbone alone, default s", "backbone alone, keep s",
                                  "backbone alone, keep / default", "matches equal", "CPU"])
                out.writerow([f"{args.backbone}, {args.precision}", size, f"{med['default']['pair']:.2f}",
                              f"{med['keep']['pair']:.2f}", f"{med['keep']['pair'] / med['default']['pair']:.2f}",
                              f"{med['default']['backbone']:.2f}", f"{med['keep']['backbone']:.2f}",
                              f"{med['keep']['backbone'] / med['default']['backbone']:.2f}", "yes" if same else "NO",
                              f"{cpu_info()[0]} ({cpu_isa()}), {torch.get_num_threads()} threads"])
    print(f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
