"""Turning benchmark run folders into CSVs, console tables, plots and paper-style tables.

A run folder holds ``config.yaml`` (with at least ``benchmark``), ``summary.csv``
(one row) and ``per_pair.csv``. HPatches values are fractions (0..1); pose AUC and
precision are percent, as in the paper. Plots are drawn on ``matplotlib.figure.Figure``
objects (saved through the Agg canvas) rather than pyplot, so that importing this
module never switches the backend of the caller's process.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from rich.console import Console
from rich.table import Table

from .datasets import BENCHMARKS
from .metrics import HOMOGRAPHY_ACCURACY_THRESHOLDS as H_ACC_THRESHOLDS
from .metrics import MMA_THRESHOLDS
from .metrics import POSE_AUC_THRESHOLDS as AUC_THRESHOLDS


# Where the paper's numbers for each benchmark live, under results/paper/.
PAPER_TABLE_FILES = {"hpatches": "table1.csv", "megadepth": "table2.csv", "yfcc": "table3.csv"}

# Summary columns a run must have to be reported at all; the illumination/viewpoint
# split columns are optional because a run may be restricted to one kind of sequence.
REQUIRED_SUMMARY_COLUMNS = {
    "hpatches": ["n_pairs", "n_matches", *(f"mma@{t}" for t in MMA_THRESHOLDS),
                 *(f"h_acc@{t}" for t in H_ACC_THRESHOLDS)],
    "megadepth": ["n_pairs", "n_matches", *(f"auc@{t}" for t in AUC_THRESHOLDS), "precision@1e-4"],
    "yfcc": ["n_pairs", "n_matches", *(f"auc@{t}" for t in AUC_THRESHOLDS), "precision@1e-4"],
}

# Paper-table metric columns, and where each measured value comes from in summary.csv.
TABLE_METRICS = {
    "hpatches": {f"h_acc@{t}": f"h_acc@{t}" for t in H_ACC_THRESHOLDS},
    "megadepth": {**{f"auc@{t}": f"auc@{t}" for t in AUC_THRESHOLDS}, "P": "precision@1e-4"},
    "yfcc": {**{f"auc@{t}": f"auc@{t}" for t in AUC_THRESHOLDS}, "P": "precision@1e-4"},
}
# Measured-only columns: the paper prints no MMA table (only Fig. 5) and no pair counts.
TABLE_EXTRAS = {"hpatches": ["n_pairs", "mma@3"], "megadepth": ["n_pairs"], "yfcc": ["n_pairs"]}

# Our short run labels -> the paper's method names, after lower-casing and removing spaces.
METHOD_ALIASES = {"sift": "sift+nn", "r2d2": "r2d2+nn", "superpoint+sg": "superpoint+superglue"}

CSV_FLOAT_FORMAT = "%.8g"


# --------------------------------------------------------------------------- files


def _write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Write through a temporary file in the same folder, then rename over ``path``.

    The rename is atomic on one filesystem, so an interrupted write leaves either the
    old file or the new one, never a truncated mix.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp_name)
    try:
        write(tmp_path)
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


def write_csv(df: pd.DataFrame, path: str | Path) -> Path:
    """Write ``df`` without its index, floats as ``%.8g`` (inf stays ``inf``), atomically."""
    path = Path(path)
    _write_atomically(path, lambda tmp: df.to_csv(tmp, index=False, float_format=CSV_FLOAT_FORMAT))
    return path


def _save_figure(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    file_format = path.suffix.lstrip(".") or "png"
    # bbox "tight" grows the canvas to whatever the legend needs, so long labels are never cut.
    _write_atomically(path, lambda tmp: fig.savefig(tmp, format=file_format, dpi=150, bbox_inches="tight"))
    return path


# --------------------------------------------------------------------------- runs


@dataclass
class Run:
    """One benchmark run folder, loaded."""

    dir: Path
    config: dict
    summary: dict
    per_pair: pd.DataFrame
    benchmark: str
    label: str


def _read_config(path: Path) -> dict:
    if not path.is_file():
        raise ValueError(f"{path}: missing (every run folder needs its config.yaml)")
    try:
        config = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not valid YAML ({first_line})") from None
    if not isinstance(config, dict):
        raise ValueError(f"{path}: expected a mapping at the top level, got {type(config).__name__}")
    benchmark = config.get("benchmark")
    if benchmark not in BENCHMARKS:
        raise ValueError(f"{path}: 'benchmark' is {benchmark!r}, expected one of {', '.join(BENCHMARKS)}")
    return config


def _read_summary(path: Path, benchmark: str) -> dict:
    if not path.is_file():
        raise ValueError(f"{path}: missing (the run did not finish or wrote elsewhere)")
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable CSV ({type(exc).__name__})") from None
    if len(df) != 1:
        raise ValueError(f"{path}: expected exactly one row, found {len(df)}")
    missing = [c for c in REQUIRED_SUMMARY_COLUMNS[benchmark] if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing {benchmark} column(s) {', '.join(missing)}")
    return {key: _plain_value(value) for key, value in df.iloc[0].items()}


def _plain_value(value):
    """numpy scalars -> Python numbers, so summaries print and compare naturally."""
    return value.item() if isinstance(value, np.generic) else value


def load_run(run_dir: str | Path) -> Run:
    """Load a run folder; ``ValueError`` (one line, naming the file) if it is unusable.

    ``per_pair.csv`` is optional: the tables need only the summary, and a missing
    per-pair file yields an empty DataFrame (the pose CDF plot then refuses that run).
    """
    run_dir = Path(run_dir)
    config = _read_config(run_dir / "config.yaml")
    benchmark = config["benchmark"]
    summary = _read_summary(run_dir / "summary.csv", benchmark)
    per_pair_path = run_dir / "per_pair.csv"
    if per_pair_path.is_file():
        try:
            per_pair = pd.read_csv(per_pair_path)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
            raise ValueError(f"{per_pair_path}: not a readable CSV ({type(exc).__name__})") from None
    else:
        per_pair = pd.DataFrame()
    label = str(config.get("method") or run_dir.resolve().name)
    return Run(dir=run_dir, config=config, summary=summary, per_pair=per_pair, benchmark=benchmark, label=label)


# --------------------------------------------------------------------------- console


def _format_number(value, key: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    # Pair counts may come back as floats from a CSV; other integral floats (an MMA of 1.0) stay floats.
    if isinstance(value, (int, np.integer)) or (key.startswith("n_pairs") and float(value).is_integer()):
        return str(int(value))
    if isinstance(value, float):
        # Fractions need four decimals to be told apart; counts, degrees and percents two.
        return f"{value:.4f}" if abs(value) < 1.5 else f"{value:.2f}"
    return str(value)


def print_summary(summary: Mapping, title: str, console: Console | None = None) -> None:
    """Print a summary row as a rich table.

    Keys with ``_i`` / ``_v`` counterparts (HPatches splits) share a row, with the
    overall value and the illumination / viewpoint values side by side.
    """
    split_bases = {key[:-2] for key in summary if key.endswith(("_i", "_v")) and key[:-2] in summary}
    table = Table(title=title)
    table.add_column("metric")
    if split_bases:
        for header in ("overall", "illumination", "viewpoint"):
            table.add_column(header, justify="right")
    else:
        table.add_column("value", justify="right")
    for key, value in summary.items():
        if key[:-2] in split_bases and key.endswith(("_i", "_v")):
            continue  # shown in the row of its base key
        cells = [key, _format_number(value, key)]
        if split_bases:
            if key in split_bases:
                cells += [_format_number(summary[f"{key}_i"], key), _format_number(summary[f"{key}_v"], key)]
            else:
                cells += ["", ""]
        table.add_row(*cells)
    (console or Console()).print(table)


# --------------------------------------------------------------------------- plots


def _run_colors(labels: Sequence[str]) -> dict[str, tuple]:
    """One colour per run label, stable across the plots of one report."""
    palette = colormaps["tab10"].colors
    return {label: palette[i % len(palette)] for i, label in enumerate(labels)}


def plot_mma_curves(runs: Mapping[str, Mapping], path: str | Path) -> Path:
    """HPatches MMA vs threshold (1..10 px): Overall / Illumination / Viewpoint panels.

    One line per run, legend with the mean number of matches per pair (the layout of
    the paper's Fig. 5). A split whose values are all NaN (no such pairs) is left
    empty with a note rather than dropped, so panels keep their place.
    """
    if not runs:
        raise ValueError("plot_mma_curves: no runs to plot")
    colors = _run_colors(list(runs))
    thresholds = np.array(MMA_THRESHOLDS)
    fig = Figure(figsize=(13, 4.4), layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    for ax, (panel, suffix) in zip(axes, (("Overall", ""), ("Illumination", "_i"), ("Viewpoint", "_v"))):
        plotted = False
        for label, summary in runs.items():
            values = np.array([float(summary.get(f"mma@{t}{suffix}", np.nan)) for t in thresholds])
            if np.all(np.isnan(values)):
                continue
            ax.plot(thresholds, values, marker="o", markersize=3, color=colors[label], label=label)
            plotted = True
        if not plotted:
            ax.text(0.5, 0.5, "no pairs", ha="center", va="center", transform=ax.transAxes, color="gray")
        ax.set_title(panel)
        ax.set_xlabel("threshold [px]")
        ax.set_xticks(thresholds)
        ax.set_xlim(1, 10)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("MMA")
    # Build the legend from the runs, not from one panel, so runs missing a split still appear.
    handles = [Line2D([], [], marker="o", markersize=3, color=colors[label]) for label in runs]
    legend_labels = [f"{label} ({_format_count(summary.get('n_matches'))} matches)" for label, summary in runs.items()]
    fig.legend(handles, legend_labels, loc="outside lower center", ncol=min(len(runs), 3), frameon=False)
    return _save_figure(fig, path)


def _format_count(value) -> str:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return "?"
    return "?" if math.isnan(value) else f"{value:.0f}"


def pose_error_curve(errors: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Points of the cumulative pose-error curve: (0, 0), then (e_k, k / N) for finite e_k.

    N counts failures (inf / NaN errors) too, so they lower the curve without ever
    appearing on it. Joining these points with straight lines is exactly the curve
    whose normalised area is the AUC of PROTOCOLS.md §3.
    """
    errors = np.asarray(errors, dtype=np.float64)
    finite = np.sort(errors[np.isfinite(errors)])
    recall = np.arange(1, len(finite) + 1) / max(len(errors), 1)
    return np.concatenate([[0.0], finite]), np.concatenate([[0.0], recall])


def plot_pose_error_cdf(runs: Mapping[str, pd.DataFrame], path: str | Path, max_error: float = 30.0) -> Path:
    """Fraction of pairs with pose error below x, x in [0, max_error] degrees, one line per run.

    The AUC thresholds (5, 10, 20 deg) are marked: AUC@t is the area under the curve
    left of the mark, divided by t.
    """
    if not runs:
        raise ValueError("plot_pose_error_cdf: no runs to plot")
    colors = _run_colors(list(runs))
    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.subplots()
    for label, per_pair in runs.items():
        if "err_pose" not in per_pair.columns or per_pair.empty:
            raise ValueError(f"plot_pose_error_cdf: run {label!r} has no per-pair err_pose values")
        errors = per_pair["err_pose"].to_numpy(dtype=np.float64)
        x, y = pose_error_curve(errors)
        # Hold the last recall flat to the right edge, as the AUC does up to its threshold.
        x, y = np.append(x, max(max_error, x[-1])), np.append(y, y[-1])
        n_failed = int(np.sum(~np.isfinite(errors)))
        ax.plot(x, y, color=colors[label], label=f"{label} ({len(errors)} pairs, {n_failed} failed)")
    for threshold in AUC_THRESHOLDS:
        ax.axvline(threshold, color="gray", linestyle=":", linewidth=1)
        ax.text(threshold, 1.0, f" AUC@{threshold}", color="gray", fontsize=8, va="top", ha="left")
    ax.set_xlim(0, max_error)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("pose error [deg]  (max of rotation and translation angle)")
    ax.set_ylabel("fraction of pairs")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return _save_figure(fig, path)


def plot_pose_auc_bars(runs: Mapping[str, Mapping], path: str | Path, title: str) -> Path:
    """Grouped bars of AUC@5/10/20 (left panel) and precision P@1e-4 (right panel), percent.

    Bars are grouped by metric with one colour per run, so methods are compared side
    by side within each threshold.
    """
    if not runs:
        raise ValueError("plot_pose_auc_bars: no runs to plot")
    labels = list(runs)
    colors = _run_colors(labels)
    fig = Figure(figsize=(11, 4.4), layout="constrained")
    auc_ax, precision_ax = fig.subplots(1, 2, width_ratios=(3, 1.3))
    width = 0.8 / len(labels)
    groups = np.arange(len(AUC_THRESHOLDS))
    for i, label in enumerate(labels):
        values = [float(runs[label].get(f"auc@{t}", np.nan)) for t in AUC_THRESHOLDS]
        bars = auc_ax.bar(groups + (i - (len(labels) - 1) / 2) * width, values, width, color=colors[label], label=label)
        auc_ax.bar_label(bars, fmt="%.1f", fontsize=7, padding=1)
        precision = float(runs[label].get("precision@1e-4", np.nan))
        bars = precision_ax.bar(i, precision, 0.7, color=colors[label])
        precision_ax.bar_label(bars, fmt="%.1f", fontsize=7, padding=1)
    auc_ax.set_xticks(groups, [f"AUC@{t}°" for t in AUC_THRESHOLDS])
    auc_ax.set_ylabel("percent")
    auc_ax.set_ylim(0, 100)
    auc_ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=min(len(runs), 3), frameon=False)
    precision_ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right")
    precision_ax.set_title("precision P (d < 1e-4)", fontsize=10)
    precision_ax.set_ylim(0, 105)
    for ax in (auc_ax, precision_ax):
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    fig.suptitle(title)
    return _save_figure(fig, path)


# --------------------------------------------------------------------------- paper tables


def method_key(name: str) -> str:
    """Normalised method name for matching runs to paper rows: 'sift' == 'SIFT+NN', 'E3CM (Ours)' == 'e3cm'."""
    key = "".join(str(name).lower().split()).removesuffix("(ours)")
    return METHOD_ALIASES.get(key, key)


def _read_reference(path: Path, benchmark: str) -> pd.DataFrame:
    if not Path(path).is_file():
        raise ValueError(f"{path}: reference table missing")
    try:
        reference = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable CSV ({type(exc).__name__})") from None
    missing = [c for c in ("method", *TABLE_METRICS[benchmark]) if c not in reference.columns]
    if missing:
        raise ValueError(f"{path}: missing {benchmark} column(s) {', '.join(missing)}")
    return reference


def paper_table(runs: Sequence[Run], benchmark: str, reference_csv: str | Path | None = None) -> pd.DataFrame:
    """The paper's table layout: the paper's rows (source 'paper') then one row per run ('measured').

    Columns: ``method, source``, the paper's metrics (HPatches: h_acc@1/3/5 as
    fractions; pose: auc@5/10/20 and P = precision@1e-4, percent), the measured-only
    extras (``n_pairs``; HPatches also ``mma@3``), then ``d_<metric>`` = measured -
    paper on measured rows whose method matches a paper row (see ``method_key``).
    """
    if benchmark not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {benchmark!r}, expected one of {', '.join(BENCHMARKS)}")
    for run in runs:
        if run.benchmark != benchmark:
            raise ValueError(f"{run.dir}: run is on {run.benchmark!r}, the table is for {benchmark!r}")
    metrics = TABLE_METRICS[benchmark]
    extras = TABLE_EXTRAS[benchmark]

    paper_rows = []
    if reference_csv is not None:
        reference = _read_reference(Path(reference_csv), benchmark)
        for _, row in reference.iterrows():
            paper_rows.append({"method": row["method"], "source": "paper", **{m: float(row[m]) for m in metrics}})
    paper_by_key = {method_key(row["method"]): row for row in paper_rows}

    measured_rows = []
    for run in runs:
        row = {"method": run.label, "source": "measured"}
        row.update({metric: float(run.summary[column]) for metric, column in metrics.items()})
        row.update({extra: run.summary.get(extra, np.nan) for extra in extras})
        reference_row = paper_by_key.get(method_key(run.label))
        for metric in metrics:
            row[f"d_{metric}"] = row[metric] - reference_row[metric] if reference_row is not None else np.nan
        measured_rows.append(row)

    columns = ["method", "source", *metrics, *extras, *(f"d_{m}" for m in metrics)]
    return pd.DataFrame(paper_rows + measured_rows, columns=columns)


def _format_cell(column: str, value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, str):
        return value
    if column.startswith("n_"):
        return str(int(value))
    if column.startswith("d_"):
        return f"{value:+.2f}"
    return f"{value:.2f}"


def table_to_markdown(df: pd.DataFrame) -> str:
    """A pipe table (pandas' to_markdown needs ``tabulate``, which we do not depend on).

    Numbers get two decimals (fractions and percents alike), differences a sign,
    counts none, missing values '-'; text columns are left-aligned, numbers right.
    """
    columns = [str(c) for c in df.columns]
    body = [[_format_cell(column, value) for column, value in zip(columns, row)] for row in df.itertuples(index=False)]
    numeric = [pd.api.types.is_numeric_dtype(df[c]) for c in df.columns]
    widths = [max([len(column), 3, *(len(row[i]) for row in body)]) for i, column in enumerate(columns)]

    def line(cells: Sequence[str]) -> str:
        padded = [cell.rjust(w) if is_num else cell.ljust(w) for cell, w, is_num in zip(cells, widths, numeric)]
        return "| " + " | ".join(padded) + " |"

    rule = "| " + " | ".join("-" * (w - 1) + ":" if is_num else "-" * w for w, is_num in zip(widths, numeric)) + " |"
    return "\n".join([line(columns), rule, *(line(row) for row in body)]) + "\n"


def write_paper_table(df: pd.DataFrame, out_path: str | Path) -> tuple[Path, Path]:
    """Write the table as ``<out_path>.csv`` and ``<out_path>.md`` (any given suffix is replaced)."""
    out_path = Path(out_path)
    csv_path = write_csv(df, out_path.with_suffix(".csv"))
    md_path = out_path.with_suffix(".md")
    markdown = table_to_markdown(df)
    _write_atomically(md_path, lambda tmp: tmp.write_text(markdown))
    return csv_path, md_path
