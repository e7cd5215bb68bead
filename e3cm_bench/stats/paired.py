"""Paired comparison of two methods on the same pairs: a test, an interval and a verdict.

The two methods ran on the same pairs, so each pair is its own control: the test works on the
per-pair differences (Wilcoxon signed-rank, or the sign test when there are too few of them) or,
for a pass/fail metric, on the pairs where exactly one method passed (exact McNemar). The size of
the difference is the mean of B - A with a paired-bootstrap interval (pairs resampled as units).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

from .bootstrap import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, bootstrap_mean_interval

# Below this many non-zero differences the signed-rank test's distribution is too coarse to be
# worth its assumptions (symmetric differences); the sign test needs none.
MIN_WILCOXON = 6


@dataclass(frozen=True)
class PairedResult:
    """One metric compared between method A and method B on the same pairs.

    mean_diff = mean(b - a) (B minus A) over the pairs with finite values of both, [lo, hi] its
    paired-bootstrap interval at confidence 1 - alpha; mean_a and mean_b are over those same pairs.
    n is the number of pairs the test used; test is "wilcoxon", "sign" or "mcnemar".
    """

    metric: str
    n: int
    mean_a: float
    mean_b: float
    mean_diff: float
    lo: float
    hi: float
    test: str
    p_value: float
    verdict: str


def _binomial_p(k: int, m: int) -> float:
    """Two-sided exact binomial p of k successes in m fair trials; 1 with no trial."""
    if m == 0:
        return 1.0
    return float(sps.binomtest(int(k), int(m), 0.5, alternative="two-sided").pvalue)


def _differences(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """b - a per pair, with equal values (the same infinity included) a zero difference.

    An infinity against anything else gives an infinite difference of the right sign: +inf lies
    above every finite value, so it ranks above every finite difference in the signed-rank test.
    """
    with np.errstate(invalid="ignore"):
        d = b - a
    d[a == b] = 0.0
    return d


def _rank_ready(d: np.ndarray) -> np.ndarray:
    """Differences with each infinity replaced by a finite stand-in beyond every finite |d|.

    The signed-rank test only uses the signs and the ranks of |d|; one common magnitude for all
    infinities keeps them tied with each other and above every finite difference.
    """
    inf = np.isinf(d)
    if not inf.any():
        return d
    finite_abs = np.abs(d[~inf])
    big = 2.0 * (float(finite_abs.max()) if finite_abs.size else 1.0) + 1.0
    out = d.copy()
    out[inf] = np.sign(d[inf]) * big
    return out


def compare_paired(
    a: np.ndarray,
    b: np.ndarray,
    metric: str,
    higher_is_better: bool = True,
    binary: bool = False,
    alpha: float = 0.05,
    n_samples: int = BOOTSTRAP_SAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> PairedResult:
    """Compare per-pair values a (method A) and b (method B) of the same pairs, in the same order.

    Pairs where either value is NaN are dropped. binary (0/1 values): exact McNemar, the two-sided
    binomial test on the discordant pairs (p = 1 without any). Otherwise the two-sided Wilcoxon
    signed-rank test on the non-zero differences b - a (p = 1 if all are zero), or the sign test
    when fewer than 6 differences are non-zero. Infinite values take part in the test (+inf above
    every finite value); the mean difference and its bootstrap interval (at confidence 1 - alpha,
    `n_samples` resamples, `seed`) use the pairs where both values are finite.

    Verdict: a winner when p < alpha and the interval excludes 0 on the side of the direction the
    test found (the median non-zero difference, or the discordance); when some value is infinite,
    or no pair is finite, the test alone decides. The direction then names "A better" or "B better"
    by `higher_is_better`; otherwise "no difference detectable with {n} pairs".
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie strictly between 0 and 1, got {alpha!r}")
    a = np.asarray(a, dtype=float).ravel()
    b = np.asarray(b, dtype=float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"a and b must hold the same pairs: {a.size} and {b.size} values")
    keep = ~(np.isnan(a) | np.isnan(b))
    a, b = a[keep], b[keep]
    n = int(a.size)

    if binary:
        if not np.isin(a, (0.0, 1.0)).all() or not np.isin(b, (0.0, 1.0)).all():
            raise ValueError(f"{metric}: binary values must be 0 or 1")
        b_only = int(np.sum((a == 0) & (b == 1)))  # pairs only B passed
        a_only = int(np.sum((a == 1) & (b == 0)))  # pairs only A passed
        test = "mcnemar"
        p_value = _binomial_p(b_only, b_only + a_only)
        direction = int(np.sign(b_only - a_only))
    else:
        d = _differences(a, b)
        nonzero = d[d != 0]
        if nonzero.size < MIN_WILCOXON:
            test = "sign"
            p_value = _binomial_p(int(np.sum(nonzero > 0)), nonzero.size)
        else:
            test = "wilcoxon"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                res = sps.wilcoxon(_rank_ready(nonzero), zero_method="wilcox", alternative="two-sided")
            p_value = float(res.pvalue)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            median = float(np.median(nonzero)) if nonzero.size else 0.0
        # The median of -inf and +inf is nan: no direction from it, as for an exact 0.
        direction = 0 if math.isnan(median) else int(np.sign(median))
        if direction == 0 and nonzero.size:
            # An even count split around zero: fall back on which side carries the larger ranks.
            ranks = sps.rankdata(np.abs(_rank_ready(nonzero)))
            direction = int(np.sign(ranks[nonzero > 0].sum() - ranks[nonzero < 0].sum()))

    finite = np.isfinite(a) & np.isfinite(b)
    fa, fb = a[finite], b[finite]
    if fa.size:
        mean_a, mean_b = float(fa.mean()), float(fb.mean())
        mean_diff = float((fb - fa).mean())
        lo, hi = bootstrap_mean_interval(fb - fa, n_samples=n_samples, confidence=1.0 - alpha, seed=seed)
    else:
        mean_a = mean_b = mean_diff = lo = hi = math.nan

    significant = p_value < alpha and direction != 0
    if significant and finite.all() and fa.size:
        # The interval must exclude 0 on the side the test points to.
        significant = lo > 0 if direction > 0 else hi < 0
    if significant:
        b_wins = (direction > 0) == higher_is_better
        verdict = "B better" if b_wins else "A better"
    else:
        verdict = f"no difference detectable with {n} pairs"
    return PairedResult(metric, n, mean_a, mean_b, mean_diff, float(lo), float(hi), test, float(p_value), verdict)


def verdict_line(result: PairedResult) -> str:
    """One readable line: metric, n, both means, B - A with its interval, the test and p, the verdict."""
    r = result
    return (f"{r.metric}: n={r.n}, A {r.mean_a:.4g}, B {r.mean_b:.4g}, "
            f"B-A {r.mean_diff:+.4g} [{r.lo:+.4g}, {r.hi:+.4g}], {r.test} p={r.p_value:.3g}: {r.verdict}")
