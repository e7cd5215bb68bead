"""A run made again from its record: a run's config.yaml holds everything its numbers depend on
(the benchmark, the method's identity, the dataset as it was loaded, the evaluation settings,
the --limit), so it is the run's configuration, and `e3cm-bench rerun RUN --out NEW` makes the
same run in another folder from it alone: the same pairs, matched by the same method, scored
under the same settings, so per_pair.csv comes out byte for byte the same (cost.csv, the time
and memory, is a measurement and moves with the machine).

Each part is read back by the one reader of that part (benchmarks/from_record.py): the method from
its identity (a built-in matcher's only: a record is data and never names code to run), the
dataset from dataset_load, the evaluation from its block. What only decides how the matching
ran (the feature cache, the device, shards) is not part of the result and takes this machine's
defaults.

A record made by this version also holds `given`: the options as the user gave them, by section,
in the flags' names (pipeline/resolve.py), with its digest. A rerun resolves `given` again (the run's
where and how much are the rerun's, the dataset dataset_load's: absolute paths). Where `given` was
edited (its digest differs) the edit is the new run, in the names the user types; where it was not
and its resolution differs from the record's identity or evaluation blocks (a block edited, or a
default that moved since), the blocks hold, as they do for an older record without `given`.

A record may be edited into another run (another seed, RANSAC threshold or dataset option):
the readers skip keys they do not know, which suits an older record but would let a misspelt
edit pass unnoticed, so a rerun checks every key of the parts it reads first, and refuses an
unknown one in one line naming it and the nearest known key.
"""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.benchmarks.eval_options import RECONSTRUCTION_FIELDS
from e3cm_bench.benchmarks.from_record import benchmark_of, dataset_source, evaluation_of, method_of
from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.method.options import METHOD_OPTIONS
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.request import RUN_OPTIONS, RunRequest
from e3cm_bench.storage.run_config import SAMPLE_OPTIONS, RunConfig

# Top-level keys of records older versions wrote, read by nothing a rerun uses.
LEGACY_KEYS = ("match_options",)


def check_keys(config: RunConfig, benchmark) -> None:
    """Every key of the parts a rerun reads is one its reader knows (each reader's own key set): a
    ValueError naming the file, the key and the nearest known one otherwise."""
    record = config.record or {}
    known = {
        "": RunConfig.record_keys() | set(LEGACY_KEYS),
        "identity": MethodSpec.identity_keys(),
        "evaluation": EvalSettings.record_keys(),
        "dataset_load": {"root", "skip_bad", "options"},
        # an older sfm or reconstruct record's reconstruction protocol (evaluation options now: evaluation_of)
        "dataset_load.options": set(benchmark.option_names) | set(SAMPLE_OPTIONS)
        | (set(RECONSTRUCTION_FIELDS) if benchmark.eval_defaults else set()),
    }
    load = record.get("dataset_load") if isinstance(record.get("dataset_load"), dict) else {}
    parts = {"": record, "identity": record.get("identity"), "evaluation": record.get("evaluation"),
             "dataset_load": load, "dataset_load.options": load.get("options")}
    for part, values in parts.items():
        for key in values or {}:
            if key not in known[part]:
                name = f"{part}.{key}" if part else str(key)
                raise ValueError(f"{config.where}: {name} is not a key a run's record holds"
                                 f"{did_you_mean(str(key), known[part])}")


def recorded_limit(config: RunConfig) -> int | None:
    """The run's --limit as its record gives it (dataset.limit), by --limit's own check (kind and
    range; null: every pair). A record without the key is read as every pair only where the run
    evaluated every pair: one that evaluated fewer had a limit, and the key was lost or misspelt."""
    dataset = config.dataset
    if "limit" not in dataset:
        done, total = dataset.get("n_pairs_evaluated"), dataset.get("n_pairs")
        if all(isinstance(v, int) and not isinstance(v, bool) for v in (done, total)) and done < total:
            raise ValueError(f"{config.where}: dataset.limit is missing, but the run evaluated {done} of its {total} "
                             f"pairs{did_you_mean('limit', dataset)}; write limit: {done} (or null: every pair)")
        return None
    RUN_OPTIONS["limit"].check(dataset["limit"], f"{config.where}: dataset.limit")
    return dataset["limit"]


def check_identity_values(config: RunConfig) -> None:
    """The method options a record gives as values (the identity's max_side and seed, the
    evaluation's seed: --seed's), each by its flag's own check (options.METHOD_OPTIONS: kind and
    range; null: none), naming the key."""
    identity = config.identity if isinstance(config.identity, dict) else {}
    for name in ("max_side", "seed"):
        METHOD_OPTIONS[name].check(identity.get(name), f"{config.where}: identity.{name}")
    evaluation = config.evaluation if isinstance(config.evaluation, dict) else {}
    METHOD_OPTIONS["seed"].check(evaluation.get("seed"), f"{config.where}: evaluation.seed")


def rerun_request(run: str | Path, out: str | Path, device: str = "cpu", overwrite: bool = False) -> RunRequest:
    """The RunRequest that makes `run` (a folder or its config.yaml) again in `out`."""
    config = RunConfig.read(run)
    if config.shard is not None:
        raise ValueError(f"{config.where}: a shard's record; rerun the merged run (its folder above shards/)")
    if config.imported_files:
        raise ValueError(f"{config.where}: an imported run's matches came from files, not a method; "
                         "import them again (e3cm-bench import)")
    benchmark = benchmark_of(config)
    check_keys(config, benchmark)
    check_identity_values(config)
    limit = recorded_limit(config)  # before any work: a run of every pair where a few were asked is no rerun
    root, skip_bad, options = dataset_source(config, benchmark)
    benchmark.check_dataset_values(options, f"{config.where}: dataset_load.options: ")
    out = Path(out)
    if out.resolve() == config.path.parent.resolve():  # read() always says where the record came from
        raise ValueError(f"{out}: is the run itself; give another --out")
    run = {"out": out, "root": Path(root), "skip_bad": skip_bad, "limit": limit, "device": device,
           "overwrite": overwrite}
    if config.given is not None:
        request = from_given(config, benchmark, run, options)
        if request is not None:
            return request
    from e3cm_bench.pipeline.resolve import resolve_request  # the one builder of a request

    return resolve_request(benchmark, {"run": run, "dataset": options}, where=f"{config.where}: ",
                           recorded=(method_of(config), evaluation_of(config)))


def from_given(config: RunConfig, benchmark, run: dict, options: dict) -> RunRequest | None:
    """The request the record's `given` resolves to (`run` and `options` in place of its own where and
    how much and its dataset); None where `given` is as written and the identity or evaluation
    block says otherwise (module docstring): then the blocks make the run."""
    from dataclasses import asdict

    from e3cm_bench.pipeline.resolve import resolve_request
    from e3cm_bench.storage.run_config import given_digest

    if not isinstance(config.given, dict):
        raise ValueError(f"{config.where}: given must map sections (method, evaluation, ...) to options")
    # the run's where and how much are this rerun's, its dataset dataset_load's; a section no run has is refused
    given = {s: v for s, v in config.given.items() if s not in ("run", "dataset")}
    request = resolve_request(benchmark, {**given, "run": run, "dataset": options}, where=f"{config.where}: given: ")
    if request.method is None:
        raise ValueError(f"{config.where}: given names no method to rerun")
    if given_digest(config.given) != config.given_digest:  # edited: the user's words are the new run
        return request
    # both read as their readers read them (lists and tuples alike)
    same = (method_of(config).identity() == request.method.identity()
            and asdict(evaluation_of(config)) == asdict(request.ev))
    return request if same else None


def rerun(run: str | Path, out: str | Path, device: str = "cpu", overwrite: bool = False,
          console: Console | None = None):
    """Make the run again in `out` from its record; returns the new summary row."""
    from e3cm_bench.pipeline.runner import run_benchmark

    return run_benchmark(rerun_request(run, out, device, overwrite), console=console)
