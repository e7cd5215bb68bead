"""The two-view protocol sweep (issue 69): runs' cached matches scored again, without
matching, under each cell of estimator x threshold, with several RANSAC seeds per cell; each
cell's ranking of the runs with intervals, Kendall's tau between each cell's ranking and the
default cell's, and the rank flips with their paired intervals.

Why: a two-view ranking can move with the evaluation's estimator and threshold (the complaint
users of matcher benchmarks raise most), and glue-factory reports each method at its best
threshold chosen on the test pairs. Here a tuned threshold is chosen on one half of the pairs
(`split_pairs`: the pairs whose name hashes even) and reported on the other, never on the pairs
it is reported on.

A cell (`Cell`) is an estimator (opencv with ransac, magsac = USAC_MAGSAC or accurate =
USAC_ACCURATE; poselib; pycolmap) and a threshold in one of three units: ``px`` (pixels of the
stored images, PROTOCOLS §3), ``mpx`` (pixels of the images as matched, SuperGlue's way) or ``f``
(a fraction of the pair's mean focal length, the normalised threshold of OpenCV's essential
matrix on normalised points). The default cell is the first run's own evaluation.

Every cell scores each pair with seeds seed, seed+1, ... (the evaluation's seed, as --repeats);
a method's number is the mean over seeds of the AUC over pairs, its interval two-level (pairs and
seeds resampled, sfm.metrics.two_level_summary); a difference's interval resamples the pairs of
both methods together and each method's seeds on its own (stats.compare on AUCs).

Products in OUT, locked while a sweep writes it (as a run folder is): cells/CELL.csv (each pair's
err_pose per run and seed, a run's columns named by its `key`, never its label: a sweep resumes
from them), sweep.csv (cell, method, AUC@5/10/20 with intervals, the seeds' spread, rank), tau.csv
(each cell's Kendall tau against the default cell, and its flips), flips.csv (each flipped pair
of methods: B - A in the default cell and in the cell, with the cell's interval), sweep.md,
ranks.png and sweep.yaml (the runs with their keys and fingerprints, the cells, seeds and split).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from itertools import combinations
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.benchmarks import EvalSettings
from e3cm_bench.geometry import metrics
from e3cm_bench.geometry.estimators import ESTIMATORS, POSE_METHODS
from e3cm_bench.ground.files import refuse_link, save_yaml, write_atomically, write_csv
from e3cm_bench.ground.locks import FolderLock
from e3cm_bench.ground.matches import distinct
from e3cm_bench.reporting.tables import sweep_markdown
from e3cm_bench.stats.bootstrap import (BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, CONFIDENCE, percentile_interval,
                                        resample_indices)
from e3cm_bench.stats.ranking import kendall_tau, ranks

UNITS = {"px": "pixels of the stored images", "mpx": "pixels of the images as matched",
         "f": "a fraction of the pair's mean focal length"}
DEFAULT_ESTIMATORS = "opencv-ransac,opencv-magsac,opencv-accurate,poselib,pycolmap"
DEFAULT_THRESHOLDS = "0.5px,1px,2px"
AUCS = tuple(f"auc@{t}" for t in metrics.POSE_AUC_THRESHOLDS)
MOST_SEEDS = 20  # each seed is one more RANSAC per pair, cell and run


@dataclass(frozen=True)
class Cell:
    estimator: str  # a backend of geometry.estimators
    method: str  # OpenCV's robust method (POSE_METHODS); "ransac" for the others
    threshold: float
    unit: str  # UNITS
    tuned: bool = False  # each run at the px threshold its tuning half chose (tuned_thresholds)

    @property
    def name(self) -> str:
        estimator = f"{self.estimator}-{self.method}" if self.estimator == "opencv" else self.estimator
        return f"{estimator} tuned" if self.tuned else f"{estimator} {self.threshold:g}{self.unit}"

    @property
    def file_name(self) -> str:
        return re.sub(r"[^A-Za-z0-9.@-]+", "_", self.name)

    def settings(self, ev: EvalSettings, focal: float, seed: int) -> EvalSettings:
        """The evaluation of one pair in this cell."""
        value = self.threshold
        px, frame = (value * focal, "original") if self.unit == "f" else (value,
                "matched" if self.unit == "mpx" else "original")
        return replace(ev, estimator=self.estimator, opencv_method=self.method, pose_ransac_px=float(px),
                       pose_ransac_frame=frame, seed=int(seed), repeats=1)


def cell_of(ev: EvalSettings) -> Cell:
    """The cell a run was evaluated in (its own estimator, method and threshold)."""
    unit = "mpx" if ev.pose_ransac_frame == "matched" else "px"
    method = ev.opencv_method if ev.estimator == "opencv" else "ransac"
    return Cell(ev.estimator, method, float(ev.pose_ransac_px), unit)


def parse_estimators(text: str) -> list[tuple[str, str]]:
    """"opencv-ransac,opencv-magsac,poselib" -> [(estimator, method)]; one line for a bad name."""
    found = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        estimator, _, method = part.partition("-")
        method = method or "ransac"
        if estimator not in ESTIMATORS or method not in POSE_METHODS or (estimator != "opencv" and method != "ransac"):
            known = ", ".join([f"opencv-{m}" for m in POSE_METHODS] + [e for e in ESTIMATORS if e != "opencv"])
            raise ValueError(f"--estimators: unknown estimator {part!r}; choose among {known}")
        found.append((estimator, method))
    if not found:
        raise ValueError("--estimators: name at least one estimator")
    return found


def parse_thresholds(text: str) -> list[tuple[float, str]]:
    """"0.5px,1mpx,1e-3f" -> [(value, unit)] (a bare number is in px); one line for a bad one."""
    found = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        match = re.fullmatch(r"([0-9.eE+-]+)(px|mpx|f)?", part)
        value = None
        if match:
            try:
                value = float(match.group(1))
            except ValueError:
                value = None
        if value is None or not math.isfinite(value) or value <= 0 or value > 1000:
            raise ValueError(f"--thresholds: {part!r} is no threshold; give positive numbers with a unit: "
                             "0.5px (stored pixels), 1mpx (matched pixels), 5e-4f (fraction of the focal length)")
        found.append((value, match.group(2) or "px"))
    if not found:
        raise ValueError("--thresholds: name at least one threshold")
    return found


def grid(estimators: str, thresholds: str, default: Cell) -> list[Cell]:
    """The default cell first, then every estimator x threshold (the default not twice)."""
    cells = [default]
    for estimator, method in parse_estimators(estimators):
        for value, unit in parse_thresholds(thresholds):
            cell = Cell(estimator, method, value, unit)
            if cell not in cells:
                cells.append(cell)
    return cells


def split_pairs(names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(tune, report) masks: a pair is in the tuning half when the sha256 of its name is even (a
    split that does not depend on the pairs' order or on which other pairs a run holds)."""
    even = np.asarray([hashlib.sha256(n.encode()).digest()[-1] % 2 == 0 for n in names], bool)
    return even, ~even


# ------------------------------------------------------------------------------------ scoring
@dataclass
class SweepRun:
    """A run to sweep: its label, its folder, its pairs (by name) and cached matches."""

    label: str
    folder: Path
    benchmark: object
    ev: EvalSettings
    pairs: dict
    cache: object
    fingerprint: str
    identity: dict | None = None

    @property
    def key(self) -> str:
        """Its name in cells/*.csv: its identity, fingerprint and folder, never its label (issue 81)."""
        text = json.dumps([self.identity, self.fingerprint, str(Path(self.folder).resolve())], sort_keys=True,
                          default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


def score_cell(run: SweepRun, names: Sequence[str], cell: Cell, seeds: int) -> np.ndarray:
    """err_pose of each pair (rows, in `names`' order) under each seed (columns) in `cell`."""
    errors = np.full((len(names), seeds), np.inf)
    for i, name in enumerate(names):
        pair = run.pairs[name]
        matches, _ = distinct(run.cache.read(name))
        focal = float(np.mean([pair.K0[0, 0], pair.K0[1, 1], pair.K1[0, 0], pair.K1[1, 1]]))
        for s in range(seeds):
            ev = cell.settings(run.ev, focal, run.ev.seed + s)
            errors[i, s] = float(run.benchmark.evaluate_pair(pair, matches, ev)["err_pose"])
    return errors


def cell_errors(runs: Sequence[SweepRun], names: Sequence[str], cell: Cell, seeds: int, out: Path,
                progress: Callable[[str], None] = print) -> dict[str, np.ndarray]:
    """Each run's pairs x seeds errors in `cell`, read from OUT/cells/CELL.csv where a sweep wrote
    them (same pairs and seeds, the run's `key`), else computed and added there (the columns of
    the runs of other sweeps into this --out are kept: each resumes)."""
    path = refuse_link(out / "cells") / f"{cell.file_name}.csv"  # a cell is never written through a link
    done = pd.read_csv(path) if path.is_file() else None
    table = done if done is not None and list(done["pair"]) == list(names) else pd.DataFrame({"pair": list(names)})
    found, added = {}, False
    for run in runs:
        columns = [f"{run.key}_s{s}" for s in range(seeds)]
        if all(c in table.columns for c in columns):
            found[run.label] = table[columns].to_numpy(np.float64)
            continue
        progress(f"sweep: {cell.name}: {run.label} ({len(names)} pairs x {seeds} seed(s))")
        found[run.label] = score_cell(run, names, cell, seeds)
        table = table.assign(**{c: found[run.label][:, s] for s, c in enumerate(columns)})
        added = True
    if added:
        write_csv(table, path)
    return found


# ---------------------------------------------------------------------------------- statistics
def mean_auc(errors: np.ndarray, threshold: float, seeds: np.ndarray | None = None) -> float:
    columns = range(errors.shape[1]) if seeds is None else seeds
    return float(np.mean([metrics.pose_auc(errors[:, s], (threshold,))[0] for s in columns]))


def auc_interval(errors: np.ndarray, threshold: float, n_samples: int, seed: int) -> tuple[float, float]:
    """Two levels: the pairs resampled, and with each resample the seeds (its own generator)."""
    idx = resample_indices(errors.shape[0], n_samples, seed)
    rng = np.random.default_rng(seed + 1)
    k = errors.shape[1]
    values = [mean_auc(errors[row], threshold, rng.integers(0, k, k) if k > 1 else None) for row in idx]
    return percentile_interval(np.asarray(values), CONFIDENCE)


def difference_interval(a: np.ndarray, b: np.ndarray, threshold: float, n_samples: int,
                        seed: int) -> tuple[float, float]:
    """AUC(b) - AUC(a) over paired resamples of the pairs, each method's seeds on their own."""
    idx = resample_indices(a.shape[0], n_samples, seed)
    rng = np.random.default_rng(seed + 1)
    values = []
    for row in idx:
        seeds_a, seeds_b = rng.integers(0, a.shape[1], a.shape[1]), rng.integers(0, b.shape[1], b.shape[1])
        values.append(mean_auc(b[row], threshold, seeds_b) - mean_auc(a[row], threshold, seeds_a))
    return percentile_interval(np.asarray(values), CONFIDENCE)


# ------------------------------------------------------------------------------------- driver
@dataclass
class SweepResult:
    table: pd.DataFrame  # sweep.csv
    taus: pd.DataFrame  # tau.csv
    flips: pd.DataFrame  # flips.csv
    default: str  # the default cell's name
    metric: str


def tuned_thresholds(errors_by_cell: dict[Cell, dict[str, np.ndarray]], tune: np.ndarray, threshold: float,
                     estimator: tuple[str, str]) -> dict[str, float]:
    """Each run's threshold (of the estimator's cells) with the best AUC on the tuning half."""
    cells = [c for c in errors_by_cell if (c.estimator, c.method) == estimator and not c.tuned and c.unit == "px"]
    labels = list(next(iter(errors_by_cell.values())))
    chosen = {}
    for label in labels:
        best = max(cells, key=lambda c: (mean_auc(errors_by_cell[c][label][tune], threshold), -c.threshold))
        chosen[label] = best.threshold
    return chosen


def sweep(runs: Sequence[SweepRun], cells: Sequence[Cell], seeds: int, out: Path, metric: str = "auc@10",
          tune: bool = False, n_samples: int = BOOTSTRAP_SAMPLES, progress: Callable[[str],
                  None] = print) -> SweepResult:
    """The sweep of the module docstring over the pairs every run holds (in the first run's order)."""
    if metric not in AUCS:
        raise ValueError(f"--metric {metric!r}: choose one of {', '.join(AUCS)}")
    threshold = float(metric.split("@")[1])
    names = [n for n in runs[0].pairs if all(n in r.pairs for r in runs[1:])]
    if not names:
        raise ValueError("sweep: the runs share no pair")
    tune_mask, report_mask = split_pairs(names) if tune else (None, np.ones(len(names), bool))
    errors_by_cell = {cell: cell_errors(runs, names, cell, seeds, out, progress=progress) for cell in cells}
    if tune:
        for estimator in dict.fromkeys((c.estimator, c.method) for c in cells if c.unit == "px"):
            chosen = tuned_thresholds(errors_by_cell, tune_mask, threshold, estimator)
            cell = Cell(estimator[0], estimator[1], float("nan"), "px", tuned=True)
            # each run's errors at its chosen threshold: that cell's, already scored
            errors_by_cell[cell] = {label: errors_by_cell[Cell(estimator[0], estimator[1], chosen[label], "px")][label]
                                    for label in chosen}
            save_yaml({"split": "tuning half: pairs whose name's sha256 is even", "thresholds_px": chosen},
                      out / "cells" / f"{cell.file_name}.yaml")
    rows, values = [], {}
    for cell, found in errors_by_cell.items():
        values[cell] = {label: mean_auc(e[report_mask], threshold) for label, e in found.items()}
        cell_ranks = ranks(values[cell])
        for label, e in found.items():
            reported = e[report_mask]
            row = {"cell": cell.name, "estimator": cell.estimator, "method": cell.method,
                   "threshold": cell.threshold, "unit": cell.unit, "run": label, "n_pairs": int(reported.shape[0]),
                   "seeds": seeds, "rank": cell_ranks[label]}
            for key in AUCS:
                t = float(key.split("@")[1])
                row[key] = mean_auc(reported, t)
                row[f"{key}_lo"], row[f"{key}_hi"] = auc_interval(reported, t, n_samples, BOOTSTRAP_SEED)
                each = [metrics.pose_auc(reported[:, s], (t,))[0] for s in range(seeds)]
                row[f"{key}_sd"] = float(np.std(each, ddof=1)) if seeds > 1 else 0.0
            rows.append(row)
    default = cells[0]
    taus, flips = [], []
    for cell, found in errors_by_cell.items():
        tau, p = kendall_tau(values[default], values[cell])
        flipped = 0
        for a, b in combinations(list(found), 2):
            before = values[default][b] - values[default][a]
            now = values[cell][b] - values[cell][a]
            if before * now >= 0 or cell == default:  # a tie on either side is no flip
                continue
            flipped += 1
            lo, hi = difference_interval(found[a][report_mask], found[b][report_mask], threshold, n_samples,
                                         BOOTSTRAP_SEED)
            flips.append({"cell": cell.name, "a": a, "b": b, f"default_{metric}_b_minus_a": before,
                          f"{metric}_b_minus_a": now, "lo": lo, "hi": hi, "excludes_0": bool(lo > 0 or hi < 0)})
        taus.append({"cell": cell.name, "kendall_tau": tau, "p": p, "flips": flipped, "n_runs": len(found)})
    return SweepResult(pd.DataFrame(rows), pd.DataFrame(taus),
                       pd.DataFrame(flips, columns=["cell", "a", "b", f"default_{metric}_b_minus_a",
                                                    f"{metric}_b_minus_a", "lo", "hi", "excludes_0"]),
                       default.name, metric)


def run_sweep(runs: Sequence[SweepRun], cells: Sequence[Cell], seeds: int, out: Path, metric: str, tune: bool,
              progress: Callable[[str], None] = print) -> tuple[SweepResult, list[Path]]:
    """`sweep` and `write_sweep` with OUT locked as a run folder is: a second sweep into it is refused meanwhile."""
    with FolderLock(out):
        result = sweep(runs, cells, seeds, out, metric, tune, progress=progress)
        return result, write_sweep(result, runs, cells, seeds, tune, out)


def write_sweep(result: SweepResult, runs: Sequence[SweepRun], cells: Sequence[Cell], seeds: int, tune: bool,
                out: Path) -> list[Path]:
    """sweep.csv, tau.csv, flips.csv, sweep.md, ranks.png and sweep.yaml in OUT."""
    from e3cm_bench.drawing.plots import rank_figure

    written = [write_csv(result.table, out / "sweep.csv"), write_csv(result.taus, out / "tau.csv"),
               write_csv(result.flips, out / "flips.csv")]
    save_yaml({"runs": [{"label": r.label, "folder": str(r.folder), "fingerprint": r.fingerprint, "key": r.key}
                        for r in runs],
               "default_cell": result.default, "cells": [c.name for c in cells], "seeds": seeds,
               "metric": result.metric, "units": UNITS,
               "split": ("tuned cells: thresholds chosen on the pairs whose name's sha256 is even, every number "
                         "reported on the others" if tune else "none: every number on every pair")},
              out / "sweep.yaml")
    text = sweep_markdown(result)  # written, as every file here, by a rename: never through a link
    written += [out / "sweep.yaml", write_atomically(out / "sweep.md", lambda tmp: tmp.write_text(text))]
    figure = rank_figure(result.table, result.metric)
    written.append(write_atomically(out / "ranks.png",
                                    lambda tmp: figure.savefig(tmp, format="png", dpi=120, bbox_inches="tight")))
    return written


def load_runs(run_dirs: Sequence[Path]) -> list[SweepRun]:
    """The runs to sweep: folders of one two-view pose benchmark with their cached matches; one
    line naming the folder where one is not."""
    from e3cm_bench.benchmarks import PoseBenchmark
    from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
    from e3cm_bench.reporting.runs import load_run
    from e3cm_bench.storage import RunFolder
    from e3cm_bench.storage.fingerprint import of_config

    if len(run_dirs) < 2:
        raise ValueError("sweep: give at least two runs (a ranking needs two methods)")
    runs = []
    for folder in run_dirs:
        run = load_run(folder)
        if not isinstance(run.benchmark, PoseBenchmark):
            raise ValueError(f"{run.dir}: a {run.benchmark.name} run; the sweep re-scores two-view pose runs "
                             "(megadepth, yfcc, scannet and sets in their layouts)")
        if runs and run.benchmark.name != runs[0].benchmark.name:
            raise ValueError(f"{run.dir}: a {run.benchmark.name} run beside {runs[0].benchmark.name} runs; "
                             "sweep runs of one benchmark")
        cache = RunFolder(run.dir).cache()
        cached = set(cache.names())
        loaded = load_run_pairs(run.dir)
        pairs = {p.name: p for p in loaded.pairs if p.name in cached}
        if not pairs:
            raise ValueError(f"{RunFolder(run.dir).matches_path}: holds no matches of the run's pairs")
        runs.append(SweepRun(run.label, run.dir, run.benchmark, evaluation_of(run.run_config), pairs, cache,
                             of_config(run.run_config), run.run_config.identity))
    labels = [r.label for r in runs]
    if len(set(labels)) < len(labels):  # two runs of one method: named by their folders
        for r in runs:
            r.label = str(r.folder.name) if len({x.folder.name for x in runs}) == len(runs) else str(r.folder)
    return runs


def check_seeds(seeds: int) -> int:
    if int(seeds) != seeds or not 1 <= seeds <= MOST_SEEDS:
        raise ValueError(f"--seeds {seeds}: give 1 to {MOST_SEEDS} (each seed is one more RANSAC per pair, cell and "
        "run)")
    return int(seeds)
