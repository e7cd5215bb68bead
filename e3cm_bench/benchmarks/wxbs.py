"""WxBS (wide multiple-baseline stereo, Mishkin et al. 2015; release v1.1): the fundamental matrix.

The reference is the evaluation of the `wxbs-benchmark` package (0.0.4, `metrics.py` and
`evaluation.py`): F is estimated from a method's matches; each hand-labelled ground-truth
correspondence (`corrs.txt`) gets its symmetric epipolar distance w.r.t. that F (in pixels,
not squared); a pair scores the fraction of its correspondences within each threshold
0, 1, ..., 19 px, and the benchmark the mean of those fractions over the pairs. The
reference stops at that curve; mAA@10px, the number RoMa v2 and LoMa publish, is read here as
the mean of the curve at 1, 2, ..., 10 px (the 0 px point says nothing: no distance is
exactly 0). A pair whose F cannot be estimated scores 0 at every threshold (the reference
would be handed no matrix at all; counting the pair keeps a failing method from looking
better by failing).

Dataset: ``root/v1.1/<category>/<pair>/`` with ``01.png|jpg``, ``02.png|jpg``, ``corrs.txt``
(x1 y1 x2 y2 per line, pixels of the stored images) and ``crossval_errors.txt``, as the
release zip unpacks; ``root`` may also be the ``v1.1`` folder itself. Pair names are
``<category>/<pair>`` as the reference names them. Two pairs, ``kyiv_dolltheater2`` and
``petrzin``, are the release's validation pairs; the default split is the test set.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from e3cm_bench.datasets.base import DatasetError, Pair, PairList, require_directory
from e3cm_bench.geometry.estimators import fundamental
from e3cm_bench.geometry.two_view import to_homogeneous
from e3cm_bench.ground.images import header_size
from e3cm_bench.ground.matches import Matches
from e3cm_bench.benchmarks.base import Benchmark, DatasetOption, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings

if TYPE_CHECKING:
    from matplotlib.figure import Figure

VERSION = "v1.1"
THRESHOLDS = tuple(range(20))  # px: the reference's np.arange(20)
MAA_THRESHOLDS = tuple(range(1, 11))  # px: mAA@10px averages the curve at these
VALIDATION_PAIRS = ("kyiv_dolltheater2", "petrzin")  # the reference's WxBSDataset.validation_pairs
SPLITS = ("test", "val", "all")
IMAGE_SUFFIXES = (".png", ".jpg")
MAA = "maa@10"
# The default longer side for matching, WxBS's and EVD's. Their images are 600-1000 px on the
# longer side (three larger, WxBS's thermal ones about 250, never enlarged) and most WxBS images
# are 800 wide: 800 matches those at their stored size, as the reference evaluates, and keeps all
# 14 CPU runs of the built-in methods (Lite0) near half an hour. Measured against 640: WxBS
# mAA@10px rises for six of the seven methods (docs/wxbs-evd.md); the committed results use 800.
DEFAULT_MAX_SIDE = 800
# How far outside its image (pixels) a hand-labelled correspondence may lie: every one of the
# release's 33 pairs here lies within its images (some on the border itself); a click a pixel
# or two past the border is a labelling slip, a point further out is not on the image at all.
EDGE_TOLERANCE_PX = 2.0


def recall_key(threshold: int) -> str:
    return f"recall@{threshold}"


# ----------------------------------------------------------------------------- metrics (numpy)


def symmetric_epipolar_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance in pixels (not squared) of each correspondence x0 <-> x1
    w.r.t. F (x1^T F x0 = 0): sqrt(r^2 (1/|l1|^2 + 1/|l0|^2)), r the algebraic residual and
    l1 = F x0, l0 = F^T x1 the two epipolar lines (their first two entries). An epipolar line
    without direction (a = b = 0) puts the correspondence at infinity, as the reference does."""
    p0, p1 = to_homogeneous(x0), to_homogeneous(x1)
    F = np.asarray(F, dtype=np.float64)
    line1 = p0 @ F.T  # F x0, in image 1
    line0 = p1 @ F  # F^T x1, in image 0
    residual2 = np.sum(p1 * line1, axis=1) ** 2
    norm1 = line1[:, 0] ** 2 + line1[:, 1] ** 2
    norm0 = line0[:, 0] ** 2 + line0[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        squared = residual2 * (1.0 / norm1 + 1.0 / norm0)
    squared[(norm1 == 0) | (norm0 == 0)] = np.inf
    return np.sqrt(squared)


def recall_curve(F: np.ndarray | None, corrs: np.ndarray, thresholds: Sequence[float] = THRESHOLDS) -> np.ndarray:
    """Fraction of the ground-truth correspondences (N x 4: x0 y0 x1 y1) whose symmetric
    epipolar distance w.r.t. F is <= each threshold; all zeros without an F."""
    if F is None:
        return np.zeros(len(thresholds))
    distances = symmetric_epipolar_distance(F, corrs[:, :2], corrs[:, 2:4])
    return np.array([np.mean(distances <= t) for t in thresholds], dtype=np.float64)


def maa(curve: Sequence[float] | np.ndarray, thresholds: Sequence[float] = THRESHOLDS) -> float:
    """mAA@10px of a recall curve over THRESHOLDS: its mean at 1..10 px."""
    by_threshold = dict(zip(thresholds, np.asarray(curve, dtype=np.float64)))
    return float(np.mean([by_threshold[t] for t in MAA_THRESHOLDS]))


def summarize_wxbs(rows: Sequence[Mapping]) -> dict:
    """The benchmark's numbers from per_pair rows: the mean curve, mAA@10px, and both per category."""
    rows = list(rows)
    summary = _block(rows, "", curve=True)
    for category in sorted({str(r["category"]) for r in rows}):
        summary.update(_block([r for r in rows if str(r["category"]) == category], f"_{category}", curve=False))
    return summary


def _block(rows: Sequence[Mapping], suffix: str, curve: bool) -> dict:
    """The numbers of some rows; the whole curve only for all of them (per category, the curve
    of 1 to 10 pairs would be noise in every table: its mAA@10px says what there is to say)."""
    means = [_mean([float(r[recall_key(t)]) for r in rows]) for t in THRESHOLDS]
    out = {f"n_pairs{suffix}": len(rows), f"n_matches{suffix}": _mean([float(r["n_matches"]) for r in rows]),
           f"n_failures{suffix}": sum(1 for r in rows if not _found(r))}
    out[f"{MAA}{suffix}"] = maa(means) if rows else float("nan")
    if curve:
        out.update({f"{recall_key(t)}{suffix}": value for t, value in zip(THRESHOLDS, means)})
    return out


def _found(row: Mapping) -> bool:
    return bool(int(row["f_found"]))


def _mean(values: Sequence[float] | np.ndarray) -> float:
    values = np.asarray(values, dtype=np.float64)
    return float(np.mean(values)) if values.size else float("nan")


# ----------------------------------------------------------------------------- dataset


@dataclass
class CorrespondencePair(Pair):
    """A pair whose ground truth is hand-labelled correspondences (N x 4: x0 y0 x1 y1, pixels of
    the stored images), where a homography or pose pair has H or K and T."""

    corrs: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))


class WxBS(PairList):
    """The WxBS pairs of one split (test: the release's test pairs; val: its 2 validation
    pairs; all), each a CorrespondencePair, its category in ``Pair.category`` (a sampling level, as a
    sequence or a scene is)."""

    name = "wxbs"

    def __init__(self, root: str | Path, split: str = "test", skip_bad: bool = False) -> None:
        if split not in SPLITS:
            raise DatasetError(f"WxBS split must be one of {', '.join(SPLITS)}, got {split!r}")
        root = require_directory(root, "WxBS")
        # The release zip unpacks into v1.1/; the version folder itself is accepted as the root too.
        self.root = root / VERSION if (root / VERSION).is_dir() else root
        self.split = split
        pairs, bad = [], []
        for folder in self._pair_folders():
            name = f"{folder.parent.name}/{folder.name}"
            try:
                pairs.append(self._pair(folder, name))
            except DatasetError as error:
                bad.append((name, str(error)))
        if not pairs and not bad:
            raise DatasetError(f"{self.root}: no WxBS pair folder (<category>/<pair>/corrs.txt) found")
        super().__init__(pairs, self.root, skip_bad, bad)

    def _pair_folders(self) -> list[Path]:
        # A pair is a folder holding corrs.txt: a folder without one (a README, a stray
        # download) is not a pair, while one whose images are missing is, and is reported.
        folders = sorted(p.parent for p in self.root.glob("*/*/corrs.txt"))
        if self.split == "all":
            return folders
        validation = self.split == "val"
        return [f for f in folders if (f.name in VALIDATION_PAIRS) == validation]

    @staticmethod
    def _pair(folder: Path, name: str) -> CorrespondencePair:
        image0, image1 = (_image_path(folder, stem) for stem in ("01", "02"))
        corrs = read_correspondences(folder / "corrs.txt")
        check_inside(corrs, (header_size(image0), header_size(image1)), folder / "corrs.txt")
        return CorrespondencePair(name=name, image0=image0, image1=image1, category=folder.parent.name,
                                  corrs=corrs)

    def settings(self) -> dict:
        return {"dataset": self.name, "root": str(self.root), "version": VERSION, "split": self.split}


def _image_path(folder: Path, stem: str) -> Path:
    """The pair's image `stem` (.png or .jpg, as the release mixes both); when neither exists,
    the name the other image's suffix implies, so that the error names the file looked for."""
    for suffix in IMAGE_SUFFIXES:
        if (folder / f"{stem}{suffix}").is_file():
            return folder / f"{stem}{suffix}"
    other = next((p.suffix for p in folder.glob("0[12].*") if p.suffix in IMAGE_SUFFIXES), IMAGE_SUFFIXES[0])
    return folder / f"{stem}{other}"


def read_correspondences(path: Path) -> np.ndarray:
    """corrs.txt: N x 4 (x0 y0 x1 y1), finite, at least one line."""
    if not path.is_file():
        raise DatasetError(f"{path}: ground-truth correspondence file not found")
    try:
        corrs = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        reason = " ".join(str(error).split())  # one line
        raise DatasetError(f"{path}: not a numeric table ({reason})") from None
    if corrs.size == 0:
        raise DatasetError(f"{path}: no correspondences")
    if corrs.shape[1] != 4:
        raise DatasetError(f"{path}: expected 4 columns (x1 y1 x2 y2), got {corrs.shape[1]}")
    if not np.all(np.isfinite(corrs)):
        raise DatasetError(f"{path}: non-finite coordinates (NaN or inf)")
    return corrs


def check_inside(corrs: np.ndarray, sizes, path: Path) -> None:
    """Refuse ground truth that lies off its images (more than EDGE_TOLERANCE_PX outside
    [0, w] x [0, h]): no F brings such a point near its epipolar line, so the pair would score
    0 whatever the method, without a word. sizes: each image's (w, h), None where its header
    cannot be read: then nothing is checked, and the image check that follows names the image."""
    if any(size is None for size in sizes):
        return
    for side, (w, h) in enumerate(sizes):
        x, y = corrs[:, 2 * side], corrs[:, 2 * side + 1]
        off = (
            (x < -EDGE_TOLERANCE_PX)
            | (y < -EDGE_TOLERANCE_PX)
            | (x > w + EDGE_TOLERANCE_PX)
            | (y > h + EDGE_TOLERANCE_PX)
        )
        if off.any():
            first = int(np.flatnonzero(off)[0])
            raise DatasetError(f"{path}: {int(off.sum())} of {len(corrs)} correspondences lie outside image "
                               f"0{side + 1} ({w} x {h} px), first on row {first + 1} at ({x[first]:g}, {y[first]:g}); "
                               "ground truth off the image cannot be scored")


# ----------------------------------------------------------------------------- benchmark


def threshold_curves_figure(curves: Mapping[str, Sequence[float]], thresholds: Sequence[float],
                            xlabel: str, ylabel: str, title: str, log_x: bool = False,
                            bands: Mapping[str, Sequence[tuple[float, float]]] | None = None) -> Figure:
    """One line per run: a metric against its pixel thresholds (WxBS recall, EVD accuracy), with
    its bootstrap interval at each threshold as a band (bands: label -> (lo, hi) per threshold)."""
    # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.subplots()
    for label, curve in curves.items():
        line, = ax.plot(thresholds, curve, "-o", markersize=3, label=label)
        lo, hi = np.array((bands or {}).get(label, [(np.nan, np.nan)] * len(thresholds)), dtype=float).T
        if not np.all(np.isnan(lo)):
            ax.fill_between(thresholds, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
    if log_x:
        ax.set_xscale("log")
    ax.set_ylim(0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return fig


@dataclass(frozen=True)
class WxBSBenchmark(Benchmark):
    """Pairs carry hand-labelled correspondences; matches are scored through the F they give."""

    ransac_field: str = "fundamental_ransac_px"
    table_metrics: Mapping[str, str] = field(default_factory=lambda: {"mAA@10px": MAA})
    table_extras: tuple[str, ...] = ("n_pairs", "recall@1", "recall@5", "recall@10")
    report_columns: tuple[str, ...] = ("n_matches", MAA, "recall@10")
    paired_columns: tuple[tuple[str, bool], ...] = ((MAA, True), ("recall@1", True), ("recall@10", True))
    failure: tuple[str, float] | None = None  # a pair's score is a fraction, no threshold makes it a miss

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates(["pair", "category", "n_matches", "n_gt", "f_found", MAA, *map(recall_key, THRESHOLDS)])

    def estimate(self, matches: Matches, ev: EvalSettings) -> np.ndarray | None:
        """The evaluation's F from the matches (estimators.fundamental, seeded by ev.seed)."""
        import cv2

        cv2.setRNGSeed(int(ev.seed))
        return fundamental(
            matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64),
            ev.fundamental_ransac_px, ev.fundamental_max_iters, ev.fundamental_confidence,
            ev.estimator, ev.seed, ev.opencv_method,
        )

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        corrs = pair.corrs
        F = self.estimate(matches, ev)
        curve = recall_curve(F, corrs)
        return {"pair": pair.name, "category": pair.category, "n_matches": len(matches.keypoints0),
                "n_gt": len(corrs), "f_found": int(F is not None), MAA: maa(curve),
                **{recall_key(t): float(v) for t, v in zip(THRESHOLDS, curve)}}

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        return summarize_wxbs(rows)

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        # summarize_wxbs on arrays read once: the same keys, in the same order, as the same
        # float64 means over the same values in the same order. The categories are those of all
        # rows (the bootstrap's check on range(n) makes sure the keys agree).
        rows = list(rows)
        n_matches = np.asarray([r["n_matches"] for r in rows], dtype=np.float64)
        found = np.asarray([_found(r) for r in rows], dtype=bool)
        recall = np.asarray([[r[recall_key(t)] for t in THRESHOLDS] for r in rows], dtype=np.float64).reshape(
            -1, len(THRESHOLDS)
        )
        category = np.asarray([str(r["category"]) for r in rows])
        maa_columns = [THRESHOLDS.index(t) for t in MAA_THRESHOLDS]

        def block(idx: np.ndarray, suffix: str, curve: bool) -> dict:
            means = [_mean(recall[idx, j]) for j in range(len(THRESHOLDS))]
            out = {f"n_pairs{suffix}": int(idx.size), f"n_matches{suffix}": _mean(n_matches[idx]),
                   f"n_failures{suffix}": int(np.count_nonzero(~found[idx]))}
            out[f"{MAA}{suffix}"] = float(np.mean([means[j] for j in maa_columns])) if idx.size else float("nan")
            if curve:
                out.update({f"{recall_key(t)}{suffix}": value for t, value in zip(THRESHOLDS, means)})
            return out

        def summarize(idx: Sequence[int]) -> dict:
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            summary = block(idx, "", curve=True)
            for name in sorted(set(category[idx].tolist())):
                summary.update(block(idx[category[idx] == name], f"_{name}", curve=False))
            return summary

        return summarize

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
        # WxBS has no ground-truth F; the one the hand-labelled correspondences themselves give
        # (normalised 8-point on all of them) stands in for it in drawings only, never in a metric.
        from e3cm_bench.geometry.two_view import estimate_fundamental

        corrs = pair.corrs
        F = estimate_fundamental(corrs[:, :2], corrs[:, 2:4], "8point")
        if F is None:
            return np.zeros(len(matches.keypoints0), dtype=bool)
        return symmetric_epipolar_distance(F, matches.keypoints0, matches.keypoints1) <= ev.correct_px

    def required_summary_columns(self) -> list[str]:
        return ["n_pairs", "n_matches", MAA, *map(recall_key, THRESHOLDS)]

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        self._plot({label: summary}, out / "wxbs_recall.png")

    def plot_comparison(self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path) -> list[Path]:
        return [
            self._plot({label: s for label, (s, _) in runs.items()}, stem.with_name(stem.stem + "_wxbs_recall.png"))
        ]

    @staticmethod
    def _plot(summaries: Mapping[str, Mapping], path: Path) -> Path:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        names = {label: f"{label} (mAA@10px {float(s[MAA]):.3f})" for label, s in summaries.items()}
        curves = {names[label]: [float(s[recall_key(t)]) for t in THRESHOLDS] for label, s in summaries.items()}
        bands = {names[label]: [plots.interval(s, recall_key(t)) for t in THRESHOLDS] for label, s in summaries.items()}
        fig = threshold_curves_figure(curves, THRESHOLDS, "symmetric epipolar distance threshold [px]",
                                      "recall of the ground-truth correspondences",
                                      f"WxBS: F from the matches; bands: {plots.interval_note(summaries)}", bands=bands)
        return plots._save_figure(fig, path)


WXBS = WxBSBenchmark(
    name="wxbs",
    dataset=WxBS,
    dataset_options=(
        DatasetOption(
            "split", "text", "test (default: the release's test pairs), val (its 2 validation pairs) or all."
        ),
    ),
    summary="WxBS v1.1: F from the matches; recall of the hand-labelled correspondences at 0..19 px, mAA@10px, per "
            "category.",
    default_max_side=DEFAULT_MAX_SIDE,
    default_protocol="wxbs",  # the reference's estimator; --protocol default is e3cm-bench's own
)
BENCHMARKS = (WXBS,)
