"""Run-to-run spread of the demo's metrics, from which `check`'s default tolerances are chosen.

Runs the demo with several estimator seeds (the data stays the same) and once with a
single CPU thread, then prints, per metric, the largest difference from the seed-0 run
over all methods and both sets, and twice that as the proposed tolerance. Deterministic
methods (e3cm top8, direct, sift) are matched once and only re-evaluated under other seeds.

    python scripts/demo_spread.py [--out runs/spread] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd

DETERMINISTIC = ("e3cm", "direct", "sift")  # draw no random numbers while matching
SETS = ("hpatches", "scenes")


def table(run: Path, set_name: str) -> pd.DataFrame:
    t = pd.read_csv(run / f"{set_name}_table.csv").set_index("method")
    return t.drop(columns=[c for c in ("source", "n_pairs") if c in t.columns])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/spread"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    variants = {f"seed{s}": (s, {}) for s in args.seeds}
    variants["threads1"] = (args.seeds[0], {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})
    reference = args.out / f"seed{args.seeds[0]}"
    for name, (seed, env) in variants.items():
        out = args.out / name
        if out != reference and not env and (reference / "hpatches").is_dir():
            for set_name in SETS:  # the seed changes no match of these: reuse them, evaluate anew
                for method in DETERMINISTIC:
                    if not (out / set_name / method).exists():
                        shutil.copytree(reference / set_name / method, out / set_name / method)
        command = [sys.executable, "-m", "e3cm_bench.cli", "demo", "--out", str(out), "--seed", str(seed)]
        print("+", " ".join(command), env or "", flush=True)
        subprocess.run(command, check=True, env={**os.environ, **env}, stdout=subprocess.DEVNULL)

    rows = []
    for set_name in SETS:
        base = table(reference, set_name)
        for name in variants:
            other = table(args.out / name, set_name)
            diff = (other - base).abs()
            for metric in diff.columns:
                rows.append({"set": set_name, "variant": name, "metric": metric, "max_abs_diff": diff[metric].max(),
                             "worst_method": diff[metric].idxmax()})
    spread = pd.DataFrame(rows)
    print(spread.to_string(index=False))
    worst = spread.groupby("metric")["max_abs_diff"].max()
    print("\nlargest difference per metric, and twice that:")
    print(pd.DataFrame({"max_abs_diff": worst, "2x": 2 * worst}).to_string())


if __name__ == "__main__":
    main()
