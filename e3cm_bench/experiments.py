"""From options to runs: one benchmark run of one method, and the paper experiments in configs/.

An experiment config (YAML) names a benchmark, dataset options and a list of methods;
`reproduce` runs every method into OUT/<label>/ (each run reuses its cached matches) and
writes the paper-layout table and the comparison plots into OUT/.
"""

from __future__ import annotations

import json
from pathlib import Path

from rich.console import Console

from . import report
from .config import load_yaml
from .datasets import BENCHMARKS, DATASETS
from .matchers import MATCHERS, NEEDS_BACKBONE, build_matcher
from .runner import DEFAULT_MAX_SIDE, EvalSettings, RunSpec, run_benchmark

REPO_RESULTS = Path(__file__).resolve().parents[1] / "results"
DATASET_OPTIONS = {"hpatches": ("exclude_large", "sequences"), "megadepth": ("scene_info",), "yfcc": ("pairs",)}
METHOD_KEYS = {"label", "matcher", "backbone", "weights", "cascade_estimator", "sampson_px", "ratio", "max_side"}


def make_dataset(benchmark: str, root: Path, skip_missing: bool = False, **options):
    if benchmark not in DATASETS:
        raise ValueError(f"unknown benchmark {benchmark!r}; choose one of {', '.join(BENCHMARKS)}")
    return DATASETS[benchmark](root, skip_missing=skip_missing, **{k: v for k, v in options.items() if v is not None})


def matcher_settings(matcher: str, estimator: str = "top8", sampson_px=None, ratio=None) -> dict:
    """The E3CMSettings / DFM fields that apply to `matcher` (others are ignored, not guessed)."""
    settings: dict = {}
    if matcher in NEEDS_BACKBONE and ratio is not None:
        settings["ratio"] = tuple(float(r) for r in ratio)
    if matcher == "e3cm":
        settings["estimator"] = estimator
        if sampson_px is not None:
            settings["sampson_px"] = tuple(float(s) for s in sampson_px)
    return settings


def default_label(matcher: str, backbone: str, estimator: str = "top8") -> str:
    label = matcher if matcher not in NEEDS_BACKBONE or backbone == "vgg19" else f"{matcher}-{backbone}"
    return label if matcher != "e3cm" or estimator == "top8" else f"{label}-{estimator}"


def method_identity(method: dict, experiment: dict, backbone_override: str | None = None) -> tuple[str, str, str]:
    """(backbone, cascade estimator, label) of one method of an experiment config.

    The default label follows the method's own backbone and estimator; a backbone forced
    on every deep method (reproduce --backbone) is appended in brackets.
    """
    matcher = method["matcher"]
    own_backbone = method.get("backbone", experiment.get("backbone", "vgg19"))
    estimator = method.get("cascade_estimator", "top8")
    label = method.get("label") or default_label(matcher, own_backbone, estimator)
    if backbone_override and matcher in NEEDS_BACKBONE and backbone_override != own_backbone:
        label = f"{label} [{backbone_override}]"
    return backbone_override or own_backbone, estimator, label


def run_method(
    benchmark: str,
    dataset,
    out: Path,
    matcher: str = "e3cm",
    backbone: str = "vgg19",
    weights: str | None = None,
    device: str = "cpu",
    settings: dict | None = None,
    max_side: int | None = None,
    limit: int | None = None,
    seed: int = 0,
    overwrite: bool = False,
    eval_only: bool = False,
    viz: int = 0,
    label: str | None = None,
    ransac_px: float | None = None,
    console: Console | None = None,
) -> dict:
    """One benchmark run of one matcher; `max_side=None` takes the benchmark default, 0 = full size."""
    console = console or Console()
    settings = settings or {}
    max_side = DEFAULT_MAX_SIDE[benchmark] if max_side is None else max_side
    max_side = max_side or None
    label = label or default_label(matcher, backbone, settings.get("estimator", "top8"))
    match_options = {
        "matcher": matcher,
        "backbone": backbone if matcher in NEEDS_BACKBONE else None,
        "weights": str(weights) if weights else None,
        "settings": json.loads(json.dumps(settings)),  # tuples -> lists, as YAML stores them
        "max_side": max_side,
    }
    ev = EvalSettings(seed=seed)
    if ransac_px is not None:
        if benchmark == "hpatches":
            ev.homography_ransac_px = ransac_px
        else:
            ev.pose_ransac_px = ransac_px
    spec = RunSpec(
        benchmark=benchmark, out=Path(out), method=label, match_options=match_options, max_side=max_side,
        limit=limit, overwrite=overwrite, eval_only=eval_only, viz=viz, device=device, eval=ev,
    )
    console.print(
        f"resize: longer side {'at most ' + str(max_side) + ' px' if max_side else 'unchanged (full resolution)'}; "
        f"seed {seed}; matcher {matcher}" + (f" ({backbone})" if matcher in NEEDS_BACKBONE else "")
    )
    return run_benchmark(spec, dataset, lambda: build_matcher(matcher, backbone, match_options["weights"], device, settings=settings), console)


def load_experiment(path: Path) -> dict:
    """Read and check an experiment config (configs/*.yaml)."""
    config = load_yaml(path)
    if config.get("benchmark") not in BENCHMARKS:
        raise ValueError(f"{path}: 'benchmark' must be one of {', '.join(BENCHMARKS)}")
    methods = config.get("methods")
    if not isinstance(methods, list) or not methods:
        raise ValueError(f"{path}: 'methods' must be a non-empty list")
    labels = set()
    for i, method in enumerate(methods):
        if not isinstance(method, dict) or method.get("matcher") not in MATCHERS:
            raise ValueError(f"{path}: methods[{i}] needs 'matcher', one of {', '.join(MATCHERS)}")
        unknown = set(method) - METHOD_KEYS
        if unknown:
            raise ValueError(f"{path}: methods[{i}] has unknown key(s) {', '.join(sorted(unknown))}")
        _, _, label = method_identity(method, config)
        if label in labels:
            raise ValueError(f"{path}: two methods are labelled {label!r}")
        labels.add(label)
    unknown = set(config.get("dataset") or {}) - set(DATASET_OPTIONS[config["benchmark"]])
    if unknown:
        raise ValueError(f"{path}: dataset option(s) {', '.join(sorted(unknown))} do not apply to {config['benchmark']}")
    return config


def reproduce(
    config_path: Path,
    root: Path,
    out: Path,
    backbone: str | None = None,
    limit: int | None = None,
    device: str = "cpu",
    dataset_overrides: dict | None = None,
    skip_missing: bool = False,
    max_side: int | None = None,
    compare: bool = True,
    console: Console | None = None,
) -> tuple[Path, Path]:
    """Run every method of an experiment config, then write its table and plots.

    backbone: replaces the backbone of every deep method (e.g. efficientnet_lite0 offline);
    the labels then say so. Returns the table's CSV and Markdown paths.
    """
    console = console or Console()
    experiment = load_experiment(config_path)
    benchmark = experiment["benchmark"]
    options = {**(experiment.get("dataset") or {}), **{k: v for k, v in (dataset_overrides or {}).items() if v}}
    dataset = make_dataset(benchmark, root, skip_missing=skip_missing, **options)
    out = Path(out)
    run_dirs = []
    for method in experiment["methods"]:
        matcher = method["matcher"]
        net, estimator, label = method_identity(method, experiment, backbone)
        run_dir = out / label.replace(" ", "_").replace("[", "").replace("]", "")
        console.rule(f"{experiment.get('name', config_path.stem)}: {label}")
        run_method(
            benchmark, dataset, run_dir, matcher=matcher, backbone=net, weights=method.get("weights"), device=device,
            settings=matcher_settings(matcher, estimator, method.get("sampson_px"), method.get("ratio")),
            max_side=max_side if max_side is not None else method.get("max_side", experiment.get("max_side")),
            limit=limit, seed=int(experiment.get("seed", 0)), label=label, console=console,
        )
        run_dirs.append(run_dir)
    return write_table(run_dirs, out / "table", compare=compare, console=console)


def write_table(
    run_dirs: list[Path], out_path: Path, reference: Path | None = None, compare: bool = True, console: Console | None = None
) -> tuple[Path, Path]:
    """Collect runs into the paper's layout (CSV + Markdown) plus the comparison plot beside it.

    compare=False drops the measured - paper difference columns: on data other than the
    paper's full benchmark (e.g. the shared samples) the differences mean nothing.
    """
    console = console or Console()
    runs = [report.load_run(d) for d in run_dirs]
    benchmark = runs[0].benchmark
    if reference is None:
        candidate = REPO_RESULTS / "paper" / report.PAPER_TABLE_FILES[benchmark]
        reference = candidate if candidate.is_file() else None
        if reference is None:
            console.print(f"[yellow]note[/]: {candidate} not found; the table has no paper reference rows")
    table = report.paper_table(runs, benchmark, reference)
    if not compare:
        table = table.drop(columns=[c for c in table.columns if c.startswith("d_")])
    csv_path, md_path = report.write_paper_table(table, out_path)
    if benchmark == "hpatches":
        report.plot_mma_curves({r.label: r.summary for r in runs}, out_path.with_name(out_path.stem + "_mma.png"))
    else:
        report.plot_pose_auc_bars({r.label: r.summary for r in runs}, out_path.with_name(out_path.stem + "_pose_auc.png"),
                                  title=f"{benchmark}: pose AUC and precision")
        report.plot_pose_error_cdf({r.label: r.per_pair for r in runs}, out_path.with_name(out_path.stem + "_pose_cdf.png"))
    console.print(md_path.read_text())
    console.print(f"table: {csv_path}, {md_path}")
    return csv_path, md_path
