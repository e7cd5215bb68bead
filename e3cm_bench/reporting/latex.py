"""A paper table as LaTeX: booktabs rules, each number with its interval as the CSV and the
Markdown hold it (``0.73 [0.53, 0.93]``), the best value of each compared column in bold.

The table is a bare ``tabular`` to ``\\input`` into a paper whose preamble loads booktabs. It
holds the method and its numbers: the differences from the paper, the protocol and the paper
row compared with stay in the CSV and the Markdown (they explain a run, a paper prints none).
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from e3cm_bench.benchmarks import intervals
from e3cm_bench.ground.files import write_atomically
from e3cm_bench.drawing.formats import format_interval, format_number, is_count
from e3cm_bench.reporting.tables import display_cells

# What LaTeX reads as a command in text mode, and what it takes to print it.
_SPECIALS = {"&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{", "}": r"\}",
             "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "\\": r"\textbackslash{}"}
# Columns a paper table leaves out: they explain a measured row; the CSV keeps them.
_LEFT_OUT = ("source", "vs_paper", "protocol")


def escape(text: str) -> str:
    """Text with LaTeX's special characters printed as themselves."""
    return "".join(_SPECIALS.get(char, char) for char in str(text))


def lower_is_better(column: str) -> bool:
    """An error (a reprojection error, a pose error) is best lowest; every other compared
    column (accuracy, AUC, precision, mAA, MMA, recall) highest."""
    return "error" in column


# Figures that describe a reconstruction rather than score it: no best among them.
_DESCRIPTIVE = ("mean_track_length",)


def compared_columns(table: pd.DataFrame, columns: list[str]) -> list[str]:
    """The columns whose best value is bold: the paper's metrics and the measured numbers with an
    interval; never a count (how much was run or registered: formats.is_count) or a descriptive
    figure."""
    with_interval = {
        c for c in columns if intervals.lo_key(c) in table.columns and table[intervals.lo_key(c)].notna().any()
    }
    paper_metrics = {
        c for c in columns if c in table.columns and table.loc[table["source"] == "paper", c].notna().any()
    }
    return [c for c in columns if c in with_interval | paper_metrics and not is_count(c) and c not in _DESCRIPTIVE]


def best_rows(table: pd.DataFrame, column: str) -> set[int]:
    """The rows holding the column's best value as printed (ties at the printed precision all bold)."""
    shown = {}
    for k, value in enumerate(table[column]):
        text = format_number(value, column)
        try:
            number = float(text)
        except ValueError:
            continue
        if not math.isnan(number):
            shown[k] = number
    if not shown:
        return set()
    best = (min if lower_is_better(column) else max)(shown.values())
    return {k for k, number in shown.items() if number == best}


def _cell(record: dict, column: str, bold: bool) -> str:
    value = record[column]
    lo, hi = record.get(intervals.lo_key(column)), record.get(intervals.hi_key(column))
    text = format_interval(value, lo, hi, column) if lo is not None else format_number(value, column)
    if text == "-":
        return "--"
    number, _, bounds = text.partition(" ")
    number = rf"\textbf{{{escape(number)}}}" if bold else escape(number)
    return f"{number} {escape(bounds)}".strip()


def table_to_latex(table: pd.DataFrame, caption: str | None = None) -> str:
    """The table (tables.paper_table's layout) as a booktabs ``tabular`` in a ``table`` float with
    `caption` (escaped): the paper's rows, a rule, the measured rows; the method left, the
    numbers right."""
    shown, _, _ = display_cells(table)
    columns = [c for c in shown if c not in _LEFT_OUT and not c.startswith("d_")]
    bold = {c: best_rows(table, c) for c in compared_columns(table, columns[1:])}
    records = table.to_dict("records")
    lines = [r"\begin{table}", r"\centering", r"\begin{tabular}{l" + "r" * (len(columns) - 1) + "}", r"\toprule",
             " & ".join(escape(c) for c in columns) + r" \\", r"\midrule"]
    previous = None
    for k, record in enumerate(records):
        if previous is not None and record["source"] != previous:
            lines.append(r"\midrule")  # the paper's rows, then the measured ones
        previous = record["source"]
        method = escape(record[columns[0]])
        cells = ["{}" + method if method.startswith("[") else method]  # else `\\ [` reads as a row's spacing
        cells += [_cell(record, c, k in bold.get(c, set())) for c in columns[1:]]
        lines.append(" & ".join(cells) + r" \\")
    confidence = next((r.get("confidence") for r in records if r.get("confidence") == r.get("confidence")
                       and r.get("confidence") is not None), None)
    said = (f"[lo, hi]: {float(confidence):.0%} bootstrap interval over the pairs; bold: the best of each column"
            if confidence is not None else "bold: the best of each column")
    lines += [r"\bottomrule", r"\end{tabular}", r"\caption{" + escape(caption if caption else said) + "}",
              r"\end{table}"]
    return "\n".join([r"% needs \usepackage{booktabs}", f"% {said}", *lines]) + "\n"


def write_latex_table(table: pd.DataFrame, out_path: str | Path, caption: str | None = None) -> Path:
    """Write ``<out_path>.tex`` (any given suffix is replaced)."""
    text = table_to_latex(table, caption)
    return write_atomically(Path(out_path).with_suffix(".tex"), lambda tmp: tmp.write_text(text))
