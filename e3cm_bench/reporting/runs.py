"""Run folders as the reports read them: one finished run loaded (`load_run`: its RunConfig,
summary and per-pair rows, each refused in one line naming the file), and what a report asks of
it (the paper row it compares with, its evaluation settings, intervals and protocol).

A run folder holds ``config.yaml`` (with at least ``benchmark``), ``summary.csv``
(one row) and ``per_pair.csv``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.benchmarks import intervals
from e3cm_bench.benchmarks import Benchmark
from e3cm_bench.ground.files import read_csv, read_keyed_csv
from e3cm_bench.benchmarks.from_record import benchmark_of, evaluation_of
from e3cm_bench.storage import RunConfig, RunFolder


@dataclass
class Run:
    """One benchmark run folder, loaded."""

    dir: Path
    run_config: RunConfig  # its config.yaml
    summary: dict
    per_pair: pd.DataFrame
    benchmark: Benchmark
    label: str

    @property
    def folder(self) -> RunFolder:
        return RunFolder(self.dir)

    @property
    def config(self) -> dict:
        """The config.yaml record as read (RunConfig.record)."""
        return self.run_config.record


# per_pair.csv columns that hold names; every other column of the benchmark's holds numbers.
TEXT_PAIR_COLUMNS = ("pair", "sequence", "scene", "category")  # category: WxBS (benchmarks/wxbs.py)


def _read_per_pair(path: Path, benchmark: Benchmark) -> pd.DataFrame:
    """A run's per-pair rows, refused in one line naming the file where the report could not
    use them: a pair with two rows (the tables index rows by pair; one of the two would be
    taken at random), or a number column holding text."""
    table = read_keyed_csv(path, "per-pair table", ["pair"])
    numeric = set(benchmark.pair_columns(benchmark.eval_settings())) | set(benchmark.report_columns)
    for column in [c for c in table.columns if c in numeric and c not in TEXT_PAIR_COLUMNS]:
        values = pd.to_numeric(table[column], errors="coerce")
        bad = values.isna() & table[column].notna()
        if bad.any():
            first = int(bad.to_numpy().nonzero()[0][0])
            raise ValueError(f"{path}: column {column} holds {table[column].iloc[first]!r}, not a number "
                             f"(pair {table['pair'].iloc[first]}, line {first + 2})")
        table[column] = values
    return table


def _read_summary(path: Path, benchmark: Benchmark) -> dict:
    df = read_csv(path, what="summary (the run did not finish or wrote elsewhere)")
    if len(df) != 1:
        raise ValueError(f"{path}: expected exactly one row, found {len(df)}")
    missing = [c for c in benchmark.required_summary_columns() if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing {benchmark.name} column(s) {', '.join(missing)}")
    # numpy scalars -> Python numbers, so summaries print and compare naturally.
    return {key: value.item() if isinstance(value, np.generic) else value for key, value in df.iloc[0].items()}


def load_run(run_dir: str | Path) -> Run:
    """Load a run folder; ``ValueError`` (one line, naming the file) if it is unusable.

    ``per_pair.csv`` is optional: the tables need only the summary, and a missing
    per-pair file yields an empty DataFrame (the pose CDF plot then refuses that run).
    """
    folder = RunFolder(run_dir)
    run_dir = folder.path
    config = RunConfig.read(folder.config_path)
    benchmark = benchmark_of(config)
    summary = _read_summary(folder.summary_path, benchmark)
    per_pair_path = folder.per_pair_path
    per_pair = _read_per_pair(per_pair_path, benchmark) if per_pair_path.is_file() else pd.DataFrame()
    label = str(config.method or run_dir.resolve().name)
    return Run(dir=run_dir, run_config=config, summary=summary, per_pair=per_pair, benchmark=benchmark, label=label)


def paper_row_of(run: Run) -> str | None:
    """The paper row a run compares with: its matcher's registry entry names it (the paper's
    E3CM numbers came from the authors' released code, e3cm-release; its DFM numbers from
    the DFM release), when the run was made as the paper's were (the entry says which
    settings keep it so) on the paper's VGG19. Our variants and ablations have none."""
    from e3cm_bench.backbones.names import DEFAULT_BACKBONE
    from e3cm_bench.matchers import get_matcher

    identity = run.run_config.identity or {}
    if identity.get("backbone") not in (None, DEFAULT_BACKBONE):
        return None
    try:
        entry = get_matcher(identity.get("matcher"))
    except (ValueError, TypeError):  # a plugin not installed here, or an imported run
        return None
    if entry.paper_row is None or not entry.paper_setting(identity.get("settings") or {}):
        return None
    return entry.paper_row


def eval_settings_of(run: Run):
    """The EvalSettings a run was evaluated with (its config.yaml's evaluation block; defaults for
    fields it lacks); None when the block cannot be read as settings."""
    try:
        return evaluation_of(run.run_config)
    except ValueError:
        return None


def run_intervals(run: Run) -> dict:
    """The run's intervals: those of its summary.csv; for a run written before intervals, those
    recomputed from its per_pair.csv when its pairs reproduce its summary (intervals.recompute);
    else none ({}), and its tables show the numbers alone."""
    if intervals.has_intervals(run.summary):
        return run.summary
    ev = eval_settings_of(run)
    if ev is None or run.per_pair.empty:
        return {}
    return intervals.recompute(run.benchmark, run.summary, run.per_pair, ev) or {}


def protocol_of(run: Run) -> tuple[str, bool]:
    """The run's evaluation protocol and whether it is a standard one."""
    from e3cm_bench.method.protocols import PROTOCOLS

    name = run.run_config.protocol
    protocol = PROTOCOLS.get(name)
    return name, bool(protocol and protocol.standard)
