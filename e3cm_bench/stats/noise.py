"""The regression gate's noise model: is a change in an aggregate larger than a rerun on
another CPU would make it?

Each pair of a baseline run has an ensemble of values (its own value plus one per noise
draw: gate/ensemble.py reruns the run with every CPU-dependent stage perturbed). From those:

- a **count** aggregate (the fraction of pairs under a threshold, e.g. h_acc@1) is a sum of
  independent Bernoulli variables, one per pair, with p_i = the share of the pair's members
  under the threshold: Poisson-binomial, exact (`count_gate`);
- any other aggregate (a mean, an AUC) is resampled: each sample takes, for every pair, one
  of its members at random and recomputes the aggregate (`member_picks` + the caller's
  summary), and the gate uses the samples' mean and spread with a Student t tail
  (`resampled_gate`).

A change is flagged where its two-sided tail probability under that distribution is below
``alpha``. Every gated metric is higher-is-better, so a flagged fall is a regression and a
flagged rise an improvement. Pure functions: arrays in, verdicts out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from e3cm_bench.stats.aggregate import count_tail, poisson_binomial_pmf

# A check's false-alarm rate: the chance that a check of runs made on another machine, with
# nothing else changed, flags anything. Split evenly over the metrics it gates (Bonferroni).
CHECK_ALPHA = 0.01
RESAMPLES = 4000
# The CSVs keep 8 significant digits: a difference below this relative size is no change.
RESOLUTION = 1e-6
# A pair's value (an error in px or degrees, a count, a fraction) computed from float32
# keypoints: a move below this size (relative, at least absolute) is no move.
PAIR_RESOLUTION = 1e-4


def metric_alpha(n_metrics: int, check_alpha: float = CHECK_ALPHA) -> float:
    """Each metric's false-alarm rate when a check gates n_metrics of them."""
    return check_alpha / max(int(n_metrics), 1)


@dataclass(frozen=True)
class Gate:
    """One metric of one run against its noise distribution."""

    metric: str
    kind: str  # "count" (Poisson-binomial) or "resampled"
    baseline: float
    measured: float
    expected: float  # the mean under noise
    spread: float  # the standard deviation under noise
    low: float  # the band that holds 1 - alpha of the noise distribution
    high: float
    p_value: float  # two-sided tail probability of the measured value under noise
    alpha: float

    @property
    def status(self) -> str:
        if math.isnan(self.measured) and not math.isnan(self.baseline):
            return "regression"
        if self.p_value >= self.alpha:
            return "ok"
        return "regression" if self.measured < self.expected else "improvement"


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= RESOLUTION * max(1.0, abs(a), abs(b))


def count_gate(metric: str, passes: Sequence[np.ndarray], measured: float, baseline: float, alpha: float) -> Gate:
    """A fraction of pairs (measured, baseline) against the Poisson-binomial distribution of
    its count; passes[i]: pair i's members, True where the pair passes the threshold.

    p_i is the predictive share (k_i + 1/2) / (m_i + 1) of pair i's k_i passing members of m_i
    (Jeffreys' prior): a pair that passed in every one of 21 members still fails a new rerun
    with probability 1/44, as a new draw may land outside everything the members showed."""
    p = np.array([(np.sum(np.asarray(m, bool)) + 0.5) / (len(m) + 1) for m in passes], float)
    n = len(p)
    pmf = poisson_binomial_pmf(p)
    mean = float(p.sum())
    sd = float(np.sqrt(np.sum(p * (1 - p))))
    cdf = np.cumsum(pmf)
    k_lo = int(np.searchsorted(cdf, alpha / 2, side="right"))
    k_hi = int(np.searchsorted(cdf, 1 - alpha / 2, side="left"))
    if math.isnan(measured):
        p_value = 0.0
    else:
        observed = int(round(measured * n))
        below, above = count_tail(p, observed)
        p_value = float(min(1.0, 2 * min(below, above)))
    return Gate(metric, "count", baseline, measured, mean / max(n, 1), sd / max(n, 1),
                k_lo / max(n, 1), min(k_hi, n) / max(n, 1), p_value, alpha)


def member_picks(member_counts: Sequence[int], n_samples: int = RESAMPLES, seed: int = 0) -> np.ndarray:
    """(n_samples, n_pairs) member indices: each sample picks one member of every pair,
    uniformly and independently."""
    counts = np.asarray(member_counts, int)
    if np.any(counts < 1):
        raise ValueError("every pair needs at least one member")
    rng = np.random.default_rng(seed)
    return (rng.random((n_samples, len(counts))) * counts).astype(int)


def resampled_gate(metric: str, samples: np.ndarray, measured: float, baseline: float, alpha: float,
                   draws: int) -> Gate:
    """An aggregate against the samples of its noise distribution (member_picks), through
    their mean m and standard deviation s. The spread comes from `draws` reruns, so a new
    run is judged by the predictive Student t: (x - m) / (s sqrt(1 + 1/draws)) with `draws`
    degrees of freedom (a t tail reaches the small alphas a check needs, where a few
    thousand samples cannot, and widens as the ensemble shrinks)."""
    samples = np.asarray(samples, float)
    samples = samples[np.isfinite(samples)]
    if len(samples) == 0:
        mean, sd = float("nan"), 0.0
    else:
        mean, sd = float(samples.mean()), float(samples.std(ddof=1)) if len(samples) > 1 else 0.0
    from scipy.stats import t as student

    df = max(int(draws), 1)
    scale = sd * math.sqrt(1 + 1 / df)
    half = float(student.ppf(1 - alpha / 2, df)) * scale
    if math.isnan(measured) or math.isnan(mean):
        p_value = 1.0 if math.isnan(measured) and math.isnan(mean) else 0.0
    elif _close(measured, mean):
        p_value = 1.0
    elif scale == 0:
        p_value = 0.0
    else:
        p_value = float(2 * student.sf(abs(measured - mean) / scale, df))
    return Gate(metric, "resampled", baseline, measured, mean, sd, mean - half, mean + half, p_value, alpha)


@dataclass(frozen=True)
class PairMove:
    """One pair's value in a checked run against its own ensemble."""

    pair: str
    column: str
    baseline: float
    measured: float
    low: float  # the smallest and largest value the pair took over its members
    high: float

    @property
    def delta(self) -> float:
        return self.measured - self.baseline

    @property
    def inside(self) -> bool:
        """Within the pair's own noise: between its members' extremes (inf: a member failed too).
        A new value from the same noise falls outside the extremes of K+1 members with
        probability 2/(K+2) (9% for K = 20): a few such pairs are expected, many are not."""
        m, lo, hi = self.measured, self.low, self.high
        if np.isnan(m) or np.isnan(lo):
            return bool(np.isnan(m) and np.isnan(lo))
        if np.isinf(m):
            return bool(m == (hi if m > 0 else lo))
        return bool(lo - PAIR_RESOLUTION * max(1.0, abs(lo)) <= m <= hi + PAIR_RESOLUTION * max(1.0, abs(hi)))


def pair_moves(pairs: Sequence[str], column: str, baseline: np.ndarray, members: Sequence[np.ndarray],
               measured: np.ndarray) -> list[PairMove]:
    """The pairs whose value moved from the baseline's, each with its members' range."""
    moves = []
    for name, before, own, now in zip(pairs, baseline, members, measured):
        before, now = float(before), float(now)
        same = (before == now) or (np.isnan(before) and np.isnan(now)) or (
            np.isfinite(before) and np.isfinite(now) and abs(before - now) <= PAIR_RESOLUTION * max(1.0, abs(before)))
        if same:
            continue
        own = np.asarray(own, float)
        finite = own[~np.isnan(own)]
        low, high = (float(finite.min()), float(finite.max())) if len(finite) else (float("nan"), float("nan"))
        moves.append(PairMove(str(name), column, before, now, low, high))
    return moves
