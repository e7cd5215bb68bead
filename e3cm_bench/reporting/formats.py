"""How numbers are written for people: console tables, Markdown tables, plot legends."""

from __future__ import annotations

import math

import numpy as np


def format_number(value, key: str, decimals: int = 2, fraction_decimals: int = 2) -> str:
    """One number as text: '-' when missing, pair counts as integers, differences signed.

    Values below 1.5 are fractions (MMA, h_acc) and get ``fraction_decimals``; counts,
    degrees and percents get ``decimals``. Text passes through.
    """
    if isinstance(value, str):
        return value
    try:
        number = float(value)
    except (TypeError, ValueError):
        return "-"
    if math.isnan(number):
        return "-"
    if key.startswith("d_"):
        return f"{number:+.{decimals}f}"
    # Pair counts may come back as floats from a CSV; other integral floats (an MMA of 1.0) stay floats.
    if isinstance(value, (int, np.integer)) or (key.startswith("n_pairs") and number.is_integer()):
        return str(int(number))
    return f"{number:.{fraction_decimals if abs(number) < 1.5 else decimals}f}"


def format_interval(value, lo, hi, key: str, decimals: int = 2, fraction_decimals: int = 2) -> str:
    """A number with its interval, ``0.73 [0.47, 0.93]``; the number alone when a bound is missing.

    The bounds are written as the number is (same decimals, a sign for differences), so that
    the three read as one.
    """
    text = format_number(value, key, decimals, fraction_decimals)
    try:
        lo, hi = float(lo), float(hi)
    except (TypeError, ValueError):
        return text
    if text == "-" or math.isnan(lo) or math.isnan(hi):
        return text
    # The bounds take the number's own precision, so 0.9 and its bound 1.6 keep one format.
    places = fraction_decimals if abs(float(value)) < 1.5 and not key.startswith("d_") else decimals
    sign = "+" if key.startswith("d_") else ""
    return f"{text} [{lo:{sign}.{places}f}, {hi:{sign}.{places}f}]"
