"""Plots of benchmark runs: MMA curves (paper Fig. 5), homography accuracy bars (HPatches'
headline), pose-error CDF, pose AUC bars.

Every number a plot shows from summary.csv is drawn with its bootstrap interval (the ``m_lo``,
``m_hi`` columns, intervals.py): a band around a curve, an error bar on a bar. Empirical
cumulative curves are drawn as steps, as they are: a curve over 2 pairs has 2 steps.

Drawn on ``matplotlib.figure.Figure`` objects (saved through the Agg canvas) rather than
pyplot, so that importing this module never switches the backend of the caller's process.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from e3cm_bench.ground.files import write_atomically
from e3cm_bench.geometry.metrics import MMA_THRESHOLDS, POSE_AUC_THRESHOLDS as AUC_THRESHOLDS, pose_error_curve
from e3cm_bench.drawing.formats import format_number, plot_format


# PDF and SVG carry their creation date unless told not to: without it the same run's plot is
# the same file, as a PNG is.
_NO_DATE = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}


def _save_figure(fig: Figure, path: str | Path) -> Path:
    """Save as the path says; a .png path in the format --format chose (formats.plot_format),
    under the same name with that suffix. Returns the path written."""
    path = Path(path)
    if path.suffix in ("", ".png"):
        path = path.with_suffix("." + plot_format())
    file_format = path.suffix.lstrip(".")
    metadata = _NO_DATE.get(file_format)
    # bbox "tight" grows the canvas to whatever the legend needs, so long labels are never cut.
    return write_atomically(path, lambda tmp: fig.savefig(tmp, format=file_format, dpi=150, bbox_inches="tight",
                                                          metadata=metadata))


def interval(summary: Mapping, key: str) -> tuple[float, float]:
    """(lo, hi) of `key`'s bootstrap interval in a summary; NaN where the run has none."""
    bounds = []
    for suffix in ("_lo", "_hi"):
        try:
            bounds.append(float(summary.get(key + suffix, np.nan)))
        except (TypeError, ValueError):
            bounds.append(np.nan)
    return bounds[0], bounds[1]


def error_bars(values: Sequence[float], bounds: Sequence[tuple[float, float]]) -> np.ndarray | None:
    """matplotlib's yerr (2, n): the distances from each value down to lo and up to hi; None where
    no value has an interval (a bar without one is drawn without a bar, not with a zero bar)."""
    values = np.asarray(values, dtype=np.float64)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in zip(*bounds)) if len(bounds) else (values, values)
    if np.all(np.isnan(lo)) or np.all(np.isnan(hi)):
        return None
    # A bound on the wrong side of its value cannot come from a percentile interval of the mean of a
    # set that holds the value, but a summary written by hand may hold one: draw nothing there.
    below, above = np.clip(values - lo, 0, None), np.clip(hi - values, 0, None)
    return np.nan_to_num(np.vstack([below, above]), nan=0.0)


def interval_note(runs: Mapping[str, Mapping]) -> str:
    """What the bands and bars are, at the confidence the runs recorded (95% by default)."""
    levels = {float(s.get("confidence", 0.95)) for s in runs.values() if s.get("confidence") == s.get("confidence")}
    level = f"{levels.pop():.0%}" if len(levels) == 1 else "95%" if not levels else "per-run"
    return f"{level} bootstrap interval over the pairs"


def _run_colors(labels: Sequence[str]) -> dict[str, tuple]:
    """One colour per run label, stable across the plots of one report."""
    palette = colormaps["tab10"].colors
    return {label: palette[i % len(palette)] for i, label in enumerate(labels)}


def mma_figure(runs: Mapping[str, Mapping]) -> Figure:
    """HPatches MMA vs threshold (1..10 px): Overall / Illumination / Viewpoint panels.

    One line per run, legend with the mean number of matches per pair (the layout of
    the paper's Fig. 5). A split whose values are all NaN (no such pairs) is left
    empty with a note rather than dropped, so panels keep their place.
    """
    if not runs:
        raise ValueError("MMA plot: no runs to plot")
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
            lo, hi = np.array([interval(summary, f"mma@{t}{suffix}") for t in thresholds]).T
            if not np.all(np.isnan(lo)):
                ax.fill_between(thresholds, lo, hi, color=colors[label], alpha=0.15, linewidth=0)
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
    legend_labels = [
        f"{label} ({format_number(summary.get('n_matches'), 'n_matches', decimals=0)} matches)"
        for label, summary in runs.items()
    ]
    fig.legend(handles, legend_labels, loc="outside lower center", ncol=min(len(runs), 3), frameon=False,
               title=f"bands: {interval_note(runs)}", title_fontsize=8)
    return fig


def plot_mma_curves(runs: Mapping[str, Mapping], path: str | Path) -> Path:
    return _save_figure(mma_figure(runs), path)


def grouped_bars(ax, runs: Mapping[str, Mapping], keys: Sequence[str], colors: Mapping[str, tuple], fmt: str,
                 scale: float = 1.0) -> None:
    """Bars of summary values `keys` (one group per key, one bar per run) with their intervals as
    error bars and the value written above the bar."""
    labels = list(runs)
    width = 0.8 / len(labels)
    groups = np.arange(len(keys))
    for i, label in enumerate(labels):
        values = [float(runs[label].get(k, np.nan)) * scale for k in keys]
        bounds = [tuple(b * scale for b in interval(runs[label], k)) for k in keys]
        yerr = error_bars(values, bounds)
        bars = ax.bar(groups + (i - (len(labels) - 1) / 2) * width, values, width, color=colors[label], label=label,
                      yerr=yerr, error_kw={"elinewidth": 1, "capsize": 2, "ecolor": "#333"})
        ax.bar_label(bars, fmt=fmt, fontsize=7, padding=1 if yerr is None else 3)


def h_acc_figure(runs: Mapping[str, Mapping], thresholds: Sequence[int] = (1, 3, 5)) -> Figure:
    """HPatches' headline: homography accuracy h_acc@1/3/5 (the fraction of pairs whose corner
    error is within t px), one bar per run with its bootstrap interval."""
    if not runs:
        raise ValueError("h_acc plot: no runs to plot")
    colors = _run_colors(list(runs))
    fig = Figure(figsize=(9, 4.6), layout="constrained")
    ax = fig.subplots()
    keys = [f"h_acc@{t}" for t in thresholds]
    grouped_bars(ax, runs, keys, colors, "%.2f")
    ax.set_xticks(np.arange(len(keys)), [f"h_acc@{t} px" for t in thresholds])
    ax.set_ylabel("fraction of pairs (corner error <= t)")
    ax.set_ylim(0, 1.12)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    n_pairs = {int(float(s.get("n_pairs", 0) or 0)) for s in runs.values()}
    pairs = f"{n_pairs.pop()} pairs" if len(n_pairs) == 1 else "pairs differ between runs"
    ax.set_title(f"homography accuracy ({pairs}); bars: {interval_note(runs)}")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=min(len(runs), 4), frameon=False)
    return fig


def plot_h_acc_bars(runs: Mapping[str, Mapping], path: str | Path) -> Path:
    return _save_figure(h_acc_figure(runs), path)


def pose_error_cdf_figure(runs: Mapping[str, pd.DataFrame], max_error: float = 30.0) -> Figure:
    """Fraction of pairs with pose error below x, x in [0, max_error] degrees, one line per run.

    The AUC thresholds (5, 10, 20 deg) are marked: AUC@t is the area under the curve
    left of the mark, divided by t.
    """
    if not runs:
        raise ValueError("pose-error plot: no runs to plot")
    colors = _run_colors(list(runs))
    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.subplots()
    for label, per_pair in runs.items():
        if "err_pose" not in per_pair.columns or per_pair.empty:
            raise ValueError(f"pose-error plot: run {label!r} has no per-pair err_pose values")
        errors = per_pair["err_pose"].to_numpy(dtype=np.float64)
        x, y = pose_error_curve(errors)
        # Hold the last recall flat to the right edge, as the AUC does up to its threshold.
        x, y = np.append(x, max(max_error, x[-1])), np.append(y, y[-1])
        n_failed = int(np.sum(~np.isfinite(errors)))
        # The fraction of pairs with error <= x is a step function: it rises at each pair's error.
        ax.step(x, y, where="post", color=colors[label], label=f"{label} ({len(errors)} pairs, {n_failed} failed)")
        # The AUC integrates the same points joined by straight lines (PROTOCOLS: the reference
        # codes' trapezoid rule), drawn faintly so that the area the numbers measure is visible.
        ax.plot(x, y, color=colors[label], linewidth=0.8, linestyle="--", alpha=0.5)
    for threshold in AUC_THRESHOLDS:
        ax.axvline(threshold, color="gray", linestyle=":", linewidth=1)
        ax.text(threshold, 1.0, f" AUC@{threshold}", color="gray", fontsize=8, va="top", ha="left")
    ax.set_xlim(0, max_error)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("pose error [deg]  (max of rotation and translation angle)")
    ax.set_ylabel("fraction of pairs with error <= x")
    ax.set_title("steps: the pairs' errors; dashed: the curve the AUC integrates", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return fig


def plot_pose_error_cdf(runs: Mapping[str, pd.DataFrame], path: str | Path, max_error: float = 30.0) -> Path:
    return _save_figure(pose_error_cdf_figure(runs, max_error), path)


def pose_auc_figure(runs: Mapping[str, Mapping], title: str) -> Figure:
    """Grouped bars of AUC@5/10/20 (left panel) and precision P@1e-4 (right panel), percent.

    Bars are grouped by metric with one colour per run, so methods are compared side
    by side within each threshold.
    """
    if not runs:
        raise ValueError("pose AUC plot: no runs to plot")
    labels = list(runs)
    colors = _run_colors(labels)
    fig = Figure(figsize=(11, 4.4), layout="constrained")
    auc_ax, precision_ax = fig.subplots(1, 2, width_ratios=(3, 1.3))
    groups = np.arange(len(AUC_THRESHOLDS))
    grouped_bars(auc_ax, runs, [f"auc@{t}" for t in AUC_THRESHOLDS], colors, "%.1f")
    for i, label in enumerate(labels):
        precision = float(runs[label].get("precision@1e-4", np.nan))
        yerr = error_bars([precision], [interval(runs[label], "precision@1e-4")])
        bars = precision_ax.bar(i, precision, 0.7, color=colors[label], yerr=yerr,
                                error_kw={"elinewidth": 1, "capsize": 2, "ecolor": "#333"})
        precision_ax.bar_label(bars, fmt="%.1f", fontsize=7, padding=1 if yerr is None else 3)
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
    fig.suptitle(f"{title}; bars: {interval_note(runs)}")
    return fig


def plot_pose_auc_bars(runs: Mapping[str, Mapping], path: str | Path, title: str) -> Path:
    return _save_figure(pose_auc_figure(runs, title), path)


# --------------------------------------------------------------------------- stereo self-calibration

CALIBRATION_PANELS = (
    ("yaw", "deg"),
    ("pitch", "deg"),
    ("roll", "deg"),
    ("tx", "unit t"),
    ("ty", "unit t"),
    ("tz", "unit t"),
)


def calibration_boxplot_figure(windows: pd.DataFrame, frames: int) -> Figure:
    """The paper's Fig. 7: one panel per error component, one box per matcher (windows of `frames`)."""
    chosen = windows[windows["frames"] == frames]
    if chosen.empty:
        raise ValueError(f"calibration plot: no windows of {frames} frames")
    methods = list(dict.fromkeys(chosen["method"]))
    colors = _run_colors(methods)
    fig = Figure(figsize=(13, 6.5), layout="constrained")
    for ax, (column, unit) in zip(fig.subplots(2, 3).ravel(), CALIBRATION_PANELS):
        data = [chosen.loc[chosen["method"] == m, column].replace([np.inf, -np.inf], np.nan).dropna().to_numpy()
                for m in methods]
        boxes = ax.boxplot(data, patch_artist=True, widths=0.6)
        for patch, method in zip(boxes["boxes"], methods):
            patch.set_facecolor(colors[method])
            patch.set_alpha(0.6)
        ax.set_xticks(range(1, len(methods) + 1), methods, rotation=20, ha="right")
        ax.axhline(0, color="gray", linewidth=0.8)
        ax.set_title(f"{column} error [{unit}]")
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"stereo rig self-calibration error, windows of {frames} frames")
    return fig


def plot_calibration_boxplots(windows: pd.DataFrame, frames: int, path: str | Path) -> Path:
    return _save_figure(calibration_boxplot_figure(windows, frames), path)


def calibration_vs_frames_figure(summary: pd.DataFrame) -> Figure:
    """Fig. 8 style: mean absolute rotation and translation error against the frames pooled."""
    methods = list(dict.fromkeys(summary["method"]))
    colors = _run_colors(methods)
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    for ax, (column, label) in zip(fig.subplots(1, 2), (("rotation", "largest angle error [deg]"),
                                                        ("translation", "largest unit-t component error"))):
        for method in methods:
            rows = summary[summary["method"] == method].sort_values("frames")
            ax.plot(rows["frames"], rows[column], marker="o", color=colors[method], label=method)
        ax.set_xlabel("frames pooled")
        ax.set_ylabel(f"mean {label}")
        ax.set_xticks(sorted(summary["frames"].unique()))
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    fig.axes[0].legend(fontsize=8)
    return fig


def plot_calibration_vs_frames(summary: pd.DataFrame, path: str | Path) -> Path:
    return _save_figure(calibration_vs_frames_figure(summary), path)


MATCHING_TIME = "seconds per pair (matching only; log scale)"  # the x axis of a benchmark's cost plot


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points (seconds, accuracy) no other point beats on both (at most as slow and
    at least as accurate, better on one), by increasing time: the curve a reader chooses along."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -np.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def cost_accuracy_figure(runs: Mapping[str, Mapping], metric: str, x_label: str = MATCHING_TIME) -> Figure:
    """Accuracy (`metric`) against the mean seconds per pair, one point per run with both
    intervals (bootstrap over the pairs), the Pareto front drawn through the runs no other
    beats on both; log-scaled time."""
    labels = [label for label, s in runs.items()
              if np.isfinite(float(s.get("seconds_per_pair", np.nan))) and np.isfinite(float(s.get(metric, np.nan)))]
    colors = _run_colors(list(runs))
    fig = Figure(figsize=(7.5, 4.8))
    ax = fig.subplots()
    points = [(float(runs[k]["seconds_per_pair"]), float(runs[k][metric])) for k in labels]
    for label, (x, y) in zip(labels, points):
        xerr = error_bars([x], [interval(runs[label], "seconds_per_pair")])
        yerr = error_bars([y], [interval(runs[label], metric)])
        ax.errorbar([x], [y], xerr=xerr, yerr=yerr, fmt="o", color=colors[label], capsize=3, label=label)
    front = pareto_front(points)
    if len(front) > 1:
        ax.plot([points[i][0] for i in front], [points[i][1] for i in front], "--", color="0.5", lw=1,
                label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel(x_label)
    ax.set_ylabel(metric)
    ax.set_title(f"{metric} against {x_label.split(' (')[0]}; bars: {interval_note({k: runs[k] for k in labels})}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    return fig


def plot_cost_accuracy(runs: Mapping[str, Mapping], metric: str, path: str | Path,
                       x_label: str = MATCHING_TIME) -> Path:
    return _save_figure(cost_accuracy_figure(runs, metric, x_label), path)


def rank_figure(table: pd.DataFrame, metric: str) -> Figure:
    """The protocol sweep's ranks (pipeline/sweep.py): one line per run across the cells (the
    default cell first), rank 1 at the top; each point labelled with the run's metric."""
    cells = list(dict.fromkeys(table["cell"]))
    runs = list(dict.fromkeys(table["run"]))
    colors = _run_colors(runs)
    fig = Figure(figsize=(max(6.0, 1.1 * len(cells) + 2.5), 1.0 + 0.55 * len(runs)))
    ax = fig.add_subplot()
    for run in runs:
        rows = table[table["run"] == run].set_index("cell").reindex(cells)
        ax.plot(range(len(cells)), rows["rank"], "-o", color=colors[run], label=run)
        for x, (rank, value) in enumerate(zip(rows["rank"], rows[metric])):
            if np.isfinite(rank):
                ax.annotate(
                    f"{value:.0f}", (x, rank), textcoords="offset points", xytext=(0, 5), ha="center", fontsize=7
                )
    ax.set_xticks(range(len(cells)), cells, rotation=35, ha="right", fontsize=8)
    ax.set_yticks(range(1, len(runs) + 1))
    ax.set_ylim(len(runs) + 0.6, 0.4)
    ax.set_ylabel(f"rank by {metric}")
    ax.set_title(f"Ranks per protocol cell (labels: {metric}; first cell: the runs' own)", fontsize=9)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.grid(axis="y", alpha=0.3)
    return fig
