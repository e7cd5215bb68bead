"""Does the evaluation's estimator change the order of the methods? Re-evaluates the cached
sample runs of scripts/results/make_sample_results.sh (runs/sample/) with OpenCV and with PoseLib
(copies; the runs stay as they are) and writes one table per sample (prints measured figures).

    python scripts/results/estimator_table.py [--data ../shared/data] [--runs runs/sample] [--out results/sample/estimators]
"""

from __future__ import annotations

import argparse
import shutil
from dataclasses import replace
from pathlib import Path

import pandas as pd
from rich.console import Console

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.benchmarks.from_record import evaluation_of
from e3cm_bench.ground.files import write_csv
from e3cm_bench.pipeline.runner import run_benchmark
from e3cm_bench.storage import RunFolder

# sample -> (benchmark, root below --data, dataset options, metrics to compare)
SAMPLES = {
    "table1_hpatches": ("hpatches", "hpatches-sequences-release", {}, ["h_acc@1", "h_acc@3", "h_acc@5"]),
    "table2_kitti": ("megadepth", "megadepth_test_1500", {"scene_info": ["scene_info/kitti00_seq.npz"]},
                     ["auc@5", "auc@10", "auc@20"]),
    "table3_scannet": ("yfcc", "scannet_sample", {"pairs": "pairs_with_gt.txt"}, ["auc@5", "auc@10", "auc@20"]),
}
ESTIMATORS = ("opencv", "poselib")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--runs", type=Path, default=Path("runs/sample"))
    parser.add_argument("--work", type=Path, default=Path("runs/estimators"))
    parser.add_argument("--out", type=Path, default=Path("results/sample/estimators"))
    args = parser.parse_args()
    console = Console(quiet=True)
    args.out.mkdir(parents=True, exist_ok=True)
    for sample, (name, root, options, columns) in SAMPLES.items():
        benchmark = get_benchmark(name)
        root = args.data / root
        options = {k: ([root / x for x in v] if isinstance(v, list) else root / v) for k, v in options.items()}
        rows = []
        for run in sorted(d for d in (args.runs / sample).iterdir() if RunFolder(d).matches_path.is_file()):
            config = RunFolder(run).run_config()
            settings = evaluation_of(config)
            for estimator in ESTIMATORS:
                copy = args.work / sample / estimator / run.name
                if not copy.exists():
                    shutil.copytree(run, copy)
                summary = run_benchmark(benchmark, copy, None, root=root, dataset_options=options, eval_only=True,
                                        ev=replace(settings, estimator=estimator), console=console).iloc[0]
                rows.append({"method": config.method, "estimator": estimator,
                             **{c: round(float(summary[c]), 2 if name != "hpatches" else 3)
                                for c in columns}})
        table = pd.DataFrame(rows)
        write_csv(table, args.out / f"{sample}.csv")
        key = columns[1]
        print(f"\n{sample} ({benchmark.name}; {key} ranks the methods)\n")
        print("| method | " + " | ".join(f"{c} {e}" for c in columns for e in ESTIMATORS) + " |")
        print("|---" * (1 + len(columns) * len(ESTIMATORS)) + "|")
        for method, group in table.groupby("method", sort=True):
            values = group.set_index("estimator")
            print(f"| {method} | " + " | ".join(f"{values.loc[e, c]:g}" for c in columns for e in ESTIMATORS) + " |")
        ranks = {e: order(table[table.estimator == e], key) for e in ESTIMATORS}
        for estimator, text in ranks.items():
            print(f"\norder by {key}, {estimator}: {text}")
        print(f"same order: {ranks['opencv'] == ranks['poselib']}")


def order(rows: pd.DataFrame, key: str) -> str:
    """Methods from best to worst by `key`; tied methods joined by '='."""
    groups = rows.groupby(key, sort=True)["method"].apply(lambda m: " = ".join(sorted(m)))
    return " > ".join(reversed(list(groups)))


if __name__ == "__main__":
    main()
