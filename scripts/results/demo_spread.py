"""`check`'s tolerances from the spread of the demo's metrics across environments.

Reads the demo tables of every cell of an environment matrix (scripts/results/env_matrix.sh:
OUT/<torch>/<variant>/demo/{hpatches,scenes}_table.csv; variants: native kernels, oneDNN one
instruction set lower, ATen's default kernels, one thread), and writes, per benchmark, method
and metric, the range measured (max - min over the cells) and the tolerance: twice the range,
floored at one step of the metric (one pair of 15 for h_acc, one point for MMA@3 and AUC,
0.1 for P). Estimator seeds move nothing (OpenCV 5's RANSAC ignores cv2.setRNGSeed), so
they are not part of the matrix.

    python scripts/results/demo_spread.py --matrix runs/env_matrix [--write results/baselines/demo_tolerances.csv]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pandas as pd

SETS = {"hpatches": "hpatches", "scenes": "yfcc"}  # demo set -> benchmark name
NOT_METRICS = ("method", "source", "n_pairs", "vs_paper", "protocol")
FLOORS = {"h_acc@1": 0.07, "h_acc@3": 0.07, "h_acc@5": 0.07, "mma@3": 0.01, "auc@5": 1.0, "auc@10": 1.0,
          "auc@20": 1.0, "P": 0.1}


def cells(matrix: Path) -> list[tuple[str, str, Path]]:
    """(torch, variant, demo folder) of each cell with both tables."""
    found = []
    for demo in sorted(matrix.glob("*/*/demo")):
        if all((demo / f"{s}_table.csv").is_file() for s in SETS):
            found.append((demo.parent.parent.name, demo.parent.name, demo))
    return found


def spread(matrix: Path) -> pd.DataFrame:
    rows = []
    for torch_version, variant, demo in cells(matrix):
        for set_name, benchmark in SETS.items():
            table = pd.read_csv(demo / f"{set_name}_table.csv")
            for _, row in table.iterrows():
                for metric in (c for c in table.columns if c not in NOT_METRICS):
                    rows.append({"benchmark": benchmark, "method": row["method"], "metric": metric,
                                 "cell": f"{torch_version}/{variant}", "value": float(row[metric])})
    values = pd.DataFrame(rows)
    if values.empty:
        raise SystemExit(f"{matrix}: no cell with both demo tables (run scripts/results/env_matrix.sh first)")
    grouped = values.groupby(["benchmark", "method", "metric"], sort=False)["value"]
    out = grouped.agg(["min", "max", "count"]).reset_index()
    out["spread"] = out["max"] - out["min"]
    out["tolerance"] = [max(2 * s, FLOORS.get(m, 0.0)) for s, m in zip(out["spread"], out["metric"])]
    # Rounded up to two significant digits, so the file reads as chosen, not as noise.
    out["tolerance"] = [math.ceil(t / 10 ** (math.floor(math.log10(t)) - 1)) * 10 ** (math.floor(math.log10(t)) - 1)
                        for t in out["tolerance"]]
    return out.rename(columns={"count": "cells"})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--matrix", type=Path, default=Path("runs/env_matrix"))
    parser.add_argument("--write", type=Path, default=None, help="write the tolerances CSV (check --tolerances)")
    args = parser.parse_args()
    found = cells(args.matrix)
    print(f"{len(found)} cells: {', '.join(f'{t}/{v}' for t, v, _ in found)}")
    table = spread(args.matrix)
    with pd.option_context("display.width", 200, "display.max_rows", 500):
        print(table.round(4).to_string(index=False))
    if args.write:
        columns = ["benchmark", "method", "metric", "tolerance", "spread", "min", "max", "cells"]
        table[columns].round(6).to_csv(args.write, index=False)
        print(f"written: {args.write}")


if __name__ == "__main__":
    main()
