"""Plots draw the bootstrap interval every number has: bands around curves,
error bars on bars; the headline h_acc has its plot; empirical cumulative curves are steps."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PolyCollection

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.benchmarks.wxbs import threshold_curves_figure
from e3cm_bench.drawing import plots

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def hpatches_summary(h_acc: tuple[float, float, float], width: float = 0.1) -> dict:
    summary = {"n_pairs": 10, "n_matches": 500.0, "confidence": 0.95}
    for suffix in ("", "_i", "_v"):
        for t in range(1, 11):
            value = min(1.0, 0.5 + 0.05 * t)
            summary.update({f"mma@{t}{suffix}": value, f"mma@{t}{suffix}_lo": value - width,
                            f"mma@{t}{suffix}_hi": min(1.0, value + width)})
    for t, value in zip((1, 3, 5), h_acc):
        summary.update({f"h_acc@{t}": value, f"h_acc@{t}_lo": max(0.0, value - 0.3), f"h_acc@{t}_hi": min(1.0, value + 0.1)})
    return summary


def bands_of(ax) -> list[tuple[float, float]]:
    """(min, max) y of every filled band in an axis."""
    return [(float(p.get_paths()[0].vertices[:, 1].min()), float(p.get_paths()[0].vertices[:, 1].max()))
            for p in ax.collections if isinstance(p, PolyCollection)]


def test_mma_curves_carry_their_interval_as_a_band():
    runs = {"a": hpatches_summary((0.8, 1.0, 1.0)), "b": hpatches_summary((0.5, 0.9, 1.0), width=0.02)}
    fig = plots.mma_figure(runs)
    for ax in fig.axes:
        bands = bands_of(ax)
        assert len(bands) == 2  # one per run
        assert np.ravel(bands) == pytest.approx([runs["a"]["mma@1_lo"], runs["a"]["mma@10_hi"],
                                                 runs["b"]["mma@1_lo"], runs["b"]["mma@10_hi"]])
    assert "bootstrap interval" in fig.legends[0].get_title().get_text()
    # a summary without intervals (written before they existed) is drawn without a band
    bare = {k: v for k, v in runs["a"].items() if not k.endswith(("_lo", "_hi"))}
    assert bands_of(plots.mma_figure({"old": bare}).axes[0]) == []


def test_the_headline_h_acc_has_a_plot_with_error_bars(tmp_path):
    runs = {"sift": hpatches_summary((1.0, 1.0, 1.0)), "e3cm": hpatches_summary((0.8, 1.0, 1.0)),
            "release": hpatches_summary((0.5, 0.6, 0.6))}
    path = plots.plot_h_acc_bars(runs, tmp_path / "h_acc.png")
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    ax = plots.h_acc_figure(runs).axes[0]
    heights = [bar.get_height() for bar in ax.patches]
    assert heights == pytest.approx([runs[m][f"h_acc@{t}"] for m in runs for t in (1, 3, 5)])
    # each bar's error bar spans its interval: the segments' ends are lo and hi
    segments = [seg for container in ax.containers if hasattr(container, "lines") and container.lines[2]
                for seg in container.lines[2][0].get_segments()]
    assert np.ravel([(s[0][1], s[1][1]) for s in segments]) == pytest.approx(
        np.ravel([(runs[m][f"h_acc@{t}_lo"], runs[m][f"h_acc@{t}_hi"]) for m in runs for t in (1, 3, 5)]))
    assert "10 pairs" in ax.get_title() and "95% bootstrap interval" in ax.get_title()


def test_hpatches_comparison_draws_h_acc_first(tmp_path):
    runs = {"a": (hpatches_summary((0.8, 1.0, 1.0)), pd.DataFrame()), "b": (hpatches_summary((1.0, 1.0, 1.0)), pd.DataFrame())}
    written = get_benchmark("hpatches").plot_comparison(runs, tmp_path / "table")
    assert [p.name for p in written] == ["table_h_acc.png", "table_mma.png"]


def test_pose_bars_have_error_bars_and_the_cdf_is_a_step_curve():
    summary = {"auc@5": 40.0, "auc@10": 60.0, "auc@20": 75.0, "precision@1e-4": 90.0,
               **{f"{k}_lo": v - 10 for k, v in (("auc@5", 40.0), ("auc@10", 60.0), ("auc@20", 75.0), ("precision@1e-4", 90.0))},
               **{f"{k}_hi": v + 5 for k, v in (("auc@5", 40.0), ("auc@10", 60.0), ("auc@20", 75.0), ("precision@1e-4", 90.0))}}
    auc_ax, precision_ax = plots.pose_auc_figure({"m": summary}, "t").axes
    for ax, keys in ((auc_ax, ("auc@5", "auc@10", "auc@20")), (precision_ax, ("precision@1e-4",))):
        segments = [seg for c in ax.containers if hasattr(c, "lines") and c.lines[2] for seg in c.lines[2][0].get_segments()]
        assert np.ravel([(s[0][1], s[1][1]) for s in segments]) == pytest.approx(
            np.ravel([(summary[k] - 10, summary[k] + 5) for k in keys]))
    # 2 pairs: the curve rises in 2 steps (drawn as steps, not slopes between the points)
    ax = plots.pose_error_cdf_figure({"m": pd.DataFrame({"err_pose": [2.0, 7.0]})}).axes[0]
    (curve,) = [line for line in ax.get_lines() if line.get_label().startswith("m (")]
    assert curve.get_drawstyle() == "steps-post"
    assert curve.get_xdata().tolist() == [0.0, 2.0, 7.0, 30.0] and curve.get_ydata().tolist() == [0.0, 0.5, 1.0, 1.0]


def test_wxbs_and_evd_curves_carry_bands():
    curves = {"a": [0.1, 0.5, 0.9]}
    fig = threshold_curves_figure(curves, [1, 5, 10], "x", "y", "t", bands={"a": [(0.0, 0.2), (0.4, 0.6), (0.8, 1.0)]})
    assert np.ravel(bands_of(fig.axes[0])) == pytest.approx([0.0, 1.0])
    assert bands_of(threshold_curves_figure(curves, [1, 5, 10], "x", "y", "t").axes[0]) == []


def test_error_bars_skip_missing_intervals():
    assert plots.error_bars([0.5, 0.7], [(np.nan, np.nan), (np.nan, np.nan)]) is None
    yerr = plots.error_bars([0.5, 0.7], [(0.4, 0.9), (np.nan, np.nan)])
    assert yerr.ravel() == pytest.approx([0.1, 0.0, 0.4, 0.0])
