"""How numbers are written for people: console tables, Markdown tables, plot legends."""

from __future__ import annotations

import math
import os
from contextlib import contextmanager

import numpy as np

# The width of text written to a log or a pipe: what a CI log or a terminal's default shows.
PIPE_WIDTH = 80


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
    # Counts may come back as floats from a CSV; other integral floats (an MMA of 1.0) stay floats.
    if isinstance(value, (int, np.integer)) or (is_count(key) and number.is_integer()):
        return str(int(number))
    return f"{number:.{fraction_decimals if abs(number) < 1.5 else decimals}f}"


# Columns that count things (pairs, failures, images registered, models, 3D points): an
# integral value is printed as an integer (a mean over pairs, such as n_matches', keeps decimals).
COUNT_COLUMNS = ("registered_images", "n_images", "points")


def is_count(key: str) -> bool:
    return key.startswith("n_") or key in COUNT_COLUMNS


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


def fit_columns(columns: list[str], rows: list[list[str]], right: list[bool], width: int, keep: int = 1) -> list[str]:
    """A text table as lines no wider than `width`, no cell cut: the columns two spaces apart
    (numbers right-aligned where `right` says so); where they do not fit side by side, they are
    shown in consecutive blocks, each repeating the first `keep` columns (the method) so that
    every row reads on one line. A single column wider than `width` still gets a block of its
    own (its lines are then as wide as that column)."""
    widths = [max([len(c), *(len(row[k]) for row in rows)]) for k, c in enumerate(columns)]
    keep = min(keep, len(columns))
    fixed = sum(widths[:keep]) + 2 * keep
    blocks: list[list[int]] = []
    for k in range(keep, len(columns)):
        if blocks and fixed + sum(widths[j] + 2 for j in blocks[-1]) + widths[k] <= width:
            blocks[-1].append(k)
        else:
            blocks.append([k])
    lines: list[str] = []
    for n, block in enumerate(blocks or [[]]):
        shown = [*range(keep), *block]

        def line(cells: list[str]) -> str:
            return "  ".join(
                cells[j].rjust(widths[j]) if right[j] else cells[j].ljust(widths[j]) for j in shown
            ).rstrip()

        if n:
            lines.append("")
        lines += [line(columns), "  ".join("-" * widths[j] for j in shown), *(line(row) for row in rows)]
    return lines


class LogConsole:
    """Mixed into a rich Console: a message (a line of plain text) is one physical line wherever
    the console does not write to a terminal (a pipe, a log, CI), however long, so that a log
    never breaks a sentence or a path and grep finds it whole; on a terminal rich wraps it at the
    terminal's width. Tables and listings are laid out by their own width (text_width) either way."""

    @property
    def soft_wrap(self) -> bool:
        return self._soft_wrap or not self.is_terminal

    @soft_wrap.setter
    def soft_wrap(self, value: bool) -> None:
        self._soft_wrap = value


def text_width(console) -> int:
    """The width a table or message is laid out for: the terminal's where the console writes to
    one; else COLUMNS where set, else 80. (rich alone takes the width of whichever of stdin,
    stdout and stderr is a terminal, so `cmd > log` from a wide terminal wrote lines as wide.)"""
    try:
        terminal = console.file.isatty()
    except (AttributeError, ValueError, OSError):
        terminal = False
    if terminal:
        return console.width
    columns = os.environ.get("COLUMNS", "")
    return int(columns) if columns.isdigit() and int(columns) > 0 else PIPE_WIDTH


def print_wrapped(console, line: str, hang: int = 4) -> None:
    """A line of plain text within text_width(console), words kept whole (a path too), its
    continuation lines indented `hang` spaces more than it (a listing's entries stay apart)."""
    import textwrap

    lead = len(line) - len(line.lstrip(" "))
    lines = textwrap.wrap(line, text_width(console), subsequent_indent=" " * (lead + hang), break_long_words=False,
                          break_on_hyphens=False) or [""]
    console.print("\n".join(lines), markup=False, highlight=False, soft_wrap=True)


# The file format of every plot a command writes (--format). The benchmarks name their plots
# .png (plot_run, plot_comparison); plots.py saves each in this format instead. It travels in
# the environment, not as an argument, so that the worker processes of --workers and a SLURM
# array's tasks (which write a merged run's plots) inherit it; png by default, so that
# committed results stay byte-identical.
PLOT_FORMATS = ("png", "pdf", "svg")
PLOT_FORMAT_ENV = "E3CM_BENCH_PLOT_FORMAT"


def plot_format() -> str:
    """The format plots are saved in now: --format's, else png."""
    chosen = os.environ.get(PLOT_FORMAT_ENV) or "png"
    if chosen not in PLOT_FORMATS:
        raise ValueError(f"{PLOT_FORMAT_ENV}={chosen}: the plot format is one of {', '.join(PLOT_FORMATS)}")
    return chosen


def check_plot_format(chosen: str) -> str:
    if chosen not in PLOT_FORMATS:
        raise ValueError(f"--format {chosen}: expected one of {', '.join(PLOT_FORMATS)}")
    return chosen


@contextmanager
def plots_as(chosen: str):
    """Plots written inside are saved as `chosen` (png, pdf, svg); the previous setting after."""
    previous = os.environ.get(PLOT_FORMAT_ENV)
    os.environ[PLOT_FORMAT_ENV] = check_plot_format(chosen)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(PLOT_FORMAT_ENV, None)
        else:
            os.environ[PLOT_FORMAT_ENV] = previous
