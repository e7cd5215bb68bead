"""The sfm results of docs/sfm.md: every built-in method (CNN ones on efficientnet_lite0) on a
multi-view set, matched together (each image through the backbone once for all methods), each
into OUT/SET/METHOD, then the set's table in OUT/SET/table.{csv,md}.

    python scripts/results/sfm_results.py kitti --out /tmp/sfm-results
    python scripts/results/sfm_results.py synth --out /tmp/sfm-results
    python scripts/results/sfm_results.py kitti --eval-only --merge-px 2 --out /tmp/sfm-results  # after copying
    python scripts/results/sfm_results.py side --out /tmp/sfm-results --to results/sfm

The runs are made under the sfm benchmark's default protocol; sfm_protocol_grid.py evaluates
their matches again under others (and under the default with other seeds) on copies.

side: each run's two-view numbers beside its multi-view ones, in TO/two_view_vs_multi_view.csv,
and each run's config.yaml, summary.csv, per_pair.csv and sfm/per_seed.csv copied to TO/SET/METHOD/. The two-view
numbers are the pose benchmark's (megadepth: the essential-matrix RANSAC of PROTOCOLS §3) on the
same pairs and the same cached matches, so the two columns differ only in what is made of the
matches; for KITTI, results/sample/table2_kitti holds the pose benchmark's own 31 pairs too.

kitti: the shared KITTI 00 frames (../shared/data/megadepth_test_1500, kitti00_seq.npz), pair
synth: the room scene rendered from 10 views (e3cm_bench/apps/synth/multiview.py, written under
OUT/data). Both with the pair graph a sequential window of 3 (each image with the next 3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.apps.demo import BACKBONE, METHODS
from e3cm_bench.pipeline.experiments import write_table
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.runner import run_methods

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "megadepth_test_1500"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("set", choices=("kitti", "synth", "side"))
    parser.add_argument("--to", type=Path, default=Path("results/sfm"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--eval-only", action="store_true", help="reconstruct and evaluate the cached matches again")
    parser.add_argument("--merge-px", type=float, default=0.0,
                        help="the sets' keypoint merge radius; above 0 the runs go to OUT/SET-mergeR/")
    parser.add_argument("--window", type=int, default=3, help="the pair graph's window (default 3)")
    parser.add_argument("--views", type=int, default=10, help="synth's number of views (default 10)")
    args = parser.parse_args()
    bench = get_benchmark("sfm")
    if args.set == "side":
        side_by_side(args.out, args.to, args.methods)
        return
    if args.set == "kitti":
        root, options = SHARED, {"scene_info": SHARED / "scene_info" / "kitti00_seq.npz", "window": str(args.window)}
    else:
        from e3cm_bench.apps.synth.multiview import write_multiview

        root = args.out / "data" / "room"
        options = {"scene_info": write_multiview(root, n_views=args.views), "window": str(args.window)}
    dataset = bench.load_dataset(root, **options)
    ev = bench.resolve_eval(seed=0, given={"merge_px": args.merge_px} if args.merge_px else None)
    out = args.out / (args.set + (f"-merge{args.merge_px:g}" if args.merge_px else ""))
    runs = [(out / label, MethodSpec.create(backbone=BACKBONE, max_side=bench.max_side(None), seed=0, label=label,
                                            **METHODS[label]))
            for label in args.methods]
    load = {"root": str(Path(root).resolve()), "skip_bad": False, "options": {k: str(v) for k, v in options.items()}}
    if args.eval_only:  # the reconstruction and metrics again, from the cached matches
        from e3cm_bench.pipeline.runner import run_benchmark

        for run_dir, _ in runs:
            run_benchmark(bench, run_dir, dataset=dataset, dataset_load=load, ev=ev, eval_only=True)
    else:
        run_methods(bench, runs, dataset, ev=ev, dataset_load=load)
    write_table([run_dir for run_dir, _ in runs], out / "table", paper_rows=False, compare=False)


def two_view(run_dir: Path) -> tuple[dict, pd.DataFrame]:
    """The pose benchmark's summary (with intervals) and rows on an sfm run's pairs and matches,
    and IMC's stereo mAA of the same errors with its interval."""
    from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
    from e3cm_bench.pipeline.evaluate import evaluate_stage
    from e3cm_bench.storage import RunFolder
    from e3cm_bench.sfm.metrics import maa
    from e3cm_bench.stats.bootstrap import bootstrap_interval

    run = load_run_pairs(run_dir)  # the sfm run's pairs, loaded as the run loaded them
    per_pair, summary, _ = evaluate_stage(get_benchmark("megadepth"), run.pairs, RunFolder(run_dir).cache(),
                                          evaluation_of(run.config))
    errors = per_pair["err_pose"].to_numpy(float)
    summary["maa"] = maa(errors)
    bounds = bootstrap_interval(list(errors), lambda rows: {"maa": maa(rows)}, keys=["maa"])
    summary["maa_lo"], summary["maa_hi"] = bounds["maa"]
    return summary, per_pair


def side_by_side(out: Path, to: Path, methods: list[str]) -> None:
    import shutil

    from e3cm_bench.storage import RunFolder

    rows = []
    sets = sorted((p.name for p in out.iterdir() if p.is_dir() and p.name.split("-")[0] in ("kitti", "synth")),
                  key=lambda name: (name.split("-")[0], name))
    for set_name in sets:
        for label in methods:
            run_dir = out / set_name / label
            run, copy = RunFolder(run_dir), RunFolder(to / set_name / label)
            if not run.summary_path.is_file():
                print(f"{run_dir}: no summary.csv; left out")
                continue
            copy.path.mkdir(parents=True, exist_ok=True)
            for name in ("config_path", "summary_path", "per_pair_path"):
                shutil.copyfile(getattr(run, name), getattr(copy, name))
            if (run_dir / "sfm" / "per_seed.csv").is_file():  # each mapper seed's numbers
                shutil.copyfile(run_dir / "sfm" / "per_seed.csv", copy.path / "per_seed.csv")
            multi = pd.read_csv(run.summary_path).iloc[0]
            two, _ = two_view(run_dir)
            row = {"set": set_name, "method": label, "n_pairs": int(multi["n_pairs"])}
            for key in ("auc@5", "auc@10", "auc@20", "maa"):
                row[f"two_view_{key}"] = two[key]
                row[f"two_view_{key}_lo"], row[f"two_view_{key}_hi"] = two[f"{key}_lo"], two[f"{key}_hi"]
            for key in ("auc@5", "auc@10", "auc@20", "maa"):
                row[key] = multi[key]
                row[f"{key}_lo"], row[f"{key}_hi"] = multi[f"{key}_lo"], multi[f"{key}_hi"]
            for key in ("n_failures", "registered_images", "n_images", "n_models", "points", "mean_track_length",
                        "mean_reprojection_error", "auc@10_sd", "mapper", "mapper_seeds", "merge", "verification",
                        "track_length_database", "repeat_share", "merge_displacement_px"):
                row[key] = multi.get(key)
            rows.append(row)
        for table in ("table.csv", "table.md"):
            if (out / set_name / table).is_file():
                shutil.copyfile(out / set_name / table, to / set_name / table)
    table = pd.DataFrame(rows)
    for (set_name, group) in table.groupby("set", sort=False):
        for key in ("two_view_auc@10", "auc@10"):
            # rank 1 = best; ties share the better rank
            table.loc[group.index, f"rank_{key}"] = group[key].rank(ascending=False, method="min").astype(int)
    to.mkdir(parents=True, exist_ok=True)
    table.to_csv(to / "two_view_vs_multi_view.csv", index=False, float_format="%.6g")
    print(table[["set", "method", "two_view_auc@10", "auc@10", "maa", "registered_images", "n_models",
                 "rank_two_view_auc@10", "rank_auc@10"]].to_string())


if __name__ == "__main__":
    main()
