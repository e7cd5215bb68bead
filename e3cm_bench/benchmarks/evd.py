"""EVD (the Extreme View Dataset, CMP Prague): a homography under extreme viewpoint change.

The reference is the evaluation of the `wxbs-benchmark` package (0.0.4, `metrics.py` and
`evaluation.py`): H is estimated from a method's matches; every pixel of image 1 is mapped by
the estimate and by the ground truth, and the pair's error is the mean distance between the
two over the part of image 1 that is visible in image 2. That part is found the reference's
way, with OpenCV: a mask of ones warped into image 2 by the ground truth and back (bilinear,
both times), and kept where the result is above zero; reproducing OpenCV's fixed-point
interpolation in numpy would only add a second, subtly different border. The benchmark
reports the fraction of pairs whose error is within each of 10 thresholds spaced evenly in
log from 1 to 20 px, and their mean, mAA. The distances are computed in float64 (the
reference: float32, about 1e-4 px at these coordinates). A pair without an H has error inf
(the reference's example puts the identity there, whose error on these pairs is far above 20 px:
the same misses).

Dataset: ``root/1/NAME.png``, ``root/2/NAME.png`` and ``root/h/NAME.txt`` (3 x 3, image 1 ->
image 2), as the release zip unpacks into ``EVD/``. Pairs are named by NAME.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from e3cm_bench.datasets.base import DatasetError, Pair, PairList, require_directory
from e3cm_bench.datasets.hpatches import read_homography
from e3cm_bench.geometry.estimators import homography_geometry, load_estimator
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.ground.matches import Matches
from e3cm_bench.benchmarks.base import Benchmark, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.benchmarks.wxbs import DEFAULT_MAX_SIDE, threshold_curves_figure

# The reference's np.logspace(np.log2(1.0), np.log2(20), 10, base=2.0): 1 .. 20 px.
THRESHOLDS = tuple(float(t) for t in np.logspace(np.log2(1.0), np.log2(20.0), 10, base=2.0))
MAA = "maa"


def accuracy_key(threshold: float) -> str:
    return f"acc@{threshold:.3g}"


# ----------------------------------------------------------------------------- metrics (numpy)


def visible_mask(shape0: tuple[int, int], shape1: tuple[int, int], H_gt: np.ndarray) -> np.ndarray:
    """Boolean (h0, w0): the pixels of image 1 (shape0 = (h, w)) that H_gt maps into image 2
    (shape1) and back, the reference's way (OpenCV warps of a mask of ones, kept above zero)."""
    h0, w0 = shape0
    h1, w1 = shape1
    ones = np.ones((h0, w0))
    into1 = cv2.warpPerspective(ones, H_gt, (w1, h1))
    return cv2.warpPerspective(into1, np.linalg.inv(H_gt), (w0, h0)) > 0


def visible_part_error(shape0: tuple[int, int], shape1: tuple[int, int], H_gt: np.ndarray,
                       H: np.ndarray | None) -> float:
    """Mean distance (px) between each visible pixel of image 1 mapped by H and by H_gt; inf
    without an H, or with one that sends a visible pixel to infinity."""
    if H is None:
        return float("inf")
    mask = visible_mask(shape0, shape1, H_gt)
    if not mask.any():
        return float("nan")  # no overlap: the ground truth itself is broken, not the method
    ys, xs = np.nonzero(mask)
    points = np.stack([xs, ys], axis=1).astype(np.float64)
    error = np.linalg.norm(warp_points(H, points) - warp_points(H_gt, points), axis=1)
    mean = float(np.mean(error))
    return mean if np.isfinite(mean) else float("inf")


def accuracy_curve(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] = THRESHOLDS) -> list[float]:
    """Fraction of pairs whose error is <= each threshold (NaN and inf count as misses)."""
    errors = np.asarray(errors, dtype=np.float64)
    if errors.size == 0:
        return [float("nan")] * len(thresholds)
    return [float(np.mean(errors <= t)) for t in thresholds]


def summarize_evd(rows: Sequence[Mapping]) -> dict:
    rows = list(rows)
    errors = np.asarray([float(r["h_error"]) for r in rows], dtype=np.float64)
    curve = accuracy_curve(errors)
    n_matches = np.asarray([float(r["n_matches"]) for r in rows], dtype=np.float64)
    summary = {"n_pairs": len(rows), "n_matches": float(np.mean(n_matches)) if rows else float("nan"),
               "n_failures": int(np.count_nonzero(~np.isfinite(errors))),
               MAA: float(np.mean(curve)) if rows else float("nan")}
    summary.update({accuracy_key(t): value for t, value in zip(THRESHOLDS, curve)})
    return summary


# ----------------------------------------------------------------------------- dataset


class EVD(PairList):
    """The 15 EVD pairs: image 1, image 2 and the ground-truth H (normalised to H[2, 2] = 1, as
    the reference reads it; the scale of an H changes no mapped point)."""

    name = "evd"

    def __init__(self, root: str | Path, skip_bad: bool = False) -> None:
        self.root = require_directory(root, "EVD")
        first = self.root / "1"
        if not first.is_dir():
            raise DatasetError(f"{first}: EVD image folder not found (expected 1/, 2/ and h/ under the root)")
        pairs, bad = [], []
        for image0 in sorted(first.glob("*.png")):
            try:
                pairs.append(self._pair(image0))
            except DatasetError as error:
                bad.append((image0.stem, str(error)))
        if not pairs and not bad:
            raise DatasetError(f"{first}: no .png image")
        super().__init__(pairs, self.root, skip_bad, bad)

    def _pair(self, image0: Path) -> Pair:
        H = read_homography(self.root / "h" / f"{image0.stem}.txt")
        return Pair(name=image0.stem, image0=image0, image1=self.root / "2" / image0.name, H=H / H[2, 2])

    def settings(self) -> dict:
        return {"dataset": self.name, "root": str(self.root)}


# ----------------------------------------------------------------------------- benchmark


@dataclass(frozen=True)
class EVDBenchmark(Benchmark):
    """Pairs carry H (image 1 -> image 2 pixels); matches are scored through the H they give."""

    ransac_field: str = "homography_ransac_px"
    table_metrics: Mapping[str, str] = field(default_factory=lambda: {"mAA": MAA})
    table_extras: tuple[str, ...] = ("n_pairs", "n_failures", "acc@5.28", "acc@10.3")
    report_columns: tuple[str, ...] = ("n_matches", "h_error")
    paired_columns: tuple[tuple[str, bool], ...] = (("h_error", False),)
    failure: tuple[str, float] | None = ("h_error", THRESHOLDS[-1])  # a miss at every threshold
    count_metrics: Mapping[str, tuple[str, float]] = field(
        default_factory=lambda: {accuracy_key(t): ("h_error", t) for t in THRESHOLDS}
    )

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates(["pair", "n_matches", "h_found", "h_error"])

    def estimate(self, matches: Matches, ev: EvalSettings) -> np.ndarray | None:
        """The evaluation's H from the matches (estimators.homography, seeded by ev.seed)."""
        cv2.setRNGSeed(int(ev.seed))
        return load_estimator(ev.estimator).homography(
            matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64),
            ev.homography_ransac_px, ev.homography_max_iters, ev.homography_confidence, ev.seed, ev.opencv_method,
        )

    def two_view_geometry(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict | None:
        """The evaluation's own H (`estimate`: its robust method, threshold and seed) and the
        matches within its threshold."""
        cv2.setRNGSeed(int(ev.seed))
        return homography_geometry(
            matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64),
            ev.homography_ransac_px, ev.homography_max_iters, ev.homography_confidence,
            ev.estimator, ev.seed, ev.opencv_method,
        )

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        (w0, h0), (w1, h1) = ((int(v) for v in matches.info[key]) for key in ("size0", "size1"))
        H = self.estimate(matches, ev)
        return {"pair": pair.name, "n_matches": len(matches.keypoints0), "h_found": int(H is not None),
                "h_error": visible_part_error((h0, w0), (h1, w1), pair.H, H)}

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        return summarize_evd(rows)

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        # summarize_evd on arrays read once: the same keys, in the same order, from the same values.
        rows = list(rows)
        errors = np.asarray([float(r["h_error"]) for r in rows], dtype=np.float64)
        n_matches = np.asarray([float(r["n_matches"]) for r in rows], dtype=np.float64)

        def summarize(idx: Sequence[int]) -> dict:
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            picked = errors[idx]
            curve = accuracy_curve(picked)
            out = {"n_pairs": int(idx.size), "n_matches": float(np.mean(n_matches[idx])) if idx.size else float("nan"),
                   "n_failures": int(np.count_nonzero(~np.isfinite(picked))),
                   MAA: float(np.mean(curve)) if idx.size else float("nan")}
            out.update({accuracy_key(t): value for t, value in zip(THRESHOLDS, curve)})
            return out

        return summarize

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
        err = np.linalg.norm(warp_points(pair.H, matches.keypoints0) - matches.keypoints1, axis=1)
        return err <= ev.correct_px

    def required_summary_columns(self) -> list[str]:
        return ["n_pairs", "n_matches", MAA, *map(accuracy_key, THRESHOLDS)]

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        self._plot({label: summary}, out / "evd_accuracy.png")

    def plot_comparison(self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path) -> list[Path]:
        return [
            self._plot({label: s for label, (s, _) in runs.items()}, stem.with_name(stem.stem + "_evd_accuracy.png"))
        ]

    @staticmethod
    def _plot(summaries: Mapping[str, Mapping], path: Path) -> Path:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        names = {label: f"{label} (mAA {float(s[MAA]):.3f})" for label, s in summaries.items()}
        curves = {names[label]: [float(s[accuracy_key(t)]) for t in THRESHOLDS] for label, s in summaries.items()}
        bands = {
            names[label]: [plots.interval(s, accuracy_key(t)) for t in THRESHOLDS] for label, s in summaries.items()
        }
        fig = threshold_curves_figure(
            curves,
            THRESHOLDS,
            "mean visible-part reprojection error threshold [px]",
            "fraction of pairs",
            f"EVD: H from the matches; bands: {plots.interval_note(summaries)}",
            log_x=True,
            bands=bands,
        )
        return plots._save_figure(fig, path)


EVD_BENCHMARK = EVDBenchmark(
    name="evd", dataset=EVD, dataset_options=(),
    summary="EVD: H from the matches; accuracy of the visible-part reprojection error at 10 thresholds 1..20 px, mAA.",
    default_max_side=DEFAULT_MAX_SIDE,  # wxbs.py says why
    default_protocol="wxbs",  # the reference's estimator; --protocol default is e3cm-bench's own
)
BENCHMARKS = (EVD_BENCHMARK,)
