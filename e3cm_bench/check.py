"""`e3cm-bench check`: compare runs' summaries with a committed baseline (CI regression check).

A baseline is a CSV with one row per run: ``benchmark, method`` and the metrics checked
(the paper-table metrics of the benchmark, plus MMA@3 for homography benchmarks). A metric
that fell by more than its tolerance is a regression (exit 1); one that rose by more is a
notice, since a silent improvement is also a change worth seeing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .files import read_csv, write_atomically, write_csv
from .formats import format_number
from .report import Run, load_run

# Tolerances (absolute, in the metric's own unit: fractions for HPatches, percent for pose),
# from the spread measured over repeated demo runs (scripts/demo_spread.py; README
# "Regression check"): estimator seeds 0, 1, 2 gave identical numbers (OpenCV 5's RANSAC
# ignores cv2.setRNGSeed), one CPU thread instead of two moved the deep methods' features
# by rounding and with them the scene poses: largest differences auc@5 12.1, auc@10 9.2,
# auc@20 3.3, P 0.066, MMA@3 0.000002, h_acc 0. Each tolerance is twice that, and never
# below one pair's worth for h_acc (1 of 15 pairs) or one point of MMA.
DEFAULT_TOLERANCES = {
    "mma@3": 0.01,
    "h_acc@1": 0.07,
    "h_acc@3": 0.07,
    "h_acc@5": 0.07,
    "auc@5": 25.0,
    "auc@10": 19.0,
    "auc@20": 7.0,
    "P": 0.15,
}
KEYS = ("benchmark", "method")


def baseline_metrics(run: Run) -> dict[str, float]:
    """The metrics of a run that a baseline records: its table columns (+ mma@3 where present)."""
    values = {metric: float(run.summary[column]) for metric, column in run.benchmark.table_metrics.items()}
    if "mma@3" in run.summary:
        values["mma@3"] = float(run.summary["mma@3"])
    return values


def find_runs(paths: list[Path]) -> list[Run]:
    """Run folders given, or found below the folders given (those holding config.yaml + summary.csv)."""
    runs = []
    for path in paths:
        path = Path(path)
        if not path.is_dir():
            raise ValueError(f"{path}: not a folder")
        if (path / "config.yaml").is_file():
            runs.append(load_run(path))
            continue
        found = sorted(p.parent for p in path.rglob("config.yaml") if (p.parent / "summary.csv").is_file())
        if not found:
            raise ValueError(f"{path}: no run folder (config.yaml + summary.csv) in it")
        runs += [load_run(p) for p in found]
    return runs


def write_baseline(runs: list[Run], path: Path) -> Path:
    rows = [{"benchmark": run.benchmark.name, "method": run.label, **baseline_metrics(run)} for run in runs]
    return write_csv(pd.DataFrame(rows), path)


@dataclass
class Finding:
    benchmark: str
    method: str
    metric: str
    baseline: float
    measured: float
    tolerance: float

    @property
    def delta(self) -> float:
        return self.measured - self.baseline

    @property
    def status(self) -> str:
        if np.isnan(self.baseline) and np.isnan(self.measured):
            return "ok"
        if np.isnan(self.measured) or self.delta < -self.tolerance:
            return "regression"
        if np.isnan(self.baseline) or self.delta > self.tolerance:
            return "improvement"
        return "ok"


def parse_tolerances(items: list[str] | None) -> dict[str, float]:
    tolerances = dict(DEFAULT_TOLERANCES)
    for item in items or []:
        metric, sep, value = item.partition("=")
        try:
            tolerances[metric.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not metric.strip():
            raise ValueError(f"--tolerance: expected METRIC=VALUE (e.g. auc@10=2.5), got {item!r}")
    return tolerances


def compare(runs: list[Run], baseline_path: Path, tolerances: dict[str, float]) -> tuple[list[Finding], list[str]]:
    """Each baseline metric of each run, and the problems that are no metric (runs missing)."""
    baseline = read_csv(baseline_path, what="baseline (write one with check --update)")
    missing_columns = [c for c in KEYS if c not in baseline.columns]
    if missing_columns:
        raise ValueError(f"{baseline_path}: missing column(s) {', '.join(missing_columns)}")
    rows = {(str(r["benchmark"]), str(r["method"])): r for _, r in baseline.iterrows()}
    seen, findings, problems = set(), [], []
    for run in runs:
        key = (run.benchmark.name, run.label)
        if key not in rows:
            problems.append(f"{run.dir}: {key[1]} on {key[0]} is not in the baseline {baseline_path}")
            continue
        seen.add(key)
        measured = baseline_metrics(run)
        for metric in baseline.columns:
            if metric in KEYS or pd.isna(rows[key][metric]) and metric not in measured:
                continue
            tolerance = tolerances.get(metric)
            if tolerance is None:
                raise ValueError(f"{baseline_path}: no tolerance for metric {metric!r}; pass --tolerance {metric}=T")
            findings.append(Finding(key[0], key[1], metric, float(rows[key][metric]),
                                    float(measured.get(metric, np.nan)), tolerance))
    for key in rows:
        if key not in seen:
            problems.append(f"{baseline_path}: {key[1]} on {key[0]} has no run among those checked")
    return findings, problems


def markdown_summary(findings: list[Finding], problems: list[str], baseline_path: Path) -> str:
    """A Markdown report (GitHub Actions: append it to $GITHUB_STEP_SUMMARY)."""
    marks = {"ok": "ok", "regression": "**regression**", "improvement": "improved"}
    lines = [f"### e3cm-bench check against `{baseline_path}`", ""]
    bad = [f for f in findings if f.status == "regression"]
    lines.append(f"{len(findings)} metrics checked: {len(bad)} regression(s), "
                 f"{sum(f.status == 'improvement' for f in findings)} improvement(s), {len(problems)} problem(s).")
    lines += ["", "| benchmark | method | metric | baseline | measured | change | tolerance | status |",
              "|---|---|---|---:|---:|---:|---:|---|"]
    for f in findings:
        lines.append(f"| {f.benchmark} | {f.method} | {f.metric} | {format_number(f.baseline, f.metric, fraction_decimals=4)} | "
                     f"{format_number(f.measured, f.metric, fraction_decimals=4)} | "
                     f"{format_number(f.delta, 'd_', decimals=4 if abs(f.baseline) < 1.5 else 2)} | {f.tolerance:g} | {marks[f.status]} |")
    lines += [f"- {problem}" for problem in problems]
    return "\n".join(lines) + "\n"


def write_summary(text: str, path: Path) -> None:
    """Append (GitHub's step summary file is shared by the steps of a job)."""
    previous = Path(path).read_text() if Path(path).is_file() else ""
    write_atomically(path, lambda tmp: tmp.write_text(previous + text))
