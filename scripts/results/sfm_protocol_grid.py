"""The sfm protocol grid of docs/sfm.md ("The protocol"): every method's cached sfm matches
(made by sfm_results.py kitti / synth into RUNS/SET/METHOD) reconstructed and scored again under
each protocol of {incremental, global} x {exact, merge 2 px, hloc's quantization} x
{estimator, COLMAP verification}, K mapper seeds each; and the seed check of issue 60 (the
default protocol's AUC@10 under --seed 0 and --seed 1).

    python scripts/results/sfm_protocol_grid.py grid --runs runs/sfm-results --scratch /tmp/grid --to results/sfm
    python scripts/results/sfm_protocol_grid.py seeds --runs runs/sfm-results --scratch /tmp/grid --to results/sfm
    python scripts/results/sfm_protocol_grid.py table --parts /tmp/kitti.csv /tmp/synth.csv --to results/sfm \
        --runs runs/sfm-results --scratch /tmp/grid

RUNS is only read: each method's config.yaml and matches.h5 are copied to SCRATCH/SET/CELL/METHOD
and evaluated there (--eval-only). seeds evaluates the default protocol into SCRATCH/default/SET/METHOD
(then `sfm_results.py side --out SCRATCH/default` remakes results/sfm/ from them) and with
--seed 1 into SCRATCH/default-seed1/, then compare's err_pose verdict between every two --check
methods at each seed (TO/seed_verdicts.csv). grid writes TO/protocol_grid.csv (one row per set, method and
protocol: the mean over seeds, its interval over pairs and seeds, the seeds' spread, the models'
and the tracks' numbers); seeds writes TO/seed_stability.csv.
"""

from __future__ import annotations

import argparse
import shutil
from dataclasses import asdict, replace
from itertools import combinations, product
from pathlib import Path

import pandas as pd

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.benchmarks.eval_options import RECONSTRUCTION_FIELDS
from e3cm_bench.benchmarks.from_record import evaluation_of
from e3cm_bench.apps.demo import METHODS
from e3cm_bench.pipeline.runner import run_benchmark
from e3cm_bench.reporting.compare import compare_runs
from e3cm_bench.reporting.runs import load_run
from e3cm_bench.storage import RunFolder

MAPPERS = ("incremental", "global")
MERGES = {"exact": {"merge": "exact"}, "merge2": {"merge": "radius", "merge_px": 2.0}, "quantize": {"merge": "quantize"}}
VERIFICATIONS = ("estimator", "colmap")
KEEP = ("auc@5", "auc@10", "auc@20", "maa")
FACTS = ("n_failures", "registered_images", "n_models", "mean_track_length", "mean_reprojection_error",
         "track_length_database", "repeat_share", "merge_displacement_px")


def evaluate_copy(source: Path, target: Path, protocol: dict, seed: int = 0) -> dict:
    """source's cached matches evaluated in `target` under `protocol` (sfm's evaluation options by
    name, and dataset options such as the window); a target already evaluated under it (its config.yaml's evaluation block, seed included)
    is read, not evaluated again, so that an interrupted grid resumes."""
    made, into = RunFolder(source), RunFolder(target)
    config = made.run_config()
    bench = get_benchmark("sfm")
    older = evaluation_of(config, seed=seed)
    # the run's own protocol under the cell's (its merge radius only where the cell gives one)
    given = {k: v for k, v in asdict(older).items() if k in RECONSTRUCTION_FIELDS and k != "merge_px"}
    evaluation = {k: v for k, v in protocol.items() if k not in bench.option_names}  # a window is the dataset's
    resolved = bench.resolve_eval(older.protocol, seed, {**given, **evaluation})
    ev = replace(older, **{k: getattr(resolved, k) for k in RECONSTRUCTION_FIELDS})
    if into.summary_path.is_file() and asdict(evaluation_of(into.run_config())) == asdict(ev):
        return pd.read_csv(into.summary_path).iloc[0].to_dict()
    if not into.matches_path.is_file():
        target.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(made.config_path, into.config_path)
        for block in made.matches_path.parent.glob(made.matches_path.stem + "*.h5"):  # every block of the cache
            shutil.copyfile(block, into.matches_path.parent / block.name)
    load = config.dataset_load
    options = {**{k: v for k, v in load["options"].items() if k in bench.option_names},
               **{k: v for k, v in protocol.items() if k in bench.option_names}}
    dataset = bench.load_dataset(load["root"], **options)
    run_benchmark(bench, target, dataset=dataset, ev=ev, eval_only=True,
                  dataset_load={**load, "options": {k: str(v) for k, v in options.items()}})
    return pd.read_csv(into.summary_path).iloc[0].to_dict()


def row_of(set_name: str, method: str, cell: dict, summary: dict) -> dict:
    row = {"set": set_name, "method": method, **cell}
    for key in KEEP:
        row[key] = summary[key]
        row[f"{key}_lo"], row[f"{key}_hi"] = summary[f"{key}_lo"], summary[f"{key}_hi"]
        row[f"{key}_sd"] = summary.get(f"{key}_sd")
    for key in FACTS:
        row[key] = summary.get(key)
    return row


def done_methods(runs: Path, set_name: str, methods: list[str]) -> list[str]:
    found = [m for m in methods if RunFolder(runs / set_name / m).summary_path.is_file()]
    for m in sorted(set(methods) - set(found)):
        print(f"{runs / set_name / m}: no summary.csv (matching not finished?); left out")
    return found


def grid(runs: Path, scratch: Path, to: Path, sets: list[str], methods: list[str], seeds: int,
         merges: tuple[str, ...] = tuple(MERGES)) -> None:
    rows = []
    out = to / "protocol_grid.csv"
    for set_name in sets:
        for method in done_methods(runs, set_name, methods):
            for mapper, merge, verification in product(MAPPERS, merges, VERIFICATIONS):
                cell = {"mapper": mapper, "merge": merge, "verification": verification}
                protocol = {"mapper": mapper, "verification": verification, "mapper_seeds": seeds, **MERGES[merge]}
                target = scratch / set_name / f"{mapper}-{merge}-{verification}" / method
                summary = evaluate_copy(runs / set_name / method, target, protocol)
                rows.append(row_of(set_name, method, cell, summary))
                print(f"{set_name} {method} {mapper} {merge} {verification}: AUC@10 {summary['auc@10']:.1f} "
                      f"[{summary['auc@10_lo']:.1f}, {summary['auc@10_hi']:.1f}] sd {summary['auc@10_sd']:.1f}",
                      flush=True)
                to.mkdir(parents=True, exist_ok=True)
                pd.DataFrame(rows).to_csv(out, index=False, float_format="%.6g")  # as it goes: a long grid
    print(f"-> {out}")


def seed_check(runs: Path, scratch: Path, to: Path, sets: list[str], methods: list[str], check: list[str]) -> None:
    """The default protocol's AUC@10 with the evaluation seed 0, and 1 for the `check` methods
    (issue 60's check: at most 5 points apart for SIFT and e3cm-plus on KITTI)."""
    rows = []
    for set_name in sets:
        for method in done_methods(runs, set_name, methods):
            row = {"set": set_name, "method": method}
            for seed in (0, 1) if method in check else (0,):
                # seed 0's folders (SCRATCH/default/SET/METHOD) are what sfm_results.py side reads
                where = scratch / ("default" if seed == 0 else "default-seed1") / set_name / method
                summary = evaluate_copy(runs / set_name / method, where, {}, seed=seed)
                for key in ("auc@10", "auc@10_lo", "auc@10_hi", "auc@10_sd", "maa"):
                    row[f"{key}_seed{seed}"] = summary[key]
            if "auc@10_seed1" in row:
                row["auc@10_moved"] = abs(row["auc@10_seed1"] - row["auc@10_seed0"])
                # issue 69's bar: each seed's figure inside the other's interval
                row["each_inside_other"] = bool(row["auc@10_lo_seed0"] <= row["auc@10_seed1"] <= row["auc@10_hi_seed0"]
                                                and row["auc@10_lo_seed1"] <= row["auc@10_seed0"] <= row["auc@10_hi_seed1"])
            rows.append(row)
            print(row, flush=True)
    to.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(to / "seed_stability.csv", index=False, float_format="%.6g")
    print(f"-> {to / 'seed_stability.csv'}")
    verdicts = []
    for set_name in sets:
        checked = [m for m in done_methods(runs, set_name, methods) if m in check]
        for a, b in combinations(checked, 2):
            row = {"set": set_name, "a": a, "b": b}
            for seed, folder in ((0, "default"), (1, "default-seed1")):
                found = compare_runs(load_run(scratch / folder / set_name / a), load_run(scratch / folder / set_name / b))
                pose = next(r for r in found.results if r.metric == "err_pose")
                row.update({f"verdict_seed{seed}": pose.verdict, f"d_seed{seed}": pose.diff,
                            f"d_lo_seed{seed}": pose.lo, f"d_hi_seed{seed}": pose.hi})
            row["same_verdict"] = row["verdict_seed0"] == row["verdict_seed1"]
            verdicts.append(row)
            print(row, flush=True)
    pd.DataFrame(verdicts).to_csv(to / "seed_verdicts.csv", index=False, float_format="%.6g")
    print(f"-> {to / 'seed_verdicts.csv'} (compare's err_pose verdict, B - A, at each evaluation seed)")


def wide(to: Path, parts: list[Path]) -> None:
    """TO/protocol_grid.csv from the grid CSVs `parts` (one per set, say), and its AUC@10 per
    method side by side, TO/protocol_grid_auc10.csv: each cell "mean [lo, hi] sd S (registered)"."""
    table = pd.concat([pd.read_csv(p) for p in parts], ignore_index=True)
    to.mkdir(parents=True, exist_ok=True)
    table.to_csv(to / "protocol_grid.csv", index=False, float_format="%.6g")
    keys = ["set", "mapper", "merge", "verification"]
    table["cell"] = [f"{r['auc@10']:.1f} [{r['auc@10_lo']:.1f}, {r['auc@10_hi']:.1f}] sd {r['auc@10_sd']:.1f} "
                     f"({r['registered_images']:.0f}/{r['n_models']:.1f})" for _, r in table.iterrows()]
    shown = table.pivot_table(index=keys, columns="method", values="cell", aggfunc="first", sort=False).reset_index()
    order = [m for m in METHODS if m in shown.columns]
    shown[keys + order].to_csv(to / "protocol_grid_auc10.csv", index=False)
    print(shown[keys + order].to_string())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("grid", "seeds", "table"))
    parser.add_argument("--parts", nargs="*", type=Path, default=[], help="table: the grid CSVs to put together")
    parser.add_argument("--runs", type=Path, required=True, help="the sfm runs: RUNS/SET/METHOD (only read)")
    parser.add_argument("--scratch", type=Path, required=True, help="where the copies are evaluated")
    parser.add_argument("--to", type=Path, default=Path("results/sfm"))
    parser.add_argument("--sets", nargs="*", default=["kitti", "synth"])
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--seeds", type=int, default=3, help="mapper seeds per protocol (default 3)")
    parser.add_argument("--merges", nargs="*", default=list(MERGES), help="grid: the merge cells (default all three)")
    parser.add_argument("--check", nargs="*", default=["sift", "e3cm-plus"],
                        help="seeds: the methods evaluated with --seed 1 too (default sift e3cm-plus)")
    args = parser.parse_args()
    if args.step == "table":
        wide(args.to, args.parts)
    elif args.step == "grid":
        grid(args.runs, args.scratch, args.to, args.sets, args.methods, args.seeds, tuple(args.merges))
    else:
        seed_check(args.runs, args.scratch, args.to, args.sets, args.methods, args.check)


if __name__ == "__main__":
    main()
