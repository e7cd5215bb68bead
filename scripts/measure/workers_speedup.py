"""Wall time of one process against --workers N on this machine, alternating, same run.

    python scripts/measure/workers_speedup.py --root ../shared/data/hpatches-sequences-release [--workers 2] [--repeat 2]

Each round runs the same HPatches benchmark (direct, EfficientNet-Lite0, --max-side 320 by
default) once in one process with all threads and once as N worker processes with the
threads divided, into fresh folders, and prints the times, the ratio, and whether the
numbers agree (they may not: the thread count changes the rounding of the CNN features).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from e3cm_bench.storage import RunFolder


def run(args: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *args], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--matcher", default="direct")
    parser.add_argument("--max-side", default="320")
    options = parser.parse_args()
    common = ["hpatches", "--root", str(options.root), "--matcher", options.matcher, "--backbone", "efficientnet_lite0",
              "--max-side", options.max_side]
    times = {"1 process": [], f"{options.workers} workers": []}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(options.repeat):
            for name, extra in (("1 process", []), (f"{options.workers} workers", ["--workers", str(options.workers)])):
                out = Path(tmp) / f"{name.replace(' ', '_')}_{round_}"
                times[name].append(run([*common, "--out", str(out), *extra]))
                print(f"round {round_ + 1}: {name}: {times[name][-1]:.1f} s", flush=True)
        same = RunFolder(Path(tmp) / "1_process_0").summary_path.read_bytes() == \
            RunFolder(Path(tmp) / f"{options.workers}_workers_0").summary_path.read_bytes()
    best = {name: min(values) for name, values in times.items()}
    one, many = best.values()
    print(f"best of {options.repeat}: 1 process {one:.1f} s, {options.workers} workers {many:.1f} s, "
          f"ratio {many / one:.2f}; summaries {'identical' if same else 'differ'}")


if __name__ == "__main__":
    main()
