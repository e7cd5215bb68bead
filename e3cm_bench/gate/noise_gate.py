"""`check` against a noise model: each run's metrics and pairs against what a rerun on another
CPU would give (stats/noise.py for the statistics, ensemble.py for the draws).

A baseline is three files side by side (`check --update`):

- ``demo_hpatches.csv``: the aggregate row of each run, with its identity and environment;
- ``demo_hpatches.pairs.csv``: every pair's per_pair.csv values of each run;
- ``demo_hpatches.noise.csv``: the same values once per noise draw (``--ensemble K``).

A pair's members are its baseline value and its K draws. `check` reads only these files and
the checked runs' CSVs, so it stays fast; the ensemble's cost is paid once, at --update.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.ground.files import read_keyed_csv, write_csv
from e3cm_bench.stats.noise import RESAMPLES, Gate, PairMove, count_gate, member_picks, pair_moves, resampled_gate

PAIRS_SUFFIX = ".pairs.csv"
KEY_COLUMNS = ("benchmark", "method", "pair")
# Columns of per_pair.csv that describe a pair rather than measure it.
LABEL_COLUMNS = ("pair", "sequence")


def pairs_path(baseline: Path) -> Path:
    """``demo_hpatches.csv`` -> ``demo_hpatches.pairs.csv``."""
    baseline = Path(baseline)
    return baseline.with_name(baseline.stem + PAIRS_SUFFIX)


def per_pair_rows(runs: Sequence) -> pd.DataFrame:
    """The per-pair baseline of runs (report.Run): benchmark, method, then per_pair.csv's
    columns; a run without per_pair.csv has none (its aggregate row is all it is checked by)."""
    tables = []
    for run in runs:
        if run.per_pair.empty:
            continue
        table = run.per_pair.copy()
        table.insert(0, "method", run.label)
        table.insert(0, "benchmark", run.benchmark.name)
        tables.append(table)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=list(KEY_COLUMNS))


def write_pair_baseline(runs: Sequence, path: Path) -> Path | None:
    """The per-pair baseline beside the aggregate one; none (and no stale one) without pairs."""
    rows = per_pair_rows(runs)
    if rows.empty:
        Path(path).unlink(missing_ok=True)
        return None
    return write_csv(rows, path)


def read_pair_baseline(path: Path) -> pd.DataFrame:
    return read_keyed_csv(path, "per-pair baseline (write one with check --update)", KEY_COLUMNS)


@dataclass
class RunModel:
    """One baseline run's pairs and each pair's members (baseline row first, then the draws)."""

    benchmark: str
    method: str
    baseline: pd.DataFrame  # one row per pair, indexed by pair
    members: dict[str, pd.DataFrame] = field(default_factory=dict)  # pair -> its member rows
    draws: int = 0

    def values(self, column: str) -> list[np.ndarray]:
        return [self.members[p][column].to_numpy(float) for p in self.baseline.index]


def run_models(pair_baseline: pd.DataFrame, noise: pd.DataFrame) -> dict[tuple[str, str], RunModel]:
    """A RunModel per (benchmark, method) of the noise table; the pairs those draws hold must be
    exactly the baseline's (a noise table from other runs is refused)."""
    models = {}
    for (bench, method), draws in noise.groupby(["benchmark", "method"], sort=False):
        base = pair_baseline[(pair_baseline["benchmark"] == bench) & (pair_baseline["method"] == method)]
        if base.empty:
            raise ValueError(f"the noise ensemble holds {method} on {bench}, which the per-pair baseline lacks; "
                             "rewrite both with check --update --ensemble K")
        base = base.drop(columns=["benchmark", "method"]).set_index("pair", drop=False)
        if set(draws["pair"]) != set(base.index):
            raise ValueError(f"the noise ensemble of {method} on {bench} holds other pairs than its baseline; "
                             "rewrite both with check --update --ensemble K")
        members = {}
        for pair, rows in draws.groupby("pair", sort=False):
            own = base.loc[[pair]]
            values = rows.drop(columns=["benchmark", "method", "draw"]).set_index("pair", drop=False)
            members[pair] = pd.concat([own, values[[c for c in own.columns if c in values.columns]]])
        models[(bench, method)] = RunModel(bench, method, base, members, draws=int(draws["draw"].nunique()))
    return models


@dataclass
class RunVerdict:
    benchmark: str
    method: str
    gates: list[Gate]
    moves: list[PairMove]
    n_pairs: int
    draws: int


def gate_run(run, model: RunModel, baseline_values: dict[str, float], measured: dict[str, float], alpha: float,
             ev, n_samples: int = RESAMPLES) -> RunVerdict:
    """Each metric of `run` (report.Run) against `model`; baseline_values: the baseline's
    aggregate row (metric -> value), whose metrics are the ones gated; measured: the run's."""
    benchmark = run.benchmark
    measured_rows = run.per_pair.set_index("pair", drop=False) if not run.per_pair.empty else pd.DataFrame()
    missing = [p for p in model.baseline.index if p not in measured_rows.index]
    if missing:
        raise ValueError(f"{run.dir}: per_pair.csv lacks {len(missing)} of the baseline's pairs (first: {missing[0]})")
    measured_rows = measured_rows.loc[list(model.baseline.index)]
    pairs = list(model.baseline.index)
    # Every member of every pair as one row list; a sample picks one member per pair.
    stacked, offsets = [], []
    for pair in pairs:
        offsets.append(len(stacked))
        stacked += model.members[pair].to_dict("records")
    counts = [len(model.members[p]) for p in pairs]
    summarize = benchmark.indexed_summary(stacked, ev)
    picks = member_picks(counts, n_samples) + np.asarray(offsets)[None, :]
    samples: list[dict] | None = None
    gates = []
    for metric, before in baseline_values.items():
        now = float(measured.get(metric, np.nan))
        if metric in benchmark.count_metrics:
            column, threshold = benchmark.count_metrics[metric]
            passes = [np.asarray(v <= threshold) for v in model.values(column)]
            gates.append(count_gate(metric, passes, now, before, alpha))
            continue
        if samples is None:
            samples = [summarize(row) for row in picks]
        column = benchmark.table_metrics.get(metric, metric)
        gates.append(
            resampled_gate(
                metric, np.array([s.get(column, np.nan) for s in samples], float), now, before, alpha, model.draws
            )
        )
    moves = []
    for column in model.baseline.columns:
        if column in LABEL_COLUMNS or column not in measured_rows.columns:
            continue
        if not pd.api.types.is_numeric_dtype(model.baseline[column]):
            continue
        moves += pair_moves(pairs, column, model.baseline[column].to_numpy(float), model.values(column),
                            measured_rows[column].to_numpy(float))
    return RunVerdict(benchmark.name, run.label, gates, moves, len(pairs), model.draws)
