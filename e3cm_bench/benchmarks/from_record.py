"""What a run's record rebuilds: the benchmark it was made on, its evaluation settings, the
method that made it, and its pairs with their ground truth, loaded again as the run loaded
them. The record itself (storage/run_config.py) is plain data that imports nothing above the
ground floor; these readers sit here, above the benchmarks and methods they build."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.benchmarks.eval_options import RECONSTRUCTION_FIELDS
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.storage.run_config import SAMPLE_OPTIONS, RunConfig


def benchmark_of(config: RunConfig):
    """The registered Benchmark the run was made on; ValueError naming the file if none is."""
    try:
        return get_benchmark(config.benchmark)
    except ValueError as error:
        raise ValueError(f"{config.where}: {error}") from None


def evaluation_of(config: RunConfig, seed: int | None = None) -> EvalSettings:
    """The EvalSettings the run was evaluated with (its `evaluation` block; defaults for fields
    an older record lacks), with another RANSAC seed if given; ValueError naming the file when
    the block cannot be read as settings."""
    evaluation = config.evaluation
    if isinstance(evaluation, dict) and "mapper" not in evaluation:
        evaluation = {**evaluation, **older_protocol(config)}
    try:
        return EvalSettings.from_record(evaluation, **({} if seed is None else {"seed": int(seed)}))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{config.where}: its evaluation settings cannot be read ({error})") from None


def older_protocol(config: RunConfig) -> dict:
    """The reconstruction protocol of a record made before it was the evaluation's (an sfm run's
    dataset.protocol; a reconstruct run's mapper, mapper_seeds and merge_px among its dataset
    options, as typed), over its benchmark's defaults (Benchmark.eval_defaults); {} for a
    benchmark that reconstructs nothing."""
    try:
        defaults = dict(get_benchmark(str(config.benchmark)).eval_defaults)
    except ValueError:
        return {}
    if not defaults:
        return {}
    dataset = config.dataset if isinstance(config.dataset, dict) else {}
    load = config.dataset_load if isinstance(config.dataset_load, dict) else {}
    options = load.get("options") if isinstance(load.get("options"), dict) else {}
    given = dataset.get("protocol") if isinstance(dataset.get("protocol"), dict) else options
    kinds = {"mapper_seeds": int, "merge_px": float}
    given = {k: kinds.get(k, str)(v) for k, v in given.items() if k in RECONSTRUCTION_FIELDS and v is not None}
    return {**defaults, **given}


def method_of(config: RunConfig) -> MethodSpec:
    """The MethodSpec that made the run, from its identity. Only built-in matchers: a record is
    data and never names code to run (a plugin's run is not rebuilt)."""
    identity = dict(config.identity or {})
    if not identity or identity.get("plugin"):
        raise ValueError(f"{config.where}: only a built-in matcher's run can be rebuilt (no identity, or a plugin's)")
    return MethodSpec.from_identity(identity, label=str(config.method or ""))


def dataset_source(config: RunConfig, benchmark=None) -> tuple[str, bool, dict]:
    """(root, skip_bad, options) that load the run's dataset again: its ``dataset_load`` (absolute
    paths, the options as given, --sample's draw among them), else its ``dataset`` block (runs
    made before dataset_load, or from a dataset object). Options that do not apply to the
    benchmark are dropped."""
    benchmark = benchmark or benchmark_of(config)
    load, dataset = config.dataset_load, config.dataset
    if isinstance(load, dict) and load.get("root"):
        root, skip_bad, options = load["root"], bool(load.get("skip_bad")), dict(load.get("options") or {})
    elif dataset.get("root"):
        root, skip_bad = dataset["root"], bool(dataset.get("skip_bad"))
        options = {k: dataset[k] for k in benchmark.option_names if dataset.get(k) is not None}
        sample = dataset.get("sample")
        if isinstance(sample, dict) and sample.get("n"):
            options.update(sample=sample["n"], sample_seed=sample.get("seed", 0))
    else:
        raise ValueError(f"{config.where}: records no dataset root; the run's pairs cannot be loaded again")
    allowed = set(benchmark.option_names) | set(SAMPLE_OPTIONS)
    return str(root), skip_bad, {k: v for k, v in options.items() if k in allowed}


class RunPairs(NamedTuple):
    """A run's pairs loaded again, with their ground truth: `load_run_pairs`."""

    benchmark: object  # the Benchmark
    config: RunConfig
    root: Path  # the dataset's root, resolved
    pairs: list  # the run's pairs, in its order (its --limit applied)
    options: dict  # the dataset options they were loaded with
    dataset: object  # the PairList they come from (before the limit), for a rerun of the run


def load_run_pairs(run: str | Path | RunConfig) -> RunPairs:
    """The pairs of a run (a run folder, its config.yaml, or its RunConfig) as the run loaded them:
    the dataset it recorded (`dataset_source`: dataset_load, else the dataset block), with the
    bad-pair policy it recorded (skip_bad), cut to its --limit. Merging shards, exporting, the
    noise ensemble and the report's drawings all reload pairs here."""
    config = run if isinstance(run, RunConfig) else RunConfig.read(run)
    benchmark = benchmark_of(config)
    root, skip_bad, options = dataset_source(config, benchmark)
    dataset = benchmark.load_dataset(root, skip_bad=skip_bad, limit=config.limit, **options)
    pairs = list(dataset)[:config.limit] if config.limit else list(dataset)
    return RunPairs(benchmark, config, Path(root).resolve(), pairs, options, dataset)
