"""sfm: a matcher measured by the reconstruction its matches give (docs/sfm.md).

The pairs of a multi-view set's graph are matched as any pose pairs are (the match stage, its
cache, resume, shards, feature reuse, --on-matcher-error); the evaluation then scores them
together: one COLMAP database from all their matches, pycolmap's incremental mapper
(sfm/mapper.py), and each pair's pose error read from the models (sfm/metrics.py), with
AUC@5/10/20 and IMC 2020's mAA over the pairs (bootstrap intervals) and the set's own
numbers: images registered, models, points, mean track length, mean reprojection error.
The reconstruction's files stay in the run folder, under ``sfm/`` (database.db, models/N/).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.geometry import metrics
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.matches import Matches, distinct
from e3cm_bench.sfm import metrics as sfm_metrics
from e3cm_bench.sfm.dataset import MultiViewSet, SetOptions
from e3cm_bench.sfm.protocol import ReconstructionProtocol
from e3cm_bench.benchmarks.base import DUPLICATES, Benchmark, DatasetOption, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.benchmarks.pose import PoseBenchmark

WORKDIR = "sfm"  # the run folder's subfolder of the reconstruction


@dataclass(frozen=True)
class SfMBenchmark(Benchmark):
    ransac_field: str = "pose_ransac_px"
    table_metrics: Mapping[str, str] = field(default_factory=lambda: {
        **{f"auc@{t}": f"auc@{t}" for t in metrics.POSE_AUC_THRESHOLDS}, "mAA": sfm_metrics.MAA})
    table_extras: tuple[str, ...] = (
        "n_pairs",
        "n_failures",
        "registered_images",
        "n_images",
        "n_models",
        "points",
        "mean_track_length",
        "mean_reprojection_error",
        "track_length_database",
        "repeat_share",
        "merge_displacement_px",
        "mapper_seeds",
        "auc@10_sd",
    )
    report_columns: tuple[str, ...] = ("n_matches", "n_inliers", "model", "err_pose")
    failure: tuple[str, float] | None = ("err_pose", 10.0)  # a miss at mAA's last threshold
    paired_columns: tuple[tuple[str, bool], ...] = (("err_pose", False), ("err_R", False), ("err_t", False))
    evaluates_set = True
    default_interval_seeds: int = 1  # its interval holds the mapper's seeds (--mapper-seeds), and their verification
    builds_to_limit: bool = True
    # said before matching (evaluate_set says --repeats again for the Python API's own settings)
    refused_eval: Mapping[str, tuple[tuple, str]] = field(default_factory=lambda: {
        "repeats": ((None, 1), "--repeats does not apply to sfm: its mapper is seeded, a rerun gives the same model"),
        # its interval holds the mapper's seeds and their verification draws
        "interval_seeds": ((None, 1), "--interval-seeds does not apply to sfm: --mapper-seeds K reruns the "
                                      "verification and the mapper, and its interval holds them")})

    def build_dataset(self, root: str | Path, skip_bad: bool, options: dict) -> MultiViewSet:
        """The set with its dataset options grouped (SetOptions); `first`: the run's --limit."""
        given = dict(options)
        first = given.pop("first", None)
        return MultiViewSet(root, SetOptions(**given), skip_bad=skip_bad, first=first)

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates(["pair", "bag", "n_matches", "n_inliers", "registered0", "registered1", "model",
                                "err_R", "err_t", "err_pose"])

    def row_columns(self, ev: EvalSettings, rows: Sequence[Mapping]) -> list[str]:
        # the first seed's columns as before, then each seed's (sfm_metrics.SEED_COLUMNS)
        return self.pair_columns(ev) + sfm_metrics.seed_columns(sfm_metrics.seeds_in(rows))

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        raise ValueError("sfm scores the pairs of a set together (evaluate_set), not one at a time")

    def two_view_geometry(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict | None:
        """The pose benchmarks' relative pose and RANSAC inliers: the two-view geometry the
        reconstruction's database holds (sfm/mapper.py), so that `export --to colmap` of an
        sfm run writes the same one."""
        return PoseBenchmark.two_view_geometry(pair, matches, ev)

    def evaluate_set(self, pairs: Sequence[Pair], matches: Sequence[Matches], ev: EvalSettings,
                     workdir: Path | None, matcher: str | None = None) -> tuple[list[dict], dict]:
        from e3cm_bench.sfm.evaluate import reconstruct_set
        from e3cm_bench.sfm.protocol import keypoints_are_detections, protocol_of

        if ev.repeats > 1:
            raise ValueError("--repeats does not apply to sfm: its mapper is seeded (--mapper-seeds reruns it)")
        kept = [distinct(m) for m in matches]
        folder = Path(workdir) if workdir is not None else None
        protocol = protocol_of(ev).resolved(keypoints_are_detections(matcher))
        with tempfile.TemporaryDirectory(prefix="e3cm-sfm-") as tmp:
            where = (folder if folder is not None else Path(tmp)) / WORKDIR
            rows, numbers = reconstruct_set(pairs, [k for k, _ in kept], ev, where, protocol)
        for row, (_, repeats) in zip(rows, kept):
            row[DUPLICATES] = repeats
        if folder is not None:
            print(f"sfm: {protocol.mapper} mapper, {protocol.mapper_seeds} seed(s), merge {protocol.merge_label()}, "
                  f"{protocol.verification} verification; COLMAP's log in {where}/**/mapper.log")
        return rows, numbers

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        return self.indexed_summary(rows, ev)(range(len(rows)))

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        # the mean over the mapper's seeds of each seed's summary, on arrays read once
        errors, n_matches = sfm_metrics.seed_errors(rows)

        def summarize(idx: Sequence[int]) -> dict:
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            return sfm_metrics.summarize_seeds(errors[idx], n_matches[idx])

        return summarize

    def interval_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict] | None:
        """Two levels: the bootstrap's pairs (bags, then their pairs, where there are several
        bags), and with each resample of pairs a resample of the seeds (sfm_metrics.two_level_summary)."""
        errors, n_matches = sfm_metrics.seed_errors(rows)
        return sfm_metrics.two_level_summary(errors, n_matches, bags=sfm_metrics.bags_of(rows))

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
        distances = metrics.epipolar_distances(matches.keypoints0, matches.keypoints1, pair.K0, pair.K1, pair.T_0to1)
        return distances < ev.precision_thresholds[0]

    def required_summary_columns(self) -> list[str]:
        return ["n_pairs", "n_matches", *self.table_metrics.values(), "registered_images", "n_models"]

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        plots.plot_pose_error_cdf({label: per_pair}, out / "pose_error_cdf.png")

    def plot_comparison(self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path) -> list[Path]:
        # matplotlib, on first use: the command line's help reads this registry (cli/common.py, Startup)
        from e3cm_bench.drawing import plots

        cdf = stem.with_name(stem.stem + "_pose_cdf.png")
        return [plots.plot_pose_error_cdf({label: p for label, (_, p) in runs.items()}, cdf)]


SFM = SfMBenchmark(
    name="sfm", dataset=MultiViewSet,
    dataset_options=(
        DatasetOption("scene_info", "path", "A MegaDepth scene_info .npz: the set's images (paths under ROOT), "
                      "intrinsics and absolute poses."),
        DatasetOption("colmap_model", "path", "A COLMAP sparse model folder (cameras and images, .bin or .txt) "
                      "as ground truth; its images under ROOT."),
        DatasetOption("pairs", "path", "A SuperGlue-format pair list: these pairs are matched, reconstructed "
                      "together and evaluated against their relative poses."),
        DatasetOption("window", "text", "Pair graph: each image with the next K in the set's order "
                      "(default: every pair)."),
        DatasetOption("graph", "path", "Pair graph: a file of image-name pairs to match (name0 name1 per line)."),
        DatasetOption("allow_disconnected", "flag", "A pair graph in several connected components (sets of images "
                      "no pair joins) is refused; with this, each component is reconstructed as its own bag."),
        DatasetOption("absolute_paths", "flag", "Images may lie anywhere (absolute paths, '..'), each named by its "
                      "absolute path; without it every image must be under ROOT."),
        DatasetOption("max_pairs", "text", "The most pairs the graph may hold (default 20000); the count is "
                      "checked before a pair is made."),
    ),
    summary="Multi-view: the matches of a set's pair graph reconstructed by pycolmap's mapper; pose "
            "AUC@5/10/20 and IMC mAA of the pairs from the models, images registered, models, points.",
    default_max_side=1200,
    # the reconstruction's protocol, evaluation options of sfm's (eval_options.py), defaults in one place
    eval_defaults=ReconstructionProtocol().record(),
)
BENCHMARKS = (SFM,)
