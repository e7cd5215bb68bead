"""Statistics for benchmark results: pure functions, arrays in, numbers out.

bootstrap: percentile-bootstrap intervals over pairs (`bootstrap_interval`, `bootstrap_mean_interval`).
aggregate: the Poisson-binomial count of successes and resampled aggregates over rerun ensembles.
paired: two methods on the same pairs, one statistic's paired-bootstrap interval, its p and verdict (`compare_paired`).
"""

from .aggregate import (
    count_bounds,
    count_tail,
    poisson_binomial_cdf,
    poisson_binomial_pmf,
    resample_aggregate,
)
from .bootstrap import (
    BOOTSTRAP_SAMPLES,
    BOOTSTRAP_SEED,
    CONFIDENCE,
    bootstrap_interval,
    bootstrap_mean_interval,
    resample_indices,
)
from .paired import PairedResult, compare_paired, verdict_line

__all__ = [
    "BOOTSTRAP_SAMPLES", "BOOTSTRAP_SEED", "CONFIDENCE", "PairedResult", "bootstrap_interval",
    "bootstrap_mean_interval", "compare_paired", "count_bounds", "count_tail", "poisson_binomial_cdf",
    "poisson_binomial_pmf", "resample_aggregate", "resample_indices", "verdict_line",
]
