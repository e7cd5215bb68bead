"""The evaluate stage of a run: cached matches + ground truth -> per-pair rows, the summary,
and the reports (CSVs, the run's plot, --viz drawings). Shared by the runner, merged shards
and imported matches; it never matches."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

import pandas as pd
from rich.console import Console

from .benchmarks import Benchmark, EvalSettings
from .cache import MatchCache, check_free_space
from .datasets.base import Pair
from .files import write_csv
from .images import load_image
from .intervals import metric_keys, summary_intervals
from .run import FAILED_ATTR, RunFolder
from .viz import draw_matches, save_image

# Until every reader asks RunFolder: the two names importers still use.
CONFIG_FILE = RunFolder.CONFIG
CACHE_FILE = RunFolder.MATCHES


def evaluate_stage(
    benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings
) -> tuple[pd.DataFrame, dict]:
    """Every pair's row from its cached matches and ground truth, and the summary of the rows.

    The summary holds each metric's bootstrap interval over the pairs beside it (``<metric>_lo``,
    ``<metric>_hi``, and the bootstrap's samples, seed and confidence: intervals.py).
    """
    rows = [benchmark.evaluate_pair(pair, cache.read(pair.name), ev) for pair in pairs]
    if ev.repeats > 1:
        summary = repeated_summary(benchmark, pairs, cache, ev, rows)
    else:
        summary = benchmark.summarize(rows, ev)
        summary.update(summary_intervals(benchmark, rows, ev, summary=summary))
    return pd.DataFrame(rows, columns=benchmark.pair_columns(ev)), summary


def repeated_summary(benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings,
                     first: list[dict]) -> dict:
    """--repeats K: the summary of each of K evaluations (seeds ev.seed + r; the first is
    `first`, the run's own), their mean as the run's numbers, each metric's standard deviation
    over the repeats (``<metric>_sd``), and the bootstrap interval over pairs of that mean.
    per_pair.csv keeps the first repeat's rows."""
    repeats = [first] + [[benchmark.evaluate_pair(pair, cache.read(pair.name), replace(ev, seed=ev.seed + r))
                          for pair in pairs] for r in range(1, ev.repeats)]
    each = [benchmark.summarize(rows, ev) for rows in repeats]
    keys = metric_keys(each[0])
    summary = dict(each[0])
    for key in keys:
        values = np.array([s[key] for s in each], float)
        summary[key] = float(np.mean(values))
        summary[f"{key}_sd"] = float(np.std(values, ddof=1))
    summary["repeats"] = ev.repeats
    indexed = [benchmark.indexed_summary(rows, ev) for rows in repeats]

    def mean_over_repeats(idx) -> dict:
        picked = [f(idx) for f in indexed]
        return {key: float(np.mean([p[key] for p in picked])) for key in keys}

    summary.update(summary_intervals(benchmark, first, ev, summary=summary, indexed=mean_over_repeats))
    return summary


def write_reports(
    benchmark: Benchmark, folder: RunFolder, label: str, per_pair: pd.DataFrame, summary: dict,
    pairs: list[Pair], cache: MatchCache, ev: EvalSettings, viz: int,
) -> None:
    """per_pair.csv, summary.csv, the run's plot, and drawings of the first `viz` pairs."""
    write_csv(per_pair, folder.per_pair_path)
    write_csv(pd.DataFrame([summary]), folder.summary_path)
    benchmark.plot_run(label, summary, per_pair, folder.path)
    for pair in pairs[:viz]:
        matches = cache.read(pair.name)
        canvas = draw_matches(
            load_image(pair.image0), load_image(pair.image1), matches.keypoints0, matches.keypoints1,
            correct=benchmark.correct_mask(pair, matches, ev), max_lines=400,
        )
        save_image(folder.drawing_path(pair.name), canvas)


REPORT_BYTES = 16 << 20  # a run's CSVs and plots, with room to spare
VIZ_BYTES = 2 << 20      # one match drawing


def evaluate_and_report(
    benchmark: Benchmark, out: RunFolder | Path, label: str, pairs: list[Pair], skipped: list[tuple[str, str]], cache,
    ev: EvalSettings, viz: int, console: Console,
) -> tuple[list[Pair], dict]:
    """The evaluate stage and the reports of a run (or of merged shards) over its pairs but the
    skipped ones; returns the pairs evaluated and the summary."""
    folder = out if isinstance(out, RunFolder) else RunFolder(out)
    out = folder.path
    failed = {name for name, _ in skipped}
    pairs = [p for p in pairs if p.name not in failed]
    if not pairs:
        raise ValueError(f"{out}: no pair could be matched ({skipped[0][1]})")
    per_pair, summary = evaluate_stage(benchmark, pairs, cache, ev)
    if skipped:  # a clean run keeps the usual columns; a run with holes says so in its summary
        summary["n_skipped"] = len(skipped)
    failures = matcher_failures(pairs, cache)
    if failures:  # scored as failures (no matches); the count says how many were the matcher's
        summary["n_failed"] = len(failures)
    check_free_space(out, REPORT_BYTES + max(viz, 0) * VIZ_BYTES)  # the reports (tables, plots) need room too
    write_skipped(skipped, folder.skipped_path, console)
    write_failures(failures, folder.failures_path, console)
    write_reports(benchmark, folder, label, per_pair, summary, pairs, cache, ev, viz)
    return pairs, summary


def write_skipped(skipped: list[tuple[str, str]], path: Path, console: Console) -> None:
    """skipped.csv (pair, reason) when pairs were skipped; no stale file when none were."""
    if not skipped:
        path.unlink(missing_ok=True)
        return
    write_csv(pd.DataFrame(skipped, columns=["pair", "reason"]), path)
    console.print(f"{len(skipped)} pair(s) skipped for bad input, listed in {path} (first: {skipped[0][1]})", markup=False)


def matcher_failures(pairs: list[Pair], cache) -> list[tuple[str, str]]:
    """(pair, message) of the pairs stored as the matcher's failures (--on-matcher-error fail-pair)."""
    failures = []
    for pair in pairs:
        message = cache.read(pair.name).info.get(FAILED_ATTR)
        if message is not None:
            failures.append((pair.name, str(message)))
    return failures


def write_failures(failures: list[tuple[str, str]], path: Path, console: Console) -> None:
    """failures.csv (pair, error) when the matcher failed on pairs; no stale file when it did not."""
    if not failures:
        path.unlink(missing_ok=True)
        return
    write_csv(pd.DataFrame(failures, columns=["pair", "error"]), path)
    console.print(f"{len(failures)} pair(s) failed in the matcher and count as failures, listed in {path} "
                  f"(first: {failures[0][1]})", markup=False)
