"""e3cm-bench command line: one thin function per subcommand."""

from __future__ import annotations

import functools
import inspect
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

from .backbones import BACKBONES, BackboneError
from .cache import DiskFullError
from .benchmarks import BENCHMARKS, Benchmark, get_benchmark
from .benchmarks.protocols import PROTOCOLS, get_protocol
from .files import load_yaml_text, save_npz, writable_folder
from .benchmarks import EvalSettings
from . import check as regression
from .datasets.base import DatasetError, Pair
from .devices import keep_freed_memory
from .demo import METHODS as DEMO_METHODS
from .demo import run_demo
from .calibration.run import CalibrationSettings, run_calibration
from .synth.stereo import write_stereo_sequence
from .synth.textures import demo_pair
from .experiments import reproduce as reproduce_experiment
from .experiments import EXPERIMENT_COPY, merge_experiment, write_table
from .images import load_image
from .matchers import get_matcher
from .matching import ESTIMATORS
from .paper import config_names, resolve_config
from .method import MethodSpec, parse_numbers
from .run import RunConfig
from .run.stage import MatchOptions
from .runner import match_pair, run_benchmark
from .download import find_root
from .run.launch import check_workers, run_shards
from .run.shards import merge_run, parse_shard
from .viz import draw_matches, save_image

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Training-free deep feature matching (E3CM, DFM, SIFT+NN) and the HPatches / MegaDepth-1500 / YFCC100M benchmarks.",
)
console = Console()
err_console = Console(stderr=True)

# Options shared by `match` and the benchmark commands.
MatcherOpt = Annotated[str, typer.Option("--matcher", help="A matcher's name (e3cm-bench matchers lists them: built-ins and installed plugins) or package.module:factory.")]
BackboneOpt = Annotated[str, typer.Option("--backbone", help=f"One of: {', '.join(BACKBONES)}.")]
WeightsOpt = Annotated[Optional[Path], typer.Option("--weights", help="Local state-dict file for the backbone (instead of the ImageNet download).")]
DeviceOpt = Annotated[str, typer.Option("--device", help="cpu, cuda or mps.")]
EstimatorOpt = Annotated[Optional[str], typer.Option("--estimator", "--cascade-estimator", help=f"e3cm: how the cascade estimates F per level: {', '.join(ESTIMATORS)} (default top8 = the paper).")]
SampsonOpt = Annotated[Optional[str], typer.Option("--sampson-px", help="Sampson thresholds in pixels for levels 0,1,2,3, comma-separated.")]
RatioOpt = Annotated[Optional[str], typer.Option("--ratio", help="Ratio-test thresholds for levels 0..4, comma-separated.")]
LabelOpt = Annotated[Optional[str], typer.Option("--label", help="Method name in tables and plots (default: matcher[-backbone]).")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="KEY=VALUE: a further matcher setting (repeatable), e.g. variant=corrected (dfm), ratio_at=own (e3cm), cascade=false (e3cm-release), num_levels=4, channel_order=bgr.")]
PrecisionOpt = Annotated[str, typer.Option("--precision", help="Backbone precision: fp32 (exact, default), bf16 (CPUs with AVX-512 BF16/AMX, GPUs), fp16 (GPUs), or auto: bf16 where the device computes it natively, else fp32 (fp16 on a GPU without bf16).")]
ChannelOrderOpt = Annotated[str, typer.Option("--channel-order", help="rgb (default) or bgr: the channel order fed to the network (the E3CM release's eval scripts feed BGR).")]
BackboneBatchOpt = Annotated[Optional[int], typer.Option("--backbone-batch", show_default="8 on a GPU, 1 on a CPU", help="Images per backbone pass: when a pair needs a pass, the coming pairs' images of the same size that the feature cache lacks go through the network with it (for GPUs; needs the cache).")]
FeatureCacheOpt = Annotated[Optional[float], typer.Option("--feature-cache-mb", show_default="half the available memory, at most 16 GiB", help="Memory (MiB) for the feature maps of images that have pairs left (what does not fit goes to the run folder, up to half the free disk, at most 64 GiB); 0 = no reuse. Never changes a result.")]
ProtocolOpt = Annotated[str, typer.Option("--protocol", help=f"Evaluation preset: {', '.join(PROTOCOLS)} (docs/benchmarks.md: Protocols).")]


def parse_settings(pairs: list[str] | None, precision: str = "fp32", channel_order: str = "rgb", device: str = "cpu") -> dict:
    """['variant=corrected', 'num_levels=4'] -> {'variant': 'corrected', 'num_levels': 4} (YAML values);
    a precision other than fp32 and a channel order other than rgb join them (the defaults are
    left out, so that runs with them keep their identity). --precision auto is resolved for
    `device` here (the identity records what runs); a precision that will be emulated is said."""
    if precision != "fp32":
        from .devices import resolve_precision

        precision, warning = resolve_precision(precision, device)
        if warning:
            err_console.print(f"[yellow]warning[/]: {warning}", highlight=False, soft_wrap=True)
    settings = {} if precision == "fp32" else {"precision": precision}
    if channel_order != "rgb":
        settings["channel_order"] = channel_order
    for item in pairs or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        settings[key.strip()] = load_yaml_text(value)
    return settings


# The commands that write run folders (with every benchmark's own): only their rerun resumes at
# the first pair not written.
RESUMING_COMMANDS = frozenset({"reproduce", "import_matches", "calibrate", "demo"})


def os_error_line(exc: OSError, resumes: bool = False) -> str:
    """One line for an OSError: the file, the problem, and for a full disk what to do (`resumes`:
    the command is a benchmark's or one of RESUMING_COMMANDS)."""
    import errno

    where = exc.filename or ""
    text = exc.strerror or str(exc)
    if isinstance(exc, DiskFullError) or exc.errno != errno.ENOSPC:
        return f"{where}: {text}" if where and where not in text else text
    # The free space of the filesystem that filled: the nearest existing folder of the file
    # named. A failed write() names no file: then nothing is quoted, not some other disk's space.
    existing = next((p for p in (Path(where), *Path(where).parents) if p.exists()), None) if where else None
    free = ""
    try:
        free = f" ({shutil.disk_usage(existing).free / 2**20:.1f} MiB free there)" if existing is not None else ""
    except OSError:
        pass
    return (f"{where or 'the output folder'}: no space left on device{free}; free some space and rerun the same "
            "command" + (": every pair already written resumes" if resumes else ""))


def friendly_errors(command):
    """Bad input ends in one line on stderr and a non-zero exit, never a traceback.

    E3CM_BENCH_DEBUG=1 lets the exception through with its traceback (for developers).
    """

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (DatasetError, BackboneError, ValueError, FileNotFoundError, KeyError) as exc:
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except MemoryError as exc:
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else "not enough memory"
            err_console.print(f"[bold red]error:[/] out of memory: {detail}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except OSError as exc:  # a full disk, a folder that cannot be written: what and where, in one line
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            name = command.__name__
            line = os_error_line(exc, resumes=name in RESUMING_COMMANDS or name.replace("_", "-") in BENCHMARKS)
            err_console.print(f"[bold red]error:[/] {line}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: matches written so far are kept; rerun the same command to resume")
            raise typer.Exit(130) from None

    return wrapper


@app.command()
@friendly_errors
def match(
    image0: Annotated[Optional[Path], typer.Argument(help="First image (omit both for the built-in demo pair).")] = None,
    image1: Annotated[Optional[Path], typer.Argument(help="Second image.")] = None,
    matcher: MatcherOpt = "e3cm",
    backbone: Annotated[Optional[str], typer.Option("--backbone", help=f"One of: {', '.join(BACKBONES)} (default vgg19; the demo uses efficientnet_lite0, which needs no download).")] = None,
    weights: WeightsOpt = None,
    max_side: Annotated[Optional[int], typer.Option("--max-side", help="Resize so the longer side is at most N px.")] = None,
    device: DeviceOpt = "cpu",
    estimator: EstimatorOpt = None,
    sampson_px: SampsonOpt = None,
    ratio: RatioOpt = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the robust estimators inside the matcher.")] = 0,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("e3cm-match"),
    settings: SetOpt = None,
    precision: PrecisionOpt = "fp32",
    channel_order: ChannelOrderOpt = "rgb",
) -> None:
    """Match two images: writes OUT/matches.npz and OUT/matches.png, prints counts and stage times."""
    if (image0 is None) != (image1 is None):
        raise ValueError("give two images, or none for the built-in demo pair")
    writable_folder(out, create=False)  # before any work: a folder that cannot take the results is one line now
    H = None
    if image0 is None:
        img0, img1, H = demo_pair()
        backbone = backbone or "efficientnet_lite0"
        console.print(f"demo: a procedural 640x480 scene and its warp by a known homography; backbone {backbone}")
    else:
        img0, img1 = load_image(image0), load_image(image1)
        backbone = backbone or "vgg19"
    method = MethodSpec.create(
        matcher, backbone, weights, estimator, parse_numbers(sampson_px, "--sampson-px"),
        parse_numbers(ratio, "--ratio"), max_side or None, seed,
        options=parse_settings(settings, precision, channel_order, device) if get_matcher(matcher, allow_import=True).needs_backbone else parse_settings(settings),
    )
    kept = keep_freed_memory()  # the second image's pass reuses the first's pages, as in a run (docs/speed.md)
    t = time.perf_counter()
    m = method.build(device)
    t_load = time.perf_counter() - t
    result = match_pair(m, img0, img1, method.max_side, method.seed_for_matching)
    k0, k1 = result.keypoints0, result.keypoints1

    writable_folder(out)
    save_npz(out / "matches.npz", keypoints0=k0, keypoints1=k1, scores=result.scores)
    correct = None
    if H is not None:
        correct = get_benchmark("hpatches").correct_mask(Pair("demo", Path(), Path(), H=H), result, EvalSettings())
    save_image(out / "matches.png", draw_matches(img0, img1, k0, k1, correct=correct, max_lines=500))

    console.print(f"[bold]{len(k0)} matches[/] ({get_matcher(matcher).name}, {method.backbone or 'no backbone'}) -> {out}/matches.npz, matches.png")
    if correct is not None:
        console.print(f"demo ground truth: {correct.mean() * 100 if len(correct) else 0:.1f}% of matches within 3 px")
    info = result.info
    if "counts_before" in info:
        levels = sorted(info["counts_before"], reverse=True)
        console.print("matches per level (after refinement -> after epipolar rejection): " + ", ".join(
            f"L{l}: {info['counts_before'][l]}->{info['counts_after'][l]}" for l in levels))
        for level, note in sorted(info.get("rejection", {}).items(), reverse=True):
            if note != "applied":
                console.print(f"level {level}: rejection {note}")
    timings = {"model load": t_load, **info.get("timings", {})}
    console.print("time per stage (s): " + ", ".join(f"{k} {v:.3f}" for k, v in timings.items()))
    console.print(f"allocator: {kept}", markup=False)


def _method(bench: Benchmark, matcher: str, backbone: str, weights: Path | None, estimator: str | None,
            sampson_px: str | None, ratio: str | None, max_side: int | None, seed: int, label: str | None,
            settings: list[str] | None, protocol: str, precision: str = "fp32",
            channel_order: str = "rgb", device: str = "cpu") -> MethodSpec:
    """The method of a benchmark command (Benchmark.resolve_method, as experiment configs get theirs)."""
    deep = get_matcher(matcher, allow_import=True).needs_backbone
    # precision and channel order concern deep matchers only
    options = parse_settings(settings, precision, channel_order, device) if deep else parse_settings(settings)
    return bench.resolve_method(
        matcher, protocol=protocol, backbone=backbone, weights=weights, estimator=estimator,
        sampson_px=parse_numbers(sampson_px, "--sampson-px"), ratio=parse_numbers(ratio, "--ratio"),
        max_side=max_side, seed=seed, label=label, settings=options,
    )


@dataclass(frozen=True)
class Scale:
    """How a run's shards run: --shard K/N here, --workers N local processes, --devices one per
    device, or --launcher slurm with --shards N; at most one of them."""

    shard: str | None = None
    workers: int = 0
    devices: str | None = None
    launcher: str = "local"
    shards: int = 0

    def check(self) -> None:
        several = [option for option, given in (("--shard", self.shard), ("--workers", self.workers),
                                                ("--devices", self.devices), ("--launcher slurm", self.launcher == "slurm"))
                   if given]
        if len(several) > 1:
            raise ValueError(f"{' and '.join(several)} do not go together: each says how the shards run")
        if not self.devices:
            check_workers(self.workers)
        if self.launcher == "slurm" and not self.shards:
            raise ValueError("--launcher slurm needs --shards N")


def run_command(bench: Benchmark, dataset_options: dict, out: Path, root: Path | None, matcher: str, backbone: str,
                weights: Path | None, max_side: int | None, limit: int | None, device: str, seed: int,
                overwrite: bool, eval_only: bool, viz: int, estimator: str | None, sampson_px: str | None,
                ratio: str | None, label: str | None, settings: list[str] | None, protocol: str, precision: str,
                channel_order: str, feature_cache_mb: float | None, backbone_batch: int | None, skip_bad: bool,
                ransac_px: float | None, pose_estimator: str | None, repeats: int, on_matcher_error: str,
                pair_timeout: float | None,
                shard: str | None, workers: int, devices: str | None, launcher: str, shards: int) -> None:
    """What every benchmark command does with its options (the commands are made by benchmark_command)."""
    method = _method(bench, matcher, backbone, weights, estimator, sampson_px, ratio, max_side, seed, label, settings,
                     protocol, precision, channel_order, device)
    scale = Scale(shard, workers, devices, launcher, shards)
    scale.check()
    console.print(get_protocol(protocol, bench.name).line(), markup=False)
    ev = bench.resolve_eval(protocol, seed, ransac_px, pose_estimator, repeats)
    run = dict(benchmark=bench.name, out=out, method=method, root=find_root(bench.name, root),
               dataset_options=dataset_options, skip_bad=skip_bad, ev=ev, limit=limit, overwrite=overwrite, viz=viz,
               options=MatchOptions(feature_cache_mb, backbone_batch=backbone_batch, on_matcher_error=on_matcher_error,
                                    pair_timeout=pair_timeout))
    if workers or devices:
        device_list = devices.split(",") if devices else ["cpu"] * workers
        run_shards(run, len(device_list), devices=device_list, console=console)
    elif launcher == "slurm":
        run_shards(run, shards, launcher="slurm", console=console)
    else:
        run_benchmark(**run, eval_only=eval_only, device=device, shard=parse_shard(shard) if shard else None,
                      console=console)


# Options of the benchmark commands.
ShardOpt = Annotated[Optional[str], typer.Option("--shard", help="K/N: run only the K-th of N slices of the pairs, into OUT/shards/K-of-N/ (the last shard merges).")]
WorkersOpt = Annotated[int, typer.Option("--workers", help="Run N shards at once in N local processes, CPU threads divided among them, then merge.")]
DevicesOpt = Annotated[Optional[str], typer.Option("--devices", help="cuda:0,cuda:1,...: one shard and process per device, then merge.")]
LauncherOpt = Annotated[str, typer.Option("--launcher", help="slurm: submit --shards N as a SLURM array (submitit; runs locally where SLURM is absent).")]
ShardsOpt = Annotated[int, typer.Option("--shards", help="Number of shards for --launcher slurm.")]
RootOpt = Annotated[Optional[Path], typer.Option("--root", help="Dataset root folder (default: the downloaded data under $E3CM_BENCH_DATA, else ./data; e3cm-bench datasets).")]
OutOpt = Annotated[Path, typer.Option("--out", help="Run folder (config.yaml, matches.h5, CSVs, plots).")]
MaxSideOpt = Annotated[Optional[int], typer.Option("--max-side", help="Longer image side for matching (0 = full resolution).")]
LimitOpt = Annotated[Optional[int], typer.Option("--limit", help="Only the first N pairs.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of every RANSAC (set before each pair).")]
OverwriteOpt = Annotated[bool, typer.Option("--overwrite", help="Discard matches already in --out.")]
EvalOnlyOpt = Annotated[bool, typer.Option("--eval-only", help="Recompute the metrics from matches.h5 without matching.")]
VizOpt = Annotated[int, typer.Option("--viz", help="Draw the first N pairs (green: correct by ground truth, red: not).")]
SkipBadOpt = Annotated[bool, typer.Option("--skip-bad", "--skip-missing", help="Skip the pairs with bad input (images missing or cut short, unusable ground truth), list them in skipped.csv and count them; --skip-missing is the old name.")]
CompareOpt = Annotated[bool, typer.Option("--compare/--no-compare", help="Difference columns (measured - paper); off for data other than the paper's benchmark.")]
RansacOpt = Annotated[Optional[float], typer.Option("--ransac-px", help="Threshold of the evaluation RANSAC in px (HPatches 3, pose 0.5).")]
RepeatsOpt = Annotated[int, typer.Option("--repeats", help="Run the evaluation's RANSAC K times (seeds SEED..SEED+K-1, no rematching): the summary is their mean, with each metric's spread (_sd).")]
OnMatcherErrorOpt = Annotated[str, typer.Option("--on-matcher-error", help="stop (default): a matcher that raises on a pair ends the run (the pairs before it are kept); fail-pair: that pair counts as a failure (no matches), its message goes to failures.csv, and the run goes on.")]
PairTimeoutOpt = Annotated[Optional[float], typer.Option("--pair-timeout", help="Seconds a matcher may take on one pair; past them the pair fails as --on-matcher-error says (POSIX, main thread; default: no limit).")]
PoseEstimatorOpt = Annotated[Optional[str], typer.Option("--pose-estimator", help="Robust estimator of the evaluation (relative pose; HPatches: the homography): opencv (default) or poselib (pip install 'e3cm-bench[poselib]'); --eval-only may change it.")]

# Every benchmark command's options, in the order --help lists them; the benchmark's own
# dataset options (Benchmark.dataset_options) come between the two groups.
_NO_DEFAULT = inspect.Parameter.empty
COMMON_BEFORE = (
    ("out", OutOpt, _NO_DEFAULT), ("root", RootOpt, None), ("matcher", MatcherOpt, "e3cm"),
    ("backbone", BackboneOpt, "vgg19"), ("weights", WeightsOpt, None), ("max_side", MaxSideOpt, None),
    ("limit", LimitOpt, None), ("device", DeviceOpt, "cpu"), ("seed", SeedOpt, 0), ("overwrite", OverwriteOpt, False),
    ("eval_only", EvalOnlyOpt, False), ("viz", VizOpt, 0), ("estimator", EstimatorOpt, None),
    ("sampson_px", SampsonOpt, None), ("ratio", RatioOpt, None), ("label", LabelOpt, None), ("settings", SetOpt, None),
    ("protocol", ProtocolOpt, "default"), ("precision", PrecisionOpt, "fp32"), ("channel_order", ChannelOrderOpt, "rgb"),
    ("feature_cache_mb", FeatureCacheOpt, None), ("backbone_batch", BackboneBatchOpt, None),
)
COMMON_AFTER = (
    ("skip_bad", SkipBadOpt, False), ("ransac_px", RansacOpt, None), ("pose_estimator", PoseEstimatorOpt, None),
    ("repeats", RepeatsOpt, 1), ("on_matcher_error", OnMatcherErrorOpt, "stop"),
    ("pair_timeout", PairTimeoutOpt, None), ("shard", ShardOpt, None), ("workers", WorkersOpt, 0), ("devices", DevicesOpt, None),
    ("launcher", LauncherOpt, "local"), ("shards", ShardsOpt, 0),
)
# A dataset option's kind (benchmarks/base.py OPTION_KINDS) -> its type and default on the command line.
OPTION_TYPES = {"flag": (bool, False), "path": (Optional[Path], None), "paths": (Optional[list[Path]], None),
                "names": (Optional[list[str]], None), "text": (Optional[str], None)}


def dataset_parameters(bench: Benchmark) -> list[inspect.Parameter]:
    """The command-line options of a benchmark's dataset options."""
    params = []
    for option in bench.command_options():
        kind, default = OPTION_TYPES[option.kind]
        annotation = Annotated[kind, typer.Option(option.flag, help=option.help)]
        params.append(inspect.Parameter(option.name, inspect.Parameter.KEYWORD_ONLY, default=default,
                                        annotation=annotation))
    return params


def benchmark_command(bench: Benchmark):
    """The command `e3cm-bench NAME` of a registered benchmark: the common options and its own
    dataset options (typer reads the signature built here, as it reads a written one)."""

    def command(**given) -> None:
        dataset_options = {o.name: given.pop(o.name) for o in bench.command_options()}
        run_command(bench, dataset_options, **given)

    common = lambda group: [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default,  # noqa: E731
                                              annotation=annotation) for name, annotation, default in group]
    params = common(COMMON_BEFORE) + dataset_parameters(bench) + common(COMMON_AFTER)
    command.__signature__ = inspect.Signature(params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    command.__name__ = command.__qualname__ = bench.name.replace("-", "_")
    command.__doc__ = bench.summary or f"The {bench.name} benchmark."
    return friendly_errors(command)


for _bench in BENCHMARKS.values():
    app.command(_bench.name)(benchmark_command(_bench))


@app.command()
@friendly_errors
def table(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders (each with config.yaml and summary.csv), one benchmark.")],
    out: Annotated[Path, typer.Option("--out", help="Table path; .csv and .md are written, plus a plot beside them.")],
    reference: Annotated[Optional[Path], typer.Option("--reference", help="Paper numbers (default: the shipped e3cm_bench/paper/tableN.csv).")] = None,
    compare: CompareOpt = True,
) -> None:
    """Collect runs into the paper's table layout, with the paper's numbers and differences."""
    write_table(list(run_dirs), out, reference, compare, console)


@app.command()
@friendly_errors
def report(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders of one benchmark (each with config.yaml, summary.csv, per_pair.csv).")],
    out: Annotated[Path, typer.Option("--out", help="Folder of the site (index.html, pairs/, runs/, img/).")] = Path("report"),
    compare: CompareOpt = True,
) -> None:
    """A static site of runs: the paper-layout table, plots, every pair per method (sortable, filterable)
    and match drawings of the worst and a sample of pairs; opens from the file system, no server."""
    from .reportsite import write_report

    write_report(list(run_dirs), out, console=console, compare=compare)


@app.command("compare")
@friendly_errors
def compare_command(
    run_a: Annotated[Path, typer.Argument(help="Run folder A (config.yaml, summary.csv, per_pair.csv).")],
    run_b: Annotated[Path, typer.Argument(help="Run folder B, of the same benchmark.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for compare.csv and compare.md.")] = None,
    mma: Annotated[Optional[str], typer.Option("--mma", help="Homography: the mma@k compared: 3 (default), 1,3,5 or all.")] = None,
    alpha: Annotated[float, typer.Option("--alpha", help="False-alarm rate of each test; intervals at 1 - alpha.")] = 0.05,
) -> None:
    """Two runs of one benchmark, pair by pair on the pairs both hold: per metric the mean
    difference B - A with its paired-bootstrap interval, a paired test (Wilcoxon or sign;
    McNemar for pass/fail) and a verdict."""
    from .compare_runs import compare_runs, parse_mma, print_comparison, write_comparison
    from .report import load_run

    first, second = load_run(run_a), load_run(run_b)
    columns = set(first.per_pair.columns) & set(second.per_pair.columns)
    comparison = compare_runs(first, second, mma=parse_mma(mma, sorted(columns)), alpha=alpha)
    print_comparison(comparison, console)
    if out is not None:
        csv_path, md_path = write_comparison(comparison, out)
        console.print(f"compare: {csv_path}, {md_path}", markup=False)


@app.command()
@friendly_errors
def reproduce(
    config: Annotated[str, typer.Argument(help=f"Experiment config: a shipped name ({', '.join(config_names())}) or a YAML file.")],
    out: OutOpt,
    root: RootOpt = None,
    backbone: Annotated[Optional[str], typer.Option("--backbone", help="Use this backbone for every deep method (labels say so).")] = None,
    limit: LimitOpt = None,
    device: DeviceOpt = "cpu",
    max_side: MaxSideOpt = None,
    scene_info: Annotated[Optional[list[Path]], typer.Option("--scene-info", help="MegaDepth: scene_info files instead of the config's.")] = None,
    pairs: Annotated[Optional[Path], typer.Option("--pairs", help="YFCC: pair list instead of the default.")] = None,
    sequences: Annotated[Optional[list[str]], typer.Option("--sequences", help="HPatches: sequences to keep.")] = None,
    skip_bad: SkipBadOpt = False,
    compare: CompareOpt = True,
    shard: ShardOpt = None,
    methods: Annotated[Optional[str], typer.Option("--methods", help="Comma-separated labels: run only these methods of the config (e.g. without the peers).")] = None,
) -> None:
    """Run every method of a paper experiment (reusing cached matches) and write its table."""
    config = resolve_config(config)
    overrides = {"scene_info": scene_info, "pairs": pairs, "sequences": sequences}
    if root is None:
        from .experiments import load_experiment

        root = find_root(load_experiment(config)["benchmark"], None)
    reproduce_experiment(config, root, out, backbone=backbone, limit=limit, device=device, dataset_overrides=overrides,
                         skip_bad=skip_bad, max_side=max_side, compare=compare, console=console,
                         shard=parse_shard(shard) if shard else None, only=methods.split(",") if methods else None)


@app.command()
@friendly_errors
def merge(
    run_dir: Annotated[Path, typer.Argument(help="A sharded run's --out (with shards/), or a sharded reproduce's --out.")],
    viz: VizOpt = 0,
    compare: CompareOpt = True,
) -> None:
    """Merge the shards of a run (or of every method of a reproduce) into the usual CSVs, plots and config.yaml."""
    if (run_dir / EXPERIMENT_COPY).is_file():
        merge_experiment(run_dir, compare=compare, console=console)
    else:
        merge_run(run_dir, viz=viz, console=console)


@app.command()
@friendly_errors
def demo(
    out: Annotated[Path, typer.Option("--out", help="Folder for the data, the runs, the tables and the plots.")] = Path("e3cm-demo"),
    seed: Annotated[int, typer.Option("--seed", help="Seed of every robust estimator (the data is always the same).")] = 0,
    quick: Annotated[bool, typer.Option("--quick", help="Fewer pairs of the same kinds (a smoke test).")] = False,
    methods: Annotated[Optional[str], typer.Option("--methods", help=f"Comma-separated subset of: {', '.join(DEMO_METHODS)}.")] = None,
    device: DeviceOpt = "cpu",
) -> None:
    """The whole toolkit offline: writes embedded data, runs e3cm, e3cm-ransac, direct, dfm and sift
    (EfficientNet-Lite0) on HPatches-format sequences and a non-planar scene, prints both tables."""
    run_demo(out, seed=seed, quick=quick, methods=methods.split(",") if methods else None, device=device, console=console)
    console.print(f"demo: tables, plots and match drawings under {out}/ (hpatches_table.md, scenes_table.md, */viz/)")


@app.command()
@friendly_errors
def check(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders, or folders holding run folders (e.g. e3cm-demo/hpatches).")],
    baseline: Annotated[Path, typer.Option("--baseline", help="Baseline CSV (benchmark, method, metrics, environment), e.g. results/baselines/demo_hpatches.csv.")],
    tolerance: Annotated[Optional[list[str]], typer.Option("--tolerance", help="METRIC=T, or METHOD:METRIC=T for one method: allowed fall (absolute) of a metric; repeatable; wins over --tolerances.")] = None,
    tolerances: Annotated[Optional[Path], typer.Option("--tolerances", help="CSV of tolerances: benchmark, method, metric, tolerance (* = any; the most specific row applies; other columns ignored).")] = None,
    update: Annotated[bool, typer.Option("--update", help="Write the baseline from these runs (aggregate + per-pair values, each run's identity and environment) instead of checking.")] = False,
    ensemble: Annotated[int, typer.Option("--ensemble", help="With --update: rerun every run K times under CPU-scale perturbations and store the draws beside the baseline (the noise model check then gates with).")] = 0,
    ensemble_dir: Annotated[Optional[Path], typer.Option("--ensemble-dir", help="Work folder of the ensemble's reruns (resumable; default .e3cm-ensemble/BASELINE_NAME).")] = None,
    alpha: Annotated[float, typer.Option("--alpha", help="False-alarm rate of the whole check under the noise model (split over its metrics).")] = regression.CHECK_ALPHA,
    summary: Annotated[Optional[Path], typer.Option("--summary", help="Append a Markdown report here (e.g. $GITHUB_STEP_SUMMARY).")] = None,
) -> None:
    """Compare runs with a baseline: exit 1 naming each metric that fell beyond its noise (or its tolerance).

    With a noise ensemble beside the baseline (check --update --ensemble K), a metric is flagged
    only where its change lies outside what a rerun on another CPU gives, at the false-alarm
    rate --alpha per check; the pairs that moved are named, each against its own noise. Runs
    the ensemble does not hold are checked against tolerances. Where a run's versions or CPU
    settings differ from its baseline row's, one line names each difference (information)."""
    runs = regression.find_runs(run_dirs)
    if update:
        _update_baseline(runs, baseline, ensemble, ensemble_dir)
        return
    if not 0 < alpha < 1:
        raise ValueError(f"--alpha must be between 0 and 1, got {alpha}")
    bad, lines, text = 0, [], ""
    others, checked = runs, 0
    if regression.has_noise_model(baseline):
        verdicts, others, metric_alpha = regression.gate(runs, baseline, alpha)
        checked += sum(len(v.gates) for v in verdicts)
        for verdict in verdicts:
            lines += regression.verdict_lines(verdict)
        bad += sum(g.status == "regression" for v in verdicts for g in v.gates)
        text += regression.gate_markdown(verdicts, metric_alpha, alpha, baseline)
        console.print(f"noise model: {regression.noise_path(baseline)} (false-alarm rate {alpha:g} per check, "
                      f"{metric_alpha:.2g} per metric)", highlight=False, markup=False)
    limits = regression.Tolerances.load(tolerance, tolerances)
    findings, problems = regression.compare(others, baseline, limits, checked_runs=[(r.benchmark.name, r.label) for r in runs])
    checked += len(findings)
    notes = regression.environment_notes(runs, baseline)
    if findings or problems or others is runs:
        text += regression.markdown_summary(findings, problems, baseline, notes, tolerance_file=tolerances)
    if summary is not None:
        regression.write_summary(text, summary)
    for note in notes:
        console.print(note, highlight=False, markup=False, soft_wrap=True)  # one line, however long
    styles = {"regression": "bold red", "improvement": "yellow", "moved": "dim"}
    for status, line in lines:
        console.print(f"[{styles[status]}]{status}[/]: ", end="", highlight=False)
        console.print(line, highlight=False, markup=False, soft_wrap=True)
    for f in findings:
        if f.status != "ok":
            style = "bold red" if f.status == "regression" else "yellow"
            console.print(f"[{style}]{f.status}[/]: {f.method} on {f.benchmark}: {f.metric} {f.baseline:.4g} -> "
                          f"{f.measured:.4g} (tolerance {f.tolerance:g})", highlight=False)
    for problem in problems:
        console.print(f"[bold red]problem[/]: {problem}", highlight=False)
    bad += sum(f.status == "regression" for f in findings) + len(problems)
    console.print(f"check: {checked} metrics of {len(runs)} runs against {baseline}: "
                  + ("no regression" if not bad else f"{bad} regression(s)/problem(s)"))
    if bad:
        raise typer.Exit(1)


def _update_baseline(runs, baseline: Path, ensemble: int, ensemble_dir: Path | None) -> None:
    """check --update: the baseline files, and with --ensemble K its noise draws."""
    from .ensemble import build_ensemble, write_noise

    if ensemble < 0:
        raise ValueError(f"--ensemble must be 0 (none) or a number of draws, got {ensemble}")
    regression.write_baseline(runs, baseline)
    console.print(f"baseline: {len(runs)} runs written to {baseline} and {regression.noise_gate.pairs_path(baseline)}")
    noise = regression.noise_path(baseline)
    if not ensemble:
        if noise.is_file():  # draws around the old baseline would judge the new one
            noise.unlink()
            console.print(f"removed {noise}: its draws belong to the previous baseline (--ensemble K writes new ones)")
        return
    work = ensemble_dir or Path(".e3cm-ensemble") / baseline.stem
    console.print(f"ensemble: {ensemble} draws of {len(runs)} runs in {work} (resumable)", highlight=False)
    t = time.perf_counter()
    table = build_ensemble(runs, range(1, ensemble + 1), work, console=console)
    write_noise(table, noise)
    console.print(f"ensemble: {noise} written, {len(table)} pair draws in {time.perf_counter() - t:.0f} s", highlight=False)


@app.command()
@friendly_errors
def calibrate(
    root: Annotated[Path, typer.Option("--root", help="Stereo sequence: KITTI odometry (image_0/, image_1/, calib.txt) or raw (image_00/data, image_01/data, calib_cam_to_cam.txt) layout.")],
    out: OutOpt,
    matcher: Annotated[list[str], typer.Option("--matcher", help="Matcher(s) to compare (repeatable), as for the benchmarks (e3cm-bench matchers).")] = ["e3cm"],  # noqa: B006
    backbone: BackboneOpt = "vgg19",
    weights: WeightsOpt = None,
    frames: Annotated[list[int], typer.Option("--frames", help="Window sizes in frames (repeatable; default 1 3 5 10).")] = [1, 3, 5, 10],  # noqa: B006
    max_side: Annotated[Optional[int], typer.Option("--max-side", help="Longer image side for matching (default: full resolution).")] = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "cpu",
    unrectified: Annotated[bool, typer.Option("--unrectified", help="KITTI raw: the unrectified images (K_0x, R_01, T_01) instead of the rectified ones (P_rect_0x).")] = False,
    overwrite: OverwriteOpt = False,
    settings: Annotated[Optional[list[str]], typer.Option("--set", help="KEY=VALUE: a further setting of the deep matchers (repeatable), e.g. refine=ncc; the label shows it.")] = None,
) -> None:
    """Stereo rig self-calibration (paper Sec. 4.4): extrinsic errors per window of frames, per matcher."""
    options = parse_settings(settings)
    given = " ".join(item.strip() for item in settings or [])
    methods = []
    for name in matcher:
        deep = get_matcher(name, allow_import=True).needs_backbone
        label = f"{name} {given}".strip() if deep and given else name
        label = label if backbone == "vgg19" or not deep else f"{label} [{backbone}]"
        methods.append(MethodSpec.create(name, backbone=backbone, weights=weights, max_side=max_side or None, seed=seed,
                                         label=label, options=options if deep else None))
    run_calibration(root, out, methods, CalibrationSettings(frames=tuple(frames), seed=seed), device=device,
                    unrectified=unrectified, overwrite=overwrite, console=console)


@app.command()
@friendly_errors
def download(
    name: Annotated[str, typer.Argument(help="hpatches, megadepth-1500, yfcc or scannet-1500.")],
    to: Annotated[Optional[Path], typer.Option("--to", help="Folder for the data (default: $E3CM_BENCH_DATA, else ./data).")] = None,
    origin: Annotated[Optional[str], typer.Option("--from", help="A mirror URL or a file already downloaded, instead of the source's URL.")] = None,
    sha256: Annotated[Optional[str], typer.Option("--sha256", help="The expected sha256 of the --from file.")] = None,
    check: Annotated[bool, typer.Option("--check", help="Only check what is in place (counts against a complete copy).")] = False,
) -> None:
    """Fetch a benchmark's data (progress, resume, sha256), unpack it safely, and check it."""
    from .datasets.sources import data_dir, get_source
    from .download import check as check_data
    from .download import download as fetch_data

    source = get_source(name)
    to = to or data_dir()
    if not check:
        root = fetch_data(source, to, origin, sha256, console)
        console.print(f"{source.name}: in {root}", markup=False)
    console.print(check_data(source, to), markup=False)


@app.command()
@friendly_errors
def datasets(
    to: Annotated[Optional[Path], typer.Option("--to", help="The data folder (default: $E3CM_BENCH_DATA, else ./data).")] = None,
) -> None:
    """Where each benchmark's data is looked for, and whether it is missing, incomplete or complete."""
    from .datasets.sources import SOURCES, data_dir
    from .download import status

    to = to or data_dir()
    console.print(f"data folder: {to} (benchmark commands use it when --root is not given)", markup=False)
    for source in SOURCES.values():
        console.print(status(source, to), markup=False, highlight=False, soft_wrap=True)


def import_matches(
    benchmark: Annotated[str, typer.Argument(help=f"The benchmark: {', '.join(BENCHMARKS)}.")],
    out: OutOpt,
    root: RootOpt = None,
    hloc: Annotated[Optional[tuple[Path, Path]], typer.Option("--hloc", help="FEATURES.h5 MATCHES.h5 written by hloc (or in its layout).")] = None,
    npz: Annotated[Optional[Path], typer.Option("--npz", help="Folder of <pair name>.npz (keypoints0, keypoints1, optional scores).")] = None,
    colmap: Annotated[Optional[Path], typer.Option("--colmap", help="A COLMAP database.db (images named by their path under the root; needs pycolmap).")] = None,
    gluefactory: Annotated[Optional[Path], typer.Option("--gluefactory", help="glue-factory's predictions.h5 (its evaluation cache).")] = None,
    pixel_origin: Annotated[Optional[str], typer.Option("--pixel-origin", help="center (top-left pixel's centre at 0,0) or corner (at 0.5,0.5): overrides the format's own (hloc, npz: center; colmap, gluefactory: corner).")] = None,
    limit: Annotated[Optional[int], typer.Option("--limit", help="Only the first N pairs (as a benchmark run's --limit).")] = None,
    label: LabelOpt = None,
    skip_bad: SkipBadOpt = False,
    overwrite: OverwriteOpt = False,
    viz: VizOpt = 0,
    seed: SeedOpt = 0,
    ransac_px: RansacOpt = None,
    pose_estimator: PoseEstimatorOpt = None,
    protocol: ProtocolOpt = "default",
    **dataset_options,
) -> None:
    """Evaluate matches made by another tool: writes a normal run folder (matches.h5, config.yaml with the sources' sha256, CSVs, plots)."""
    from .imported import ColmapSource, GluefactorySource, HlocSource, NpzSource, import_run

    given = [name for name, value in (("--hloc", hloc), ("--npz", npz), ("--colmap", colmap),
                                      ("--gluefactory", gluefactory)) if value is not None]
    if len(given) != 1:
        raise ValueError("give one source: --hloc FEATURES.h5 MATCHES.h5, --npz DIR, --colmap DATABASE.db or "
                         f"--gluefactory PREDICTIONS.h5 (given: {', '.join(given) or 'none'})")
    bench = get_benchmark(benchmark)
    root = find_root(bench.name, root)
    mine = {o.name for o in bench.command_options()}
    foreign = sorted(OPTION_FLAGS[k] for k, v in dataset_options.items() if k not in mine and v not in (None, False, []))
    if foreign:
        raise ValueError(f"{', '.join(foreign)} do(es) not apply to {bench.name}")
    options = {k: v for k, v in dataset_options.items() if k in mine}
    dataset = bench.load_dataset(root, skip_bad=skip_bad, **options)
    ev = bench.resolve_eval(protocol, seed, ransac_px, pose_estimator)
    if hloc is not None:
        source = HlocSource(*hloc, origin=pixel_origin)
    elif npz is not None:
        source = NpzSource(npz, origin=pixel_origin)
    elif colmap is not None:
        source = ColmapSource(colmap, origin=pixel_origin)
    else:
        source = GluefactorySource(gluefactory, bench.name, origin=pixel_origin)
    import_run(bench, dataset, root, out, source, ev=ev, label=label, skip_bad=skip_bad, overwrite=overwrite, viz=viz,
               console=console, limit=limit, dataset_load=RunConfig.dataset_load_of(root, skip_bad, options))


def all_dataset_parameters() -> list[inspect.Parameter]:
    """Every registered benchmark's dataset options, once each (for `import`, which takes the
    benchmark as an argument); the help names the benchmarks an option applies to."""
    seen: dict[str, tuple[object, list[str]]] = {}
    for bench in BENCHMARKS.values():
        for option in bench.command_options():
            seen.setdefault(option.name, (option, []))[1].append(bench.name)
    params = []
    for name, (option, names) in seen.items():
        kind, default = OPTION_TYPES[option.kind]
        annotation = Annotated[kind, typer.Option(option.flag, help=f"{', '.join(names)}: {option.help}")]
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation))
    return params


def _with_dataset_options(command):
    """`command` with every benchmark's dataset options added to its signature (typer reads it)."""
    signature = inspect.signature(command, eval_str=True)
    fixed = [p for p in signature.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    fixed = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) if p.default is not inspect.Parameter.empty else p
             for p in fixed]
    params = fixed + all_dataset_parameters()
    command.__signature__ = inspect.Signature(params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


OPTION_FLAGS = {o.name: o.flag for bench in BENCHMARKS.values() for o in bench.command_options()}
app.command("import")(friendly_errors(_with_dataset_options(import_matches)))


@app.command()
@friendly_errors
def matchers(
    names: Annotated[Optional[list[str]], typer.Argument(help="Only these matchers (names or package.module:factory).")] = None,
) -> None:
    """Every matcher: its origin (built-in, plugin package and version, module), what it is, its settings and defaults."""
    from .matchers import broken_plugins, entries

    shown = [get_matcher(name, allow_import=True) for name in names] if names else entries()
    for line in describe_matchers(shown):
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    for name, why in ([] if names else sorted(broken_plugins().items())):
        console.print(f"{name}  (not loaded) {why}", markup=False, highlight=False, soft_wrap=True)


def describe_matchers(shown) -> list[str]:
    """The `matchers` listing: a head line per matcher, then its settings with their defaults."""
    import dataclasses

    from .matchers import BackboneSettings

    lines = []
    for entry in shown:
        lines.append(f"{entry.name}  ({entry.origin})  {entry.description}")
        if entry.preset_of is not None:
            lines.append(f"    = {entry.preset_of} with " + ", ".join(f"{k}={v}" for k, v in entry.preset.items()))
            continue
        settings = []
        for f in entry.setting_fields():
            if not f.init:
                continue
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            settings.append(f"{f.name}={_setting_text(default)}")
        lines.append("    settings: " + (", ".join(settings) or "none"))
        if entry.needs_backbone:
            net = ", ".join(f"{f.name}={_setting_text(f.default)}" for f in dataclasses.fields(BackboneSettings))
            lines.append(f"    backbone: --backbone, --weights; {net}")
        if entry.model:
            lines.append("    model: --device, --weights FILE (else the library's weights, downloaded into its cache once)")
        if entry.requires:
            lines.append(f"    needs: {', '.join(entry.requires)} (pip install 'e3cm-bench[peers]')")
        if entry.shorthands:
            lines.append("    shorthands: " + ", ".join(f"--{n.replace('_', '-')}" for n in entry.shorthands))
        if entry.paper_row:
            lines.append(f"    paper row: {entry.paper_row}")
    return lines


def _setting_text(value) -> str:
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    if isinstance(value, bool):
        return str(value).lower()
    return "none" if value is None else str(value)


synth_app = typer.Typer(no_args_is_help=True, help="Write synthetic data with exact ground truth.")
app.add_typer(synth_app, name="synth")


@synth_app.command("stereo")
@friendly_errors
def synth_stereo(
    out: Annotated[Path, typer.Option("--out", help="Sequence folder (KITTI odometry layout).")],
    frames: Annotated[int, typer.Option("--frames", help="Number of stereo frames.")] = 20,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the scene, the rig's drift and its path.")] = 0,
) -> None:
    """A stereo rig with a drifted extrinsic (about 1 degree each angle) moving through the demo's room scene."""
    root = write_stereo_sequence(out, frames=frames, seed=seed)
    console.print(f"synth stereo: {frames} frames in {root} (image_0/, image_1/, calib.txt, poses.txt)")


@app.command("export")
@friendly_errors
def export_matches(
    run: Annotated[Path, typer.Argument(help="A run folder (config.yaml, matches.h5).")],
    out: Annotated[Path, typer.Argument(help="Folder for the files.")],
    to: Annotated[str, typer.Option("--to", help="colmap (database.db), hloc (features.h5, matches.h5), gluefactory (predictions.h5) or npz (the folder import --npz reads).")],
    pixel_origin: Annotated[Optional[str], typer.Option("--pixel-origin", help="center or corner: overrides the format's own convention (hloc, npz: center; colmap, gluefactory: corner).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the files already in OUT.")] = False,
) -> None:
    """Write a run's matches for another tool: COLMAP, hloc, glue-factory or npz (docs: Matches in and out)."""
    from .interchange import export_run

    export_run(run, to, out, origin=pixel_origin, overwrite=overwrite, console=console)


if __name__ == "__main__":  # pragma: no cover
    app()
