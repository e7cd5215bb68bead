"""RANSAC's spread beside the pairs' (issue 69, item 5): from a protocol sweep's cells (e3cm-bench
sweep --seeds K), for each run and cell, the AUC@10 of each seed, their standard deviation, the
width of the interval over pairs alone (seed 0) and of the two-level interval (pairs and seeds).

    python scripts/measure/ransac_spread.py SWEEP_OUT [SWEEP_OUT ...]

Prints one CSV row per sweep, cell and run, and per sweep the median ratio of the seeds' sd to
the pairs-only interval's half-width.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.geometry import metrics
from e3cm_bench.pipeline.sweep import auc_interval
from e3cm_bench.stats.bootstrap import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED


def main() -> None:
    print("sweep,cell,run,seeds,auc10_seed_sd,pairs_only_width,two_level_width,sd_over_half_width")
    for out in map(Path, sys.argv[1:]):
        ratios = []
        for path in sorted((out / "cells").glob("*.csv")):
            table = pd.read_csv(path)
            runs = sorted({c.rsplit("_s", 1)[0] for c in table.columns if c != "pair"})
            for run in runs:
                columns = sorted((c for c in table.columns if c.rsplit("_s", 1)[0] == run), key=lambda c: int(c.rsplit("_s", 1)[1]))
                errors = table[columns].to_numpy(np.float64)
                each = [metrics.pose_auc(errors[:, s], (10,))[0] for s in range(errors.shape[1])]
                sd = float(np.std(each, ddof=1)) if len(each) > 1 else 0.0
                lo1, hi1 = auc_interval(errors[:, :1], 10.0, BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED)
                lo2, hi2 = auc_interval(errors, 10.0, BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED)
                ratio = sd / ((hi1 - lo1) / 2) if hi1 > lo1 else float("nan")
                ratios.append(ratio)
                print(f"{out.name},{path.stem},{run},{errors.shape[1]},{sd:.3f},{hi1 - lo1:.3f},{hi2 - lo2:.3f},{ratio:.3f}")
        print(f"# {out}: median sd / pairs-only half-width {np.nanmedian(ratios):.3f}, max {np.nanmax(ratios):.3f} "
              f"over {len(ratios)} run x cell", flush=True)


if __name__ == "__main__":
    main()
