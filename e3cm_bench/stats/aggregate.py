"""Distributions of benchmark aggregates over per-pair uncertainty.

Two views of one question, "how much can the aggregate move if each pair's outcome is uncertain":

* exact: the number of successes among pairs that succeed independently with probabilities p_i
  follows the Poisson-binomial distribution (`poisson_binomial_pmf`, `count_bounds`, `count_tail`);
* sampled: when pair i took several values over reruns (noise, seeds), `resample_aggregate` picks
  one value per pair independently and evaluates any aggregate (a mean, an AUC, a fraction).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

# Same reason as in bootstrap: draw the (n_samples, n_pairs) pick matrix a bounded block at a time.
# Picks are generated a bounded number of entries at a time, so that many resamples of a large
# benchmark do not materialise one huge (n_samples, n) matrix. numpy's generator gives the same
# stream whether it draws one matrix or consecutive blocks of rows; the bootstrap draws through
# the same helper, so the two agree by construction.
_BLOCK_ENTRIES = 1 << 21


def _probabilities(p: Sequence[float]) -> np.ndarray:
    q = np.asarray(p, dtype=float).ravel()
    if np.isnan(q).any():
        raise ValueError("success probabilities must not be NaN")
    return np.clip(q, 0.0, 1.0)


def poisson_binomial_pmf(p: Sequence[float]) -> np.ndarray:
    """P(K = k) for k = 0..n, K the number of successes among independent Bernoulli(p_i) trials.

    Exact up to rounding: the PMF is built one trial at a time (a convolution with [1 - p_i, p_i]),
    O(n^2) work in all. p is clipped to [0, 1]; an empty p gives [1.0] (no trial, no success).
    """
    q = _probabilities(p)
    pmf = np.zeros(q.size + 1)
    pmf[0] = 1.0
    for k, pk in enumerate(q):
        # After k trials only pmf[0..k] is non-zero; adding a trial moves mass p_k one count up.
        head = pmf[:k + 1].copy()
        pmf[:k + 1] = head * (1.0 - pk)
        pmf[1:k + 2] += head * pk
    return pmf


def poisson_binomial_cdf(p: Sequence[float]) -> np.ndarray:
    """P(K <= k) for k = 0..n (see `poisson_binomial_pmf`), non-decreasing, ending at exactly 1."""
    cdf = np.minimum(np.cumsum(poisson_binomial_pmf(p)), 1.0)
    # All the mass lies in 0..n; rounding in the sum must not leave the last entry short of 1.
    cdf[-1] = 1.0
    return cdf


def count_bounds(p: Sequence[float], alpha: float) -> tuple[int, int]:
    """The equal-tailed 1 - alpha range [k_lo, k_hi] of the Poisson-binomial success count.

    k_lo is the smallest k with P(K <= k) > alpha/2 and k_hi the smallest k with
    P(K <= k) >= 1 - alpha/2. Each tail left out weighs at most alpha/2 (P(K < k_lo) <= alpha/2,
    P(K > k_hi) <= alpha/2), so the range holds at least 1 - alpha of the mass, and moving either
    end inwards makes its tail exceed alpha/2.
    """
    if not 0.0 <= alpha < 1.0:
        raise ValueError(f"alpha must lie in [0, 1), got {alpha!r}")
    cdf = poisson_binomial_cdf(p)
    n = cdf.size - 1
    k_lo = int(np.searchsorted(cdf, alpha / 2.0, side="right"))
    k_hi = int(np.searchsorted(cdf, 1.0 - alpha / 2.0, side="left"))
    return min(k_lo, n), min(k_hi, n)


def count_tail(p: Sequence[float], k_observed: int) -> tuple[float, float]:
    """(P(K <= k_observed), P(K >= k_observed)) for the Poisson-binomial success count K.

    Each tail is summed from its own end of the PMF, so a small upper tail is not lost to 1 - cdf.
    """
    pmf = poisson_binomial_pmf(p)
    n = pmf.size - 1
    k = int(k_observed)
    # A tail that spans the whole support is exactly 1, whatever the rounding of its sum.
    lower = 0.0 if k < 0 else 1.0 if k >= n else float(min(pmf[:k + 1].sum(), 1.0))
    upper = 0.0 if k > n else 1.0 if k <= 0 else float(min(pmf[k:].sum(), 1.0))
    return lower, upper


def _pick_blocks(lengths: np.ndarray, n_samples: int, seed: int) -> Iterator[np.ndarray]:
    """Consecutive row blocks of the (n_samples, n_pairs) matrix of picked positions, for `seed`."""
    rng = np.random.default_rng(seed)
    n_pairs = lengths.size
    rows_per_block = max(1, _BLOCK_ENTRIES // max(n_pairs, 1))
    for start in range(0, n_samples, rows_per_block):
        rows = min(rows_per_block, n_samples - start)
        if n_pairs == 0:
            yield np.empty((rows, 0), dtype=np.int64)
        else:
            # Column i draws uniformly from range(lengths[i]), independently of the other columns.
            yield rng.integers(0, lengths, size=(rows, n_pairs), dtype=np.int64)


def resample_aggregate(
    draws: Sequence[np.ndarray],
    aggregate: Callable[[np.ndarray], float],
    n_samples: int = 10000,
    seed: int = 0,
    vectorized: bool = False,
) -> np.ndarray:
    """Samples of an aggregate when every pair takes one of its rerun values at random.

    draws[i] is the 1-D array of values pair i took over an ensemble of reruns (lengths may differ;
    NaN and inf are values like any other). Sample s picks, for every pair independently, one of its
    own values uniformly at random, and evaluates `aggregate` on the n_pairs picked values.

    vectorized: `aggregate` takes the whole (rows, n_pairs) matrix of picks and returns one value
    per row; otherwise it is called once per sample on a 1-D array. Both see the same picks for one
    seed. Returns the n_samples aggregate values as a float array.
    """
    if int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    arrays = [np.asarray(d, dtype=float).ravel() for d in draws]
    lengths = np.array([a.size for a in arrays], dtype=np.int64)
    if (lengths == 0).any():
        raise ValueError(f"pair {int(np.argmin(lengths))} has no values to draw from")
    flat = np.concatenate(arrays) if arrays else np.empty(0)
    # Pair i's values start at offsets[i] in flat: a pick of position j is flat[offsets[i] + j].
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64) if arrays else np.empty(0, np.int64)
    out = np.empty(int(n_samples))
    s = 0
    for picks in _pick_blocks(lengths, int(n_samples), seed):
        values = flat[offsets + picks]
        rows = len(values)
        if vectorized:
            res = np.asarray(aggregate(values), dtype=float).ravel()
            if res.size != rows:
                raise ValueError(f"a vectorized aggregate must return one value per row: {rows} rows, got {res.size}")
            out[s:s + rows] = res
        else:
            for r in range(rows):
                out[s + r] = float(aggregate(values[r]))
        s += rows
    return out
