"""The quick demo against its targets: `e3cm-bench demo --quick` in a fresh folder,
as a new user runs it (a subprocess, stdout a pipe), measured.

Prints: wall seconds and CPU seconds (user + system of the process and its children; the
wall time depends on what else the machine runs, so the load average is printed beside it),
the lines printed and the widest, the headline numbers per method (HPatches h_acc@1, scenes
auc@10) and how many distinct values they take, whether illumination pairs were run, and
whether `demo --help` names every method the demo runs. Then each target, met or not:
under 90 s, at most 60 lines, at least two methods' headline numbers differ, illumination
pairs included, the help names what runs. Exits 1 if a target is missed.

    python scripts/maintain/demo_time.py [--out DIR] [--keep]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

TARGET_SECONDS = 90.0
TARGET_LINES = 60


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="Folder for the demo (default: a temporary one).")
    parser.add_argument("--keep", action="store_true", help="Keep the demo's folder.")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="demo-time-")) if args.out is None else args.out
    out = work / "demo"
    if out.exists():
        raise SystemExit(f"{out}: exists; the measure needs a fresh folder")
    command = [sys.executable, "-m", "e3cm_bench.cli", "demo", "--quick", "--out", str(out)]
    load_before = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "COLUMNS": "80"})
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if run.returncode != 0:
        print(run.stdout + run.stderr)
        raise SystemExit(f"demo --quick failed (exit {run.returncode})")
    lines = run.stdout.splitlines() + run.stderr.splitlines()
    help_text = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", "demo", "--help"], capture_output=True,
                               text=True, env={**os.environ, "COLUMNS": "200"}).stdout
    from e3cm_bench.apps.demo import METHODS

    hpatches = pd.read_csv(out / "hpatches_table.csv").set_index("method")
    scenes = pd.read_csv(out / "scenes_table.csv").set_index("method")
    sequences = sorted(p.name for p in (out / "data" / "hpatches").iterdir() if p.is_dir())
    n_illumination = sum(s.startswith("i_") for s in sequences) * 5
    print(f"command: {' '.join(command[1:])}")
    print(f"wall: {wall:.1f} s   cpu (user+sys): {cpu:.1f} s   load average (1 min) before: {load_before:.2f}, "
          f"cores: {os.cpu_count()}")
    print(f"printed: {len(lines)} lines, widest {max(map(len, lines), default=0)} columns")
    print(f"pairs: hpatches {int(hpatches['n_pairs'].iloc[0])} ({n_illumination} illumination), "
          f"scenes {int(scenes['n_pairs'].iloc[0])}")
    print("headline per method: hpatches h_acc@1 / h_acc@3, scenes auc@10")
    for method in hpatches.index:
        print(f"  {method:<13} {hpatches.loc[method, 'h_acc@1']:.2f} / {hpatches.loc[method, 'h_acc@3']:.2f}   "
              f"{scenes.loc[method, 'auc@10']:.1f}")
    distinct = hpatches["h_acc@1"].round(6).nunique()
    # The command's description (above its options), not the --methods option's list of choices.
    description = help_text.split("Options")[0]
    missing_in_help = [m for m in METHODS if m not in description]
    targets = [
        (f"under {TARGET_SECONDS:.0f} s (wall)", wall < TARGET_SECONDS),
        (f"at most {TARGET_LINES} lines", len(lines) <= TARGET_LINES),
        (f"headline differs between methods ({distinct} distinct h_acc@1 values)", distinct >= 2),
        (f"illumination pairs included ({n_illumination})", n_illumination > 0),
        ("the help names every method run" + (f" (missing: {', '.join(missing_in_help)})" if missing_in_help else ""),
         not missing_in_help),
    ]
    for text, met in targets:
        print(f"{'met   ' if met else 'MISSED'} {text}")
    if not args.keep and args.out is None:
        shutil.rmtree(work)
    return 0 if all(met for _, met in targets) else 1


if __name__ == "__main__":
    sys.exit(main())
