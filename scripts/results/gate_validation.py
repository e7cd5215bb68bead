"""The regression gate's noise model, validated: its false-alarm rate on ensemble draws held
out from the fit, its verdict on runs from CPUs it never saw, and its power against known
degradations. Prints one table per part; docs/results.md "Noise model" quotes them.

    python scripts/results/gate_validation.py --demo e3cm-demo [--other NAME=DIR ...] [--out results/docs/gate]

--demo: the demo folder the committed baselines were written from (its run folders hold the
matches the degradations start from). --other NAME=DIR: a demo folder made on another CPU or
with other kernels (e.g. OPENBLAS_CORETYPE=Haswell e3cm-bench demo --out DIR), or the
per-pair files of one (../shared/cpu-runs/...); checked against the committed baselines.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.gate import noise_gate
from e3cm_bench.benchmarks.from_record import evaluation_of
from e3cm_bench.gate.check import baseline_metrics, read_baseline
from e3cm_bench.gate.ensemble import noise_path, read_noise
from e3cm_bench.pipeline.evaluate import evaluate_pair
from e3cm_bench.ground.matches import Matches
from e3cm_bench.reporting.tables import Run, load_run
from e3cm_bench.storage import RunFolder
from e3cm_bench.stats.noise import CHECK_ALPHA, metric_alpha

SETS = {"hpatches": "demo_hpatches", "scenes": "demo_scenes"}
SHIFTS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)


def summarized(run: Run, per_pair: pd.DataFrame) -> Run:
    """run with per_pair as its pairs and the summary they give."""
    ev = evaluation_of(run.run_config)
    summary = run.benchmark.summarize(per_pair.to_dict("records"), ev)
    return replace(run, per_pair=per_pair, summary=summary)


def verdicts(runs: list[Run], baseline: Path, models: dict | None = None, alpha: float | None = None):
    """noise_gate verdicts of runs against a baseline (models: a refit, else the stored one)."""
    table = read_baseline(baseline)
    metrics = [c for c in table.columns if c not in ("benchmark", "method", "environment", "identity")]
    rows = {(r["benchmark"], r["method"]): r for _, r in table.iterrows()}
    if models is None:
        models = noise_gate.run_models(noise_gate.read_pair_baseline(noise_gate.pairs_path(baseline)),
                                       read_noise(noise_path(baseline)))
    alpha = alpha if alpha is not None else metric_alpha(len(metrics) * len(rows))
    out = []
    for run in runs:
        key = (run.benchmark.name, run.label)
        values = {m: float(rows[key][m]) for m in metrics}
        out.append(noise_gate.gate_run(run, models[key], values, baseline_metrics(run), alpha,
                                       evaluation_of(run.run_config), n_samples=2000))
    return out


def flagged(verdict) -> list[str]:
    return [f"{g.metric} {g.status}" for g in verdict.gates if g.status != "ok"]


def held_out_false_alarms(demo: Path, baseline: Path, set_name: str) -> pd.DataFrame:
    """Each draw in turn left out of the fit and checked as a run: whole checks flagged."""
    pairs = noise_gate.read_pair_baseline(noise_gate.pairs_path(baseline))
    noise = read_noise(noise_path(baseline))
    runs = {r.label: r for r in (load_run(p) for p in sorted((demo / set_name).iterdir()) if RunFolder(p).config_path.is_file())}
    rows = []
    for draw in sorted(noise["draw"].unique()):
        models = noise_gate.run_models(pairs, noise[noise["draw"] != draw])
        checked = []
        for method, run in runs.items():
            own = noise[(noise["draw"] == draw) & (noise["method"] == method)].drop(columns=["benchmark", "method", "draw"])
            checked.append(summarized(run, own.reset_index(drop=True)))
        for v in verdicts(checked, baseline, models):
            rows.append({"set": set_name, "draw": draw, "method": v.method, "metrics": len(v.gates),
                         "flagged": "; ".join(flagged(v)),
                         "pairs_outside": len({m.pair for m in v.moves if not m.inside})})
    return pd.DataFrame(rows)


def other_cpu(name: str, folder: Path, baseline: Path, set_name: str) -> pd.DataFrame:
    runs = [load_run(p) for p in sorted((folder / set_name).iterdir()) if RunFolder(p).config_path.is_file()]
    rows = []
    for v in verdicts(runs, baseline):
        moved = sorted({m.pair for m in v.moves})
        outside = sorted({m.pair for m in v.moves if not m.inside})
        rows.append({"set": set_name, "cpu": name, "method": v.method, "flagged": "; ".join(flagged(v)) or "none",
                     "pairs_moved": len(moved), "pairs_outside_own_noise": len(outside),
                     "outside": ", ".join(outside)})
    return pd.DataFrame(rows)


def other_aggregates(name: str, table: Path, demo: Path, baseline: Path, set_name: str) -> pd.DataFrame:
    """Aggregates measured elsewhere (a baseline CSV written on another CPU, whose pairs were not
    kept) against the model: this machine's runs with their summary's gated metrics replaced."""
    other = read_baseline(table).set_index("method")
    runs = []
    for path in sorted((demo / set_name).iterdir()):
        if RunFolder(path).config_path.is_file():
            run = load_run(path)
            summary = dict(run.summary)
            for metric, column in {**run.benchmark.table_metrics, "mma@3": "mma@3"}.items():
                if metric in other.columns and column in summary:
                    summary[column] = float(other.loc[run.label, metric])
            runs.append(replace(run, summary=summary))
    rows = []
    for v in verdicts(runs, baseline):
        rows.append({"set": set_name, "cpu": name, "method": v.method,
                     "flagged": "; ".join(flagged(v)) or "none",
                     "smallest_p": min(g.p_value for g in v.gates)})
    return pd.DataFrame(rows)


def degraded(run: Run, pairs, change) -> Run:
    """run re-evaluated from its cached matches after change(matches, pair) -> matches."""
    cache = run.folder.cache()
    ev = evaluation_of(run.run_config)
    rows = [evaluate_pair(run.benchmark, pair, change(cache.read(pair.name), pair), ev) for pair in pairs]
    return summarized(run, pd.DataFrame(rows, columns=run.benchmark.pair_columns(ev)))


def power(demo: Path, baseline: Path, set_name: str) -> pd.DataFrame:
    """Per method: the smallest shift of every keypoint in image 1 that the gate flags, and
    whether two pairs turned into failures are flagged."""
    rows = []
    for path in sorted((demo / set_name).iterdir()):
        if not RunFolder(path).config_path.is_file():
            continue
        run = load_run(path)
        dataset = run.run_config.dataset
        options = {k: dataset[k] for k in run.benchmark.option_names if dataset.get(k) is not None}
        pairs = run.benchmark.load_dataset(dataset["root"], **options).pairs
        smallest = None
        for shift in SHIFTS:
            def moved(m: Matches, pair, s=shift) -> Matches:
                return Matches(m.keypoints0, m.keypoints1 + np.float32([s, 0.0]), m.scores, m.info)

            if any(g.status == "regression" for g in verdicts([degraded(run, pairs, moved)], baseline)[0].gates):
                smallest = shift
                break
        best = list(run.per_pair.sort_values(run.benchmark.failure[0])["pair"][:2])

        def failed(m: Matches, pair) -> Matches:
            if pair.name in best:
                return Matches(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), None, m.info)
            return m

        v = verdicts([degraded(run, pairs, failed)], baseline)[0]
        rows.append({"set": set_name, "method": run.label, "smallest_shift_flagged_px": smallest,
                     "two_failures_flagged": "; ".join(flagged(v)) or "not flagged"})
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", type=Path, required=True)
    parser.add_argument("--baselines", type=Path, default=Path("results/baselines"))
    parser.add_argument("--other", action="append", default=[], help="NAME=DIR")
    parser.add_argument("--other-aggregates", action="append", default=[],
                        help="NAME=DIR: a folder holding demo_hpatches.csv and demo_scenes.csv written elsewhere")
    parser.add_argument("--only", default="false_alarms,other_cpus,other_aggregates,power",
                        help="comma-separated parts to run")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    parts: dict[str, list[pd.DataFrame]] = {"false_alarms": [], "other_cpus": [], "other_aggregates": [], "power": []}
    only = set(args.only.split(","))
    for set_name, stem in SETS.items():
        baseline = args.baselines / f"{stem}.csv"
        if "false_alarms" in only:
            parts["false_alarms"].append(held_out_false_alarms(args.demo, baseline, set_name))
        for item in args.other if "other_cpus" in only else []:
            name, _, folder = item.partition("=")
            parts["other_cpus"].append(other_cpu(name, Path(folder), baseline, set_name))
        for item in args.other_aggregates if "other_aggregates" in only else []:
            name, _, folder = item.partition("=")
            parts["other_aggregates"].append(other_aggregates(name, Path(folder) / f"{stem}.csv", args.demo, baseline,
                                                              set_name))
        if "power" in only:
            parts["power"].append(power(args.demo, baseline, set_name))
    pd.set_option("display.width", 250)
    pd.set_option("display.max_colwidth", 90)
    for name, tables in parts.items():
        if not tables:
            continue
        table = pd.concat(tables, ignore_index=True)
        print(f"\n== {name}")
        if name == "false_alarms":
            checks = table.groupby(["set", "draw"])["flagged"].apply(lambda f: (f != "").any())
            per_metric = (table["flagged"] != "").sum() / table["metrics"].sum()
            print(f"held-out draws: {len(checks)} checks, {int(checks.sum())} flagged anything "
                  f"(rate {checks.mean():.3f}; stated {CHECK_ALPHA}); metrics flagged: {per_metric:.4f}")
            print(table[table["flagged"] != ""].to_string(index=False))
        else:
            print(table.to_string(index=False))
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            table.to_csv(args.out / f"{name}.csv", index=False)


if __name__ == "__main__":
    main()
