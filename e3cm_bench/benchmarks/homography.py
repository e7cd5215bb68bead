"""Homography benchmarks (HPatches): MMA at 1..10 px and homography accuracy (PROTOCOLS §2)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.geometry import metrics

from e3cm_bench.datasets.base import Pair
from e3cm_bench.datasets.hpatches import HPatches
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.ground.matches import Matches
from e3cm_bench.benchmarks.base import Benchmark, DatasetOption, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings


@dataclass(frozen=True)
class HomographyBenchmark(Benchmark):
    """Pairs carry H (image 0 -> image 1 pixels); HPatches-style i_/v_ sequence names split the MMA."""

    table_metrics: Mapping[str, str] = field(
        default_factory=lambda: {f"h_acc@{t}": f"h_acc@{t}" for t in metrics.HOMOGRAPHY_ACCURACY_THRESHOLDS}
    )
    table_extras: tuple[str, ...] = ("n_pairs", "mma@3")
    report_columns: tuple[str, ...] = ("n_matches", "mma@3", "h_error")
    failure: tuple[str, float] | None = ("h_error", 3.0)  # the h_acc@3 miss
    count_metrics: Mapping[str, tuple[str, float]] = field(
        default_factory=lambda: {f"h_acc@{t}": ("h_error", float(t)) for t in metrics.HOMOGRAPHY_ACCURACY_THRESHOLDS}
    )

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates([*metrics.HPATCHES_PAIR_COLUMNS, *_precision_columns(ev)])

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        width, height = (int(v) for v in matches.info["size0"])
        k0, k1 = _in_origin(matches.keypoints0, ev), _in_origin(matches.keypoints1, ev)
        if ev.homography_pixel_origin == "corner":
            # glue-factory's corner error takes the image corners (0, 0) .. (w, h) of the corner
            # convention; metrics' corners are (0, 0) .. (w - 1, h - 1): the same points for a
            # size one larger, exactly.
            width, height = width + 1, height + 1
        scoring = metrics.HomographyScoring(ev.homography_ransac_px, ev.homography_max_iters, ev.homography_confidence,
                                            ev.estimator)
        row = metrics.evaluate_homography_pair(k0, k1, pair.H, width, height, seed=ev.seed, scoring=scoring)
        if ev.match_precision_px:
            error = np.nan_to_num(metrics.symmetric_homography_error(k0, k1, pair.H), nan=np.inf)
            for t, column in zip(ev.match_precision_px, _precision_columns(ev)):
                # glue-factory: strictly below t; a pair without matches scores 0 (its nan_to_num)
                row[column] = float(np.mean(error < t)) if len(error) else 0.0
        return {"pair": pair.name, "sequence": pair.sequence, **row}

    @classmethod
    def two_view_geometry(cls, pair: Pair, matches: Matches, ev: EvalSettings) -> dict | None:
        """H by the evaluation's estimator, threshold and seed, on the matches as stored (the
        pixel-centre convention), with the matches within the threshold as its inliers."""
        from e3cm_bench.geometry.estimators import homography_geometry

        return homography_geometry(matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64),
                                   ev.homography_ransac_px, ev.homography_max_iters, ev.homography_confidence,
                                   estimator=ev.estimator, seed=ev.seed)

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        summary = metrics.summarize_hpatches(rows)
        for column in _precision_columns(ev):
            summary.update(_precision_summary(_column(list(rows), column), column))
        return summary

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        # metrics.summarize_hpatches on arrays read once: the same keys in the same order and the
        # same float64 means over the same values in the same order, so equal bit for bit.
        rows = list(rows)
        n_matches = _column(rows, "n_matches")
        mma = {t: _column(rows, f"mma@{t}") for t in metrics.MMA_THRESHOLDS}
        h_error = _column(rows, "h_error")
        splits = {s: np.array([str(r["sequence"]).startswith(f"{s}_") for r in rows], dtype=bool) for s in ("i", "v")}
        precision = {column: _column(rows, column) for column in _precision_columns(ev)}

        def block(idx: np.ndarray, suffix: str) -> dict:
            out = {f"n_pairs{suffix}": int(idx.size), f"n_matches{suffix}": _mean(n_matches[idx])}
            out.update({f"mma@{t}{suffix}": _mean(mma[t][idx]) for t in metrics.MMA_THRESHOLDS})
            return out

        def summarize(idx: Sequence[int]) -> dict:
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            summary = block(idx, "")
            for split, mask in splits.items():
                summary.update(block(idx[mask[idx]], f"_{split}"))
            for t in metrics.HOMOGRAPHY_ACCURACY_THRESHOLDS:
                summary[f"h_acc@{t}"] = _mean((h_error[idx] <= t).astype(np.float64))
            for column, values in precision.items():
                summary.update(_precision_summary(values[idx], column))
            return summary

        return summarize

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
        err = np.linalg.norm(
            warp_points(pair.H, _in_origin(matches.keypoints0, ev)) - _in_origin(matches.keypoints1, ev), axis=1
        )
        return err <= ev.correct_px

    def required_summary_columns(self) -> list[str]:
        # The illumination/viewpoint split columns are optional: a run may hold one kind only.
        return ["n_pairs", "n_matches", *(f"mma@{t}" for t in metrics.MMA_THRESHOLDS), *self.table_metrics.values()]

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        plots.plot_mma_curves({label: summary}, out / "mma.png")

    def plot_comparison(self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path) -> list[Path]:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        summaries = {label: summary for label, (summary, _) in runs.items()}
        # The headline (h_acc, the table's columns) first, then the MMA curves of the paper's Fig. 5.
        return [plots.plot_h_acc_bars(summaries, stem.with_name(stem.stem + "_h_acc.png")),
                plots.plot_mma_curves(summaries, stem.with_name(stem.stem + "_mma.png"))]


def _in_origin(points: np.ndarray, ev: EvalSettings) -> np.ndarray:
    """Keypoints (ours: centre convention) as float64 in the convention the ground-truth H is
    applied in (EvalSettings.homography_pixel_origin)."""
    from e3cm_bench.interchange.pixels import to_origin

    return to_origin(points, ev.homography_pixel_origin)


def _precision_columns(ev: EvalSettings) -> list[str]:
    return [metrics.precision_column(t) for t in ev.match_precision_px]


def _precision_summary(values: np.ndarray, column: str) -> dict:
    """glue-factory's match precision over the pairs: the mean, and its own summary, the median
    over the pairs (its "m" + key)."""
    return {column: _mean(values), f"m{column}": float(np.median(values)) if values.size else float("nan")}


def _column(rows: Sequence[Mapping], key: str) -> np.ndarray:
    return np.asarray([r[key] for r in rows], dtype=np.float64)


def _mean(values: np.ndarray) -> float:
    """metrics' mean of a summary: float64 np.mean, NaN for no values."""
    return float(np.mean(values)) if values.size else float("nan")


HPATCHES = HomographyBenchmark(
    name="hpatches", dataset=HPatches,
    dataset_options=(
        DatasetOption("exclude_large", "flag", "The 108-sequence / 540-pair protocol (D2-Net)."),
        DatasetOption("sequences", "names", "Keep these sequences (names or globs; repeatable)."),
    ),
    summary="HPatches: MMA@1..10 px (overall / illumination / viewpoint) and homography accuracy.",
    default_max_side=None, ransac_field="homography_ransac_px", paper_table="table1.csv",
)
BENCHMARKS = (HPATCHES,)
