"""`e3cm-bench demo`: the whole toolkit, offline, on data it writes itself.

Writes the embedded data (synth/layouts.py: HPatches-format sequences of matplotlib's
photograph, and pairs of a non-planar room scene in the YFCC pair-list format), runs every
demo method through the ordinary benchmark runs, and writes the two tables with their
plots, a few match drawings, and which of the paper's orderings hold on these data.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from rich.console import Console

from .benchmarks import EvalSettings, get_benchmark
from .files import write_atomically
from .method import MethodSpec
from .synth.layouts import write_demo_data

BACKBONE = "efficientnet_lite0"  # the ImageNet backbone that needs no download
# label -> MethodSpec.create options; every deep method uses BACKBONE.
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
    "hpatches": ("hpatches", "HPatches-format sequences of a real photograph (homographies, photometric changes)"),
    "scenes": ("yfcc", "two views of a non-planar room scene (YFCC pair-list format)"),
}


def run_demo(
    out: str | Path = "e3cm-demo", seed: int = 0, quick: bool = False, methods: list[str] | None = None,
    viz: int = 2, device: str = "cpu", console: Console | None = None,
) -> dict[str, pd.DataFrame]:
    """Run the demo into `out`; returns each set's table (measured rows only).

    seed: the seed of every robust estimator (matching and evaluation); the data itself is
    always generated with seed 0, so runs with other seeds measure run-to-run spread.
    quick: fewer, the same kind of pairs (tests).
    """
    from .experiments import write_table  # here, not at the top: the command line's help reads METHODS
    from .runner import run_methods  # without loading scipy (cli/common.py, Startup)

    console = console or Console()
    out = Path(out)
    methods = methods or list(METHODS)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown demo method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    console.print(f"demo: writing the embedded data under {out / 'data'} (reused when present)")
    data = write_demo_data(out / "data", seed=0, quick=quick)
    roots = {"hpatches": (data["hpatches"], {}), "scenes": (data["scenes"], {"pairs": data["scenes"] / "pairs_with_gt.txt"})}
    tables = {}
    for step, (set_name, (benchmark_name, description)) in enumerate(SETS.items(), 1):
        benchmark = get_benchmark(benchmark_name)
        root, options = roots[set_name]
        dataset = benchmark.load_dataset(root, **options)
        # All methods matched together: each image goes through the backbone once for all.
        console.rule(f"demo {step}/{len(SETS)}: {set_name} - {', '.join(methods)}")
        runs = [(out / set_name / label,
                 MethodSpec.create(backbone=BACKBONE, max_side=benchmark.max_side(None), seed=seed, label=label,
                                   **METHODS[label]))
                for label in methods]
        run_methods(benchmark, runs, dataset, ev=EvalSettings(seed=seed), viz=viz, device=device, console=console)
        run_dirs = [run_dir for run_dir, _ in runs]
        console.rule(f"{set_name}: {description}; deep methods use {BACKBONE}")
        csv_path, _ = write_table(run_dirs, out / f"{set_name}_table", paper_rows=False, compare=False, console=console)
        tables[set_name] = pd.read_csv(csv_path)
    lines = orderings(tables) or ["none judged: the orderings compare e3cm, e3cm-ransac, direct and dfm"]
    text = "\n".join(f"- {line}" for line in lines) + "\n"
    write_atomically(out / "orderings.md", lambda tmp: tmp.write_text(text))
    console.print("[bold]The paper's orderings on these data[/]\n" + text)
    return tables


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
        claim("cascade precision above direct (scenes, e3cm vs direct, P)", value("scenes", "e3cm", "P"),
              value("scenes", "direct", "P"), " %"),
        claim("cascade precision above direct (scenes, e3cm-ransac vs direct, P)", value("scenes", "e3cm-ransac", "P"),
              value("scenes", "direct", "P"), " %"),
        claim("cascade MMA@3 above direct (hpatches, e3cm vs direct)", value("hpatches", "e3cm", "mma@3"),
              value("hpatches", "direct", "mma@3"), ""),
        claim("E3CM above DFM on the non-planar scene (AUC@10)", value("scenes", "e3cm", "auc@10"),
              value("scenes", "dfm", "auc@10"), " %"),
        claim("E3CM above DFM on the non-planar scene (P)", value("scenes", "e3cm", "P"), value("scenes", "dfm", "P"), " %"),
    ]
    return [line for line in found if line]
