"""Paired comparison of two methods on the same pairs: one statistic, its interval, its p and a verdict.

The two methods ran on the same pairs, so each pair is its own control. One rule holds for every
metric, so that the numbers shown beside each other cannot contradict each other:

- the statistic is the mean of the per-pair values (bounded values: a fraction of matches, a
  0/1 pass, a precision), or their median where a value can be infinite (an error where the
  pair failed counts as +inf, worse than any error; a mean over it would not exist, and dropping
  the pair would hide the failure);
- B - A is the statistic of B minus that of A, over the same n pairs (those where neither value
  is NaN); its interval is the percentile interval of the same difference over paired bootstrap
  resamples (the pairs resampled as units, A and B together);
- the verdict is read from that interval: "B better" or "A better" when it excludes 0 (which
  side is better: `higher_is_better`), else "no difference detectable";
- values of several reconstructions per pair (sfm: one column per mapper seed, a pairs x seeds
  array each): the statistic is over all of a method's values, and each bootstrap resample
  draws the pairs (A and B together) and, for each method on its own, its seeds (with
  replacement): seeds are not paired, the seed k of A has nothing to do with the seed k of B;
- pairs in groups (sfm's bags: the pairs of one reconstruction): each resample draws the groups,
  then each drawn group's pairs (stats.bootstrap.nested_resample), A and B together;
- p is the same bootstrap's two-sided p: the smallest 1 - confidence at which that interval
  excludes 0, so p < alpha exactly when the verdict names a winner.

A percentile bootstrap is optimistic with few pairs (its interval is narrower than its nominal
level below a few dozen pairs); docs/results.md says so where the verdicts are read.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from e3cm_bench.stats.bootstrap import (BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, groups_of, nested_resample,
                                        percentile_interval, resample_indices)

STATISTICS = ("mean", "median")
NO_DIFFERENCE = "no difference detectable"
# The resampled pair indices are built in blocks of this many resamples (memory: block x n ints).
_BLOCK = 256


@dataclass(frozen=True)
class Resampling:
    """How compare_paired's bootstrap draws: `n_samples` resamples from `seed`; `groups`, each
    pair's group label (sfm's bag: a group's pairs resample together), or None."""

    n_samples: int = BOOTSTRAP_SAMPLES
    seed: int = BOOTSTRAP_SEED
    groups: np.ndarray | None = None


@dataclass(frozen=True)
class PairedResult:
    """One metric compared between method A and method B on the same n pairs.

    a, b: the statistic (mean or median) of A's and B's values over those pairs; diff = b - a;
    [lo, hi]: its paired-bootstrap interval at confidence 1 - alpha; p_value: the smallest
    1 - confidence at which that interval excludes 0; verdict: "A better", "B better" or
    "no difference detectable" (read from the interval).
    """

    metric: str
    statistic: str
    n: int
    a: float
    b: float
    diff: float
    lo: float
    hi: float
    p_value: float
    verdict: str


def _statistic(values: np.ndarray, statistic: str, axis: int | None = None) -> np.ndarray | float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # +inf and -inf averaged by a median: nan
        return np.mean(values, axis=axis) if statistic == "mean" else np.median(values, axis=axis)


def _difference(a, b):
    """b - a, with equal values (the same infinity included) a difference of 0."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    with np.errstate(invalid="ignore"):
        d = b - a
    return np.where(a == b, 0.0, d)


def _crossing(sorted_d: np.ndarray, strict: bool) -> float:
    """Where the 'linear' percentile curve of sorted samples reaches 0, as a position in [0, N-1].

    strict=False: the largest position at which the curve is still <= 0 (-1 if it starts above 0);
    strict=True: the smallest position at which it is >= 0 (N if it never gets there). Positions
    are those of `percentile_interval`'s interpolation (q/100 * (N - 1)), infinities included.
    """
    n = sorted_d.size
    if strict:
        k = int(np.searchsorted(sorted_d, 0.0, side="left"))  # samples < 0
        if k == 0:
            return 0.0
        if k == n:
            return float(n)
        left, right = float(sorted_d[k - 1]), float(sorted_d[k])
        if math.isinf(left):  # the curve stays -inf until it reaches sample k
            return float(k)
        return (k - 1) + (0.0 - left) / (right - left) if math.isfinite(right) else float(k - 1)
    k = int(np.searchsorted(sorted_d, 0.0, side="right"))  # samples <= 0
    if k == 0:
        return -1.0
    if k == n:
        return float(n - 1)
    left, right = float(sorted_d[k - 1]), float(sorted_d[k])
    if math.isinf(left):  # the curve stays -inf until it reaches sample k
        return float(k)
    if math.isinf(right) or left == 0.0:  # above 0 (or +inf) right after sample k - 1
        return float(k - 1)
    return (k - 1) + (0.0 - left) / (right - left)


def bootstrap_p(samples: np.ndarray) -> float:
    """The two-sided p of 'no difference' from bootstrap samples of a difference: the smallest
    1 - c at which `percentile_interval(samples, c)` excludes 0 (1 when it never does; 0 when
    every sample lies on one side of 0). NaN samples are ignored, as there."""
    d = np.sort(np.asarray(samples, dtype=float).ravel())
    d = d[~np.isnan(d)]
    if d.size == 0:
        return 1.0
    if d[0] == d[-1]:  # a constant: the interval is that value at every confidence
        return 1.0 if d[0] == 0 else 0.0
    last = d.size - 1
    below = _crossing(d, strict=False)  # lo > 0  <=>  (alpha/2) * last > below
    above = _crossing(d, strict=True)  # hi < 0  <=>  (1 - alpha/2) * last < above
    p_low = 2.0 * max(below, 0.0) / last if below >= 0 else 0.0
    p_high = 2.0 * (1.0 - min(above, last) / last) if above <= last else 0.0
    return float(min(1.0, p_low, p_high))


def bootstrap_differences(a: np.ndarray, b: np.ndarray, statistic: str, n_samples: int = BOOTSTRAP_SAMPLES,
                          seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """statistic(b[idx]) - statistic(a[idx]) for the paired resamples idx of `resample_indices`
    (both methods drawn with the same pairs), equal values a difference of 0."""
    idx = resample_indices(a.size, n_samples, seed)
    out = np.empty(int(n_samples))
    for start in range(0, int(n_samples), _BLOCK):
        block = idx[start:start + _BLOCK]
        out[start:start + len(block)] = _difference(_statistic(a[block], statistic, axis=1),
                                                    _statistic(b[block], statistic, axis=1))
    return out


def _two_level_differences(a: np.ndarray, b: np.ndarray, statistic: str, n_samples: int, seed: int,
                           groups: list[np.ndarray] | None = None) -> np.ndarray:
    """bootstrap_differences for pairs x seeds arrays: the pairs resampled together (in two
    stages where they come in groups), each method's seeds resampled on their own (a generator
    of seed + 1: the pairs' draws stay those of one level)."""
    idx = resample_indices(a.shape[0], n_samples, seed) if groups is None else None
    rng = np.random.default_rng(seed + 1)
    pick = np.random.default_rng(seed + 2)
    out = np.empty(int(n_samples))
    for s in range(int(n_samples)):
        rows = idx[s] if groups is None else nested_resample(groups, pick)
        seeds_a, seeds_b = rng.integers(0, a.shape[1], a.shape[1]), rng.integers(0, b.shape[1], b.shape[1])
        out[s] = _difference(_statistic(a[rows][:, seeds_a], statistic), _statistic(b[rows][:, seeds_b], statistic))
    return out


def compare_paired(
    a: np.ndarray,
    b: np.ndarray,
    metric: str,
    higher_is_better: bool = True,
    statistic: str = "mean",
    alpha: float = 0.05,
    resampling: Resampling | None = None,
) -> PairedResult:
    """Compare per-pair values a (method A) and b (method B) of the same pairs, in the same order
    (the rule of this module's docstring). Pairs where either value is NaN are dropped; +inf is a
    failure, the worst value of a lower-is-better metric, and only a median may hold one
    (ValueError for a mean over infinite values). resampling: the bootstrap's samples, seed and
    the pairs' groups (default Resampling())."""
    resampling = resampling or Resampling()
    n_samples, seed, groups = resampling.n_samples, resampling.seed, resampling.groups
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie strictly between 0 and 1, got {alpha!r}")
    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {', '.join(STATISTICS)}, got {statistic!r}")
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    seeded = a.ndim == 2 or b.ndim == 2  # pairs x seeds (the module docstring)
    a, b = (a.reshape(len(a), -1), b.reshape(len(b), -1)) if seeded else (a.ravel(), b.ravel())
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"a and b must hold the same pairs: {a.shape[0]} and {b.shape[0]} values")
    keep = ~(np.isnan(a).any(axis=1) | np.isnan(b).any(axis=1)) if seeded else ~(np.isnan(a) | np.isnan(b))
    a, b = a[keep], b[keep]
    grouped = groups_of(None if groups is None else np.asarray(groups).reshape(-1)[keep])
    if grouped is not None and not seeded:  # one column each: the same rule as one seed
        a, b, seeded = a.reshape(-1, 1), b.reshape(-1, 1), True
    n = int(a.shape[0])
    if statistic == "mean" and not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError(f"{metric}: infinite values have no mean; compare them by their median")
    if n == 0:
        return PairedResult(metric, statistic, 0, math.nan, math.nan, math.nan, math.nan, math.nan, 1.0, NO_DIFFERENCE)
    stat_a, stat_b = float(_statistic(a, statistic)), float(_statistic(b, statistic))
    diff = float(_difference(stat_a, stat_b))
    samples = (_two_level_differences(a, b, statistic, n_samples, seed, grouped) if seeded
               else bootstrap_differences(a, b, statistic, n_samples, seed))
    lo, hi = percentile_interval(samples, 1.0 - alpha)
    if lo > 0 or hi < 0:
        b_wins = (lo > 0) == higher_is_better
        verdict = "B better" if b_wins else "A better"
    else:
        verdict = NO_DIFFERENCE
    return PairedResult(metric, statistic, n, stat_a, stat_b, diff, float(lo), float(hi), bootstrap_p(samples), verdict)


def verdict_line(result: PairedResult) -> str:
    """One readable line: metric, statistic, n, A and B, B - A with its interval, p, the verdict."""
    r = result
    return (f"{r.metric} ({r.statistic}): n={r.n}, A {r.a:.4g}, B {r.b:.4g}, "
            f"B-A {r.diff:+.4g} [{r.lo:+.4g}, {r.hi:+.4g}], bootstrap p={r.p_value:.3g}: {r.verdict}")
