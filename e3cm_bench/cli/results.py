"""Commands over run folders: table, report, compare, reproduce, merge, demo and the regression check."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.text import Text

from e3cm_bench.apps.demo import METHODS as DEMO_METHODS
from e3cm_bench.paper import config_names, resolve_config
from e3cm_bench.stats.noise import CHECK_ALPHA
from e3cm_bench.cli.common import (app, console, DeviceOpt, friendly_errors, ShardOpt, LauncherOpt, ShardsOpt, RootOpt,
                                   OutOpt, MaxSideOpt, LimitOpt, VizOpt, SkipBadOpt, CompareOpt, PlotFormatOpt,
                                   PairTimeoutOpt, OverwriteOpt, typed_only)


@app.command()
@friendly_errors
def table(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders (each with config.yaml and summary.csv), one "
                                                        "benchmark.")],
    out: Annotated[str, typer.Option("--out", metavar="PATH", help="The table's file stem: STEM.csv, STEM.md (STEM.tex "
                                     "with --latex) and STEM_<plot>.png; an existing folder (or a path ending in /) "
                                     "gets table.* inside it.")],  # text: a Path drops the trailing / (a folder)
    reference: Annotated[Optional[Path], typer.Option("--reference",
                                                      help="Paper numbers (default: the shipped "
                                                           "e3cm_bench/paper/tableN.csv).")] = None,
    compare: CompareOpt = True,
    latex: Annotated[bool, typer.Option("--latex",
                                        help="Also write OUT.tex: a booktabs table for a paper (each number with its "
                                             "interval, the best per column in bold).")] = False,
    paper: Annotated[bool, typer.Option("--paper/--no-paper",
        help="The paper's rows above the runs' (--no-paper: the runs' rows only).")] = True,
    plot_format: PlotFormatOpt = "png",
    metrics: Annotated[Optional[str], typer.Option("--metrics",
                                                   help="Comma-separated columns to keep, e.g. auc@10,maa (default: "
                                                        "all the benchmark's).")] = None,
    caption: Annotated[Optional[str], typer.Option("--caption",
                                                   help="The LaTeX table's caption (default: what its brackets and "
                                                        "bold mean).")] = None,
) -> None:
    """Collect runs into the paper's table layout, with the paper's numbers and differences."""
    from e3cm_bench.pipeline.experiments import write_table
    from e3cm_bench.drawing.formats import plots_as
    from e3cm_bench.reporting.tables import TableShape

    chosen = tuple(m.strip() for m in (metrics or "").split(",") if m.strip())
    with plots_as(plot_format):
        write_table(list(run_dirs), out, reference, compare, console, paper_rows=paper, latex=latex,
                    shape=TableShape(chosen, caption))


@app.command()
@friendly_errors
def report(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders of one benchmark (each with config.yaml, "
                                                        "summary.csv, per_pair.csv).")],
    out: Annotated[Path, typer.Option("--out",
                                      help="Folder of the site (index.html, pairs/, runs/, img/).")] = Path("report"),
    compare: CompareOpt = True,
) -> None:
    """A static site of runs: the paper-layout table, plots, every pair per method (sortable, filterable)
    and match drawings of the worst and a sample of pairs; opens from the file system, no server."""
    from e3cm_bench.reporting.site import write_report

    write_report(list(run_dirs), out, console=console, compare=compare)


@app.command("compare")
@friendly_errors
def compare_command(
    run_a: Annotated[Path, typer.Argument(help="Run folder A (config.yaml, summary.csv, per_pair.csv).")],
    run_b: Annotated[Path, typer.Argument(help="Run folder B, of the same benchmark.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for compare.csv and compare.md.")] = None,
    mma: Annotated[Optional[str], typer.Option("--mma",
        help="Homography: the mma@k compared: 3 (default), 1,3,5 or all.")] = None,
    alpha: Annotated[float, typer.Option("--alpha",
                                         help="False-alarm rate of each test; intervals at 1 - alpha.")] = 0.05,
) -> None:
    """Two runs of one benchmark, pair by pair on the pairs both hold: per metric B - A of one
    statistic (the mean; the median of an error, a failure counting as +inf) with its
    paired-bootstrap interval, and the verdict read from that interval."""
    from e3cm_bench.reporting.compare import compare_runs, parse_mma, print_comparison, write_comparison
    from e3cm_bench.reporting.tables import load_run

    first, second = load_run(run_a), load_run(run_b)
    columns = set(first.per_pair.columns) & set(second.per_pair.columns)
    comparison = compare_runs(first, second, mma=parse_mma(mma, sorted(columns)), alpha=alpha)
    print_comparison(comparison, console)
    if out is not None:
        csv_path, md_path = write_comparison(comparison, out)
        console.print(f"compare: {csv_path}, {md_path}", markup=False)


@app.command("sweep")
@friendly_errors
def sweep_command(
    run_dirs: Annotated[list[Path], typer.Argument(help="Two or more run folders of one two-view pose benchmark "
                                                        "(their cached matches are scored again; nothing is "
                                                        "matched).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for sweep.csv, tau.csv, flips.csv, sweep.md, ranks.png, "
                                                    "sweep.yaml and cells/ (a sweep resumes from cells/).")],
    estimators: Annotated[str, typer.Option("--estimators",
                                            help="Comma-separated: opencv-ransac, opencv-magsac (USAC_MAGSAC), "
        "opencv-accurate (USAC_ACCURATE), poselib, pycolmap.")] = (
        "opencv-ransac,opencv-magsac,opencv-accurate,poselib,pycolmap"),
    thresholds: Annotated[str, typer.Option("--thresholds",
                                            help="Comma-separated thresholds with units: 0.5px (stored pixels), 1mpx "
        "(pixels as matched), 5e-4f (fraction of the mean focal length).")] = "0.5px,1px,2px",
    seeds: Annotated[int, typer.Option("--seeds",
                                       help="RANSAC seeds per cell (evaluation seed + 0..N-1); the intervals resample "
                                            "them with the pairs.")] = 3,
    metric: Annotated[str, typer.Option("--metric", help="The ranking's metric: auc@5, auc@10 or auc@20.")] = "auc@10",
    tune: Annotated[bool, typer.Option("--tune",
                                       help="Add a cell per estimator with each run at its best px threshold, chosen "
                                            "on half of the pairs (sha256 of the name even); every number is then "
                                            "reported on the other half.")] = False,
) -> None:
    """Two-view protocol sweep: the runs ranked again under each estimator x threshold, with
    Kendall's tau against the runs' own protocol and each rank flip's paired interval."""
    from e3cm_bench.pipeline import sweep as sweeping
    from e3cm_bench.reporting.tables import sweep_markdown
    from e3cm_bench.storage import RunFolder

    seeds = sweeping.check_seeds(seeds)
    if metric not in sweeping.AUCS:
        raise ValueError(f"--metric {metric!r}: choose one of {', '.join(sweeping.AUCS)}")
    sweeping.parse_estimators(estimators), sweeping.parse_thresholds(thresholds)  # refused before loading
    for run_dir in run_dirs:
        if out.resolve() == Path(run_dir).resolve() or RunFolder(out).config_path.is_file():
            raise ValueError(f"--out {out}: is a run folder; the sweep writes beside runs, never into one")
    runs = sweeping.load_runs(run_dirs)
    cells = sweeping.grid(estimators, thresholds, sweeping.cell_of(runs[0].ev))
    result, written = sweeping.run_sweep(runs, cells, seeds, out, metric, tune,
                                         progress=lambda line: console.print(line, markup=False))
    console.print(sweep_markdown(result), markup=False, soft_wrap=True)
    console.print(f"sweep: {', '.join(str(p) for p in written)}", markup=False, soft_wrap=True)


@app.command()
@friendly_errors
def reproduce(
    config: Annotated[str, typer.Argument(help=f"Experiment config: a shipped name ({', '.join(config_names())}) or a "
                                               "YAML file.")],
    out: OutOpt,
    root: RootOpt = None,
    backbone: Annotated[Optional[str], typer.Option("--backbone",
        help="Use this backbone for every deep method (labels say so).")] = None,
    limit: LimitOpt = None,
    device: DeviceOpt = "cpu",
    max_side: MaxSideOpt = None,
    scene_info: Annotated[Optional[list[Path]], typer.Option("--scene-info",
                                                             help="MegaDepth: scene_info files instead of the "
                                                                  "config's.")] = None,
    pairs: Annotated[Optional[Path], typer.Option("--pairs", help="YFCC: pair list instead of the default.")] = None,
    sequences: Annotated[Optional[list[str]], typer.Option("--sequences", help="HPatches: sequences to keep.")] = None,
    skip_bad: SkipBadOpt = False,
    compare: CompareOpt = True,
    shard: ShardOpt = None,
    methods: Annotated[Optional[str], typer.Option("--methods", help="Comma-separated labels: run only these methods "
                                                                    "of the config (e.g. without the peers).")] = None,
    launcher: LauncherOpt = "local",
    shards: ShardsOpt = 0,
    pair_timeout: PairTimeoutOpt = None,
    plot_format: PlotFormatOpt = "png",
    strict: Annotated[bool, typer.Option("--strict", help="A method that cannot run here is an error.")] = False,
) -> None:
    """Run every method of a paper experiment (reusing cached matches) and write its table."""
    from e3cm_bench.cli.benchmarks import Scale
    from e3cm_bench.data.download import find_root
    from e3cm_bench.pipeline.experiments import load_experiment, reproduce as reproduce_experiment
    from e3cm_bench.pipeline.resolve import resolve_request
    from e3cm_bench.drawing.formats import check_plot_format, plots_as
    from e3cm_bench.pipeline.launch import run_experiment_shards

    check_plot_format(plot_format)
    Scale(shard, 0, None, launcher, shards).check(device=device)  # the launcher's and the shards' one set of rules
    config = resolve_config(config)
    # the run's own choices; each method's come from the config (pipeline/experiments.py)
    given = {"dataset": {"scene_info": scene_info, "pairs": pairs, "sequences": sequences},
             "run": {"out": out, "root": root, "skip_bad": skip_bad, "limit": limit, "device": device, "shard": shard},
             "match": {"pair_timeout": pair_timeout}}
    request = resolve_request(load_experiment(config)["benchmark"], typed_only(reproduce, given), locate=find_root)
    choices = dict(backbone=backbone, max_side=max_side, compare=compare, strict=strict,
                   only=methods.split(",") if methods else None)
    with plots_as(plot_format):
        if launcher == "slurm":  # a SLURM array: task K runs shard K/N of every method
            run_experiment_shards(config, request, choices, shards, console=console)
        else:
            reproduce_experiment(config, request, console=console, **choices)


@app.command()
@friendly_errors
def rerun(
    run: Annotated[Path, typer.Argument(help="A run folder, or its config.yaml: the run's configuration.")],
    out: OutOpt,
    device: DeviceOpt = "cpu",
    overwrite: OverwriteOpt = False,
) -> None:
    """Make a run again from its config.yaml alone, in another folder: the same pairs, method and evaluation
    (per_pair.csv comes out the same)."""
    from e3cm_bench.pipeline.rerun import rerun as rerun_run

    rerun_run(run, out, device=device, overwrite=overwrite, console=console)


@app.command()
@friendly_errors
def merge(
    run_dir: Annotated[Path, typer.Argument(help="A sharded run's --out (with shards/), or a sharded reproduce's "
                                                 "--out.")],
    viz: VizOpt = 0,
    compare: CompareOpt = True,
    plot_format: PlotFormatOpt = "png",
) -> None:
    """Merge the shards of a run (or of every method of a reproduce) into the usual CSVs, plots and config.yaml."""
    from e3cm_bench.pipeline.experiments import EXPERIMENT_COPY, merge_experiment
    from e3cm_bench.drawing.formats import plots_as
    from e3cm_bench.pipeline.shards import merge_run

    with plots_as(plot_format):
        if (run_dir / EXPERIMENT_COPY).is_file():
            merge_experiment(run_dir, compare=compare, console=console)
        else:
            merge_run(run_dir, viz=viz, console=console)


@app.command()
@friendly_errors
def demo(
    out: Annotated[Path, typer.Option("--out",
        help="Folder for the data, the runs, the tables and the plots.")] = Path("e3cm-demo"),
    seed: Annotated[int, typer.Option("--seed",
                                      help="Seed of every robust estimator (the data is always the same).")] = 0,
    quick: Annotated[bool, typer.Option("--quick",
                                        help="Fewer pairs of the same kinds: 10 HPatches-format (viewpoint and "
                                             "illumination), 2 scene pairs.")] = False,
    methods: Annotated[Optional[str], typer.Option("--methods",
        help=f"Comma-separated subset of: {', '.join(DEMO_METHODS)}.")] = None,
    device: DeviceOpt = "cpu",
    plot_format: PlotFormatOpt = "png",
) -> None:
    """The whole toolkit offline: writes embedded data, runs e3cm, e3cm-release, e3cm-ransac, e3cm-plus,
    direct, dfm and sift (deep ones on EfficientNet-Lite0) on HPatches-format sequences and a non-planar
    scene, prints each method's headline numbers (the runs' full output: OUT/demo.log)."""
    from e3cm_bench.apps.demo import run_demo
    from e3cm_bench.drawing.formats import plots_as

    with plots_as(plot_format):
        run_demo(out, seed=seed, quick=quick, methods=methods.split(",") if methods else None, device=device,
                 console=console)
    console.print(f"demo: tables, plots and match drawings under {out}/ (hpatches_table.md, scenes_table.md, */viz/)",
                  markup=False, highlight=False)


@app.command()
@friendly_errors
def check(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders, or folders holding run folders (e.g. "
                                                        "e3cm-demo/hpatches).")],
    baseline: Annotated[Path, typer.Option("--baseline", help="Baseline CSV (benchmark, method, metrics, "
                                                              "environment), e.g. "
                                                              "results/baselines/demo_hpatches.csv.")],
    tolerance: Annotated[Optional[list[str]], typer.Option("--tolerance",
                                                           help="METRIC=T, or METHOD:METRIC=T for one method: allowed "
                                                                "fall (absolute) of a metric; repeatable; wins over "
                                                                "--tolerances.")] = None,
    tolerances: Annotated[Optional[Path], typer.Option("--tolerances",
                                                       help="CSV of tolerances: benchmark, method, metric, tolerance "
                                                            "(* = any; the most specific row applies; other columns "
                                                            "ignored).")] = None,
    update: Annotated[bool, typer.Option("--update",
                                         help="Write the baseline from these runs (aggregate + per-pair values, each "
                                              "run's identity and environment) instead of checking.")] = False,
    ensemble: Annotated[int, typer.Option("--ensemble",
                                          help="With --update: rerun every run K times under CPU-scale perturbations "
                                               "and store the draws beside the baseline (the noise model check then "
                                               "gates with).")] = 0,
    ensemble_dir: Annotated[Optional[Path], typer.Option("--ensemble-dir",
                                                         help="Work folder of the ensemble's reruns (resumable; "
                                                              "default .e3cm-ensemble/BASELINE_NAME).")] = None,
    alpha: Annotated[float, typer.Option("--alpha",
                                         help="False-alarm rate of the whole check under the noise model (split over "
                                              "its metrics).")] = CHECK_ALPHA,
    summary: Annotated[Optional[Path], typer.Option("--summary",
        help="Append a Markdown report here (e.g. $GITHUB_STEP_SUMMARY).")] = None,
) -> None:
    """Compare runs with a baseline: exit 1 naming each metric that fell beyond its noise (or its tolerance).

    With a noise ensemble beside the baseline (check --update --ensemble K), a metric is flagged
    only where its change lies outside what a rerun on another CPU gives, at the false-alarm
    rate --alpha per check; the pairs that moved are named, each against its own noise. Runs
    the ensemble does not hold are checked against tolerances. Where a run's versions or CPU
    settings differ from its baseline row's, one line names each difference (information)."""
    from e3cm_bench.gate import check as regression

    runs = regression.find_runs(run_dirs)
    if update:
        _update_baseline(runs, baseline, ensemble, ensemble_dir)
        return
    if not 0 < alpha < 1:
        raise ValueError(f"--alpha must be between 0 and 1, got {alpha}")
    if _check_runs(runs, baseline, alpha, tolerance, tolerances, summary):
        raise typer.Exit(1)


def _check_runs(runs, baseline: Path, alpha: float, tolerance, tolerances, summary) -> int:
    """check's verdict on `runs` against `baseline`, printed (and appended to `summary`): the
    number of regressions and problems."""
    from e3cm_bench.drawing.formats import text_width
    from e3cm_bench.gate import check as regression, notes as check_notes

    width = text_width(console)  # 80 columns in a CI log or a pipe
    # First: a broken per-pair baseline is refused before the noise gate reads it.
    consistency = regression.consistency_problems(runs, baseline)
    bad, lines, text, others, checked = _noise_gate(runs, baseline, alpha, width)
    limits = regression.Tolerances.load(tolerance, tolerances)
    findings, problems = regression.compare(others, baseline, limits,
                                            checked_runs=[(r.benchmark.name, r.label) for r in runs])
    problems += consistency
    checked += len(findings)
    notes = check_notes.environment_notes(runs, baseline) + check_notes.protocol_check_notes(runs, baseline)
    if findings or problems or others is runs:
        text += regression.markdown_summary(findings, problems, baseline, notes, tolerance_file=tolerances)
    if summary is not None:
        regression.write_summary(text, summary)
    # Each finding wrapped at the console's width (80 columns in a CI log), words kept whole.
    for note in notes:
        console.print(note, highlight=False, markup=False, width=width)
    styles = {"regression": "bold red", "improvement": "yellow", "moved": "dim", "problem": "bold red"}
    said = [*lines, *((f.status, f"{f.method} on {f.benchmark}: {f.metric} {f.baseline:.4g} -> {f.measured:.4g} "
                                 f"(tolerance {f.tolerance:g})") for f in findings if f.status != "ok"),
            *(("problem", problem) for problem in problems)]
    for status, line in said:
        console.print(Text.assemble((status, styles[status]), f": {line}"), highlight=False, width=width)
    bad += sum(f.status == "regression" for f in findings) + len(problems)
    # The verdict first, so that a wrapped line never splits it (CI logs are searched for it).
    console.print(("check: no regression" if not bad else f"check: {bad} regression(s)/problem(s)")
                  + f": {checked} metrics of {len(runs)} runs against {baseline}", width=width, highlight=False,
                  markup=False)
    return bad


def _noise_gate(runs, baseline: Path, alpha: float, width: int) -> tuple[int, list, str, list, int]:
    """check's gate under the noise ensemble beside the baseline, where there is one: the
    regressions it found, the lines saying them, its Markdown, the runs it does not hold (left
    to the tolerances) and how many metrics it checked."""
    from e3cm_bench.gate import check as regression

    if not regression.has_noise_model(baseline):
        return 0, [], "", runs, 0
    verdicts, others, metric_alpha = regression.gate(runs, baseline, alpha)
    lines = [line for verdict in verdicts for line in regression.verdict_lines(verdict)]
    bad = sum(g.status == "regression" for v in verdicts for g in v.gates)
    text = regression.gate_markdown(verdicts, metric_alpha, alpha, baseline)
    console.print(f"noise model: {regression.noise_path(baseline)} (false-alarm rate {alpha:g} per check, "
                  f"{metric_alpha:.2g} per metric)", highlight=False, markup=False, width=width)
    return bad, lines, text, others, sum(len(v.gates) for v in verdicts)


def _update_baseline(runs, baseline: Path, ensemble: int, ensemble_dir: Path | None) -> None:
    """check --update: the baseline files, and with --ensemble K its noise draws."""
    from e3cm_bench.gate import check as regression
    from e3cm_bench.gate.ensemble import build_ensemble, write_noise

    if ensemble < 0:
        raise ValueError(f"--ensemble must be 0 (none) or a number of draws, got {ensemble}")
    regression.write_baseline(runs, baseline)
    console.print(f"baseline: {len(runs)} runs written to {baseline} and {regression.noise_gate.pairs_path(baseline)}",
                  markup=False)
    noise = regression.noise_path(baseline)
    if not ensemble:
        if noise.is_file():  # draws around the old baseline would judge the new one
            noise.unlink()
            console.print(f"removed {noise}: its draws belong to the previous baseline (--ensemble K writes new ones)",
                          markup=False)
        return
    work = ensemble_dir or Path(".e3cm-ensemble") / baseline.stem
    console.print(f"ensemble: {ensemble} draws of {len(runs)} runs in {work} (resumable)", highlight=False,
                  markup=False)
    t = time.perf_counter()
    table = build_ensemble(runs, range(1, ensemble + 1), work, console=console)
    write_noise(table, noise)
    console.print(f"ensemble: {noise} written, {len(table)} pair draws in {time.perf_counter() - t:.0f} s",
                  highlight=False,
                  markup=False)


