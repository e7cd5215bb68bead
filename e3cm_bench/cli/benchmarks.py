"""The benchmark commands, one per registered benchmark (`e3cm-bench hpatches`, `megadepth`, ...),
made from the registry: the options every benchmark shares and each one's own dataset options."""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Annotated, Optional

import typer

from e3cm_bench.benchmarks import BENCHMARKS, Benchmark
from e3cm_bench.method.protocols import get_protocol, resolve_protocol
from e3cm_bench.ground.values import KINDS
from e3cm_bench.method.options import METHOD_OPTIONS
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.cli.common import (
    OnceEach,
    app,
    leave_defaults,
    console,
    eval_option,
    method_option,
    warn,
    DeviceOpt,
    BackboneBatchOpt,
    FeatureCacheOpt,
    FeatureReuseOpt,
    friendly_errors,
    ShardOpt,
    WorkersOpt,
    DevicesOpt,
    LauncherOpt,
    ShardsOpt,
    RootOpt,
    OutOpt,
    LimitOpt,
    OverwriteOpt,
    EvalOnlyOpt,
    VizOpt,
    SkipBadOpt,
    OnMatcherErrorOpt,
    PairTimeoutOpt,
    PlotFormatOpt,
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

    def check(self, eval_only: bool = False, device: str = "cpu") -> None:
        from e3cm_bench.pipeline.launch import check_launcher, check_workers
        from e3cm_bench.pipeline.shards import parse_shard

        check_launcher(self.launcher)
        if self.shard:
            parse_shard(self.shard)  # a K/N that is none, before anything loads
        several = [
            option
            for option, given in (
                ("--shard", self.shard),
                ("--workers", self.workers),
                ("--devices", self.devices),
                ("--launcher slurm", self.launcher == "slurm"),
            )
            if given
        ]
        if len(several) > 1:
            raise ValueError(f"{' and '.join(several)} do not go together: each says how the shards run")
        if eval_only and several and several != ["--shard"]:
            # the metrics of a merged run are recomputed from its matches.h5 in one process
            raise ValueError(f"--eval-only recomputes the metrics in this process: drop {several[0]}")
        if self.devices and device != "cpu":
            raise ValueError("--device and --devices do not go together: --devices names each shard's device")
        if not self.devices:
            check_workers(self.workers)
        if self.launcher == "slurm" and not self.shards:
            raise ValueError("--launcher slurm needs --shards N")
        if self.shards and self.launcher != "slurm":
            raise ValueError(f"--shards {self.shards} applies to --launcher slurm (local processes: --workers N)")
        if self.launcher == "slurm":
            from e3cm_bench.pipeline.launch import check_slurm

            check_slurm(self.shards)

    def device_list(self, device: str) -> list[str]:
        """The device of each local worker: --devices', else --device for each of --workers."""
        return self.devices.split(",") if self.devices else [device] * self.workers


def run_command(bench: Benchmark, given: dict) -> None:
    """What every benchmark command does with its options (the commands are made by
    benchmark_command): the flags that say how the shards run checked first (Scale), then the others,
    by section in their tables' names, resolved into the run's request (pipeline/resolve.py), which
    keeps what was typed (the flags not at their defaults) for the record."""
    from e3cm_bench.data.download import find_root
    from e3cm_bench.pipeline.resolve import resolve_request

    o = SimpleNamespace(**given)
    scale = Scale(o.shard, o.workers, o.devices, o.launcher, o.shards)
    scale.check(o.eval_only, o.device)  # the flags first: building the method may download weights
    request = resolve_request(bench.name, typed_sections(bench, given), locate=find_root, warn=warn)
    protocol = resolve_protocol(bench, given["protocol"])  # WxBS and EVD: their reference's (wxbs)
    console.print(get_protocol(protocol, bench.name).line(bench.name), markup=False)
    run_scaled(scale, request)


def typed_sections(bench: Benchmark, given: dict) -> dict:
    """A benchmark command's options by section (pipeline/resolve.py), those at their flag's default
    left out (the matcher kept: the run is a method's): what the user typed, as the record keeps it."""
    from e3cm_bench.pipeline.resolve import section_keys

    defaults = {name: default for name, _, default in common_before() + common_after(bench)}
    defaults.update((o.name, False if o.kind == "flag" else None) for o in bench.command_options())
    return leave_defaults({section: {name: given[name] for name in names if name in given}
                           for section, names in section_keys(bench).items()}, defaults)


def run_scaled(scale: Scale, request):
    """A run (a RunRequest) as `scale` says: in this process (its --shard K/N, or whole), or its
    shards in local workers or a SLURM array. Returns run_benchmark's summary in this process,
    else None (the merged summary is OUT's summary.csv, once written)."""
    from e3cm_bench.pipeline.launch import run_shards
    from e3cm_bench.pipeline.runner import run_benchmark

    if scale.workers or scale.devices:
        devices = scale.device_list(request.device)
        run_shards(request, len(devices), devices=devices, console=console)
    elif scale.launcher == "slurm":
        run_shards(request, scale.shards, devices=[request.device], launcher="slurm", console=console)
    else:
        return run_benchmark(request, console=console)
    return None


# Options of the benchmark commands.
SampleOpt = Annotated[
    Optional[int],
    typer.Option(
        "--sample",
        help="A stratified sample of N pairs: spread over the categories, scenes or sequences (--limit takes the "
             "first N).",
    ),
]
SampleSeedOpt = Annotated[int, typer.Option("--sample-seed", help="Seed of --sample's draw (recorded in config.yaml).")]


def _method(*names: str) -> tuple:
    """Method options by name, each with its typer option and default from its one declaration."""
    return tuple((name, method_option(name), METHOD_OPTIONS[name].default) for name in names)


# Where --help lists the method options it knows; one declared later (options.METHOD_OPTIONS) comes
# after them by itself, and every evaluation option (eval_options.EVAL_OPTIONS) in its table's order:
# a new one needs no line here.
_METHOD_FIRST = ("matcher", "backbone", "weights", "max_side")
_METHOD_SECOND = ("seed",)


def _other_method_options() -> tuple:
    placed = set(_METHOD_FIRST) | set(_METHOD_SECOND)
    return _method(*(name for name in METHOD_OPTIONS if name not in placed))


def eval_options(bench: Benchmark | None = None) -> tuple:
    """The evaluation options `bench` takes (Benchmark.eval_option_names; None: every one, `import`'s)
    as a command's option tuples, from their table."""
    names = bench.eval_option_names if bench is not None else tuple(EVAL_OPTIONS)
    return tuple((name, eval_option(name), EVAL_OPTIONS[name].default) for name in names)


def keyword_parameters(group: tuple) -> list[inspect.Parameter]:
    """A group of (name, typer annotation, default) as the keyword parameters typer reads."""
    return [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)
            for name, annotation, default in group]


# Every benchmark command's options, in the order --help lists them; the benchmark's own
# dataset options (Benchmark.dataset_options) come between the two groups. Functions, so that an
# option declared after this module loaded (a test's toy option) is on a command built later.
_NO_DEFAULT = inspect.Parameter.empty


def common_before() -> tuple:
    """The options --help lists before the benchmark's dataset options."""
    return (
        ("out", OutOpt, _NO_DEFAULT),
        ("root", RootOpt, None),
        *_method(*_METHOD_FIRST),
        ("limit", LimitOpt, None),
        ("sample", SampleOpt, None),
        ("sample_seed", SampleSeedOpt, 0),
        ("device", DeviceOpt, "cpu"),
        *_method(*_METHOD_SECOND),
        ("overwrite", OverwriteOpt, False),
        ("eval_only", EvalOnlyOpt, False),
        ("viz", VizOpt, 0),
        *_other_method_options(),
        ("feature_cache_mb", FeatureCacheOpt, None),
        ("backbone_batch", BackboneBatchOpt, None),
        ("feature_reuse", FeatureReuseOpt, True),
    )


def common_after(bench: Benchmark | None = None) -> tuple:
    """The options --help lists after the benchmark's dataset options (its evaluation options among them)."""
    return (
        ("skip_bad", SkipBadOpt, False),
        *eval_options(bench),
        ("on_matcher_error", OnMatcherErrorOpt, "stop"),
        ("pair_timeout", PairTimeoutOpt, None),
        ("shard", ShardOpt, None),
        ("workers", WorkersOpt, 0),
        ("devices", DevicesOpt, None),
        ("launcher", LauncherOpt, "local"),
        ("shards", ShardsOpt, 0),
        ("plot_format", PlotFormatOpt, "png"),
    )


def option_parameter(option, help_text: str) -> inspect.Parameter:
    """A dataset option as a keyword parameter typer reads as a command-line option: its kind's
    type (options.KINDS), a switch off by default, any other kind absent by default."""
    flag = option.kind == "flag"
    kind = KINDS[option.kind].cli if flag else Optional[KINDS[option.kind].cli]
    annotation = Annotated[kind, typer.Option(option.flag, help=help_text)]
    default = False if flag else None
    return inspect.Parameter(option.name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)


def dataset_parameters(bench: Benchmark) -> list[inspect.Parameter]:
    """The command-line options of a benchmark's dataset options."""
    return [option_parameter(option, option.help) for option in bench.command_options()]


def benchmark_command(bench: Benchmark):
    """The command `e3cm-bench NAME` of a registered benchmark: the common options and its own
    dataset options (typer reads the signature built here, as it reads a written one)."""

    def command(**given) -> None:
        from e3cm_bench.drawing.formats import plots_as

        with plots_as(given.pop("plot_format")):
            run_command(bench, given)

    params = keyword_parameters(common_before()) + dataset_parameters(bench) + keyword_parameters(common_after(bench))
    command.__signature__ = inspect.Signature(params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    command.__name__ = command.__qualname__ = bench.name.replace("-", "_")
    command.__doc__ = bench.summary or f"The {bench.name} benchmark."
    return friendly_errors(command)


for _bench in BENCHMARKS.values():
    app.command(_bench.name, cls=OnceEach)(benchmark_command(_bench))


