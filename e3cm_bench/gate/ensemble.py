"""The regression gate's noise ensemble: a baseline's runs rerun under perturbations at the
scale of another CPU's rounding (perturb.py), each pair's values kept per draw.

`check --update --ensemble K` calls `build_ensemble`; the draws go to a work folder (each
draw a normal run folder, so an interrupted build resumes draw by draw) and their per-pair
values to ``<baseline>.noise.csv`` beside the baseline, which is all `check` reads later.
Draw d: the features and the estimators' points perturbed with seed d, and the evaluation's
RANSAC seeded with d (estimators.seeded_order), so each draw also sees other RANSAC samples.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from rich.console import Console

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.ground.files import read_csv, read_keyed_csv, write_csv
from e3cm_bench.stats.perturb import Perturbation, perturbed
from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs, method_of
from e3cm_bench.storage import RunConfig, RunFolder

NOISE_SUFFIX = ".noise.csv"
DRAW_COLUMNS = ("benchmark", "method", "pair", "draw")


def noise_path(baseline: Path) -> Path:
    """Where a baseline's ensemble lives: ``demo_hpatches.csv`` -> ``demo_hpatches.noise.csv``."""
    baseline = Path(baseline)
    return baseline.with_name(baseline.stem + NOISE_SUFFIX)


def _dataset_of(config: RunConfig):
    """The run's pairs as it loaded them (benchmarks.records.load_run_pairs: dataset_load, skip_bad and
    --limit as recorded), as a pair list the runner takes."""
    loaded = load_run_pairs(config)
    dataset = copy.copy(loaded.dataset)  # a PairList cut to the run's pairs, as PairList.sampled cuts one
    dataset.pairs = loaded.pairs
    return dataset


def build_ensemble(runs: Sequence, draws: Sequence[int], work: Path, console: Console | None = None,
                   reseed: bool = True) -> pd.DataFrame:
    """Rerun each run (report.Run) once per draw; returns the long table of per-pair values
    (benchmark, method, pair, draw, then the per_pair.csv columns). Runs of one benchmark and
    dataset are matched together, as the demo matches them (one backbone pass per image)."""
    from e3cm_bench.pipeline.runner import run_methods

    console = console or Console()
    work = Path(work)
    groups: dict[tuple, list] = {}
    for run in runs:
        dataset = run.run_config.dataset
        key = (run.benchmark.name, str(dataset.get("root")), str(sorted(dataset.items(), key=str)))
        groups.setdefault(key, []).append(run)
    tables = []
    for (bench_name, _, _), members in groups.items():
        benchmark = get_benchmark(bench_name)
        dataset = _dataset_of(members[0].run_config)
        for draw in draws:
            t = time.perf_counter()
            # the method each run recorded (records.method_of: built-in matchers only; a plugin's
            # run is checked without an ensemble, since a record never names code to run)
            folders = [(work / bench_name / f"draw-{draw:03d}" / run.dir.name, method_of(run.run_config))
                       for run in members]
            ev = evaluation_of(members[0].run_config, seed=draw if reseed else None)
            with perturbed(Perturbation(draw=draw)):
                run_methods(benchmark, folders, dataset, ev=ev, console=Console(quiet=True))
            for run, (folder, _) in zip(members, folders):
                per_pair = read_csv(RunFolder(folder).per_pair_path)
                per_pair.insert(0, "draw", draw)
                per_pair.insert(0, "method", run.label)
                per_pair.insert(0, "benchmark", bench_name)
                tables.append(per_pair)
            console.print(f"ensemble: {bench_name} draw {draw}: {len(members)} runs in {time.perf_counter() - t:.0f} s",
                          markup=False)
    columns = list(DRAW_COLUMNS)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=columns)


def write_noise(table: pd.DataFrame, path: Path) -> Path:
    return write_csv(table, path)


def read_noise(path: Path) -> pd.DataFrame:
    return read_keyed_csv(path, "noise ensemble (write one with check --update --ensemble K)", DRAW_COLUMNS)
