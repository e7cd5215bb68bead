"""What a paper-layout table says beside its numbers (reporting/tables.py): the pairs a measured
row and its paper row each hold, what the paper's rows were measured on, the rows that could not
run and why, and a cost taken under load. Each is a text column of the table, shown as a note
below it (`paper_set_notes`) in the terminal, the Markdown and the report."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import pandas as pd

from e3cm_bench.backbones.names import DEFAULT_BACKBONE
from e3cm_bench.benchmarks import Benchmark
from e3cm_bench.ground.cost import under_load
from e3cm_bench.reporting.runs import Run

# A table's column saying, for a measured row compared with a paper row on other pairs than the
# paper's, which pairs each side holds (empty where the pair sets are the same, or no paper row);
# on the first paper row, what the paper's rows were measured on; on a row not run, why.
OTHER_PAIRS = "other_pairs"
OTHER_PAIRS_MARK = "other pairs"  # beside such a row's differences, instead of "outside CI"
NOT_RUN = "not run"  # the source of a row that could not run here (its note says why: `with_not_run`)
# A table's column saying, for a measured row whose time was taken on a loaded machine, how loaded
# (ground/cost.py under_load); its seconds_per_pair cell is marked UNDER_LOAD_MARK.
COST_NOTE = "cost_note"
UNDER_LOAD_MARK = "under load"

# The pair sets the paper's tables were measured on: the pair counts that are that set, and its name.
PAPER_SETS = {
    "table1.csv": ((540, 580), "the full HPatches sequences (540 or 580 pairs; the paper does not say which)"),
    "table2.csv": ((1500,), "MegaDepth-1500 (1500 pairs)"),
    "table3.csv": ((4000,), "the YFCC100M test list (4000 pairs)"),
}


def other_pairs(run: Run, benchmark: Benchmark) -> str:
    """'15 pairs; the paper: <its set>' where the run's pairs are not the paper's set, else ''."""
    counts, name = PAPER_SETS.get(benchmark.paper_table or "", ((), ""))
    n = run.summary.get("n_pairs")
    try:
        n = int(n) if n is not None and n == n else len(run.per_pair)
    except (TypeError, ValueError):
        n = len(run.per_pair)
    if not counts or n in counts:
        return ""
    return f"{n} pairs; the paper: {name}"


def paper_rows_note(runs: Sequence[Run], benchmark: Benchmark, n_paper: int) -> str:
    """'' where the runs are on the paper's pair set with its backbone, else what each side is:
    12 rows of the full set on VGG19 above 15 pairs on Lite0 were put side by side without a word."""
    counts, name = PAPER_SETS.get(benchmark.paper_table or "", ((), "the paper's data"))
    pairs = sorted({other_pairs(run, benchmark).split(" pairs;")[0] or "the paper's" for run in runs})
    backbones = sorted({str((run.config.get("identity") or {}).get("backbone")) for run in runs} - {"None"})
    if pairs == ["the paper's"] and set(backbones) <= {DEFAULT_BACKBONE}:
        return ""
    return (f"The {n_paper} paper rows are the paper's published numbers on {name}, its deep methods on "
            f"{DEFAULT_BACKBONE}; the measured rows are on {' or '.join(pairs)} pairs"
            + (f", deep methods on {', '.join(backbones)}" if backbones else "") + ": not measured alike.")


def cost_note(run: Run) -> str:
    """'' unless the run's match stage ran on a loaded machine (config.yaml timing.load, or a
    merged run's shards' timing), else how loaded it was."""
    record = run.config
    timings = [record.get("timing") or {}, *(((record.get("shards") or {}).get("timing") or {}).values())]
    return next((note for note in (under_load(t.get("load")) for t in timings if isinstance(t, Mapping)) if note),
                "")


def with_not_run(table: pd.DataFrame, not_run: Mapping[str, str]) -> pd.DataFrame:
    """The table and a row of source 'not run' for each {label: why} (a peer offline), why in its note."""
    rows = [{"method": label, "source": NOT_RUN, OTHER_PAIRS: f"{label} was not run: {why}"}
            for label, why in not_run.items()]
    columns = [*table.columns, *([] if OTHER_PAIRS in table.columns else [OTHER_PAIRS])]
    return pd.concat([table, pd.DataFrame(rows, columns=columns)], ignore_index=True)


def paper_set_notes(table: pd.DataFrame) -> list[str]:
    """One line per measured row compared with a paper number measured on other pairs: which
    pairs each side holds, and that the difference is therefore no regression (nor a gain); first,
    where the paper's rows were measured on other pairs or backbones than the runs, that; a row
    not run, why; a cost taken under load, how loaded the machine was."""
    notes = []
    for record in table.to_dict("records"):
        other, cost = record.get(OTHER_PAIRS), record.get(COST_NOTE)
        if record.get("source") in ("paper", NOT_RUN) and isinstance(other, str) and other:
            notes.append(other)  # what the paper's rows were measured on; why a row was not run
        elif isinstance(other, str) and other:
            n, _, paper = other.partition("; the paper: ")
            notes.append(f"{record['method']} is measured on {n}, {record['vs_paper']} in the paper on {paper}: "
                         f"its d_ columns compare two different pair sets, so they show neither a regression nor "
                         f"an improvement (its interval, over its own pairs, says nothing about them).")
        if isinstance(cost, str) and cost:
            notes.append(f"{record['method']}: {cost}; its time is not what an idle machine takes.")
    return notes
