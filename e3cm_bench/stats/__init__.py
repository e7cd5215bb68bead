"""Statistics for benchmark results: pure functions, arrays in, numbers out.

bootstrap: percentile-bootstrap intervals over pairs (`bootstrap_interval`, `bootstrap_mean_interval`).
aggregate: the Poisson-binomial count of successes and resampled aggregates over rerun ensembles.
paired: two methods on the same pairs, one statistic's paired-bootstrap interval, its p and verdict (`compare_paired`).
"""

from e3cm_bench.stats.aggregate import (
    count_bounds,
    count_tail,
    poisson_binomial_cdf,
    poisson_binomial_pmf,
    resample_aggregate,
)
from e3cm_bench.stats.bootstrap import (
    BOOTSTRAP_SAMPLES,
    BOOTSTRAP_SEED,
    CONFIDENCE,
    bootstrap_interval,
    bootstrap_mean_interval,
    resample_indices,
)

# paired.py needs scipy (2-3 s to import on a small machine): its names load on first use
# (PEP 562), so that reading a constant of this package (the command line's help reads
# noise.CHECK_ALPHA) does not import scipy.
_PAIRED = ("PairedResult", "Resampling", "compare_paired", "verdict_line")


def __getattr__(name: str):
    if name in _PAIRED:
        from e3cm_bench.stats import paired

        return getattr(paired, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BOOTSTRAP_SAMPLES", "BOOTSTRAP_SEED", "CONFIDENCE", "PairedResult", "Resampling", "bootstrap_interval",
    "bootstrap_mean_interval", "compare_paired", "count_bounds", "count_tail", "poisson_binomial_cdf",
    "poisson_binomial_pmf", "resample_aggregate", "resample_indices", "verdict_line",
]
