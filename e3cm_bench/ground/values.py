"""The kinds of value an option takes, one table for every section of a run's options.

A method option (method/options.py), an evaluation option (benchmarks/eval_options.py), a
benchmark's dataset option (benchmarks/base.py DatasetOption) and a run option
(pipeline/request.py) each name a kind here: its test of a value given as data (a config's, a
record's, the Python API's), the words of its error, and its type on the command line; a number
kind may add a `Range`. `check_value` is the one check, `KindOf` what a declared option gets from
its kind. It imports nothing of the package, so that every section reads it from below.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Optional


# ---- the kinds of value an option (a method's or a dataset's) takes, each: its test in a config
# or an API call, the words an error uses, and its type on the command line. One table for both
# the method options below and the benchmarks' DatasetOption (benchmarks/base.py).
def _text(value) -> bool:
    return isinstance(value, str) and value.strip() != ""


def _whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _number(value) -> bool:
    # finite: NaN passes no comparison (a NaN threshold fails every pair) and inf none that means anything
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value) -> bool:
    return _number(value) or isinstance(value, (list, tuple)) and bool(value) and all(_number(v) for v in value)


def _texts(value) -> bool:
    return _text(value) or isinstance(value, (list, tuple)) and bool(value) and all(_text(v) for v in value)


def _path(value) -> bool:
    return _text(value) or isinstance(value, Path)


def _paths(value) -> bool:
    return _path(value) or isinstance(value, (list, tuple)) and bool(value) and all(_path(v) for v in value)


@dataclass(frozen=True)
class Kind:
    """test: whether a value (a config's, an API caller's) is of this kind; wanted: the words of
    its error; cli: the type typer reads (a list: the option repeated)."""

    test: Callable[[object], bool]
    wanted: str
    cli: type
    ranged: str = ""  # what it says before a range, where that differs ("a whole number", not ">= 0")


# YAML reads `no` and `"no"` differently; a flag takes true/false only, since a quoted "no" is truthy.
KINDS: dict[str, Kind] = {
    "flag": Kind(lambda v: isinstance(v, bool), "true or false", bool),
    "text": Kind(_text, "non-empty text", str),
    "path": Kind(_path, "non-empty text", Path),
    "paths": Kind(_paths, "text or a list of texts", list[Path]),
    "names": Kind(_texts, "text or a list of texts", list[str]),
    "whole": Kind(_whole, "a whole number >= 0", int, "a whole number"),
    "number": Kind(_number, "a finite number", float),
    # comma-separated on the command line ("0.9,0.9,0.95"), a number or a list in a config
    "numbers": Kind(_numbers, "a number or a list of numbers (finite)", str),
    # --set KEY=VALUE (repeatable) on the command line, a mapping in a config
    "mapping": Kind(lambda v: isinstance(v, Mapping), "a mapping of NAME: VALUE", list[str]),
}


# The kinds a benchmark's dataset option may be (benchmarks/base.py DatasetOption).
DATASET_KINDS = ("flag", "path", "paths", "names", "text")


@dataclass(frozen=True)
class Range:
    """The values an option of a number kind allows besides its kind: from `low` to `high` (None:
    no bound that side), each end included unless `low_open`/`high_open` excludes it."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def holds(self, value) -> bool:
        """Whether `value` (a number, or each of a list) lies in the range."""
        if isinstance(value, (list, tuple)):
            return all(self.holds(v) for v in value)
        return not (self.low is not None and (value < self.low or self.low_open and value == self.low)
                    or self.high is not None and (value > self.high or self.high_open and value == self.high))

    def words(self) -> str:
        """What an error says the range is: "above 0 and at most 1,000", "1 to 1,000,000"."""
        low = None if self.low is None else ("above " if self.low_open else "at least ") + f"{self.low:,}"
        high = None if self.high is None else ("below " if self.high_open else "at most ") + f"{self.high:,}"
        if low and high and not (self.low_open or self.high_open):
            return f"from {self.low:,} to {self.high:,}"
        return " and ".join(w for w in (low, high) if w)


def check_value(value, kind: str, bounds: Range | None, name: str) -> None:
    """The one check of a value given as data (a record's, a config's, the Python API's, a flag's
    after typer read it): of `kind` (options.KINDS), then in `bounds`; a one-line ValueError
    naming `name` (a flag, a key), what is allowed and the value otherwise."""
    of = KINDS[kind]
    wanted = of.wanted if bounds is None else f"{of.ranged or of.wanted}, {bounds.words()}"
    if not KINDS[kind].test(value) or bounds is not None and not bounds.holds(value):
        raise ValueError(f"{name} must be {wanted}, got {value!r}")


class KindOf:
    """What its kind gives an option declared as data (a method's here, an evaluation's in
    benchmarks/eval_options.py, a run's in pipeline/request.py): the check that the kind exists,
    the one check of a value (`check`: kind and range), and the type typer reads."""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"option {self.name}: kind {self.kind!r} is not one of {', '.join(KINDS)}")

    @property
    def shown(self) -> str:
        """The name an error gives the option: its (first) flag."""
        flags = getattr(self, "flags", None)
        return flags[0] if flags else getattr(self, "flag", self.name)

    def check(self, value, name: str | None = None) -> None:
        """`value` of the option's kind and in its range (None: not given, the default); a one-line
        ValueError naming `name` (a config's or a record's key; default: the flag) otherwise."""
        if value is not None:
            check_value(value, self.kind, getattr(self, "range", None), name or self.shown)

    @property
    def cli_type(self):
        """The annotation typer reads: the kind's type, Optional where the default is None."""
        base = KINDS[self.kind].cli
        return Optional[base] if self.default is None else base
