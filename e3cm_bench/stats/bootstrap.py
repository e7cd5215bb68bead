"""Percentile bootstrap intervals over benchmark rows (pairs).

The unit that is resampled is the row: one image pair of a benchmark, with every metric the pair
produced. Resampling whole rows keeps the metrics of one pair together, so an interval on a
summary that combines several keys (a fraction under a threshold, a ratio of sums) is honest.

Every function here is pure: arrays or rows in, numbers out, and the same seed gives the same numbers.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np

from e3cm_bench.stats.aggregate import _pick_blocks

BOOTSTRAP_SAMPLES = 1000
CONFIDENCE = 0.95
BOOTSTRAP_SEED = 0



def _check_args(n_samples: int, confidence: float | None = None) -> None:
    if int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    if confidence is not None and not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie strictly between 0 and 1, got {confidence!r}")


def _index_blocks(n: int, n_samples: int, seed: int) -> Iterator[np.ndarray]:
    """Consecutive row blocks of the (n_samples, n) resampling index matrix for `seed`: the
    picks of n pairs that each hold all n rows (the same draws, block by block)."""
    yield from _pick_blocks(np.full(n, n, dtype=np.int64), n_samples, seed)


def resample_indices(n: int, n_samples: int, seed: int) -> np.ndarray:
    """Indices of `n_samples` bootstrap resamples of `n` items: an (n_samples, n) int64 array.

    Row s lists the n items of resample s, drawn uniformly with replacement from range(n) by
    ``np.random.default_rng(seed)``. With n == 0 the rows are empty.
    """
    if int(n) != n or n < 0:
        raise ValueError(f"n must be a non-negative integer, got {n!r}")
    _check_args(n_samples)
    return np.concatenate(list(_index_blocks(int(n), int(n_samples), seed)), axis=0)


def groups_of(labels) -> list[np.ndarray] | None:
    """The row indices of each distinct label (a bag of a multi-view set), in first-seen order;
    None for no labels or a single one (then rows resample as independent units)."""
    if labels is None:
        return None
    labels = np.asarray(labels).reshape(-1)
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first)
    found = [np.flatnonzero(inverse == k) for k in order]
    return found if len(found) > 1 else None


def nested_resample(groups: list[np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """One two-stage bootstrap resample of rows grouped in `groups`: the groups drawn with
    replacement, then each drawn group's rows with replacement (rows of one group, the pairs of
    one reconstruction, are not independent: resampling only rows would call their shared luck
    signal)."""
    drawn = rng.integers(0, len(groups), len(groups))
    return np.concatenate([groups[g][rng.integers(0, len(groups[g]), len(groups[g]))] for g in drawn])


def _order_statistic_percentile(sorted_x: np.ndarray, q: float) -> float:
    """numpy's 'linear' percentile of sorted values that may hold +-inf.

    np.percentile interpolates as a + t * (b - a), which turns inf - inf into nan; here two equal
    neighbours (inf included) give that value and an infinite neighbour gives the infinity.
    """
    pos = q / 100.0 * (sorted_x.size - 1)
    i = int(math.floor(pos))
    j = min(i + 1, sorted_x.size - 1)
    t = pos - i
    a, b = float(sorted_x[i]), float(sorted_x[j])
    if t == 0.0 or a == b:
        return a
    if math.isinf(a) or math.isinf(b):
        return a if math.isinf(a) else b
    return a + t * (b - a)


def percentile_interval(samples: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The equal-tailed percentile interval of bootstrap samples: their (1-c)/2 and (1+c)/2 percentiles.

    NaN samples are ignored (as np.nanpercentile does); all-NaN gives (nan, nan); constant samples
    give (v, v) exactly. Finite samples go through np.percentile (linear interpolation); samples with
    infinities are interpolated the same way without producing inf - inf.
    """
    _check_args(1, confidence)
    x = np.asarray(samples, dtype=float).ravel()
    x = x[~np.isnan(x)]
    if x.size == 0:
        return (math.nan, math.nan)
    q_lo, q_hi = 100.0 * (1.0 - confidence) / 2.0, 100.0 * (1.0 + confidence) / 2.0
    if x.min() == x.max():
        v = float(x[0])
        return (v, v)
    if np.isfinite(x).all():
        lo, hi = np.percentile(x, [q_lo, q_hi])
        return (float(lo), float(hi))
    x = np.sort(x)
    return (_order_statistic_percentile(x, q_lo), _order_statistic_percentile(x, q_hi))


def _is_reportable(value: object) -> bool:
    """A summary value gets an interval when it is a real number that is finite or nan (not bool, not inf)."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, np.ndarray):
        if value.ndim != 0 or not np.issubdtype(value.dtype, np.number):
            return False
        value = value.item()
    if not isinstance(value, (numbers.Real, np.integer, np.floating)):
        return False
    return not math.isinf(float(value))


def _as_float(value: object) -> float:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def bootstrap_interval(
    rows: Sequence[Mapping],
    summarize: Callable[[list], Mapping[str, float]],
    n_samples: int = BOOTSTRAP_SAMPLES,
    confidence: float = CONFIDENCE,
    seed: int = BOOTSTRAP_SEED,
    keys: Sequence[str] | None = None,
) -> dict[str, tuple[float, float]]:
    """Percentile-bootstrap confidence intervals of every numeric key of ``summarize(rows)``.

    The rows (one per pair) are resampled with replacement `n_samples` times (the indices of
    ``resample_indices(len(rows), n_samples, seed)``); each resample, as a list of rows, is passed to
    `summarize`, and each key's interval is the (1-c)/2 and (1+c)/2 percentiles of its values over
    the resamples (see `percentile_interval`: NaN values ignored, all-NaN gives (nan, nan), a
    constant gives (v, v)). A key missing from one resample's summary counts as NaN there.

    keys: the keys to report; by default every key whose value in the full-sample summary is a
    real number that is finite or nan. Returns {} for no rows.
    """
    _check_args(n_samples, confidence)
    rows = list(rows)
    if not rows:
        return {}
    if keys is None:
        full = summarize(list(rows))
        keys = [k for k, v in full.items() if _is_reportable(v)]
    keys = list(keys)
    values = np.full((int(n_samples), len(keys)), np.nan)
    s = 0
    for block in _index_blocks(len(rows), int(n_samples), seed):
        for idx in block:
            summary = summarize([rows[i] for i in idx])
            values[s] = [_as_float(summary.get(k, math.nan)) for k in keys]
            s += 1
    return {k: percentile_interval(values[:, j], confidence) for j, k in enumerate(keys)}


def bootstrap_means(values: np.ndarray, n_samples: int = BOOTSTRAP_SAMPLES, seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """The means of the `n_samples` bootstrap resamples of `values` (same resamples as `resample_indices`).

    A resample that draws a NaN has a NaN mean, as np.mean over the rows would give.
    """
    _check_args(n_samples)
    x = np.asarray(values, dtype=float).ravel()
    if x.size == 0:
        return np.full(int(n_samples), np.nan)
    out = np.empty(int(n_samples))
    s = 0
    with warnings.catch_warnings():
        # +inf and -inf in one resample: its mean is nan, which the percentile then ignores.
        warnings.simplefilter("ignore", RuntimeWarning)
        for block in _index_blocks(x.size, int(n_samples), seed):
            out[s:s + len(block)] = x[block].mean(axis=1)
            s += len(block)
    return out


def bootstrap_mean_interval(
    values: np.ndarray,
    n_samples: int = BOOTSTRAP_SAMPLES,
    confidence: float = CONFIDENCE,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, float]:
    """Percentile-bootstrap interval of the mean of one array, vectorised.

    The same interval ``bootstrap_interval`` gives for a summarize that returns the mean of this
    array's values, for the same seed (same resamples, same percentile rule); (nan, nan) if empty.
    """
    _check_args(n_samples, confidence)
    return percentile_interval(bootstrap_means(values, n_samples, seed), confidence)
