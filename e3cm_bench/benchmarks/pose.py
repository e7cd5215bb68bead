"""Relative-pose benchmarks (MegaDepth-1500, YFCC100M): pose AUC@5/10/20 and precision (PROTOCOLS §3)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.geometry import metrics

from e3cm_bench.datasets.base import Pair
from e3cm_bench.datasets.megadepth import MegaDepth1500
from e3cm_bench.datasets.yfcc import YFCC100M
from e3cm_bench.ground.matches import Matches
from e3cm_bench.benchmarks.base import Benchmark, DatasetOption, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.method.protocols import rotation_error


@dataclass(frozen=True)
class PoseBenchmark(Benchmark):
    """Pairs carry K0, K1 (original images) and T_0to1; matches are scored by the essential matrix."""

    ransac_field: str = "pose_ransac_px"
    table_metrics: Mapping[str, str] = field(
        default_factory=lambda: {
            **{f"auc@{t}": f"auc@{t}" for t in metrics.POSE_AUC_THRESHOLDS},
            "P": metrics.precision_key(metrics.PRECISION_THRESHOLDS[0]),
        }
    )
    report_columns: tuple[str, ...] = ("n_matches", "err_pose", "precision@1e-4")
    failure: tuple[str, float] | None = ("err_pose", 10.0)  # degrees: a miss at AUC@10's threshold

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates(["pair", "n_matches", "err_R", "err_t", "err_pose",
                                *map(metrics.precision_key, ev.precision_thresholds)])

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        scoring = metrics.PoseScoring(self.ransac_px(pair, matches, ev), ev.pose_confidence, ev.precision_thresholds,
                                      ev.estimator, rotation_error(ev.protocol), ev.opencv_method)
        row = metrics.evaluate_pose_pair(
            matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64),
            pair.K0, pair.K1, pair.T_0to1, seed=ev.seed, scoring=scoring,
            sizes=(tuple(matches.info["size0"]), tuple(matches.info["size1"])) if "size0" in matches.info else None,
        )
        return {"pair": pair.name, **row}

    def notes(self, pairs: Sequence[Pair], per_pair: pd.DataFrame, ev: EvalSettings) -> list[str]:
        rotations = [np.asarray(pair.T_0to1, dtype=np.float64)[:3, :3] for pair in pairs]
        note = metrics.rotation_note(rotations, per_pair["err_R"], rotation_error(ev.protocol))
        return [note] if note else []

    @classmethod
    def two_view_geometry(cls, pair: Pair, matches: Matches, ev: EvalSettings) -> dict | None:
        """The relative pose by the evaluation's estimator, threshold (ransac_px) and seed, with
        its RANSAC's inliers."""
        from e3cm_bench.geometry.estimators import PoseRansac, pose_geometry

        sizes = (tuple(matches.info["size0"]), tuple(matches.info["size1"])) if "size0" in matches.info else None
        ransac = PoseRansac(
            cls.ransac_px(pair, matches, ev), ev.pose_confidence, ev.estimator, ev.seed, ev.opencv_method
        )
        return pose_geometry(matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64), pair.K0,
                             pair.K1, ransac, sizes=sizes)

    @staticmethod
    def ransac_px(pair: Pair, matches: Matches, ev: EvalSettings) -> float:
        """The essential-matrix RANSAC threshold in pixels of the stored images (whose K the pair
        carries). Given in the matched images' pixels (SuperGlue's way), it is scaled by the
        ratio of the mean focal lengths: stored over matched, per image the longer sides' ratio."""
        if ev.pose_ransac_frame == "original":
            return ev.pose_ransac_px
        if ev.pose_ransac_frame != "matched":
            raise ValueError(f"pose_ransac_frame must be 'original' or 'matched', got {ev.pose_ransac_frame!r}")
        try:
            stored_over_matched = [max(matches.info[f"size{i}"]) / max(matches.info[f"match_size{i}"]) for i in (0, 1)]
        except KeyError:
            raise ValueError(f"{pair.name}: the cached matches do not record the size they were matched at, "
                             "which a threshold in matched pixels needs") from None
        focal = [pair.K0[0, 0], pair.K0[1, 1], pair.K1[0, 0], pair.K1[1, 1]]
        matched = [f / stored_over_matched[i // 2] for i, f in enumerate(focal)]
        return float(ev.pose_ransac_px * np.mean(focal) / np.mean(matched))

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        return metrics.summarize_pose(rows, ev.precision_thresholds, ev.drop_failures)

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        # metrics.summarize_pose on arrays read once: the same keys in the same order, the same
        # float64 means over the same values in the same order and the same pose_auc, so equal
        # bit for bit.
        rows = list(rows)
        n_matches = np.asarray([r["n_matches"] for r in rows], dtype=np.float64)
        errors = np.asarray([r["err_pose"] for r in rows], dtype=np.float64)
        finite = np.isfinite(errors)
        keys = [metrics.precision_key(t) for t in ev.precision_thresholds]
        precision = {key: np.asarray([r[key] for r in rows], dtype=np.float64) for key in keys}

        def mean(values: np.ndarray) -> float:
            return float(np.mean(values)) if values.size else float("nan")

        def summarize(idx: Sequence[int]) -> dict:
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            summary = {"n_pairs": int(idx.size), "n_matches": mean(n_matches[idx]),
                       "n_failures": int(np.count_nonzero(~finite[idx]))}
            chosen = errors[idx[finite[idx]]] if ev.drop_failures else errors[idx]
            for threshold, auc in zip(
                metrics.POSE_AUC_THRESHOLDS, metrics.pose_auc(chosen, metrics.POSE_AUC_THRESHOLDS)
            ):
                summary[f"auc@{threshold}"] = auc
            for key in keys:
                summary[key] = 100.0 * mean(precision[key][idx])
            return summary

        return summarize

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
        distances = metrics.epipolar_distances(matches.keypoints0, matches.keypoints1, pair.K0, pair.K1, pair.T_0to1)
        return distances < ev.precision_thresholds[0]

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        plots.plot_pose_error_cdf({label: per_pair}, out / "pose_error_cdf.png")

    def plot_comparison(self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path) -> list[Path]:
        from e3cm_bench.drawing import plots

        bars = stem.with_name(stem.stem + "_pose_auc.png")
        cdf = stem.with_name(stem.stem + "_pose_cdf.png")
        return [
            plots.plot_pose_auc_bars({label: s for label, (s, _) in runs.items()}, bars,
                                     title=f"{self.name}: pose AUC and precision"),
            plots.plot_pose_error_cdf({label: p for label, (_, p) in runs.items()}, cdf),
        ]


MEGADEPTH = PoseBenchmark(
    name="megadepth", dataset=MegaDepth1500,
    dataset_options=(DatasetOption(
        "scene_info", "paths", "scene_info .npz files (default: all under ROOT/scene_info; a ROOT in glue-factory's "
        "megadepth1500 layout needs none)."),),
    summary="MegaDepth-1500: relative pose AUC@5/10/20 and matching precision.",
    default_max_side=1200, paper_table="table2.csv",
)
YFCC = PoseBenchmark(
    name="yfcc", dataset=YFCC100M,
    dataset_options=(DatasetOption("pairs", "path", "Pair list (default ROOT/yfcc_test_pairs_with_gt.txt)."),),
    summary="YFCC100M (or any SuperGlue-format pair list): pose AUC@5/10/20 and matching precision.",
    default_max_side=1200, paper_table="table3.csv",
)
BENCHMARKS = (MEGADEPTH, YFCC)
