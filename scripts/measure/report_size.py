"""How large `e3cm-bench report` makes a site: on a synthetic HPatches-format run of N pairs
(default 1500, SIFT and SIFT with another ratio, at --max-side 320), and on any run folders
given. Prints the sizes (the site, its index page, its drawings); writes under --work.

    python scripts/measure/report_size.py --work /tmp/report-size [--pairs 1500] [RUN_DIR ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.reporting.site import write_report
from e3cm_bench.pipeline.runner import run_benchmark
from e3cm_bench.apps.synth.layouts import write_hpatches


def size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


def describe(site: Path) -> str:
    drawings = site / "img"
    return (f"site {size(site) / 2**20:.1f} MiB (index.html {size(site / 'index.html') / 2**10:.0f} KiB, "
            f"{len(list(drawings.glob('*.jpg')))} drawings {sum(p.stat().st_size for p in drawings.glob('*.jpg')) / 2**20:.1f} MiB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--pairs", type=int, default=1500, help="a multiple of 10 (5 pairs a sequence, half each kind)")
    parser.add_argument("runs", nargs="*", type=Path)
    args = parser.parse_args()
    if args.runs:
        site = write_report(args.runs, args.work / "given", compare=False)
        print(f"{len(args.runs)} given runs: {describe(site.index.parent)}")
    n = args.pairs // 10
    data = args.work / "data"
    if not data.is_dir():
        write_hpatches(data, seed=0, n_viewpoint=n, n_illumination=n)
    runs = []
    for label, options in (("sift", {}), ("sift-r0.9", {"ratio": 0.9})):
        out = args.work / "runs" / label
        method = MethodSpec.create("sift", max_side=320, options=options, label=label)
        started = time.perf_counter()
        run_benchmark("hpatches", out, method, root=data)
        print(f"{label}: {10 * n} pairs matched and evaluated in {time.perf_counter() - started:.0f} s")
        runs.append(out)
    started = time.perf_counter()
    site = write_report(runs, args.work / "site", compare=False)
    print(f"synthetic {10 * n}-pair run, 2 methods: {describe(site.index.parent)}; written in "
          f"{time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
