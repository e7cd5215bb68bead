"""e3cm_bench.stats: Poisson-binomial counts, bootstrap intervals and their coverage, paired comparisons."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from e3cm_bench.stats import (
    BOOTSTRAP_SAMPLES,
    BOOTSTRAP_SEED,
    CONFIDENCE,
    PairedResult,
    Resampling,
    bootstrap_interval,
    bootstrap_mean_interval,
    compare_paired,
    count_bounds,
    count_tail,
    poisson_binomial_cdf,
    poisson_binomial_pmf,
    resample_aggregate,
    resample_indices,
    verdict_line,
)
from e3cm_bench.stats import aggregate as aggregate_module
from e3cm_bench.stats import bootstrap as bootstrap_module


# ---------------------------------------------------------------- Poisson-binomial

def brute_force_pmf(p: np.ndarray) -> np.ndarray:
    """P(K = k) by summing the probability of each of the 2^n success patterns."""
    pmf = np.zeros(len(p) + 1)
    for outcome in itertools.product((0, 1), repeat=len(p)):
        o = np.array(outcome)
        pmf[o.sum()] += np.prod(np.where(o == 1, p, 1 - p))
    return pmf


@pytest.mark.parametrize("n", range(1, 11))
def test_poisson_binomial_matches_enumeration(n):
    rng = np.random.default_rng(100 + n)
    for _ in range(3):
        p = rng.uniform(0, 1, n)
        expected = brute_force_pmf(p)
        pmf = poisson_binomial_pmf(p)
        assert pmf.shape == (n + 1,)
        np.testing.assert_allclose(pmf, expected, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(poisson_binomial_cdf(p), np.cumsum(expected), rtol=1e-12, atol=1e-15)
    # Probabilities at the ends and repeated values take the same path.
    p = np.array([0.0, 1.0, 0.5, 0.5, 0.25, 1.0, 0.0, 0.9, 0.1, 0.3])[:n]
    np.testing.assert_allclose(poisson_binomial_pmf(p), brute_force_pmf(p), rtol=1e-12, atol=1e-15)


def test_poisson_binomial_edge_cases():
    np.testing.assert_array_equal(poisson_binomial_pmf([]), [1.0])
    np.testing.assert_array_equal(poisson_binomial_cdf([]), [1.0])
    np.testing.assert_array_equal(poisson_binomial_pmf([0.0] * 4), [1, 0, 0, 0, 0])
    np.testing.assert_array_equal(poisson_binomial_pmf([1.0] * 4), [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(poisson_binomial_cdf([1.0] * 4), [0, 0, 0, 0, 1])
    # Out-of-range probabilities are clipped to [0, 1].
    np.testing.assert_array_equal(poisson_binomial_pmf([-0.5, 1.5]), [0, 1, 0])
    # Equal p: the binomial distribution.
    from scipy.stats import binom
    np.testing.assert_allclose(poisson_binomial_pmf([0.3] * 25), binom.pmf(np.arange(26), 25, 0.3), rtol=1e-10)
    with pytest.raises(ValueError):
        poisson_binomial_pmf([0.5, float("nan")])


def test_poisson_binomial_large_n_is_a_distribution():
    p = np.random.default_rng(5).uniform(0, 1, 2000)
    pmf = poisson_binomial_pmf(p)
    assert pmf.min() >= 0 and math.isclose(pmf.sum(), 1.0, rel_tol=1e-9)
    assert math.isclose(float(np.arange(pmf.size) @ pmf), p.sum(), rel_tol=1e-9)  # E[K] = sum p
    cdf = poisson_binomial_cdf(p)
    assert np.all(np.diff(cdf) >= 0) and cdf[-1] == 1.0


@pytest.mark.parametrize("alpha", [0.01, 0.05, 0.1, 0.32])
def test_count_bounds_cover_and_are_tight(alpha):
    rng = np.random.default_rng(int(alpha * 1000))
    for n in (1, 3, 8, 30, 200):
        for _ in range(5):
            p = rng.uniform(0, 1, n) ** rng.uniform(0.3, 3)  # some sets skewed towards 0, some towards 1
            pmf = poisson_binomial_pmf(p)
            lo, hi = count_bounds(p, alpha)
            assert 0 <= lo <= hi <= n
            assert pmf[lo:hi + 1].sum() >= 1 - alpha - 1e-12
            below, above = pmf[:lo].sum(), pmf[hi + 1:].sum()
            assert below <= alpha / 2 + 1e-12 and above <= alpha / 2 + 1e-12
            # Tight: moving either end inwards leaves out a tail heavier than alpha/2.
            if lo < hi:
                assert pmf[:lo + 1].sum() > alpha / 2
                assert pmf[hi:].sum() > alpha / 2
    assert count_bounds([], alpha) == (0, 0)
    assert count_bounds([1.0] * 7, alpha) == (7, 7)
    assert count_bounds([0.0] * 7, alpha) == (0, 0)


def test_count_bounds_binomial_example():
    # Binomial(10, 0.5): P(K <= 1) = 11/1024 <= 0.025 < P(K <= 2) = 56/1024, so the 95% range is [2, 8].
    assert count_bounds([0.5] * 10, 0.05) == (2, 8)
    # A tail exactly alpha/2 is left out: Binomial(3, 0.5) has P(K = 0) = P(K = 3) = 1/8.
    assert count_bounds([0.5] * 3, 0.25) == (1, 2)
    assert count_bounds([0.5] * 2, 0.5) == (1, 1)


def test_count_tail():
    p = np.random.default_rng(7).uniform(0, 1, 9)
    pmf = brute_force_pmf(p)
    for k in range(10):
        low, high = count_tail(p, k)
        assert math.isclose(low, pmf[:k + 1].sum(), rel_tol=1e-12)
        assert math.isclose(high, pmf[k:].sum(), rel_tol=1e-12)
    assert count_tail(p, -1) == (0.0, 1.0)
    assert count_tail(p, 10) == (1.0, 0.0)
    # A small upper tail keeps its precision: 30 trials of p = 0.01 all succeeding.
    assert math.isclose(count_tail([0.01] * 30, 30)[1], 1e-60, rel_tol=1e-9)


# ---------------------------------------------------------------- bootstrap

def test_resample_indices():
    idx = resample_indices(17, 50, seed=3)
    assert idx.shape == (50, 17) and np.issubdtype(idx.dtype, np.integer)
    assert idx.min() >= 0 and idx.max() < 17
    np.testing.assert_array_equal(idx, np.random.default_rng(3).integers(0, 17, size=(50, 17)))
    np.testing.assert_array_equal(idx, resample_indices(17, 50, seed=3))
    assert not np.array_equal(idx, resample_indices(17, 50, seed=4))
    assert resample_indices(0, 5, seed=0).shape == (5, 0)


def test_resample_indices_blocks_equal_one_draw(monkeypatch):
    # The matrix is drawn in blocks of rows to bound memory; the blocks must give the same stream.
    full = resample_indices(13, 40, seed=9)
    monkeypatch.setattr(aggregate_module, "_BLOCK_ENTRIES", 13 * 3)
    np.testing.assert_array_equal(resample_indices(13, 40, seed=9), full)


def coverage(draw, true_mean: float, confidence: float, datasets: int = 1000, seed: int = 0) -> float:
    """Fraction of `datasets` synthetic data sets whose bootstrap interval of the mean holds the true mean."""
    rng = np.random.default_rng(seed)
    hits = 0
    for i in range(datasets):
        lo, hi = bootstrap_mean_interval(draw(rng), confidence=confidence, seed=i)
        hits += lo <= true_mean <= hi
    return hits / datasets


def test_bootstrap_mean_interval_coverage_normal():
    # For n = 40 normal draws the percentile interval behaves like mean +- z * sd / sqrt(n) with the
    # divisor-n sd, whose exact coverage is P(|t_39| < z * sqrt(39/40)): 0.940 at 95%, 0.491 at 50%
    # (measured: 0.939 over 6000 data sets; 0.939 and 0.490 for the ones below). 1000 data sets carry
    # a standard error of about 0.0075 at 95%, so the bounds are about 2.5 standard errors wide.
    draw = lambda rng: rng.normal(2.0, 1.5, 40)  # noqa: E731
    c95 = coverage(draw, 2.0, 0.95, seed=1)
    assert 0.92 <= c95 <= 0.96, c95
    # The check can tell intervals apart: a 50% interval covers about half the time.
    c50 = coverage(draw, 2.0, 0.50, seed=2)
    assert 0.45 <= c50 <= 0.53, c50


def test_bootstrap_mean_interval_coverage_skewed():
    # Exponential data: the percentile bootstrap under-covers for a skewed mean at n = 40
    # (measured 0.920 over 6000 data sets; 0.937 for the 1000 below); the bound says so instead of 0.95.
    c95 = coverage(lambda rng: rng.exponential(1.0, 40), 1.0, 0.95, seed=3)
    assert 0.89 <= c95 <= 0.95, c95


def test_percentile_interval_rules():
    assert bootstrap_mean_interval(np.full(12, 3.25)) == (3.25, 3.25)
    lo, hi = bootstrap_mean_interval(np.array([]))
    assert math.isnan(lo) and math.isnan(hi)
    # NaN resample means are ignored; NaN in every resample gives (nan, nan).
    lo, hi = bootstrap_mean_interval(np.array([1.0, 2.0, np.nan] + [3.0] * 5))
    assert 1.0 <= lo <= hi <= 3.0 and not math.isnan(lo)
    lo, hi = bootstrap_mean_interval(np.full(5, np.nan))
    assert math.isnan(lo) and math.isnan(hi)
    # Percentiles agree with np.nanpercentile on finite samples and survive infinities.
    x = np.random.default_rng(0).normal(size=301)
    x[::7] = np.nan
    assert bootstrap_module.percentile_interval(x, 0.9) == tuple(np.nanpercentile(x, [5, 95]))
    assert bootstrap_module.percentile_interval(np.array([1.0, 2.0] + [np.inf] * 98), 0.9) == (np.inf, np.inf)
    assert bootstrap_module.percentile_interval(np.array([-np.inf] * 50 + [1.0] * 50), 0.5)[0] == -np.inf
    with pytest.raises(ValueError):
        bootstrap_mean_interval(np.ones(4), confidence=1.0)


def make_rows(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    err = rng.exponential(4.0, n)
    return [{"pair": f"p{i}", "error": float(e), "time": 0.5} for i, e in enumerate(err)]


def summarize(rows: list) -> dict:
    err = np.array([r["error"] for r in rows])
    return {"mean_error": float(err.mean()), "under_3px": float(np.mean(err < 3.0)),
            "time": float(np.mean([r["time"] for r in rows])), "method": "e3cm", "count": len(rows),
            "ok": True, "worst": float("inf")}


def test_bootstrap_interval_agrees_with_vectorised_mean():
    rows = make_rows(60, seed=11)
    err = np.array([r["error"] for r in rows])
    got = bootstrap_interval(rows, summarize, n_samples=400, seed=5)
    # Numbers that are finite (or nan) get intervals; strings, bools and infinities do not.
    assert set(got) == {"mean_error", "under_3px", "time", "count"}
    np.testing.assert_allclose(got["mean_error"], bootstrap_mean_interval(err, n_samples=400, seed=5), rtol=1e-12)
    np.testing.assert_allclose(got["under_3px"], bootstrap_mean_interval((err < 3.0).astype(float), n_samples=400,
                                                                         seed=5), rtol=1e-12)
    assert got["time"] == (0.5, 0.5) and got["count"] == (60.0, 60.0)
    lo, hi = got["mean_error"]
    assert lo < err.mean() < hi


def test_bootstrap_interval_seeds_and_keys():
    rows = make_rows(30, seed=12)
    a = bootstrap_interval(rows, summarize, n_samples=200, seed=1)
    assert a == bootstrap_interval(rows, summarize, n_samples=200, seed=1)
    b = bootstrap_interval(rows, summarize, n_samples=200, seed=2)
    assert a["mean_error"] != b["mean_error"]
    assert set(bootstrap_interval(rows, summarize, n_samples=50, keys=["under_3px"])) == {"under_3px"}
    assert bootstrap_interval([], summarize) == {}
    # The defaults are the module's constants.
    assert (BOOTSTRAP_SAMPLES, CONFIDENCE, BOOTSTRAP_SEED) == (1000, 0.95, 0)
    assert bootstrap_interval(rows, summarize, keys=["mean_error"]) == bootstrap_interval(
        rows, summarize, n_samples=1000, confidence=0.95, seed=0, keys=["mean_error"])


def test_bootstrap_interval_nan_samples():
    # A summary that is NaN on some resamples (no row under the threshold) ignores those resamples.
    rows = [{"error": 1.0}] + [{"error": 10.0}] * 9

    def median_under(rs):
        e = np.array([r["error"] for r in rs])
        return {"median_small": float(np.median(e[e < 3])) if (e < 3).any() else float("nan")}

    assert bootstrap_interval(rows, median_under, n_samples=300, seed=0) == {"median_small": (1.0, 1.0)}
    lo, hi = bootstrap_interval([{"error": 10.0}] * 4, median_under, n_samples=50)["median_small"]
    assert math.isnan(lo) and math.isnan(hi)


# ---------------------------------------------------------------- resample_aggregate

def test_resample_aggregate_constant_draws():
    draws = [np.full(k, v) for k, v in zip((1, 3, 5, 2), (0.1, 0.7, 0.4, 0.9))]
    out = resample_aggregate(draws, np.mean, n_samples=500, seed=0)
    assert out.shape == (500,)
    np.testing.assert_allclose(out, np.mean([0.1, 0.7, 0.4, 0.9]), rtol=1e-15)


def test_resample_aggregate_mean_and_vectorised():
    rng = np.random.default_rng(4)
    draws = [rng.normal(i * 0.1, 1.0, size=rng.integers(1, 12)) for i in range(40)]
    out = resample_aggregate(draws, np.mean, n_samples=4000, seed=3)
    per_pair = np.mean([d.mean() for d in draws])
    # Each sample's mean has expectation per_pair; its sd is about 1/sqrt(40), so 4000 samples pin it to ~0.003.
    assert abs(out.mean() - per_pair) < 0.015
    assert out.std() > 0.05  # the picks do vary
    vec = resample_aggregate(draws, lambda m: m.mean(axis=1), n_samples=4000, seed=3, vectorized=True)
    np.testing.assert_allclose(vec, out, rtol=1e-12)
    assert not np.allclose(resample_aggregate(draws, np.mean, n_samples=4000, seed=4), out)


def test_resample_aggregate_picks_each_value_of_a_pair():
    # One pair with values 0, 1, 2, 3: every value is picked about a quarter of the time; inf and
    # NaN are values like any other.
    out = resample_aggregate([np.array([0.0, 1.0, 2.0, 3.0])], lambda v: v[0], n_samples=8000, seed=1)
    counts = np.bincount(out.astype(int), minlength=4) / 8000
    np.testing.assert_allclose(counts, 0.25, atol=0.025)
    out = resample_aggregate([np.array([np.inf, np.nan]), np.array([1.0])], lambda v: np.isfinite(v).sum(),
                             n_samples=1000, seed=2)
    assert set(np.unique(out)) == {1.0}
    with pytest.raises(ValueError):
        resample_aggregate([np.array([1.0]), np.array([])], np.mean, n_samples=10)
    with pytest.raises(ValueError):
        resample_aggregate([np.array([1.0, 2.0])], lambda m: m.mean(), n_samples=10, vectorized=True)


# ---------------------------------------------------------------- compare_paired
# One rule (stats/paired.py): a statistic over the same pairs, its paired-bootstrap interval,
# the verdict read from that interval and the bootstrap's p, so that none contradicts another.

def agrees(r: PairedResult, alpha: float = 0.05) -> None:
    """Verdict, interval and p of one result say the same thing."""
    excludes = r.lo > 0 or r.hi < 0
    assert (r.verdict != "no difference detectable") == excludes, r
    assert (r.p_value < alpha) == excludes, r
    if excludes:
        assert r.lo <= r.diff <= r.hi or math.isinf(r.diff), r


def test_shifted_copy_higher_is_better():
    rng = np.random.default_rng(21)
    a = rng.uniform(0.2, 0.8, 200)
    b = a + 0.05 + rng.normal(0, 0.03, 200)
    r = compare_paired(a, b, "AUC@10", higher_is_better=True)
    assert isinstance(r, PairedResult)
    assert (r.statistic, r.n, r.verdict) == ("mean", 200, "B better")
    assert r.p_value < 0.001 and r.lo < 0.05 < r.hi and r.lo > 0
    assert math.isclose(r.diff, float(np.mean(b - a)), rel_tol=1e-9)
    assert math.isclose(r.b - r.a, r.diff, rel_tol=1e-9) and math.isclose(r.a, float(a.mean()))
    agrees(r)


def test_shifted_copy_lower_is_better():
    rng = np.random.default_rng(22)
    a = rng.exponential(2.0, 150)
    b = a + 0.4 + rng.normal(0, 0.5, 150)  # B's errors are larger: A is better
    r = compare_paired(a, b, "error px", higher_is_better=False)
    assert r.verdict == "A better" and r.lo < 0.4 < r.hi and r.p_value < 0.001
    # The same data read with higher_is_better names the other method.
    assert compare_paired(a, b, "x", higher_is_better=True).verdict == "B better"


def test_independent_noise_no_difference():
    rng = np.random.default_rng(23)
    truth = rng.uniform(0, 5, 120)
    a = truth + rng.normal(0, 0.5, 120)
    b = truth + rng.normal(0, 0.5, 120)
    r = compare_paired(a, b, "error px", higher_is_better=False)
    assert r.verdict == "no difference detectable" and r.n == 120
    assert r.p_value > 0.05 and r.lo < 0 < r.hi


def test_a_failure_is_the_worst_error_and_the_median_sees_it():
    """Once, sift vs e3cm had h_error means over the 13 finite pairs of 15, an interval
    across 0 and yet a winner. A failure is +inf, the median ranks it worst, n is every pair."""
    rng = np.random.default_rng(24)
    a = rng.uniform(0.5, 2.0, 40)
    b = a + rng.normal(0, 0.05, 40)
    b[:15] = np.inf  # B fails on 15 of 40 pairs, A on none
    r = compare_paired(a, b, "h_error", higher_is_better=False, statistic="median")
    assert r.n == 40 and r.statistic == "median"
    assert r.a == pytest.approx(float(np.median(a))) and r.b == pytest.approx(float(np.median(b)))
    assert r.verdict == "A better" and r.lo > 0
    agrees(r)
    # More than half failed: B's median is +inf, so is the difference; still A better.
    b[:25] = np.inf
    r = compare_paired(a, b, "h_error", higher_is_better=False, statistic="median")
    assert math.isinf(r.b) and r.diff == math.inf and r.verdict == "A better"
    agrees(r)
    # NaN (no value at all) drops the pair; both failed is a tie, not NaN.
    a2, b2 = np.r_[np.nan, np.inf, np.inf, a[:20]], np.r_[1.0, np.inf, np.inf, a[:20]]
    r = compare_paired(a2, b2, "h_error", higher_is_better=False, statistic="median")
    assert r.n == 22 and r.diff == 0 and (r.lo, r.hi) == (0.0, 0.0) and r.verdict == "no difference detectable"
    # A mean over infinite values does not exist: refused, not silently dropped.
    with pytest.raises(ValueError, match="median"):
        compare_paired(a, b, "h_error", statistic="mean")


@pytest.mark.parametrize("seed", range(12))
def test_verdict_interval_and_p_agree_on_random_data(seed):
    """The property of the rule, on values of every kind: bounded, 0/1, errors with failures."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(3, 80))
    kind = seed % 3
    if kind == 0:
        a = rng.uniform(0, 1, n)
        b, statistic = np.clip(a + rng.normal(rng.normal(0, 0.05), 0.1, n), 0, 1), "mean"
    elif kind == 1:
        a = (rng.random(n) < 0.6).astype(float)
        b, statistic = (rng.random(n) < rng.uniform(0.3, 0.9)).astype(float), "mean"
    else:
        a = rng.exponential(2, n)
        b = a * rng.uniform(0.5, 2.0)
        a[rng.random(n) < 0.2], b[rng.random(n) < 0.3] = np.inf, np.inf
        statistic = "median"
    for alpha in (0.05, 0.2):
        agrees(compare_paired(a, b, "m", higher_is_better=kind != 2, statistic=statistic, alpha=alpha), alpha)


def test_pass_fail_difference_is_the_accuracy_difference():
    # 100 pairs: B alone passes on 25, A alone on 5, 70 concordant.
    a = np.r_[np.zeros(25), np.ones(5), np.ones(40), np.zeros(30)]
    b = np.r_[np.ones(25), np.zeros(5), np.ones(40), np.zeros(30)]
    r = compare_paired(a, b, "error < 3px")
    assert r.n == 100 and math.isclose(r.diff, 0.2) and r.lo > 0 and r.verdict == "B better"
    assert (r.a, r.b) == (0.45, 0.65)
    swapped = compare_paired(b, a, "error < 3px")
    assert swapped.verdict == "A better" and swapped.hi < 0 and math.isclose(swapped.p_value, r.p_value, abs_tol=0.01)
    assert compare_paired(a, b, "failed", higher_is_better=False).verdict == "A better"
    # Symmetric discordance: 15 each way.
    a = np.r_[np.zeros(15), np.ones(15), np.ones(40), np.zeros(30)]
    b = np.r_[np.ones(15), np.zeros(15), np.ones(40), np.zeros(30)]
    r = compare_paired(a, b, "error < 3px")
    assert r.diff == 0 and r.lo < 0 < r.hi and r.p_value > 0.5 and r.verdict == "no difference detectable"


def test_ties_constants_and_no_pairs():
    a = np.arange(20, dtype=float)
    r = compare_paired(a, a.copy(), "m")
    assert r.p_value == 1.0 and r.diff == 0.0 and (r.lo, r.hi) == (0.0, 0.0)
    assert r.verdict == "no difference detectable"
    r = compare_paired(a, a + 2.0, "m")  # every pair moved by exactly 2: the interval is a point
    assert r.lo == pytest.approx(2.0) and r.hi == pytest.approx(2.0) and r.p_value == 0.0 and r.verdict == "B better"
    r = compare_paired(np.array([np.nan]), np.array([1.0]), "m")
    assert r.n == 0 and r.verdict == "no difference detectable" and math.isnan(r.diff)


def test_bootstrap_p_is_the_interval_inverted():
    from e3cm_bench.stats.bootstrap import percentile_interval
    from e3cm_bench.stats.paired import bootstrap_p

    rng = np.random.default_rng(5)
    for samples in (rng.normal(0.3, 0.2, 1000), np.r_[np.zeros(400), np.full(600, 0.1)],
                    np.r_[rng.normal(-1, 1, 900), np.full(100, np.inf)], np.r_[np.full(30, -np.inf), rng.normal(1, 1, 970)]):
        p = bootstrap_p(samples)
        for c in np.linspace(0.5, 0.999, 60):
            lo, hi = percentile_interval(samples, c)
            if abs((1 - c) - p) > 1e-9:
                assert (lo > 0 or hi < 0) == (1 - c > p), (c, p, lo, hi)


def test_compare_paired_deterministic_and_checked():
    rng = np.random.default_rng(25)
    a, b = rng.normal(size=50), rng.normal(size=50)
    assert compare_paired(a, b, "m", resampling=Resampling(seed=3)) == compare_paired(a, b, "m", resampling=Resampling(seed=3))
    with pytest.raises(ValueError):
        compare_paired(a, b[:-1], "m")
    with pytest.raises(ValueError):
        compare_paired(a, b, "m", statistic="mode")


def test_verdict_line():
    rng = np.random.default_rng(26)
    a = rng.uniform(0.2, 0.8, 80)
    r = compare_paired(a, a + 0.1 + rng.normal(0, 0.02, 80), "AUC@5")
    line = verdict_line(r)
    assert "\n" not in line
    for part in ("AUC@5", "mean", "n=80", "p=", "B better", f"{r.a:.4g}", f"{r.b:.4g}",
                 f"{r.diff:+.4g}", f"{r.lo:+.4g}", f"{r.hi:+.4g}"):
        assert part in line, (part, line)
