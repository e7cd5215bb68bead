"""The one resolver: a run's request from what its user gave, by section, in the tables' own names.

`given` is a mapping by section, each section keyed by the names of its one table:
- ``method``: the method options (method/options.py METHOD_OPTIONS: matcher, backbone, max_side,
  seed, protocol, ...), as a command's flags, an experiment's ``methods:`` entry and MethodSpec take them;
- ``evaluation``: the evaluation options the benchmark takes (benchmarks/eval_options.py EVAL_OPTIONS:
  every benchmark's, and its own, such as sfm's mapper and mapper_seeds: Benchmark.eval_option_names);
- ``dataset``: the benchmark's own dataset options (Benchmark.command_options) and --sample's draw;
- ``run``: where and how much (RUN_KEYS: out, root, limit, viz, overwrite, eval_only, skip_bad,
  device, shard);
- ``match``: how the match stage runs (pipeline/stage.py MatchOptions' fields).

The benchmark commands, `reconstruct`, `rank`, `rerun` of a record that holds `given`, and the Python
API (`resolve_request`; run_benchmark's and run_methods' keywords through `request_from_fields`) build
their request here, so one name means one thing from the flag to the
record: the run's config.yaml keeps `given` as it came (its `given` block), beside what it resolved
to (identity, evaluation, dataset_load). An unknown section or name is one line with the nearest,
and a name given in the wrong section names the section it belongs to.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import fields
from pathlib import Path

from e3cm_bench.benchmarks import Benchmark, get_benchmark
from e3cm_bench.ground.files import yaml_plain
from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.method.options import METHOD_OPTIONS, check_method_values, with_defaults
from e3cm_bench.method.protocols import resolve_protocol
from e3cm_bench.method import spec as method_spec
from e3cm_bench.pipeline.request import RunRequest
from e3cm_bench.pipeline.shards import check_shard, parse_shard, shard_dir
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.storage.folder import RunFolder
from e3cm_bench.storage.run_config import SAMPLE_OPTIONS

SECTIONS = ("method", "evaluation", "dataset", "run", "match")
RUN_KEYS = ("out", "root", "limit", "viz", "overwrite", "eval_only", "skip_bad", "device", "shard")


def section_keys(bench: Benchmark) -> dict[str, tuple[str, ...]]:
    """Each section's names on `bench` (its dataset options are its own)."""
    return {"method": tuple(METHOD_OPTIONS), "evaluation": bench.eval_option_names,
            "dataset": bench.option_names + SAMPLE_OPTIONS,
            "run": RUN_KEYS, "match": tuple(f.name for f in fields(MatchOptions))}


def check_given(bench: Benchmark, given: Mapping, where: str = "") -> dict[str, dict]:
    """`given`'s sections and names, each one of its table's: one line for the first that is not,
    with the nearest name, or the section a name belongs to. Returns every section (empty where
    none was given)."""
    keys = section_keys(bench)
    if not isinstance(given, Mapping):
        raise ValueError(f"{where}a run's options are a mapping by section ({', '.join(SECTIONS)})")
    for section, values in given.items():
        if section not in keys:
            raise ValueError(f"{where}{section!r} is not a section of a run's options{did_you_mean(section, keys)}; "
                             f"they are {', '.join(SECTIONS)}")
        if values is not None and not isinstance(values, Mapping):
            raise ValueError(f"{where}{section}: must map option names to values, got {type(values).__name__}")
        for name in values or {}:
            if name in keys[section]:
                continue
            home = next((s for s, k in keys.items() if name in k), None)
            hint = f"; it is an option of the {home} section" if home else did_you_mean(name, keys[section])
            a = "an" if section[0] in "aeiou" else "a"
            raise ValueError(f"{where}{section}: {name!r} is not {a} {section} option of {bench.name}{hint}")
    return {section: dict(given.get(section) or {}) for section in SECTIONS}


def as_record(given: Mapping) -> dict:
    """`given` as config.yaml keeps it: the sections given, each value given (None left out), as
    YAML's plain values (paths as text, tuples as lists: files.yaml_plain)."""
    record = {section: {k: yaml_plain(v) for k, v in (values or {}).items() if v is not None}
              for section, values in given.items()}
    return {section: values for section, values in record.items() if values}


def resolve_request(benchmark: str | Benchmark, given: Mapping,
                    locate: Callable[[str, Path | None], Path] | None = None,
                    warn: Callable[[str], None] | None = None, where: str = "", *,
                    recorded: tuple | None = None) -> RunRequest:
    """The RunRequest of `given` (module docstring) on `benchmark`. Every value is checked before
    anything loads, then a busy --out is refused, and only then the method is built (it may load
    torch or download weights). locate(benchmark, root): the data folder where run.root is not
    given (the commands' data/ lookup); without it run.root is the folder as given. recorded: the
    (MethodSpec, EvalSettings) a record already resolved (rerun of a record without `given`, or
    whose blocks hold: pipeline/rerun.py), taken as they are in place of the method and evaluation
    sections."""
    bench = get_benchmark(benchmark)
    method, evaluation, dataset, run, match = (check_given(bench, given, where)[s] for s in SECTIONS)
    RunRequest.check_counts(run.get("limit"), run.get("viz") or 0)
    values = method_spec.method_values({k: v for k, v in method.items() if v is not None})
    check_method_values(with_defaults(values))  # the names too (a mistyped --matcher), before torch loads
    bench.check_dataset_values(dataset, where)
    shard = parse_shard(run["shard"]) if isinstance(run.get("shard"), str) else run.get("shard")
    if run.get("out") is not None:  # a busy folder before torch and the method load
        RunFolder(shard_dir(Path(run["out"]), shard) if shard else run["out"]).check_free()
    ev = (recorded[1] if recorded is not None
          else bench.resolve_eval(resolve_protocol(bench, values.get("protocol")), values.get("seed") or 0, evaluation))
    options = MatchOptions(**{k: v for k, v in match.items() if v is not None})
    # each command option the user left out at its default (a switch off, else none), as its flag has it
    dataset = {**{o.name: False if o.kind == "flag" else None for o in bench.command_options()}, **dataset}
    if dataset.get("sample") is None:  # the draw's seed means nothing without a draw
        dataset = {k: v for k, v in dataset.items() if k not in SAMPLE_OPTIONS}
    root = locate(bench.name, run.get("root")) if locate is not None else run.get("root")
    device = run.get("device") or "cpu"
    # no matcher named: no method (import's matches come from files, reproduce's methods from its
    # config, --eval-only scores the folder's own)
    spec = (recorded[0] if recorded is not None
            else method_spec.build_method(values, bench, device, warn=warn) if values.get("matcher") else None)
    flags = {k: bool(run.get(k)) for k in ("overwrite", "eval_only", "skip_bad")}
    return RunRequest(benchmark, run.get("out"), spec, root=None if root is None else Path(root),
                      dataset_options=dataset, ev=ev, limit=run.get("limit"), viz=run.get("viz") or 0, device=device,
                      shard=shard, options=options, given=None if recorded is not None else as_record(given), **flags)


def request_from_fields(benchmark: str | Benchmark, out=None, method=None, **values) -> RunRequest:
    """The Python API's request (run_benchmark's and run_methods' keywords: RunRequest's field
    names), made by resolve_request as every other entry's is: the run's own names are its `run`
    section, dataset_options its `dataset` section, options (a MatchOptions) its `match` section,
    so they are checked by the same tables. The method (a MethodSpec) and ev (EvalSettings; None:
    the benchmark's default protocol's, as its command has them) come already resolved and are
    taken as they are; dataset, dataset_load and given are handed over with them. A keyword that is
    no field is a TypeError naming the nearest, as a command names the nearest flag."""
    known = {f.name for f in fields(RunRequest)}  # benchmark, out and method are this function's own
    for name in values:
        if name not in known:
            raise TypeError(f"{name!r} is not a field of a run's request{did_you_mean(name, known)}; "
                            f"it has {', '.join(sorted(known))}")
    if values.get("shard") is not None:  # the API's (K, N), as documented; "K/N" text is the command line's
        check_shard(values["shard"])
    bench = get_benchmark(benchmark)
    match, default = values.pop("options", None) or MatchOptions(), MatchOptions()
    given = {"run": {"out": out, **{k: values.pop(k) for k in RUN_KEYS if k in values}},
             "dataset": values.pop("dataset_options", None) or {},
             "match": {f.name: getattr(match, f.name) for f in fields(MatchOptions)
                       if getattr(match, f.name) != getattr(default, f.name)}}
    ev = values.pop("ev", None) or bench.resolve_eval()
    request = resolve_request(benchmark, given, recorded=(method, ev))
    return request.but(**values)  # dataset, dataset_load, given: resolved values, handed over as they are
