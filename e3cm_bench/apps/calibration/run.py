"""`e3cm-bench calibrate`: matches from a stereo rig drive its self-calibration (paper Sec. 4.4).

For each matcher: match the left-right pair of every frame once (cached and resumable like
a benchmark run), then for each window of N consecutive frames (sliding by one), pool the
matches, estimate the extrinsics (calibration.estimate_extrinsics) and compare them with
the truth. The calibration error judges the matcher.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from rich.console import Console

from e3cm_bench.drawing import plots
from e3cm_bench.datasets.base import Pair
from e3cm_bench.datasets.stereo import StereoSequence, load_stereo_sequence
from e3cm_bench.ground.devices import keep_freed_memory
from e3cm_bench.ground.files import load_yaml, read_csv, save_yaml, write_csv, yaml_plain
from e3cm_bench.ground.images import load_image
from e3cm_bench.method.spec import MethodSpec, identity_changes
from e3cm_bench.reporting.tables import print_summary
from e3cm_bench.storage import RunConfig, RunFolder
from e3cm_bench.pipeline.driver import RunHook, run_pipeline
from e3cm_bench.pipeline.stage import match_stage
from e3cm_bench.apps.calibration.extrinsics import (
    ERROR_COLUMNS,
    estimate_extrinsics,
    extrinsic_errors,
    vertical_disparity,
)

FRAMES = (1, 3, 5, 10)


@dataclass(frozen=True)
class CalibrationSettings:
    """What changes the calibration but not the matches."""

    frames: tuple[int, ...] = FRAMES
    ransac_px: float = 1.0
    loss: str = "cauchy"
    loss_scale_px: float = 1.0
    seed: int = 0


def windows(n_frames: int, size: int) -> list[range]:
    """Every run of `size` consecutive frames (windows slide by one frame, as an online
    calibration that re-estimates at each new frame from the last `size` frames)."""
    return [range(start, start + size) for start in range(0, n_frames - size + 1)]


def calibrate_windows(sequence: StereoSequence, matches: list, settings: CalibrationSettings,
                      image_size) -> pd.DataFrame:
    """One row per window: errors (ERROR_COLUMNS), match counts, vertical disparity before/after."""
    rows = []
    for size in settings.frames:
        for frames in windows(len(sequence), size):
            x0 = np.concatenate([matches[i].keypoints0 for i in frames])
            x1 = np.concatenate([matches[i].keypoints1 for i in frames])
            cv2.setRNGSeed(settings.seed)  # the RANSAC start repeats
            estimate = estimate_extrinsics(x0, x1, sequence.K0, sequence.K1, settings.ransac_px, settings.loss,
                                           settings.loss_scale_px)
            row = {"frames": size, "first_frame": frames[0], "n_matches": len(x0)}
            if estimate is None:
                row.update({c: np.inf for c in ERROR_COLUMNS})
                rows.append(row)
                continue
            row.update(extrinsic_errors(estimate["R"], estimate["t"], sequence.R, sequence.t))
            row["inliers_1px"] = estimate["inliers_1px"]
            before, after = vertical_disparity(x0, x1, sequence.K0, sequence.K1, estimate["R"], estimate["t"],
                                               image_size)
            _, with_truth = vertical_disparity(x0, x1, sequence.K0, sequence.K1, sequence.R, sequence.t, image_size)
            row.update({"vdisp_before": before, "vdisp_after": after, "vdisp_after_truth": with_truth})
            rows.append(row)
    return pd.DataFrame(rows)


def summarize(windows_df: pd.DataFrame) -> pd.DataFrame:
    """Per number of frames: the mean absolute error of each component, and of rotation / translation."""
    table = windows_df.assign(**{c: windows_df[c].abs() for c in ERROR_COLUMNS})
    table["rotation"] = table[["yaw", "pitch", "roll"]].max(axis=1)
    table["translation"] = table[["tx", "ty", "tz"]].max(axis=1)
    columns = [*ERROR_COLUMNS, "rotation", "translation", "vdisp_before", "vdisp_after", "vdisp_after_truth"]
    summary = table.groupby("frames")[columns].mean().reset_index()
    summary.insert(1, "n_windows", table.groupby("frames").size().to_numpy())
    return summary


@dataclass
class CalibrationRun(RunHook):
    """The calibration hook: one method's frames matched by the match stage (cached and
    resumable like a benchmark run), then scored by its windows (windows.csv, summary.csv)."""

    folder: RunFolder
    method: MethodSpec
    sequence: StereoSequence
    pairs: list[Pair]
    settings: CalibrationSettings
    device: str
    image_size: tuple[int, int]
    overwrite: bool = False

    def open(self, console: Console) -> None:
        """The previous record checked by RunFolder (the same method and frames), the frames left."""
        self.config = RunConfig(benchmark=None, method=self.method.label, identity=self.method.identity(),
                                device=self.device, environment=RunConfig.environment_now(), command="calibrate",
                                sequence=self.sequence.describe(), calibration=asdict(self.settings))
        before = self.folder.previous(self.config.identity, None, changes=identity_changes, console=console)
        self.folder.check_frames(before, str(self.sequence.root))
        self.cache, self.todo = self.folder.resume(self.pairs, console)

    @classmethod
    def produce(cls, runs: list[CalibrationRun], console: Console) -> None:
        for run in runs:
            if run.todo:
                console.rule(f"calibrate: {run.method.label}")
                match_stage(run.method, run.todo, run.cache, run.device, console)

    def evaluate(self, console: Console) -> None:
        """Every window evaluated into windows.csv and summary.csv (the set's tables print later)."""
        matches = [self.cache.read(p.name) for p in self.pairs]
        table = calibrate_windows(self.sequence, matches, self.settings, self.image_size)
        write_csv(table, self.folder.windows_path)
        write_csv(summarize(table), self.folder.summary_path)
        self.windows = table.assign(method=self.method.label)
        return None


def run_calibration(
    root: str | Path, out: str | Path, methods: list[MethodSpec], settings: CalibrationSettings | None = None,
    device: str = "cpu", unrectified: bool = False, overwrite: bool = False, console: Console | None = None,
) -> pd.DataFrame:
    """Calibrate with each method into OUT/<label>/; comparison CSVs and plots into OUT/."""
    console = console or Console()
    settings = settings or CalibrationSettings()
    if any(n < 1 for n in settings.frames):
        raise ValueError(f"--frames must be at least 1, got {list(settings.frames)}")
    sequence = load_stereo_sequence(root, unrectified)
    if max(settings.frames) > len(sequence):
        raise ValueError(f"{sequence.root}: {len(sequence)} frames, fewer than a window of {max(settings.frames)}")
    keep_freed_memory()  # as every benchmark run does (runner._run_folders; docs/speed.md)
    height, width = load_image(sequence.left[0]).shape[:2]
    pairs = [Pair(f"{i:06d}", left, right) for i, (left, right) in enumerate(zip(sequence.left, sequence.right))]
    out = Path(out)
    console.print(f"calibrate: {sequence.layout} sequence {sequence.root}, {len(sequence)} frames, windows of "
                  f"{', '.join(map(str, settings.frames))} frames", markup=False)
    # The folder holds one calibration (sequence and settings) and the set of every method
    # calibrated into it: a later run with other methods adds to the set, and the top-level
    # tables cover all of them; another sequence or other settings are refused.
    record_path = RunFolder(out).calibration_set_path
    record = {"sequence": str(sequence.root), "calibration": asdict(settings), "methods": {}}
    if record_path.is_file() and not overwrite:
        before = load_yaml(record_path)
        if (before.get("sequence") != record["sequence"]
                or before.get("calibration") != yaml_plain(record["calibration"])):
            raise ValueError(f"{record_path}: this folder holds a calibration of another sequence or with other "
                             "settings; pass --overwrite or choose another --out")
        record["methods"] = dict(before.get("methods") or {})
    all_windows = {}
    for method in methods:
        run = CalibrationRun(RunFolder(out / method.folder), method, sequence, pairs, settings, device, (width, height),
                             overwrite)
        run_pipeline([run], console)
        all_windows[method.label] = run.windows
        record["methods"][method.label] = method.folder
        save_yaml(record, record_path)
    for label, folder in record["methods"].items():
        if label not in all_windows:  # calibrated by an earlier run into this folder
            all_windows[label] = read_csv(RunFolder(out / folder).windows_path,
                                          what=f"{label}'s windows.csv").assign(method=label)
    windows_df = pd.concat(all_windows.values(), ignore_index=True)
    write_csv(windows_df, RunFolder(out).windows_path)
    summary = pd.concat([summarize(w.drop(columns="method")).assign(method=w["method"].iloc[0])
                         for w in all_windows.values()])
    summary = summary[["method", *[c for c in summary.columns if c != "method"]]]
    write_csv(summary, RunFolder(out).summary_path)  # the set's table, where a run keeps its summary
    boxplot, vs_frames = (out / name for name in RunFolder.CALIBRATION_PLOTS)
    plots.plot_calibration_boxplots(windows_df, max(settings.frames), boxplot)
    plots.plot_calibration_vs_frames(summary, vs_frames)
    for _, row in summary[summary["frames"] == max(settings.frames)].iterrows():
        print_summary({k: row[k] for k in ("n_windows", *ERROR_COLUMNS, "vdisp_before", "vdisp_after",
                                           "vdisp_after_truth")},
                      f"{row['method']}: mean |error| over windows of {row['frames']} frames (degrees; unit t)",
                      console)
    console.print(f"calibrate: windows.csv, summary.csv, calibration_boxplot.png, calibration_vs_frames.png in {out}",
                  markup=False)
    return summary
