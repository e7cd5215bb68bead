"""`e3cm-bench report`: run folders of one benchmark -> a static site one can open from the
file system or send to a colleague (no server, no network: styles and scripts are written
into each page).

It reads the runs' own files and recomputes no metric: the table comes from summary.csv
(paper layout, report.paper_table), the pair table from per_pair.csv, the plots from the
two, each run's config.yaml is copied beside it. Match drawings are made from the cached
matches (matches.h5) and coloured by ground truth as `--viz` colours them; they are bounded
in number (the worst pairs and an even sample) and in size, so a 4000-pair run stays small.

    OUT/index.html            table, plots, runs, the pair table (sortable; filter such as
                              "pairs where A fails and B does not", kept in the URL's #hash)
    OUT/pairs/<pair>.html     one drawing per method, side by side, with the pair's numbers
    OUT/runs/<k>/             config.yaml, summary.csv, per_pair.csv, the run's plot
    OUT/img/                  comparison plots and the drawings (JPEG)

Here: the report made and written; its folder and the swap in site_folder.py, the drawings in
drawings.py, the HTML in pages.py.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from e3cm_bench.drawing.plots import plot_cost_accuracy
from e3cm_bench.ground.files import create_new, write_atomically
from e3cm_bench.ground.locks import writable_folder
from e3cm_bench.reporting.drawings import choose_pairs, draw_pairs, pair_rows
from e3cm_bench.reporting.pages import index_page, script_json, write_pair_page  # noqa: F401 - script_json: its old home
from e3cm_bench.reporting.runs import Run, load_run
from e3cm_bench.reporting.site_folder import MARKER, REPORT_ENTRIES, report_target, swap_in, terminate_as_exception  # noqa: F401
from e3cm_bench.reporting.tables import paper_reference, paper_set_notes, paper_table, without_comparison

@dataclass
class Report:
    index: Path
    pairs: list[str]      # the pairs with a page of drawings
    drawings: int
    notes: list[str]


def write_report(run_dirs: list[Path], out: Path, console: Console | None = None, reference: Path | None = None,
                 compare: bool = True) -> Report:
    """The site for `run_dirs` (one benchmark) under `out`; returns where it is and what it holds.
    compare=False leaves out the paper's rows and the differences (data that is not the paper's)."""
    console = console or Console()
    if not run_dirs:
        raise ValueError("report: give at least one run folder")
    runs = [load_run(d) for d in run_dirs]
    kinds = sorted({r.benchmark.name for r in runs})
    if len(kinds) > 1:
        listing = "; ".join(f"{k}: {', '.join(str(r.dir) for r in runs if r.benchmark.name == k)}" for k in kinds)
        raise ValueError(f"report: runs of different benchmarks ({listing}); one report per benchmark")
    labels = [r.label for r in runs]
    if len(set(labels)) != len(labels):
        raise ValueError(
            f"report: two runs share a label ({', '.join(sorted({l for l in labels if labels.count(l) > 1}))}); "
            "give each its own --label"
        )
    for run in runs:
        if run.per_pair.empty:
            raise ValueError(f"{run.folder.per_pair_path}: missing or empty; the report reads each run's pairs from it")
    benchmark = runs[0].benchmark
    target = report_target(Path(out))
    # Built in a new folder beside the target and swapped in whole at the end: a failure or a
    # signal on the way leaves the previous report as it was (and the half-built one removed).
    writable_folder(target.parent)
    built = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".report-tmp", dir=target.parent))
    try:
        with terminate_as_exception():
            report, line = _build(runs, benchmark, built, Path(out) / "index.html", reference, compare)
            swap_in(built, target)
    finally:
        shutil.rmtree(built, ignore_errors=True)  # the half-built report, or the previous one swapped out
    console.print(line, markup=False)
    for note in report.notes:
        console.print(f"[yellow]note[/]: {escape(str(note))}", highlight=False)
    return report


def _build(runs: list[Run], benchmark, out: Path, index: Path, reference: Path | None,
           compare: bool) -> tuple[Report, str]:
    """The site written into the new folder `out` (index: where its index.html will be), and the
    line that says what it holds."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(out, 0o777 & ~umask)  # mkdtemp makes it 0700; a report folder is as any other
    with create_new(out / MARKER) as f:  # first: a folder holding it is a report, to be replaced whole
        f.write(b"written by e3cm-bench report; the next report into this folder replaces it whole\n")
    for sub in ("runs", "pairs", "img"):
        (out / sub).mkdir()
    if reference is None and benchmark.paper_table and compare:
        candidate = paper_reference(benchmark)
        reference = candidate if candidate is not None and candidate.is_file() else None
    table = paper_table(runs, benchmark, reference)
    if not compare:
        table = without_comparison(table, vs_paper=True)
    notes: list[str] = paper_set_notes(table)  # a run on other pairs than the paper's: said first
    comparison = _comparison(runs, notes)
    plots = [p.relative_to(out).as_posix() for p in
             benchmark.plot_comparison({r.label: (r.summary, r.per_pair) for r in runs}, out / "img" / "comparison")]
    timed = {r.label: r.summary for r in runs if "seconds_per_pair" in r.summary}
    # accuracy against cost: the benchmark's middle threshold (h_acc@3, AUC@10) or its one metric;
    # none for reconstruct's runs, which have no metric (no ground truth)
    if timed and benchmark.table_metrics:
        metrics = list(benchmark.table_metrics.values())
        metric = metrics[1] if len(metrics) > 1 else metrics[0]
        plots.append(plot_cost_accuracy(timed, metric, out / "img" / "cost_accuracy.png").relative_to(out).as_posix())
    run_links = [_copy_run(run, out / "runs" / f"{k:02d}") for k, run in enumerate(runs, start=1)]
    pairs = pair_rows(runs)
    chosen = choose_pairs(pairs, runs)
    drawings = draw_pairs(runs, chosen, out, notes)
    for name in chosen:
        write_pair_page(out, name, runs, pairs, drawings)
    page = index_page(runs, table, plots, run_links, pairs, set(chosen), notes, comparison)
    write_atomically(out / "index.html", lambda tmp: tmp.write_text(page))
    n_drawings = sum(len(v) for v in drawings.values())
    line = f"report: {index} ({len(runs)} runs, {len(pairs)} pairs, {len(chosen)} pair pages, {n_drawings} drawings)"
    return Report(index, chosen, n_drawings, notes), line


# --------------------------------------------------------------------------- data


def _comparison(runs: list[Run], notes: list[str]):
    """The paired comparison of exactly two runs (compare_runs), or None; why not, in the notes."""
    from e3cm_bench.reporting.compare import compare_runs

    if len(runs) != 2:
        return None
    try:
        return compare_runs(runs[0], runs[1])
    except ValueError as error:
        notes.append(f"no paired comparison: {error}")
        return None


def _copy_run(run: Run, folder: Path) -> dict:
    folder.mkdir(parents=True)
    files = {}
    own = run.folder
    # the run's record and tables, and its plot (each benchmark draws one of these two)
    for name in (own.CONFIG, own.SUMMARY, own.PER_PAIR, "mma.png", "pose_error_cdf.png"):
        if (run.dir / name).is_file():
            shutil.copy(run.dir / name, folder / name)
            files[name] = (folder / name).relative_to(folder.parents[1]).as_posix()
    return files
