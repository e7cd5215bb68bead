"""`e3cm-bench demo`: the whole toolkit, offline, on data it writes itself.

Writes the embedded data (synth/layouts.py: HPatches-format sequences of matplotlib's
photograph, and pairs of a non-planar room scene in the YFCC pair-list format), runs every
demo method through the ordinary benchmark runs, and writes the two tables with their
plots, a few match drawings, and which of the paper's orderings hold on these data.

The console gets a short account (a line per set and per method, at most 80 columns: the
headline numbers with their intervals, then the orderings); everything the runs print (each
run's summary table, the Markdown tables) goes to OUT/demo.log.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from rich.console import Console

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.backbones.names import OFFLINE_BACKBONE
from e3cm_bench.ground.files import write_atomically
from e3cm_bench.apps.synth.layouts import write_demo_data

BACKBONE = OFFLINE_BACKBONE  # the ImageNet backbone that needs no download
# label -> method options (options.METHOD_OPTIONS); every deep method uses BACKBONE.
METHODS = {
    "e3cm": {"matcher": "e3cm"},
    "e3cm-release": {"matcher": "e3cm-release"},
    "e3cm-ransac": {"matcher": "e3cm-ransac"},
    "e3cm-plus": {"matcher": "e3cm-plus"},
    "direct": {"matcher": "direct"},
    "dfm": {"matcher": "dfm"},
    "sift": {"matcher": "sift"},
}
# set name -> (benchmark, what the data is)
SETS = {
    "hpatches": ("hpatches", "HPatches format, a real photograph"),
    "scenes": ("yfcc", "two views of a non-planar room, YFCC format"),
}
# set name -> the table columns the console shows, the first the headline. HPatches' is h_acc@1:
# on these clean synthetic warps nearly every method is within 3 px on every pair (h_acc@3
# near 1.00 for all), while 1 px tells them apart; the Markdown tables hold @3 and @5 too.
HEADLINES = {"hpatches": ("h_acc@1", "h_acc@3", "mma@3"), "scenes": ("auc@10", "auc@20", "P")}
LOG = "demo.log"


@dataclass(frozen=True)
class _Demo:
    """What every set of one demo shares: the folder, the methods, the seed, the drawings per
    run, the device, and the two consoles (the short account and the log)."""

    out: Path
    methods: list[str]
    seed: int
    viz: int
    device: str
    console: Console
    log: Console


def run_demo(
    out: str | Path = "e3cm-demo", seed: int = 0, quick: bool = False, methods: list[str] | None = None,
    viz: int = 2, device: str = "cpu", console: Console | None = None,
) -> dict[str, pd.DataFrame]:
    """Run the demo into `out`; returns each set's table (measured rows only).

    seed: the seed of every robust estimator (matching and evaluation); the data itself is
    always generated with seed 0, so runs with other seeds measure run-to-run spread.
    quick: fewer pairs of the same kinds (10 HPatches-format pairs, viewpoint and illumination,
    and 2 scene pairs), for a first look and the tests.
    console: the short account; the runs' own output goes to OUT/demo.log.
    """
    console = console or Console()
    out = Path(out)
    methods = methods or list(METHODS)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown demo method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    data = write_demo_data(out / "data", seed=0, quick=quick)
    roots = {
        "hpatches": (data["hpatches"], {}),
        "scenes": (data["scenes"], {"pairs": data["scenes"] / "pairs_with_gt.txt"}),
    }
    for line in (f"demo{' --quick' if quick else ''}: {', '.join(methods)}",
                 f"deep methods on {BACKBONE}; data in {out / 'data'}; the runs' output: {out / LOG}"):
        console.print(line, markup=False, highlight=False)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / LOG, "w", encoding="utf-8") as log_file:
        # The runs' own account (settings, progress, each run's table, the Markdown tables): kept
        # whole in the log (this run's: a rerun writes its own), at a width that keeps tables intact.
        log = Console(file=log_file, width=120, force_terminal=False, color_system=None)
        demo = _Demo(out, methods, seed, viz, device, console, log)
        tables = {set_name: _run_set(demo, step, set_name, roots[set_name]) for step, set_name in enumerate(SETS, 1)}
    lines = orderings(tables) or ["none judged: the orderings compare e3cm, e3cm-ransac, direct and dfm"]
    text = "\n".join(f"- {line}" for line in lines) + "\n"
    write_atomically(out / "orderings.md", lambda tmp: tmp.write_text(text))
    console.print("The paper's orderings on these data:", markup=False, highlight=False)
    for line in lines:
        console.print(f"- {line}", markup=False, highlight=False)  # whole in a log (LogConsole)
    return tables


def _run_set(demo: _Demo, step: int, set_name: str, data: tuple) -> pd.DataFrame:
    """One set of the demo: every method's run (through the benchmark's one path to a method,
    Benchmark.resolve_method, under its default protocol), then its table; returns the table."""
    # here, not at the top: the command line's help reads METHODS
    from e3cm_bench.pipeline.experiments import write_table
    from e3cm_bench.pipeline.runner import run_methods  # without loading scipy (cli/common.py, Startup)

    benchmark_name, description = SETS[set_name]
    benchmark = get_benchmark(benchmark_name)
    root, options = data
    dataset = benchmark.load_dataset(root, **options)
    demo.log.rule(f"demo {step}/{len(SETS)}: {set_name} - {', '.join(demo.methods)}")
    demo.console.print(f"{step}/{len(SETS)} {set_name}: {_pairs_text(dataset)}, {description}", markup=False,
                       highlight=False)
    runs = [(demo.out / set_name / label,
             benchmark.resolve_method(backbone=BACKBONE, seed=demo.seed, label=label, **METHODS[label]))
            for label in demo.methods]
    started = time.monotonic()
    # All methods matched together: each image goes through the backbone once for all. The
    # spinner is drawn on a terminal only; a log or a pipe gets the lines below.
    with demo.console.status(f"{set_name}: matching {len(dataset)} pairs with {len(demo.methods)} methods"):
        run_methods(benchmark, runs, dataset, ev=benchmark.resolve_eval(seed=demo.seed), viz=demo.viz,
                    device=demo.device, console=demo.log)
        csv_path, _ = write_table([run_dir for run_dir, _ in runs], demo.out / f"{set_name}_table", paper_rows=False,
                                  compare=False, console=demo.log)
    table = pd.read_csv(csv_path)
    for line in headline_lines(table, HEADLINES[set_name], time.monotonic() - started):
        demo.console.print(line, markup=False, highlight=False)
    return table


def _pairs_text(dataset) -> str:
    """'10 pairs (5 illumination, 5 viewpoint)' for HPatches-format data, else '2 pairs'."""
    kinds = pd.Series([p.sequence[:2] for p in dataset]).value_counts()
    names = {"i_": "illumination", "v_": "viewpoint"}
    split = ", ".join(f"{kinds[k]} {names[k]}" for k in sorted(kinds.index) if k in names)
    return f"{len(dataset)} pairs" + (f" ({split})" if split else "")


def headline_lines(table: pd.DataFrame, columns: tuple[str, ...], seconds: float) -> list[str]:
    """The console's account of a set: a header, then a line per method with its numbers, each
    with its bootstrap interval, at most 80 columns for up to 3 columns and 14-character labels."""
    shown = [c for c in columns if c in table.columns]
    digits = {c: 1 if c.startswith(("auc", "P")) else 2 for c in shown}  # pose numbers are percent
    width = max([6, *(len(str(m)) for m in table["method"])])
    cells = []
    for _, row in table.iterrows():
        parts = []
        for c in shown:
            value, lo, hi = (row.get(k) for k in (c, f"{c}_lo", f"{c}_hi"))
            d = digits[c]
            text = "-" if pd.isna(value) else f"{value:.{d}f}"
            if not (pd.isna(value) or pd.isna(lo) or pd.isna(hi)):
                text += f" [{lo:.{d}f},{hi:.{d}f}]"
            parts.append(text)
        cells.append((str(row["method"]), parts))
    col_width = {c: max([len(c), *(len(parts[i]) for _, parts in cells)]) for i, c in enumerate(shown)}
    lines = [f"  {'method':<{width}}  " + "  ".join(f"{c:>{col_width[c]}}" for c in shown)]
    for method, parts in cells:
        lines.append(f"  {method:<{width}}  " + "  ".join(f"{p:>{col_width[c]}}" for p, c in zip(parts, shown)))
    levels = table["confidence"].dropna().unique() if "confidence" in table.columns else []
    level = f"{levels[0]:.0%}" if len(levels) == 1 else "95%"
    lines.append(f"  ({len(cells)} methods in {seconds:.0f} s; value [{level} bootstrap interval over the pairs])")
    return lines


def orderings(tables: dict[str, pd.DataFrame]) -> list[str]:
    """Which of the paper's claims hold on the demo's tables, as they came out."""

    def value(set_name: str, method: str, column: str) -> float | None:
        table = tables.get(set_name)
        if table is None or method not in set(table["method"]):
            return None
        return float(table.set_index("method").loc[method, column])

    def claim(text: str, a: float | None, b: float | None, unit: str) -> str | None:
        if a is None or b is None:
            return None
        verdict = "holds" if a > b else "does not hold"
        digits = 3 if max(abs(a), abs(b)) < 1.5 else 2  # fractions need more digits to be told apart
        return f"{text}: {verdict} ({a:.{digits}f} vs {b:.{digits}f}{unit})"

    found = [
        claim(
            "cascade precision above direct (scenes, e3cm vs direct, P)",
            value("scenes", "e3cm", "P"),
            value("scenes", "direct", "P"),
            " %",
        ),
        claim(
            "cascade precision above direct (scenes, e3cm-ransac vs direct, P)",
            value("scenes", "e3cm-ransac", "P"),
            value("scenes", "direct", "P"),
            " %",
        ),
        claim(
            "cascade MMA@3 above direct (hpatches, e3cm vs direct)",
            value("hpatches", "e3cm", "mma@3"),
            value("hpatches", "direct", "mma@3"),
            "",
        ),
        claim(
            "E3CM above DFM on the non-planar scene (AUC@10)",
            value("scenes", "e3cm", "auc@10"),
            value("scenes", "dfm", "auc@10"),
            " %",
        ),
        claim(
            "E3CM above DFM on the non-planar scene (P)",
            value("scenes", "e3cm", "P"),
            value("scenes", "dfm", "P"),
            " %",
        ),
    ]
    return [line for line in found if line]
