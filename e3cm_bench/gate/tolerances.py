"""`check`'s tolerances: how far a metric may move from its baseline before it is a regression
(or a notice): ``--tolerance`` items, a ``--tolerances`` file, DEFAULT_TOLERANCES, and
`Tolerances`, which picks the most specific of them for a metric of a method.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from e3cm_bench.ground.files import read_csv

# Tolerances (absolute, in the metric's own unit: fractions for HPatches, percent for pose),
# from the spread measured over repeated demo runs (scripts/results/demo_spread.py; docs/results.md
# "Regression check"): estimator seeds 0, 1, 2 gave identical numbers (OpenCV 5's RANSAC
# ignores cv2.setRNGSeed), one CPU thread instead of two moved the deep methods' features
# by rounding and with them the scene poses: largest differences auc@5 12.1, auc@10 9.2,
# auc@20 3.3, P 0.066, MMA@3 0.000002, h_acc 0. Each tolerance is twice that, and never
# below one pair's worth for h_acc (1 of 15 pairs) or one point of MMA.
DEFAULT_TOLERANCES = {
    "mma@3": 0.01,
    "h_acc@1": 0.07,
    "h_acc@3": 0.07,
    "h_acc@5": 0.07,
    "auc@5": 25.0,
    "auc@10": 19.0,
    "auc@20": 7.0,
    "P": 0.15,
    # sfm's mAA (IMC 2020) is a mean accuracy over thresholds 1..10 degrees, as a fraction: the
    # scale of auc@10 over 100, so auc@10's tolerance in that unit (without it, `check` of an
    # sfm run failed against its own baseline: no tolerance for mAA)
    "mAA": 0.19,
}
TOLERANCE_FILE_COLUMNS = ("benchmark", "method", "metric", "tolerance")
ANY = "*"


def _tolerance_value(text, where: str) -> float:
    """A tolerance: a finite number >= 0 (a NaN one would let every change pass)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: tolerance {text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{where}: tolerance must be a finite number >= 0, got {text!r}")
    return value


def parse_tolerance_options(items: list[str] | None) -> dict[tuple[str | None, str], float]:
    """``--tolerance`` items: ``METRIC=T`` -> (None, metric), ``METHOD:METRIC=T`` -> (method, metric)."""
    tolerances: dict[tuple[str | None, str], float] = {}
    for item in items or []:
        target, sep, value = item.partition("=")
        method, colon, metric = target.rpartition(":")
        method, metric = method.strip(), metric.strip()
        if not sep or not metric or (colon and not method):
            raise ValueError(f"--tolerance: expected METRIC=VALUE (e.g. auc@10=2.5), got {item!r}")
        try:
            float(value)
        except ValueError:
            raise ValueError(f"--tolerance: expected METRIC=VALUE (e.g. auc@10=2.5), got {item!r}") from None
        tolerances[(method or None, metric)] = _tolerance_value(value, f"--tolerance {item}")
    return tolerances


def parse_tolerances(items: list[str] | None) -> dict[str, float]:
    """DEFAULT_TOLERANCES with the ``METRIC=T`` items applied (per metric, for all methods).

    A ``METHOD:METRIC=T`` item is refused here, since a per-metric table cannot hold it: use
    `Tolerances.load`, which takes both.
    """
    tolerances = dict(DEFAULT_TOLERANCES)
    for (method, metric), value in parse_tolerance_options(items).items():
        if method is not None:
            raise ValueError(f"--tolerance: {method}:{metric} is per method; use Tolerances.load")
        tolerances[metric] = value
    return tolerances


def read_tolerance_file(path: Path) -> dict[tuple[str, str, str], float]:
    """A tolerance CSV (benchmark, method, metric, tolerance; other columns ignored; ``*`` = any)
    as ``(benchmark, method, metric) -> tolerance``; a one-line ValueError naming the file for
    missing columns, empty keys, a tolerance that is no finite number >= 0, or a repeated row."""
    path = Path(path)
    table = read_csv(path, what="tolerance file")
    table.columns = [str(c).strip() for c in table.columns]
    missing = [c for c in TOLERANCE_FILE_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(
            f"{path}: missing column(s) {', '.join(missing)} (expected {', '.join(TOLERANCE_FILE_COLUMNS)})"
        )
    tolerances: dict[tuple[str, str, str], float] = {}
    lines: dict[tuple[str, str, str], int] = {}
    for index, row in table.iterrows():
        line = int(index) + 2  # the header is line 1
        key = []
        for column in TOLERANCE_FILE_COLUMNS[:3]:
            value = row[column]
            if pd.isna(value) or not str(value).strip():
                raise ValueError(f"{path}: line {line}: empty {column}")
            key.append(str(value).strip())
        key = tuple(key)
        if key in tolerances:
            raise ValueError(f"{path}: line {line}: {', '.join(key)} is also on line {lines[key]}")
        tolerances[key] = _tolerance_value(row["tolerance"], f"{path}: line {line} ({', '.join(key)})")
        lines[key] = line
    return tolerances


@dataclass
class Tolerances:
    """Which tolerance applies to a metric of a method on a benchmark, most specific first:

    1. command line for this method (``--tolerance METHOD:METRIC=T``),
    2. command line for every method (``--tolerance METRIC=T``),
    3. file rows: benchmark+method > ``*``+method > benchmark+``*`` > ``*``+``*``,
    4. DEFAULT_TOLERANCES.
    """

    defaults: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_TOLERANCES))
    rows: Mapping[tuple[str, str, str], float] = field(default_factory=dict)
    options: Mapping[tuple[str | None, str], float] = field(default_factory=dict)

    @classmethod
    def load(cls, items: list[str] | None = None, path: Path | None = None) -> Tolerances:
        """From ``--tolerance`` items and a ``--tolerances`` file (either may be absent)."""
        options = parse_tolerance_options(items)
        rows = read_tolerance_file(path) if path is not None else {}
        return cls(rows=rows, options=options)

    def get(self, benchmark: str, method: str, metric: str) -> float | None:
        candidates = (
            self.options.get((method, metric)),
            self.options.get((None, metric)),
            self.rows.get((benchmark, method, metric)),
            self.rows.get((ANY, method, metric)),
            self.rows.get((benchmark, ANY, metric)),
            self.rows.get((ANY, ANY, metric)),
            self.defaults.get(metric),
        )
        return next((value for value in candidates if value is not None), None)
