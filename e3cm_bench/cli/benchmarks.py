"""The benchmark commands, one per registered benchmark (`e3cm-bench hpatches`, `megadepth`, ...),
made from the registry: the options every benchmark shares and each one's own dataset options."""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..backbone_names import DEFAULT_BACKBONE
from ..benchmarks import BENCHMARKS, Benchmark
from ..benchmarks.protocols import get_protocol
from .common import app, console, MatcherOpt, BackboneOpt, WeightsOpt, DeviceOpt, EstimatorOpt, SampsonOpt, RatioOpt, LabelOpt, SetOpt, PrecisionOpt, ChannelOrderOpt, BackboneBatchOpt, FeatureCacheOpt, ProtocolOpt, parse_settings, friendly_errors, ShardOpt, WorkersOpt, DevicesOpt, LauncherOpt, ShardsOpt, RootOpt, OutOpt, MaxSideOpt, LimitOpt, SeedOpt, OverwriteOpt, EvalOnlyOpt, VizOpt, SkipBadOpt, RansacOpt, RepeatsOpt, OnMatcherErrorOpt, PairTimeoutOpt, PoseEstimatorOpt


def _method(bench: Benchmark, matcher: str, backbone: str, weights: Path | None, estimator: str | None,
            sampson_px: str | None, ratio: str | None, max_side: int | None, seed: int, label: str | None,
            settings: list[str] | None, protocol: str, precision: str = "fp32",
            channel_order: str = "rgb", device: str = "cpu") -> MethodSpec:
    """The method of a benchmark command (Benchmark.resolve_method, as experiment configs get theirs)."""
    from ..matchers import get_matcher
    from ..method import parse_numbers

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
            from ..run.launch import check_workers

            check_workers(self.workers)
        if self.launcher == "slurm" and not self.shards:
            raise ValueError("--launcher slurm needs --shards N")


def run_command(bench: Benchmark, dataset_options: dict, out: Path, root: Path | None, matcher: str, backbone: str,
                weights: Path | None, max_side: int | None, limit: int | None, sample: int | None, sample_seed: int,
                device: str, seed: int,
                overwrite: bool, eval_only: bool, viz: int, estimator: str | None, sampson_px: str | None,
                ratio: str | None, label: str | None, settings: list[str] | None, protocol: str | None, precision: str,
                channel_order: str, feature_cache_mb: float | None, backbone_batch: int | None, skip_bad: bool,
                ransac_px: float | None, pose_estimator: str | None, repeats: int, on_matcher_error: str,
                pair_timeout: float | None,
                shard: str | None, workers: int, devices: str | None, launcher: str, shards: int) -> None:
    """What every benchmark command does with its options (the commands are made by benchmark_command)."""
    from ..download import find_root
    from ..run.launch import run_shards
    from ..run.shards import parse_shard
    from ..run.stage import MatchOptions
    from ..runner import run_benchmark

    protocol = protocol or bench.default_protocol  # WxBS and EVD: their reference's (wxbs)
    method = _method(bench, matcher, backbone, weights, estimator, sampson_px, ratio, max_side, seed, label, settings,
                     protocol, precision, channel_order, device)
    scale = Scale(shard, workers, devices, launcher, shards)
    scale.check()
    if sample is not None:  # a dataset option for every benchmark (Benchmark.load_dataset)
        dataset_options = {**dataset_options, "sample": sample, "sample_seed": sample_seed}
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
SampleOpt = Annotated[Optional[int], typer.Option("--sample", help="A stratified sample of N pairs: spread over the categories, scenes or sequences (--limit takes the first N).")]
SampleSeedOpt = Annotated[int, typer.Option("--sample-seed", help="Seed of --sample's draw (recorded in config.yaml).")]

# Every benchmark command's options, in the order --help lists them; the benchmark's own
# dataset options (Benchmark.dataset_options) come between the two groups.
_NO_DEFAULT = inspect.Parameter.empty
COMMON_BEFORE = (
    ("out", OutOpt, _NO_DEFAULT), ("root", RootOpt, None), ("matcher", MatcherOpt, "e3cm"),
    ("backbone", BackboneOpt, DEFAULT_BACKBONE), ("weights", WeightsOpt, None), ("max_side", MaxSideOpt, None),
    ("limit", LimitOpt, None), ("sample", SampleOpt, None), ("sample_seed", SampleSeedOpt, 0), ("device", DeviceOpt, "cpu"), ("seed", SeedOpt, 0), ("overwrite", OverwriteOpt, False),
    ("eval_only", EvalOnlyOpt, False), ("viz", VizOpt, 0), ("estimator", EstimatorOpt, None),
    ("sampson_px", SampsonOpt, None), ("ratio", RatioOpt, None), ("label", LabelOpt, None), ("settings", SetOpt, None),
    ("protocol", ProtocolOpt, None), ("precision", PrecisionOpt, "fp32"), ("channel_order", ChannelOrderOpt, "rgb"),
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


def option_parameter(option, help_text: str) -> inspect.Parameter:
    """A dataset option as a keyword parameter typer reads as a command-line option."""
    kind, default = OPTION_TYPES[option.kind]
    annotation = Annotated[kind, typer.Option(option.flag, help=help_text)]
    return inspect.Parameter(option.name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)


def dataset_parameters(bench: Benchmark) -> list[inspect.Parameter]:
    """The command-line options of a benchmark's dataset options."""
    return [option_parameter(option, option.help) for option in bench.command_options()]


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


