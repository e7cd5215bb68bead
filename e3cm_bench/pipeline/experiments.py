"""Paper experiments: paper/configs/*.yaml -> one run per method -> the paper-layout table and plots.

An experiment config (YAML) names a benchmark, dataset options and a list of methods;
`reproduce` runs every method into OUT/<label>/ (each run reuses its cached matches; the
methods are matched together, pair by pair, so that each image's feature maps are computed
once for all methods sharing a backbone) and writes the table and the comparison plots into
OUT/.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from e3cm_bench.reporting import tables as report
from e3cm_bench.benchmarks import BENCHMARKS, Benchmark, get_benchmark
from e3cm_bench.method.protocols import get_protocol, resolve_protocol
from e3cm_bench.ground.files import absolute_paths, load_yaml, save_yaml
from e3cm_bench.backbones.names import DEFAULT_BACKBONE
from e3cm_bench.matchers import get_matcher
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.ground.values import check_value
from e3cm_bench.method.options import METHOD_OPTIONS, config_keys
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.paper import resolve_config
from e3cm_bench.storage.fingerprint import protocol_items, protocol_notes
from e3cm_bench.storage import RunFolder
from e3cm_bench.pipeline.request import RunRequest
from e3cm_bench.pipeline.runner import run_benchmark, run_methods

EXPERIMENT_COPY = "experiment.yaml"  # what reproduce ran, kept in its --out (merge reads it)
NOT_RUN = "not_run"  # its key of {label: why} of the methods that could not run here
# The keys of a config and the kind of each value (options.KINDS), made from the declarations: the
# method options' (options.METHOD_OPTIONS says where a config takes each), the evaluation options'
# (eval_options.EVAL_OPTIONS: an ``evaluation:`` section, as a run's config.yaml has one), the
# experiment's own besides. Read when a config is, so an option declared later is a key too.
EXPERIMENT_OWN = {"name": "text", "benchmark": "text", "dataset": "mapping", "evaluation": "mapping"}


def method_types() -> dict[str, str]:
    return config_keys("method")


def experiment_types() -> dict[str, str]:
    return {**EXPERIMENT_OWN, **config_keys("experiment")}


def experiment_keys() -> set[str]:
    return set(experiment_types()) | {"methods"}


def _check_types(path: Path, where: str, values: dict, types: dict, nullable: tuple[str, ...] = (),
                 options: dict = METHOD_OPTIONS) -> None:
    """A one-line ValueError naming the file and the first key whose value is not of its kind or
    not in the range its entry of `options` declares (options.check_value, the flag's own check),
    checked before anything reads it (a label of 123 used as a folder name, a max_side of "big"
    compared with 0, a ransac_px of -1); `nullable` keys may also be null: the default."""
    for key, kind in types.items():
        if key not in values or values[key] is None and key in nullable:
            continue
        check_value(values[key], kind, getattr(options.get(key), "range", None), f"{path}: {where}{key!r}")


def _refuse_unknown(path: Path, where: str, values: dict, known, what: str) -> None:
    """A one-line ValueError naming the file and the first key of `values` not in `known` (the
    nearest known one, and all of them), `what` saying what the key is not."""
    unknown = sorted(set(values) - set(known), key=str)
    if unknown:
        raise ValueError(f"{path}: {where}{unknown[0]!r} is not {what}{did_you_mean(unknown[0], known)}; "
                         f"it has {', '.join(sorted(known))}")


def experiment_method(
    entry: dict, experiment: dict, benchmark: Benchmark, backbone_override: str | None = None,
    max_side_override: int | None = None, available: bool = True,
) -> MethodSpec:
    """The MethodSpec of one `methods:` entry of an experiment config.

    The default label follows the method's own backbone and estimator; a backbone forced on
    every deep method (reproduce --backbone) is appended in brackets.
    """
    given = entry_options(entry, experiment, backbone_override, max_side_override)
    own_backbone = entry.get("backbone", experiment.get("backbone")) or DEFAULT_BACKBONE
    spec = benchmark.resolve_method(entry["matcher"], available=available, **given)
    deep = spec.backbone is not None
    # The default label names the method's own backbone; a forced one is added in brackets.
    label = entry.get("label") or replace(spec, backbone=own_backbone if spec.backbone else None).default_label()
    if backbone_override and deep and backbone_override != own_backbone:
        label = f"{label} [{backbone_override}]"
    return spec.with_label(label)


def entry_options(entry: dict, experiment: dict, backbone_override: str | None = None,
                  max_side_override: int | None = None) -> dict:
    """The method options of one `methods:` entry by name (matcher and label aside): the entry's,
    else the experiment's (options.config_keys), with reproduce's --backbone and --max-side."""
    taken = (set(config_keys("method")) | set(config_keys("experiment"))) - {"matcher", "label"}
    given = {name: entry.get(name, experiment.get(name)) for name in METHOD_OPTIONS if name in taken}
    if max_side_override is not None:
        given["max_side"] = max_side_override
    given["seed"] = int(given["seed"] or 0)
    given["backbone"] = backbone_override or given["backbone"] or DEFAULT_BACKBONE
    return given


def run_given(spec: MethodSpec, entry: dict, experiment: dict, forced: tuple, dataset: dict) -> dict:
    """What a reproduced method's record keeps as its `given` (pipeline/resolve.py): its entry's
    method options (the experiment's where it has none, with --backbone and --max-side) and its label,
    the experiment's evaluation and dataset sections, so that `rerun` resolves the run from them."""
    method = {k: v for k, v in entry_options(entry, experiment, *forced).items() if v is not None}
    return {"method": {"matcher": entry["matcher"], **method, "label": spec.label},
            "evaluation": dict(experiment.get("evaluation") or {}), "dataset": dict(dataset)}


def load_experiment(path: Path) -> dict:
    """Read and check an experiment config (paper/configs/*.yaml, or one of one's own)."""
    config = load_yaml(path, what="experiment config")
    _refuse_unknown(path, "", config, experiment_keys(), "a key of an experiment")
    for section in ("dataset", "evaluation"):
        if not isinstance(config.get(section) or {}, dict):
            raise ValueError(f"{path}: '{section}' must be a mapping of {section} options")
    _check_types(path, "", config, experiment_types(), nullable=("dataset", "evaluation"))
    evaluation = config.get("evaluation") or {}
    _refuse_unknown(path, "evaluation: ", evaluation, EVAL_OPTIONS, "an evaluation option")
    _check_types(path, "evaluation: ", evaluation, {n: o.kind for n, o in EVAL_OPTIONS.items()},
                 nullable=tuple(EVAL_OPTIONS), options=EVAL_OPTIONS)
    if config.get("benchmark") not in BENCHMARKS:
        raise ValueError(f"{path}: 'benchmark' must be one of {', '.join(BENCHMARKS)}")
    benchmark = get_benchmark(config["benchmark"])
    kinds = {o.name: o.kind for o in benchmark.command_options()}
    _check_types(path, "dataset: ", config.get("dataset") or {}, kinds, nullable=tuple(kinds))
    methods = config.get("methods")
    if not isinstance(methods, list) or not methods:
        raise ValueError(f"{path}: 'methods' must be a non-empty list")
    labels, types = set(), method_types()
    for i, method in enumerate(methods):
        if not isinstance(method, dict) or not isinstance(method.get("matcher"), str):
            raise ValueError(f"{path}: methods[{i}] needs 'matcher' (e3cm-bench matchers lists them)")
        _check_types(path, f"methods[{i}]: ", method, types, nullable=tuple(set(types) - {"matcher"}))
        try:
            get_matcher(method["matcher"], allow_import=True)
        except ValueError as exc:
            raise ValueError(f"{path}: methods[{i}]: {exc}") from None
        _refuse_unknown(path, f"methods[{i}]: ", method, types, "a key of a method")
        try:
            spec = experiment_method(method, config, benchmark, available=False)
        except ValueError as exc:
            raise ValueError(f"{path}: methods[{i}]: {exc}") from None
        label = spec.label
        # The label names the run's folder under --out: '../x' or '/abs' would write outside it.
        if spec.folder in ("", ".", "..") or any(c in spec.folder for c in "/\\\0"):
            raise ValueError(f"{path}: methods[{i}]: label {label!r} is not a plain folder name "
                             "(no '/', '\\', '..' or empty label); its run folder must lie inside --out")
        if label in labels:
            raise ValueError(f"{path}: two methods are labelled {label!r}")
        labels.add(label)
    unknown = set(config.get("dataset") or {}) - set(benchmark.option_names)
    if unknown:
        raise ValueError(f"{path}: dataset option(s) {', '.join(sorted(unknown))} do not apply to {benchmark.name}")
    return config


def reproduce(
    config_path: Path | str,
    request: RunRequest,
    *,
    backbone: str | None = None,
    max_side: int | None = None,
    only: list[str] | None = None,
    compare: bool = True,
    console: Console | None = None,
    strict: bool = False,
) -> tuple[Path, Path] | None:
    """Run every method of an experiment config (or those labelled in `only`), then write its
    table and plots. config_path: a YAML file, or a shipped config's name (``table1``; paper.config_names).

    request: the run's own choices (out, root, limit, device, skip_bad, shard, the match stage's
    options; dataset_options: overrides of the config's), each method's run made from it.
    backbone: replaces the backbone of every deep method (e.g. efficientnet_lite0 offline);
    the labels then say so. max_side: replaces every method's resize. request.shard=(K, N):
    every method runs its K-th shard; the table is written once every method's shards are
    merged. Returns the table's CSV and Markdown paths (None while shards are missing).
    A method that cannot run here (a peer without its extra or weights, offline) is left out, said
    on the console and listed in the table with the reason (source "not run"); strict=True (--strict)
    makes it an error instead, before anything runs.
    """
    console = console or Console()
    config_path = resolve_config(config_path)
    experiment = load_experiment(config_path)
    benchmark = get_benchmark(experiment["benchmark"])
    options = {**(experiment.get("dataset") or {}), **{k: v for k, v in request.dataset_options.items() if v}}
    dataset = benchmark.load_dataset(request.root, skip_bad=request.skip_bad, **options)
    # No `protocol:`: the benchmark's default, as its command has it (WxBS, EVD: wxbs)
    protocol = get_protocol(resolve_protocol(benchmark, experiment.get("protocol")), benchmark.name)
    ev = benchmark.resolve_eval(protocol.name, int(experiment.get("seed", 0)), experiment.get("evaluation") or {})
    out = Path(request.out)
    methods, not_run, entries = _methods(config_path, experiment, benchmark, (backbone, max_side), only, strict,
                                         console)
    givens = [run_given(m, e, experiment, (backbone, max_side), options) for m, e in zip(methods, entries)]
    save_yaml({**experiment, "runs": [m.folder for m in methods], NOT_RUN: not_run}, out / EXPERIMENT_COPY)
    load = {"root": str(Path(request.root).resolve()), "options": {k: absolute_paths(v) for k, v in options.items()},
            "skip_bad": request.skip_bad}
    run = request.but(benchmark=benchmark, dataset=dataset, dataset_options=options, dataset_load=load, ev=ev)
    console.print(protocol.line(benchmark.name), markup=False)
    name, shard = experiment.get("name", config_path.stem), request.shard
    if shard is None:  # all methods in one pass over the pairs: each image's maps computed once for all
        console.rule(f"{name}: {', '.join(m.label for m in methods)}")
        runs = [(out / m.folder, m, g) for m, g in zip(methods, givens)]
        run_methods(benchmark, runs, dataset, dataset_load=load, ev=ev, limit=run.limit, device=run.device,
                    options=run.options, console=console)
    else:
        for method, given in zip(methods, givens):
            console.rule(f"{name}: {method.label}")
            run_benchmark(run.but(out=out / method.folder, method=method, given=given), console=console)
    run_dirs = [out / m.folder for m in methods]
    if shard is not None and not all(RunFolder(d).is_run() and RunFolder(d).run_config().shards is not None
                                     for d in run_dirs):
        console.print(f"shard {shard[0]}-of-{shard[1]} done; the table is written when every method's shards are "
                      f"(or: e3cm-bench merge {out})", markup=False)
        return None
    return _table_and_report(run_dirs, out, compare, console, not_run)


def _methods(config_path: Path, experiment: dict, benchmark: Benchmark, forced: tuple[str | None, int | None],
             only: list[str] | None, strict: bool = True, console: Console | None = None,
             ) -> tuple[list[MethodSpec], dict, list[dict]]:
    """The methods reproduce runs: every one of the config's, or those labelled in `only`, with the
    (backbone, max_side) `forced` on them; {label: why} of those that cannot run here, each said on
    the console (an error instead where `strict`, or where none can run); and the runs' entries."""
    backbone, max_side = forced
    entries = experiment["methods"]
    if only:
        # the config's own labels (a backbone forced on the deep methods adds to them later)
        labels = [experiment_method(e, experiment, benchmark, None, max_side, available=False).label for e in entries]
        unknown = sorted(set(only) - set(labels))
        if unknown:
            raise ValueError(
                f"{config_path}: --methods {', '.join(unknown)}: no such method; it has {', '.join(labels)}"
            )
        entries = [e for e, label in zip(entries, labels) if label in only]
    methods, not_run, kept = [], {}, []
    for entry in entries:
        try:
            methods.append(experiment_method(entry, experiment, benchmark, backbone, max_side))
            kept.append(entry)
        except ValueError as exc:  # a peer without its extra or weights (load_experiment checked the rest)
            label = entry.get("label", entry["matcher"])
            if strict:
                raise ValueError(f"{config_path}: {label}: {exc} (--strict; without it the rows that can run "
                                 "do, and this one is listed as not run; --methods runs a subset)") from None
            not_run[label] = str(exc)
            (console or Console()).print(f"not run: {label}: {exc}", markup=False, soft_wrap=True)  # one line
    if not methods:
        raise ValueError(f"{config_path}: none of its methods can run here ({', '.join(not_run)}); see above")
    return methods, not_run, kept


def _table_and_report(run_dirs: list[Path], out: Path, compare: bool, console: Console | None,
                      not_run: dict | None = None) -> tuple[Path, Path]:
    """OUT/table.{csv,md} with its plots (and the rows that could not run, with why), and the
    report site OUT/report/ for the same runs."""
    from e3cm_bench.reporting.site import write_report

    written = write_table(run_dirs, Path(out) / "table", compare=compare, console=console,
                          shape=report.TableShape(not_run=tuple((not_run or {}).items())))
    write_report(run_dirs, Path(out) / "report", console=console, compare=compare)
    return written


def merge_experiment(out: Path, compare: bool = True, console: Console | None = None) -> tuple[Path, Path]:
    """Merge every method of a sharded reproduce in OUT, then write its table."""
    from e3cm_bench.pipeline.shards import merge_run

    experiment = load_yaml(Path(out) / EXPERIMENT_COPY)
    run_dirs = [Path(out) / folder for folder in experiment["runs"]]
    for run_dir in run_dirs:
        merge_run(run_dir, console=console)
    return _table_and_report(run_dirs, Path(out), compare, console, experiment.get(NOT_RUN))


def write_table(
    run_dirs: list[Path],
    out_path: str | Path,
    reference: Path | None = None,
    compare: bool = True,
    console: Console | None = None,
    paper_rows: bool = True,
    latex: bool = False,
    shape: report.TableShape | None = None,
) -> tuple[Path, Path]:
    """Collect runs into the paper's layout (CSV + Markdown) plus the comparison plots beside it.

    compare=False drops the measured - paper difference columns: on data other than the
    paper's full benchmark (e.g. the shared samples) the differences mean nothing.
    Every measured number carries its bootstrap interval (``<col>_lo``, ``<col>_hi`` in the CSV;
    ``0.73 [0.47, 0.93]`` in the Markdown and on the terminal); a difference whose paper number
    lies outside that interval says so.
    paper_rows=False leaves the paper's reported rows out (data that is not the paper's).
    latex=True also writes ``<out_path>.tex``, a booktabs table for a paper (reporting/latex.py).
    out_path is the table's file stem; an existing folder (or one written with a trailing /) takes
    ``table`` inside it. shape: the metrics kept, the LaTeX caption and the methods that could not
    run (tables.TableShape). Columns no row fills are left out.
    """
    shape = shape or report.TableShape()
    if Path(out_path).is_dir() or str(out_path).endswith(("/", "\\")):
        out_path = Path(out_path) / "table"
    console = console or Console()
    runs = [report.load_run(d) for d in run_dirs]
    benchmark = runs[0].benchmark
    # the table's files (its plots are named <stem>_<plot>.png: no run file has such a name)
    stem = Path(out_path)
    RunFolder.refuse_own_files([stem.with_suffix(suffix) for suffix in (".csv", ".md", ".tex")], "table")
    if reference is None and benchmark.paper_table and paper_rows:
        candidate = report.paper_reference(benchmark)
        reference = candidate if candidate.is_file() else None
        if reference is None:
            console.print(f"[yellow]note[/]: {escape(str(candidate))} not found; the table has no paper reference rows")
    table = report.paper_table(runs, benchmark, reference)
    if not compare:
        table = report.without_comparison(table)
    if shape.not_run:  # after the comparison's columns are dropped: its note is in one of them
        table = report.with_not_run(table, dict(shape.not_run))
    table = report.without_empty_columns(report.choose_metrics(table, benchmark, shape.metrics))
    csv_path, md_path = report.write_paper_table(table, out_path)
    written = [csv_path, md_path]
    if latex:
        from e3cm_bench.reporting.latex import write_latex_table

        written.append(write_latex_table(table, out_path, shape.caption))
    benchmark.plot_comparison({r.label: (r.summary, r.per_pair) for r in runs}, Path(out_path))
    report.print_paper_table(table, console)  # the Markdown's cells, within the terminal's width
    for note in protocol_notes([(f"{r.label} in {r.dir}", protocol_items(r.run_config)) for r in runs]):
        console.print(f"note: {note}", markup=False, soft_wrap=True)  # one line, however long
    console.print(f"table: {', '.join(str(p) for p in written)}", markup=False)
    return csv_path, md_path
