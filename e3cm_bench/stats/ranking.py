"""How two rankings of the same methods agree: each method's rank by its value, and Kendall's
tau-b between two sets of values (the sweep's cells against its default cell, pipeline/sweep.py)."""

from __future__ import annotations


def ranks(values: dict[str, float]) -> dict[str, int]:
    """1 = the highest value; ties share the better rank."""
    ordered = sorted(values.values(), reverse=True)
    return {label: 1 + ordered.index(value) for label, value in values.items()}


def kendall_tau(first: dict[str, float], second: dict[str, float]) -> tuple[float, float]:
    """Kendall's tau-b of two cells' values of the same methods, and its p (scipy.stats)."""
    from scipy.stats import kendalltau

    labels = list(first)
    if len(labels) < 2:
        return float("nan"), float("nan")
    found = kendalltau([first[k] for k in labels], [second[k] for k in labels])
    return float(found.statistic), float(found.pvalue)
