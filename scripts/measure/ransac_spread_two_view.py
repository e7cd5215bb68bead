"""RANSAC's spread beside the pairs' on every two-view set (issue 69, item 5): for each run folder,
its cached matches scored again under its own evaluation settings with K seeds (no rematching),
and for each of the benchmark's table metrics the standard deviation over the seeds beside the
half-width of the interval over the pairs alone (seed 0, as a run with --repeats 1 reports it).

    python scripts/measure/ransac_spread_two_view.py RUN [RUN ...] [--seeds 5]

Prints one CSV row per run and metric, then per benchmark the median and the largest ratio of
the seeds' sd to the pairs' half-width (sfm is left out: its mapper seeds are already in its
interval). The pose sets' figures are in results/sweep/ransac_spread.csv (from the sweep's cells).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
from e3cm_bench.pipeline.evaluate import evaluate_stage
from e3cm_bench.storage import RunFolder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    print("benchmark,run,metric,seeds,seed_sd,pairs_half_width,two_level_half_width,sd_over_half_width")
    ratios: dict[str, list[float]] = {}
    for folder in args.runs:
        loaded = load_run_pairs(folder)
        benchmark, config = loaded.benchmark, loaded.config
        ev = evaluation_of(config)
        cache = RunFolder(folder).cache()
        _, single, _ = evaluate_stage(benchmark, loaded.pairs, cache, replace(ev, repeats=1))
        _, repeated, _ = evaluate_stage(benchmark, loaded.pairs, cache, replace(ev, repeats=args.seeds))
        for metric in benchmark.table_metrics.values():
            if f"{metric}_sd" not in repeated or f"{metric}_lo" not in single:
                continue
            half = (single[f"{metric}_hi"] - single[f"{metric}_lo"]) / 2
            half2 = (repeated[f"{metric}_hi"] - repeated[f"{metric}_lo"]) / 2
            sd = repeated[f"{metric}_sd"]
            ratio = sd / half if half > 0 else float("nan")
            ratios.setdefault(benchmark.name, []).append(ratio)
            print(f"{benchmark.name},{config.method},{metric},{args.seeds},{sd:.4f},{half:.4f},{half2:.4f},{ratio:.3f}",
                  flush=True)
    for name, values in ratios.items():
        finite = np.asarray([v for v in values if np.isfinite(v)])
        if finite.size:
            print(f"# {name}: {len(values)} run x metric, sd / pairs' half-width median {np.median(finite):.2f}, "
                  f"largest {finite.max():.2f}")


if __name__ == "__main__":
    main()
