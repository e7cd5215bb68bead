"""`e3cm-bench check`: compare runs' summaries with a committed baseline (CI regression check).

A baseline is a CSV with one row per run: ``benchmark, method`` and the metrics checked
(the paper-table metrics of the benchmark, plus MMA@3 for homography benchmarks). A metric
that fell by more than its tolerance is a regression (exit 1); one that rose by more is a
notice, since a silent improvement is also a change worth seeing.

The numbers move with what made them: the CPU's instruction set (oneDNN picks other
convolution kernels on AVX2 than on AVX-512), the torch build, the thread count. So the
baseline's ``environment`` column records, per row, the versions and CPU settings of the run
it was written from (`environment_string`), and a check names what differs from them
(gate/notes.py): information, never a failure.

With a noise ensemble beside the baseline (``<baseline>.noise.csv``, written by
``check --update --ensemble K``), the gate is the noise model instead (`noise_gate`): each
metric is flagged only where its change lies outside what a rerun on another CPU gives, at
a stated false-alarm rate, and the pairs that moved are named, each against its own noise.
The tolerances below then apply only to runs the ensemble does not hold.

Tolerances: a ``--tolerance`` on the command line (``METHOD:METRIC=T`` for one method,
``METRIC=T`` for all) > the most specific row of a ``--tolerances`` file (columns benchmark,
method, metric, tolerance; ``*`` = any) > DEFAULT_TOLERANCES. See `Tolerances`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.gate import noise_gate
from e3cm_bench.gate.ensemble import noise_path, read_noise
from e3cm_bench.ground.files import read_keyed_csv, write_atomically, write_csv
from e3cm_bench.reporting.escape import markdown_code, markdown_text
from e3cm_bench.drawing.formats import format_number
from e3cm_bench.stats.noise import CHECK_ALPHA, metric_alpha
from e3cm_bench.storage.fingerprint import protocol_items
from e3cm_bench.storage.environment import environment_string
from e3cm_bench.reporting.runs import Run, eval_settings_of, load_run
from e3cm_bench.gate.tolerances import (
    ANY,  # noqa: F401 - re-exported: check.ANY is the gate's name for it
    DEFAULT_TOLERANCES,  # noqa: F401 - re-exported: check.DEFAULT_TOLERANCES is the gate's name for it
    TOLERANCE_FILE_COLUMNS,  # noqa: F401 - re-exported: check.TOLERANCE_FILE_COLUMNS is the gate's name for it
    Tolerances,
    parse_tolerance_options,  # noqa: F401 - re-exported: check.parse_tolerance_options is the gate's name for it
    parse_tolerances,  # noqa: F401 - re-exported: check.parse_tolerances is the gate's name for it
    read_tolerance_file,  # noqa: F401 - re-exported: check.read_tolerance_file is the gate's name for it
)
from e3cm_bench.benchmarks.from_record import evaluation_of
from e3cm_bench.storage import RunFolder

KEYS = ("benchmark", "method")
ENVIRONMENT_COLUMN = "environment"  # not a metric: where the row's numbers were made
IDENTITY_COLUMN = "identity"  # not a metric: what made the matches (config.yaml identity, as JSON)
PROTOCOL_COLUMN = "protocol_items"  # not a metric: what the numbers were scored under (storage/fingerprint.py)
NOT_METRICS = (*KEYS, ENVIRONMENT_COLUMN, IDENTITY_COLUMN, PROTOCOL_COLUMN)


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
        found = [folder.path for folder in RunFolder.find(path)]
        if not found:
            raise ValueError(f"{path}: no run folder (config.yaml + summary.csv) in it")
        runs += [load_run(p) for p in found]
    return runs


def write_baseline(runs: list[Run], path: Path) -> Path:
    """The aggregate baseline (one row per run) and, beside it, the per-pair one; never over a
    run's own file (RUN/summary.csv as --baseline), nor its noise draws' name beside it."""
    path = Path(path)
    RunFolder.refuse_own_files([path, noise_gate.pairs_path(path), noise_path(path)], "check --update", "--baseline")
    seen: dict[tuple[str, str], Path] = {}
    for run in runs:
        key = (run.benchmark.name, run.label)
        if key in seen:
            raise ValueError(f"{run.dir}: {key[1]} on {key[0]} is also the label of {seen[key]}; "
                             "a baseline holds one run per label")
        seen[key] = run.dir
    rows = [{"benchmark": run.benchmark.name, "method": run.label, **baseline_metrics(run),
             ENVIRONMENT_COLUMN: environment_string(run.run_config),
             IDENTITY_COLUMN: json.dumps(run.run_config.identity or {}, sort_keys=True),
             PROTOCOL_COLUMN: json.dumps(protocol_items(run.run_config))} for run in runs]
    noise_gate.write_pair_baseline(runs, noise_gate.pairs_path(path))
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


def read_baseline(path: Path) -> pd.DataFrame:
    return read_keyed_csv(path, "baseline (write one with check --update)", KEYS)


def _baseline_value(value, path: Path, key: tuple[str, str], metric: str) -> float:
    """A baseline cell as a number: NaN (empty) passes, for the callers to judge; an infinity is
    refused, since every measured value would then be a change in the same direction
    (-inf: "improvement" whatever the run gives)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {metric} of {key[1]} on {key[0]} is {value!r}, not a number") from None
    if math.isinf(number):
        raise ValueError(f"{path}: column {metric}, {key[1]} on {key[0]}: {value} is not a finite number; "
                         "a baseline holds measured values (rewrite it with check --update)")
    return number


# How closely a summary.csv value must equal the one its per-pair rows give: the CSVs hold 8
# significant digits (as intervals.recompute).
AGREE_RTOL, AGREE_ATOL = 1e-6, 1e-9


def _disagreements(
    benchmark, rows: list[dict], values: Mapping[str, float], ev, where: str = "in the summary"
) -> list[str]:
    """'metric X from the pairs, Y <where>' for each checked metric the rows do not give."""
    try:
        point = benchmark.summarize(rows, ev)
    except (KeyError, TypeError, ValueError) as error:
        return [f"its pairs cannot be summarised ({type(error).__name__}: {error})"]
    out = []
    for metric, value in values.items():
        column = benchmark.table_metrics.get(metric, metric)
        if column not in point or not np.isfinite(value):
            continue
        got = float(point[column])
        if not np.isclose(got, value, rtol=AGREE_RTOL, atol=AGREE_ATOL):
            out.append(f"{metric} {got:.6g} from the pairs, {value:.6g} {where}")
    return out


def consistency_problems(runs: list[Run], baseline_path: Path) -> list[str]:
    """What makes a check's numbers unreliable, one line each: a run whose per_pair.csv does not
    give the summary.csv that check reads, and a per-pair baseline (<baseline>.pairs.csv) whose
    rows do not give the aggregate baseline's values. A per-pair baseline that exists but cannot
    be read (not a file, not a CSV, no key columns) is a ValueError naming it: check --update
    writes both, so a broken one means the baseline was damaged.

    Runs evaluated with --repeats K > 1 are left out of the first test: their summary is the mean
    over K evaluations, their per_pair.csv the first."""
    problems = []
    settings = {}
    for run in runs:
        ev = eval_settings_of(run)
        settings[(run.benchmark.name, run.label)] = ev
        repeats = run.summary.get("repeats")
        if run.per_pair.empty or ev is None or (repeats is not None and repeats == repeats and int(repeats) > 1):
            continue
        differ = _disagreements(run.benchmark, run.per_pair.to_dict("records"), baseline_metrics(run), ev)
        if differ:
            problems.append(f"{run.folder.per_pair_path} and {run.folder.summary_path} disagree: {'; '.join(differ)} "
                            "(one of them was changed after the run; rerun it with --eval-only)")
    pairs = noise_gate.pairs_path(baseline_path)
    if not os.path.lexists(pairs):
        return problems
    if not pairs.is_file():
        raise ValueError(f"{pairs}: the per-pair baseline is not a regular file; rewrite it with check --update")
    pair_rows = noise_gate.read_pair_baseline(pairs)
    if pair_rows.empty:
        raise ValueError(f"{pairs}: the per-pair baseline holds no pair; rewrite it with check --update")
    baseline = read_baseline(baseline_path)
    metrics = [c for c in baseline.columns if c not in NOT_METRICS]
    runs_by_key = {(run.benchmark.name, run.label): run for run in runs}
    for (bench, method), rows in pair_rows.groupby(["benchmark", "method"], sort=False):
        key = (str(bench), str(method))
        row = baseline[(baseline["benchmark"].astype(str) == key[0]) & (baseline["method"].astype(str) == key[1])]
        if row.empty:
            problems.append(f"{pairs}: {key[1]} on {key[0]} has pairs but no row in {baseline_path}")
            continue
        run = runs_by_key.get(key)
        if run is None or settings.get(key) is None:
            continue  # its evaluation settings come from the run; a missing run is named by compare
        values = {m: _baseline_value(row.iloc[0][m], baseline_path, key, m) for m in metrics}
        records = rows.drop(columns=["benchmark", "method"]).dropna(axis=1, how="all").to_dict("records")
        differ = _disagreements(run.benchmark, records, values, settings[key], where="in the aggregate baseline")
        if differ:
            problems.append(f"{pairs} and {baseline_path} disagree on {key[1]} on {key[0]}: {'; '.join(differ)} "
                            "(rewrite both with check --update)")
    return problems


def compare(runs: list[Run], baseline_path: Path, tolerances: Tolerances | Mapping[str, float],
            checked_runs: Sequence[tuple[str, str]] | None = None) -> tuple[list[Finding], list[str]]:
    """Each baseline metric of each run, and the problems that are no metric (runs missing).

    ``tolerances``: a `Tolerances`, or a plain ``metric -> tolerance`` mapping (parse_tolerances).
    ``checked_runs``: (benchmark, label) of every run of the check, where some were gated by the
    noise model instead: a baseline row is missing only if none of them is its run.
    """
    if not isinstance(tolerances, Tolerances):
        tolerances = Tolerances(defaults=dict(tolerances))
    baseline = read_baseline(baseline_path)
    metrics = [c for c in baseline.columns if c not in NOT_METRICS]
    if not metrics:
        raise ValueError(f"{baseline_path}: holds no metric column (only {', '.join(baseline.columns)}); "
                         "write the baseline with check --update")
    for _, metric in tolerances.options:
        if metric not in metrics:
            raise ValueError(f"{baseline_path}: has no column {metric!r}, which --tolerance asks to check "
                             f"(its metrics: {', '.join(metrics)})")
    rows = {(str(r["benchmark"]), str(r["method"])): r for _, r in baseline.iterrows()}
    seen, findings, problems = set(), [], []
    for run in runs:
        key = (run.benchmark.name, run.label)
        if key not in rows:
            problems.append(f"{run.dir}: {key[1]} on {key[0]} is not in the baseline {baseline_path}")
            continue
        seen.add(key)
        measured = baseline_metrics(run)
        checked = 0
        for metric in metrics:
            value = _baseline_value(rows[key][metric], baseline_path, key, metric)
            if np.isnan(value) and metric not in measured:
                continue  # a column of another benchmark's rows
            if np.isnan(value) and not np.isnan(measured.get(metric, np.nan)):
                raise ValueError(
                    f"{baseline_path}: {metric} of {key[1]} on {key[0]} is empty or NaN while the run "
                    "measures it; a baseline must hold every value it checks (rewrite it with check --update)"
                )
            checked += 1
            tolerance = tolerances.get(key[0], key[1], metric)
            if tolerance is None:
                raise ValueError(f"{baseline_path}: no tolerance for metric {metric!r}; pass --tolerance {metric}=T "
                                 "or give it a row in --tolerances")
            if not math.isfinite(tolerance) or tolerance < 0:  # a plain mapping is not validated on the way in
                raise ValueError(
                    f"{baseline_path}: tolerance of {metric!r} must be a finite number >= 0, got {tolerance!r}"
                )
            findings.append(Finding(key[0], key[1], metric, value, float(measured.get(metric, np.nan)), tolerance))
        if not checked:
            raise ValueError(f"{baseline_path}: no metric of {key[1]} on {key[0]} has a value to check against")
    present = seen | set(checked_runs or ())
    for key in rows:
        if key not in present:
            problems.append(f"{baseline_path}: {key[1]} on {key[0]} has no run among those checked")
    return findings, problems


def markdown_summary(findings: list[Finding], problems: list[str], baseline_path: Path,
                     notes: Sequence[str] = (), tolerance_file: Path | None = None) -> str:
    """A Markdown report (GitHub Actions: append it to $GITHUB_STEP_SUMMARY); ``notes``: the
    environment and protocol differences (gate/notes.py), listed above the table."""
    marks = {"ok": "ok", "regression": "**regression**", "improvement": "improved"}
    lines = [f"### e3cm-bench check against {markdown_code(baseline_path)}", ""]
    bad = [f for f in findings if f.status == "regression"]
    lines.append(f"{len(findings)} metrics checked: {len(bad)} regression(s), "
                 f"{sum(f.status == 'improvement' for f in findings)} improvement(s), {len(problems)} problem(s).")
    if tolerance_file is not None:
        lines += ["", f"Tolerances: the command line's, then {markdown_code(tolerance_file)}, then the defaults."]
    if notes:
        lines += [""] + [f"- {markdown_text(note)}" for note in notes]
    lines += ["", "| benchmark | method | metric | baseline | measured | change | tolerance | status |",
              "|---|---|---|---:|---:|---:|---:|---|"]
    for f in findings:
        lines.append(
            f"| {markdown_text(f.benchmark)} | {markdown_text(f.method)} | {markdown_text(f.metric)} | "
            f"{format_number(f.baseline, f.metric, fraction_decimals=4)} | "
            f"{format_number(f.measured, f.metric, fraction_decimals=4)} | "
            f"{format_number(f.delta, 'd_', decimals=4 if abs(f.baseline) < 1.5 else 2)} | {f.tolerance:g} | "
            f"{marks[f.status]} |"
        )
    lines += [f"- {markdown_text(problem)}" for problem in problems]
    return "\n".join(lines) + "\n"


def write_summary(text: str, path: Path) -> None:
    """Append (GitHub's step summary file is shared by the steps of a job); never to a run's own file."""
    RunFolder.refuse_own_files([path], "check", "--summary")
    previous = Path(path).read_text() if Path(path).is_file() else ""
    write_atomically(path, lambda tmp: tmp.write_text(previous + text))


# --------------------------------------------------------------------------- the noise model


def has_noise_model(baseline_path: Path) -> bool:
    return noise_path(baseline_path).is_file()


def gate(runs: list[Run], baseline_path: Path, check_alpha: float = CHECK_ALPHA
         ) -> tuple[list[noise_gate.RunVerdict], list[Run], float]:
    """Each run that the baseline's noise ensemble holds, against it (noise_gate.gate_run);
    returns the verdicts, the runs the ensemble lacks (checked by tolerances instead), and
    the false-alarm rate of each metric (check_alpha over every metric gated)."""
    baseline = read_baseline(baseline_path)
    rows = {(str(r["benchmark"]), str(r["method"])): r for _, r in baseline.iterrows()}
    metrics = [c for c in baseline.columns if c not in NOT_METRICS]
    models = noise_gate.run_models(noise_gate.read_pair_baseline(noise_gate.pairs_path(baseline_path)),
                                   read_noise(noise_path(baseline_path)))
    gated = [
        run for run in runs if (run.benchmark.name, run.label) in models and (run.benchmark.name, run.label) in rows
    ]
    others = [run for run in runs if run not in gated]
    plans = []
    for run in gated:
        row = rows[(run.benchmark.name, run.label)]
        measured = baseline_metrics(run)
        values = {m: _baseline_value(row[m], baseline_path, (run.benchmark.name, run.label), m) for m in metrics
                  if m in measured and not (pd.isna(row[m]) and np.isnan(measured[m]))}
        plans.append((run, values, measured))
    alpha = metric_alpha(sum(len(values) for _, values, _ in plans), check_alpha)
    verdicts = [noise_gate.gate_run(run, models[(run.benchmark.name, run.label)], values, measured, alpha,
                                    evaluation_of(run.run_config)) for run, values, measured in plans]
    return verdicts, others, alpha


def verdict_lines(verdict: noise_gate.RunVerdict, max_pairs: int = 5) -> list[tuple[str, str]]:
    """(status, line) for each flagged metric of a run, then its pairs that moved."""
    lines = []
    for g in verdict.gates:
        if g.status != "ok":
            lines.append((g.status, f"{verdict.method} on {verdict.benchmark}: {g.metric} {g.baseline:.4g} -> "
                                    f"{g.measured:.4g} (noise {g.expected:.4g}, band {g.low:.4g}..{g.high:.4g}; "
                                    f"p={g.p_value:.2g} < {g.alpha:.2g})"))
    outside = [m for m in verdict.moves if not m.inside]
    moved = sorted({m.pair for m in verdict.moves})
    if moved:
        text = (f"{verdict.method} on {verdict.benchmark}: {len(moved)} of {verdict.n_pairs} pairs moved, "
                f"{len({m.pair for m in outside})} outside their own noise ({verdict.draws} draws)")
        for m in sorted(outside, key=lambda m: -abs(m.delta) if np.isfinite(m.delta) else -np.inf)[:max_pairs]:
            text += f"; {m.pair} {m.column} {m.baseline:.4g} -> {m.measured:.4g} (noise {m.low:.4g}..{m.high:.4g})"
        lines.append(("moved", text))
    return lines


def gate_markdown(verdicts: list[noise_gate.RunVerdict], alpha: float, check_alpha: float, baseline_path: Path) -> str:
    """The noise gate's Markdown report: every metric, its noise band and p-value."""
    marks = {"ok": "ok", "regression": "**regression**", "improvement": "improved"}
    lines = [f"### e3cm-bench check against {markdown_code(baseline_path)} (noise model)", "",
             f"False-alarm rate {check_alpha:g} per check, {alpha:.2g} per metric "
             f"({sum(len(v.gates) for v in verdicts)} metrics).", "",
             "| benchmark | method | metric | baseline | measured | noise mean | band | p | status |",
             "|---|---|---|---:|---:|---:|---|---:|---|"]
    for v in verdicts:
        for g in v.gates:
            lines.append(
                f"| {markdown_text(v.benchmark)} | {markdown_text(v.method)} | {markdown_text(g.metric)} | "
                f"{g.baseline:.4g} | {g.measured:.4g} | "
                f"{g.expected:.4g} | {g.low:.4g}..{g.high:.4g} | {g.p_value:.2g} | {marks[g.status]} |"
            )
    for v in verdicts:
        for status, line in verdict_lines(v):
            if status == "moved":
                lines.append(f"- {markdown_text(line)}")
    return "\n".join(lines) + "\n"
