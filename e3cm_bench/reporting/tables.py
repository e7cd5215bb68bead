"""Run results as people read them: console summaries and paper-style tables (the paper's rows,
then one measured row per run, with intervals and differences), as CSV, Markdown and text.

HPatches values are fractions (0..1); pose AUC and precision are percent, as in the paper.
Loading a run folder is in runs.py (re-exported here), plots in plots.py, file writing in files.py.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from e3cm_bench.benchmarks import Benchmark, get_benchmark
from e3cm_bench.benchmarks import intervals
from e3cm_bench.ground.files import read_csv, write_atomically, write_csv
from e3cm_bench.reporting.escape import markdown_text
from e3cm_bench.drawing.formats import fit_columns, format_interval, format_number, text_width
from e3cm_bench.paper import PAPER_DIR
from e3cm_bench.reporting.notes import (COST_NOTE, NOT_RUN, OTHER_PAIRS, OTHER_PAIRS_MARK, PAPER_SETS,  # noqa: F401
                                        UNDER_LOAD_MARK, cost_note, other_pairs, paper_rows_note, paper_set_notes,
                                        with_not_run)
from e3cm_bench.reporting.runs import (TEXT_PAIR_COLUMNS, Run, eval_settings_of, load_run, paper_row_of,  # noqa: F401 - their old home
                   protocol_of, run_intervals)

# A table's column naming the metrics whose paper number lies outside the measured interval.
OUTSIDE = "outside_ci"
# A run's cost in the tables, after the benchmark's own columns (summary.csv's names).
# seconds_per_image: matching and mapping together, where a run maps its set (reconstruct).
COST_COLUMNS = ("seconds_per_pair", "seconds_per_image", "peak_memory_mb", "shared_peak_memory_mb")

# Our short run labels -> the paper's method names, after lower-casing and removing spaces.
METHOD_ALIASES = {"sift": "sift+nn", "r2d2": "r2d2+nn", "superpoint+sg": "superpoint+superglue"}


# --------------------------------------------------------------------------- console


def print_summary(summary: Mapping, title: str, console: Console | None = None) -> None:
    """Print a summary row as a rich table.

    Keys with ``_i`` / ``_v`` counterparts (HPatches splits) share a row, with the
    overall value and the illumination / viewpoint values side by side.
    """
    bounds = summary
    summary = {key: value for key, value in summary.items() if not intervals.is_interval_key(key)}
    split_bases = {key[:-2] for key in summary if key.endswith(("_i", "_v")) and key[:-2] in summary}
    table = Table(title=escape(title))  # a label like 'dfm [efficientnet_lite0]' is text, not markup
    if intervals.has_intervals(bounds):
        # a summary read back from summary.csv holds these settings as floats
        samples, seed = (bounds.get(k) for k in ("bootstrap_samples", "bootstrap_seed"))
        table.caption = escape(
            f"[lo, hi]: {float(bounds.get('confidence', 0.95)):.0%} bootstrap interval over the pairs "
            f"({int(samples) if samples == samples and samples is not None else '?'} resamples, "
            f"seed {int(seed) if seed == seed and seed is not None else '?'})")
    repeats = bounds.get("repeats")
    if repeats is not None and repeats == repeats and int(repeats) > 1:
        table.caption = (table.caption or "") + escape(
            f"; values: the mean over {int(repeats)} repeats of the estimation (each metric's spread: <metric>_sd "
            "in summary.csv)")
    seeds = bounds.get("mapper_seeds")
    if seeds is not None and seeds == seeds and int(seeds) > 1:  # sfm: the interval resamples the seeds too
        table.caption = (table.caption or "") + escape(
            f" and the mapper's {int(seeds)} seeds; values: the mean over the seeds (their spread: <metric>_sd, "
            "each seed's numbers: sfm/per_seed.csv)")
    table.add_column("metric")
    if split_bases:
        for header in ("overall", "illumination", "viewpoint"):
            table.add_column(header, justify="right")
    else:
        table.add_column("value", justify="right")

    def cell(key: str, value) -> str:
        # Fractions need four decimals to be told apart; counts, degrees and percents two.
        interval = intervals.interval_of(bounds, key)
        if interval is None:
            return format_number(value, key, fraction_decimals=4)
        return format_interval(value, *interval, key, fraction_decimals=4)

    for key, value in summary.items():
        if key[:-2] in split_bases and key.endswith(("_i", "_v")):
            continue  # shown in the row of its base key
        cells = [key, cell(key, value)]
        if split_bases:
            if key in split_bases:
                cells += [cell(f"{key}_i", summary[f"{key}_i"]), cell(f"{key}_v", summary[f"{key}_v"])]
            else:
                cells += ["", ""]
        table.add_row(*cells)
    (console or Console()).print(table)


# --------------------------------------------------------------------------- paper tables


def method_key(name: str) -> str:
    """Normalised method name for matching runs to paper rows: 'sift' == 'SIFT+NN', 'E3CM (Ours)' == 'e3cm'."""
    key = "".join(str(name).lower().split()).removesuffix("(ours)")
    return METHOD_ALIASES.get(key, key)


def paper_reference(benchmark: Benchmark) -> Path | None:
    """The shipped CSV of the paper's numbers for a benchmark (None: the paper reports none)."""
    return PAPER_DIR / benchmark.paper_table if benchmark.paper_table else None


def _read_reference(path: Path, benchmark: Benchmark) -> pd.DataFrame:
    reference = read_csv(path, what="reference table")
    missing = [c for c in ("method", *benchmark.table_metrics) if c not in reference.columns]
    if missing:
        raise ValueError(f"{path}: missing {benchmark.name} column(s) {', '.join(missing)}")
    return reference


def paper_table(
    runs: Sequence[Run], benchmark: str | Benchmark, reference_csv: str | Path | None = None
) -> pd.DataFrame:
    """The paper's table layout: the paper's rows (source 'paper') then one row per run ('measured').

    Columns: ``method, source``, the paper's metrics (HPatches: h_acc@1/3/5 as
    fractions; pose: auc@5/10/20 and P = precision@1e-4, percent), the measured-only
    extras (``n_pairs``; HPatches also ``mma@3``), ``vs_paper`` (the paper row a measured
    row is to be compared with, `paper_row_of`), ``protocol``, then ``d_<metric>`` =
    measured - that paper row. A run under a non-standard protocol is marked "(non-standard)".
    Then the intervals: ``outside_ci`` (the metrics whose paper number lies outside the measured
    interval, comma-separated), ``<col>_lo`` and ``<col>_hi`` for every measured column but the
    counts (NaN where the run has none, `run_intervals`), and their ``confidence``.

    A run on fewer or other pairs than the paper's set (`PAPER_SETS`: the shared samples, a
    --limit) is compared with the paper's number all the same, but its ``other_pairs`` says
    which pairs each side holds and ``outside_ci`` stays empty: an interval over these pairs
    says nothing of the distance to a number measured on others (`paper_set_notes`).
    """
    benchmark = get_benchmark(benchmark)
    for run in runs:
        if run.benchmark.name != benchmark.name:
            raise ValueError(f"{run.dir}: run is on {run.benchmark.name!r}, the table is for {benchmark.name!r}")
    table_metrics = benchmark.table_metrics
    # The runs' cost beside their accuracy (seconds per pair, with its interval; the highest
    # per-pair memory peak), where a run measured it (an imported run, or one made before, did not).
    extras = list(benchmark.table_extras) + [c for c in COST_COLUMNS if any(c in run.summary for run in runs)]

    paper_rows = []
    if reference_csv is not None:
        reference = _read_reference(Path(reference_csv), benchmark)
        for _, row in reference.iterrows():
            paper_rows.append({"method": row["method"], "source": "paper", **{m: float(row[m]) for m in table_metrics}})
    paper_by_key = {method_key(row["method"]): row for row in paper_rows}

    # Every measured number but the counts carries its interval: the summary column it comes from.
    sources = {**table_metrics, **{extra: extra for extra in extras
                                   if not extra.startswith(intervals.COUNTS) and extra not in intervals.PEAKS}}
    measured_rows = [_measured_row(run, benchmark, paper_by_key, sources, extras) for run in runs]
    if paper_rows and runs:  # said on the first paper row: what the rows above one's own were measured on
        paper_rows[0][OTHER_PAIRS] = paper_rows_note(runs, benchmark, len(paper_rows))
    columns = [
        "method",
        "source",
        *table_metrics,
        *extras,
        "vs_paper",
        "protocol",
        *(f"d_{m}" for m in table_metrics),
        OUTSIDE,
        OTHER_PAIRS,
        COST_NOTE,
        *(key for c in sources for key in (intervals.lo_key(c), intervals.hi_key(c))),
        "confidence",
    ]
    return pd.DataFrame(paper_rows + measured_rows, columns=columns)


def _measured_row(run: Run, benchmark: Benchmark, paper_by_key: dict, sources: dict, extras: list[str]) -> dict:
    """A run's row of `paper_table`: its numbers, the paper row it compares with and the
    differences from it, its intervals and the metrics whose paper number lies outside them."""
    table_metrics = benchmark.table_metrics
    protocol, standard = protocol_of(run)
    label = run.label if standard else f"{run.label} (non-standard)"
    row = {"method": label, "source": "measured"}
    row.update({metric: float(run.summary[column]) for metric, column in table_metrics.items()})
    row.update({extra: run.summary.get(extra, np.nan) for extra in extras})
    paper_row = paper_row_of(run)
    reference_row = paper_by_key.get(method_key(paper_row)) if paper_row else None
    row["vs_paper"] = reference_row["method"] if reference_row is not None else ""
    row["protocol"] = protocol
    for metric in table_metrics:
        row[f"d_{metric}"] = row[metric] - reference_row[metric] if reference_row is not None else np.nan
    elsewhere = other_pairs(run, benchmark) if reference_row is not None else ""
    row[OTHER_PAIRS], row[COST_NOTE] = elsewhere, cost_note(run)
    bounds = run_intervals(run)
    outside = []
    for column, summary_column in sources.items():
        interval = intervals.interval_of(bounds, summary_column)
        row[intervals.lo_key(column)], row[intervals.hi_key(column)] = interval or (np.nan, np.nan)
        paper_value = reference_row.get(column) if reference_row is not None else None
        if (interval is not None and paper_value is not None and not elsewhere
                and not interval[0] <= paper_value <= interval[1]):
            outside.append(column)
    row[OUTSIDE] = ", ".join(outside)
    row["confidence"] = float(bounds["confidence"]) if bounds else np.nan
    return row


@dataclass(frozen=True)
class TableShape:
    """What `table` shows: `metrics`, the metric and extra columns kept (empty: all), the
    LaTeX table's `caption` (None: one made from the benchmark and the intervals), and the
    (label, why) of methods that could not run, each a row of source 'not run' (`with_not_run`)."""

    metrics: tuple[str, ...] = ()
    caption: str | None = None
    not_run: tuple[tuple[str, str], ...] = ()


def choose_metrics(table: pd.DataFrame, benchmark: Benchmark, metrics: Sequence[str]) -> pd.DataFrame:
    """The table with only these metric (or extra) columns, each with its interval and difference;
    one line naming the choices where one is not a column of this benchmark's table."""
    if not metrics:
        return table
    offered = [c for c in [*benchmark.table_metrics, *benchmark.table_extras, *COST_COLUMNS] if c in table.columns]
    unknown = [m for m in metrics if m not in offered]
    if unknown:
        raise ValueError(f"--metrics {','.join(unknown)}: not a column of a {benchmark.name} table; choose among "
                         f"{', '.join(offered)}")
    dropped = [c for c in offered if c not in metrics]
    related = {key for c in dropped for key in (c, intervals.lo_key(c), intervals.hi_key(c), f"d_{c}")}
    return table.drop(columns=[c for c in table.columns if c in related])


def without_empty_columns(table: pd.DataFrame) -> pd.DataFrame:
    """The table without the comparison columns no row fills (vs_paper and d_* where no run has a
    paper row: a KITTI table had 25 columns, 9 of them so). The other columns stay, empty or not:
    readers index them (outside_ci empty says no paper number is outside an interval)."""
    comparison = [c for c in table.columns if c == "vs_paper" or c.startswith("d_")]
    empty = [c for c in comparison if table[c].map(lambda v: v is None or v == "" or v != v).all()]
    return table.drop(columns=empty)


def without_comparison(table: pd.DataFrame, vs_paper: bool = False) -> pd.DataFrame:
    """The table without its measured - paper columns (and `vs_paper` too if asked)."""
    drop = [c for c in table.columns
            if c.startswith("d_") or c in (OUTSIDE, OTHER_PAIRS) or (vs_paper and c == "vs_paper")]
    return table.drop(columns=drop)


def display_cells(table: pd.DataFrame) -> tuple[list[str], list[list[str]], list[bool]]:
    """The table as people read it: each number with its interval in one cell ("0.73 [0.47, 0.93]"),
    each difference from a paper number outside the measured interval marked so; the interval
    columns themselves folded away. Returns (columns, rows of text, which columns are numeric)."""
    columns = [str(c) for c in table.columns]
    folded = {c for c in columns if intervals.lo_key(c) in columns and intervals.hi_key(c) in columns}
    hidden = {key for c in folded for key in (intervals.lo_key(c), intervals.hi_key(c))}
    hidden |= {c for c in (OUTSIDE, OTHER_PAIRS, COST_NOTE, "confidence") if c in columns}
    shown = [c for c in columns if c not in hidden]
    body = []
    for record in table.to_dict("records"):
        listed = record.get(OUTSIDE)
        outside = {m.strip() for m in listed.split(",")} if isinstance(listed, str) else set()
        other_pairs = isinstance(record.get(OTHER_PAIRS), str) and bool(record.get(OTHER_PAIRS))
        cells = []
        for c in shown:
            value = record[c]
            if c in folded:
                text = format_interval(value, record[intervals.lo_key(c)], record[intervals.hi_key(c)], c)
            else:
                text = format_number(value, c)
            if c == "seconds_per_pair" and isinstance(record.get(COST_NOTE), str) and record[COST_NOTE]:
                text += f" ({UNDER_LOAD_MARK})"  # the note below says how loaded
            if c.startswith("d_") and other_pairs and text != "-":
                text += f" ({OTHER_PAIRS_MARK})"
            elif c.startswith("d_") and c[2:] in outside:
                confidence = record.get("confidence")
                level = (
                    f"{float(confidence):.0%} " if isinstance(confidence, float) and confidence == confidence else ""
                )
                text += f" (outside {level}CI)"
            cells.append(text)
        body.append(cells)
    numeric = [pd.api.types.is_numeric_dtype(table[c]) for c in shown]
    return shown, body, numeric


def table_to_markdown(df: pd.DataFrame) -> str:
    """A pipe table (pandas' to_markdown needs ``tabulate``, which we do not depend on).

    Numbers get two decimals (fractions and percents alike), differences a sign,
    counts none, missing values '-'; text columns are left-aligned, numbers right. A column
    with ``<col>_lo`` and ``<col>_hi`` beside it shows them in its cells (`display_cells`).
    """
    columns, body, numeric = display_cells(df)
    # a label's characters stay text: `sift | ok` one cell, `<b>` and `[a](b)` no HTML or link
    columns = [markdown_text(c) for c in columns]
    body = [[cell if is_num else markdown_text(cell) for cell, is_num in zip(row, numeric)] for row in body]
    widths = [max([len(column), 3, *(len(row[i]) for row in body)]) for i, column in enumerate(columns)]

    def line(cells: Sequence[str]) -> str:
        padded = [cell.rjust(w) if is_num else cell.ljust(w) for cell, w, is_num in zip(cells, widths, numeric)]
        return "| " + " | ".join(padded) + " |"

    rule = "| " + " | ".join("-" * (w - 1) + ":" if is_num else "-" * w for w, is_num in zip(widths, numeric)) + " |"
    notes = "".join(f"\nNote: {markdown_text(note)}\n" for note in paper_set_notes(df))
    return "\n".join([line(columns), rule, *(line(row) for row in body)]) + "\n" + notes


def print_paper_table(df: pd.DataFrame, console: Console | None = None) -> None:
    """The table on the terminal with the Markdown file's cells, but within the console's width
    (80 columns in a log or a pipe): the paper's rows, then the measured rows, each with the
    columns it fills; columns that do not fit side by side follow in blocks that repeat the
    method, so no row wraps and no cell is cut; then the notes on pair sets."""
    console = console or Console()
    columns, body, numeric = display_cells(df)
    width = text_width(console)
    # The paper's rows and the measured ones apart, each with only the columns it fills: the
    # paper's rows have no interval, count or difference, and need no block of '-' for them.
    groups = [[row for row, kind in zip(body, df["source"]) if kind == of] for of in ("paper", "measured", NOT_RUN)]
    lines: list[str] = []
    for rows in groups:
        if not rows:
            continue
        shown = [k for k in range(len(columns)) if k == 0 or any(row[k] not in ("-", "") for row in rows)]
        if lines:
            lines.append("")
        lines += fit_columns([columns[k] for k in shown], [[row[k] for k in shown] for row in rows],
                             [numeric[k] for k in shown], width, keep=1)
    # soft_wrap: the lines already fit; rich must not rewrap them (or pad them) a second time.
    console.print("\n".join(lines), markup=False, highlight=False, soft_wrap=True)
    for note in paper_set_notes(df):
        console.print(f"Note: {note}", markup=False, highlight=False, width=width)


def write_paper_table(df: pd.DataFrame, out_path: str | Path) -> tuple[Path, Path]:
    """Write the table as ``<out_path>.csv`` and ``<out_path>.md`` (any given suffix is replaced)."""
    out_path = Path(out_path)
    csv_path = write_csv(df, out_path.with_suffix(".csv"))
    markdown = table_to_markdown(df)
    md_path = write_atomically(out_path.with_suffix(".md"), lambda tmp: tmp.write_text(markdown))
    return csv_path, md_path


def sweep_markdown(result) -> str:
    """A protocol sweep's result (pipeline/sweep.py SweepResult) as sweep.md: each cell's tau, flips and ranking."""
    metric = result.metric
    lines = [f"# Protocol sweep: {metric} per cell (default cell: {result.default})", "",
             "| cell | Kendall tau vs default | flips | ranking (" + metric + " [95% interval]) |",
             "|---|---:|---:|---|"]
    for _, tau in result.taus.iterrows():
        chosen = result.table[result.table["cell"] == tau["cell"]].sort_values("rank")
        ranking = "; ".join(f"{r['rank']}. {r['run']} {r[metric]:.1f} [{r[metric + '_lo']:.1f}, "
                            f"{r[metric + '_hi']:.1f}]"
                            for _, r in chosen.iterrows())
        lines.append(f"| {tau['cell']} | {tau['kendall_tau']:.2f} | {tau['flips']} | {ranking} |")
    if len(result.flips):
        lines += ["", "Flips (B - A in the default cell, then in the cell with its interval):", ""]
        for _, f in result.flips.iterrows():
            mark = "" if f["excludes_0"] else " (interval holds 0)"
            lines.append(f"- {f['cell']}: {f['b']} - {f['a']}: {f.iloc[3]:+.1f} -> {f.iloc[4]:+.1f} "
                         f"[{f['lo']:+.1f}, {f['hi']:+.1f}]{mark}")
    return "\n".join(lines) + "\n"
