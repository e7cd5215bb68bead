"""Intervals on a run's numbers: a percentile bootstrap over its pairs, written beside each number.

A run's summary.csv stays one row per run; each metric ``m`` gains two columns, ``m_lo`` and
``m_hi`` (wide, so that every reader that indexes summary.csv by metric name keeps working),
and three columns record how they were made: ``bootstrap_samples``, ``bootstrap_seed`` and
``confidence``. The interval says how much the number would move with another draw of pairs
of the same kind; it says nothing of the noise of reruns on other CPUs (stats/noise.py).

Counts (``n_pairs*``, ``n_failures``, ``n_skipped``) get no interval: they are facts of the run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from e3cm_bench import stats
from e3cm_bench.benchmarks import Benchmark, EvalSettings

LO, HI = "_lo", "_hi"
SETTINGS = ("bootstrap_samples", "bootstrap_seed", "confidence")
SD, REPEATS = "_sd", "repeats"  # --repeats: a metric's spread over the repeats, and their number
INTERVAL_SEEDS = "interval_seeds"  # the RANSAC seeds the interval holds (EvalSettings.interval_seeds)
COUNTS = ("n_pairs", "n_failures", "n_skipped")  # prefixes: n_pairs_i, n_pairs_v too
# The run's highest per-pair memory peaks (pipeline/evaluate.py cost_summary): facts of this run
# on this machine, not an estimate over pairs, so no interval either.
PEAKS = ("peak_memory_mb", "gpu_peak_memory_mb", "shared_peak_memory_mb", "cache_memory_mb")


def lo_key(key: str) -> str:
    return key + LO


def hi_key(key: str) -> str:
    return key + HI


def is_interval_key(key: str) -> bool:
    """A column that belongs to an interval (a bound, a bootstrap setting, a spread over
    --repeats, their number), not a metric."""
    return key.endswith((LO, HI, SD)) or key in SETTINGS or key in (REPEATS, INTERVAL_SEEDS)


def metric_keys(summary: Mapping) -> list[str]:
    """The keys of a summary that get an interval: its numbers, but counts and interval columns."""
    keys = []
    for key, value in summary.items():
        if is_interval_key(key) or key.startswith(COUNTS) or key in PEAKS:
            continue
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            continue
        keys.append(key)
    return keys


def _same_summary(a: Mapping, b: Mapping) -> bool:
    if list(a) != list(b):
        return False
    for key in a:
        x, y = a[key], b[key]
        if isinstance(x, (int, float, np.number)) and isinstance(y, (int, float, np.number)):
            if not (x == y or (math.isnan(float(x)) and math.isnan(float(y)))):
                return False
        elif x != y:
            return False
    return True


def summary_intervals(
    benchmark: Benchmark, rows: Sequence[Mapping], ev: EvalSettings, summary: Mapping | None = None,
    n_samples: int = stats.BOOTSTRAP_SAMPLES, seed: int = stats.BOOTSTRAP_SEED, confidence: float = stats.CONFIDENCE,
    indexed: Callable[[Sequence[int]], Mapping] | None = None,
) -> dict:
    """``{m_lo, m_hi for every metric m} + the bootstrap settings`` for the per-pair `rows` of a run.

    Each resample draws len(rows) pairs with replacement and summarises them as the run's own
    summary is made (`benchmark.summarize`), through the benchmark's array form of it
    (`Benchmark.indexed_summary`) when that reproduces `summary` exactly, else row by row.
    indexed: the summary of the rows picked by index, where it is not the benchmark's own (the
    mean over repeats of the estimation, evaluate.py).
    """
    rows = list(rows)
    point = dict(summary) if summary is not None else benchmark.summarize(rows, ev)
    keys = metric_keys(point)
    out: dict = {}
    if rows and keys:
        fast = indexed or benchmark.indexed_summary(rows, ev)
        if indexed is None and not _same_summary(fast(range(len(rows))), benchmark.summarize(rows, ev)):
            fast = Benchmark.indexed_summary(benchmark, rows, ev)  # the row-by-row default
        bounds = stats.bootstrap_interval(list(range(len(rows))), fast, n_samples=n_samples, confidence=confidence,
                                          seed=seed, keys=keys)
        for key in keys:
            lo, hi = bounds.get(key, (math.nan, math.nan))
            out[lo_key(key)], out[hi_key(key)] = float(lo), float(hi)
    return {**out, "bootstrap_samples": int(n_samples), "bootstrap_seed": int(seed), "confidence": float(confidence)}


def interval_of(summary: Mapping, key: str) -> tuple[float, float] | None:
    """The (lo, hi) a summary holds for `key`, or None (a run written before intervals, or NaN bounds)."""
    try:
        lo, hi = float(summary[lo_key(key)]), float(summary[hi_key(key)])
    except (KeyError, TypeError, ValueError):
        return None
    if math.isnan(lo) or math.isnan(hi):
        return None
    return lo, hi


def has_intervals(summary: Mapping) -> bool:
    return any(key.endswith(LO) for key in summary)


def per_pair_rows(per_pair) -> list[dict]:
    """per_pair.csv (a DataFrame) as the rows `Benchmark.summarize` takes."""
    return per_pair.to_dict("records")


def recompute(benchmark: Benchmark, summary: Mapping, per_pair, ev: EvalSettings, rtol: float = 1e-6) -> dict | None:
    """Intervals for a run folder written before them, from its per_pair.csv.

    Only when the per-pair rows reproduce every point value of its summary.csv (to the CSV's
    rounding): an interval drawn from other pairs than the number's would be a false claim.
    None when they do not, or when per_pair.csv is missing.
    """
    if per_pair is None or len(per_pair) == 0 or "pair" not in per_pair.columns:
        return None
    rows = per_pair_rows(per_pair)
    try:
        point = benchmark.summarize(rows, ev)
    except (KeyError, TypeError, ValueError):
        return None
    for key in metric_keys(point):
        if key not in summary:
            return None
        a, b = float(point[key]), float(summary[key])
        if not (np.isclose(a, b, rtol=rtol, atol=1e-9) or (math.isnan(a) and math.isnan(b))):
            return None
    return summary_intervals(benchmark, rows, ev, summary=point)
