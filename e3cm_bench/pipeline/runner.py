"""A benchmark run: the pipeline's benchmark hook (`BenchmarkRun`) and the Python API over it.

run_benchmark = the pipeline (pipeline/driver.py: open the folder, RunFolder checks its
identity -> record -> the match stage, pipeline/stage.py: pairs -> matches.h5 -> the evaluate
stage, pipeline/evaluate.py: matches.h5 + ground truth -> per-pair rows -> summary, CSVs,
plots, --viz -> the record and the printed summary). Everything that reaches a CSV is
recomputed from matches.h5 plus the ground truth, so `--eval-only` is the same run without the
match stage, and an interrupted run resumes at the first pair missing from the cache.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pandas as pd
from rich.console import Console
from rich.markup import escape

from e3cm_bench.benchmarks import Benchmark
from e3cm_bench.datasets.base import Pair, PairList
from e3cm_bench.ground.cost import machine_load, worse_load
from e3cm_bench.ground.devices import check_device, keep_freed_memory
from e3cm_bench.matchers import built_settings
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.guards import describe_matcher
from e3cm_bench.method.spec import MethodSpec, identity_changes
from e3cm_bench.pipeline.driver import PairRun, run_pipeline
from e3cm_bench.pipeline.pair import match_pair
from e3cm_bench.pipeline.request import RunRequest
from e3cm_bench.pipeline.resolve import request_from_fields
from e3cm_bench.pipeline.shards import check_shard_count, merge_when_complete, shard_command, shard_dir, shard_slice
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.pipeline.stage import MatchJob, match_jobs
from e3cm_bench.storage import RunConfig, RunFolder

__all__ = ["MatchOptions", "RunRequest", "match_pair", "run_benchmark", "run_methods"]


# --------------------------------------------------------------------------- the API


def run_benchmark(benchmark: str | Benchmark | RunRequest, out=None, method: MethodSpec | None = None, *,
                  console: Console | None = None, **request) -> pd.DataFrame:
    """Run (or resume, or only evaluate) one method on one benchmark; returns summary.csv's row.

    Takes a RunRequest, or its fields as arguments: run_benchmark("hpatches", "runs/hp", method,
    root=..., limit=10). The pairs come from `dataset`, or from the benchmark's dataset at `root`
    with `dataset_options`. `method` may be None only with eval_only (the folder's own is used).
    shard=(K, N): only the K-th of N slices of the pairs, as a run in OUT/shards/K-of-N/; the
    last shard to finish merges all of them into OUT (shards.merge_run).
    """
    if not isinstance(benchmark, RunRequest):
        benchmark = request_from_fields(benchmark, out, method, **request)
    request, console = benchmark, console or Console()
    if request.method is None and not request.eval_only:
        raise ValueError("run_benchmark: a method is needed unless eval_only")
    if request.shard is not None and request.eval_only:
        raise ValueError("--eval-only applies to a whole run: use e3cm-bench merge on a sharded one")
    _check_device(request, [request.method])
    request = _with_dataset(request, console)
    run_dir = request.out if request.shard is None else shard_dir(request.out, request.shard)
    summary, = _run_folders(request, [(run_dir, request.method)], console)
    if request.shard is not None and merge_when_complete(request.out, console):
        return pd.read_csv(RunFolder(request.out).summary_path)
    return pd.DataFrame([summary])


def run_methods(benchmark: str | Benchmark, runs: list[tuple], dataset: PairList, *, console: Console | None = None,
                **request) -> list[dict]:
    """Run (or resume) several methods on the same pairs, each into its own folder: runs holds
    (OUT, METHOD) or (OUT, METHOD, GIVEN), GIVEN what its record keeps as given (pipeline/resolve.py).

    The same as one run_benchmark per method, result for result, but the pairs are matched
    in one pass (match_jobs): each image is decoded once, and passes through a backbone once
    for all the methods that share its settings. Returns each run's summary row. `request`:
    the other fields of a RunRequest (ev, limit, viz, device, dataset_load, options).
    """
    console = console or Console()
    request = request_from_fields(benchmark, dataset=dataset, **request)
    _check_device(request, [run[1] for run in runs])
    limit = request.limit
    console.print(f"{request.bench.name}: {len(dataset)} pairs" + (f", limited to the first {limit}" if limit else "")
                  + (f"; {dataset.preamble()}" if dataset.preamble() else "")
                  + f"; {len(runs)} methods matched together", markup=False)
    return _run_folders(request, runs, console)


def _check_device(request: RunRequest, methods: list) -> None:
    if any(method is not None and method.backbone is not None for method in methods):
        check_device(request.device)


def _with_dataset(request: RunRequest, console: Console) -> RunRequest:
    """The request with its pairs (given, or loaded from its root) and how to load them again;
    says how many."""
    benchmark, dataset, limit = request.bench, request.dataset, request.limit
    if dataset is None:
        if request.root is None:
            raise ValueError("run_benchmark: give the dataset or its root")
        dataset = benchmark.load_dataset(
            request.root, skip_bad=request.skip_bad, limit=limit, **request.dataset_options
        )
        request = request.but(dataset=dataset, dataset_load=RunConfig.dataset_load_of(
            request.root, request.skip_bad, request.dataset_options))
    n_total = len(dataset) + dataset.n_skipped
    console.print(
        f"{benchmark.name}: {len(dataset)} pairs"
        + (f" ({dataset.n_skipped} of {n_total} skipped: {dataset.skip_reason()})" if dataset.n_skipped else "")
        + (f", limited to the first {limit}" if limit else "")
        + (f"; {dataset.preamble()}" if dataset.preamble() else ""),
        markup=False,
    )
    return request


def _run_folders(request: RunRequest, runs: list[tuple], console: Console) -> list[dict]:
    """Each (folder, method) of the request's pairs through the pipeline, matched in one stage."""
    if request.shard is not None:  # before any folder is opened: N shards of fewer pairs leave some with none
        n = len(request.dataset)
        check_shard_count(request.shard, min(n, request.limit) if request.limit else n)
    keep_freed_memory()  # a run's passes reuse the pages of the one before (docs/speed.md); recorded in config.yaml
    # (folder, method) or (folder, method, given): a reproduced method's own `given` (experiments.run_given)
    hooks = [BenchmarkRun.of(request.but(given=run[2]) if len(run) > 2 else request, run[0], run[1]) for run in runs]
    return run_pipeline(hooks, console)


# --------------------------------------------------------------------------- the hook


@dataclass
class BenchmarkRun(PairRun):
    """The benchmark hook: a method's matches made by the match stage (resumed from the cache)."""

    request: RunRequest = None
    method: MethodSpec | None = None
    todo: list[Pair] = field(default_factory=list)

    @classmethod
    def of(cls, request: RunRequest, out, method: MethodSpec | None) -> BenchmarkRun:
        return cls(request.bench, RunFolder(out), request.ev, request.viz, request.overwrite, request=request,
                   method=method)

    def open(self, console: Console) -> None:
        """The previous record (RunFolder checks its identity), the pairs still to match, the record."""
        request, folder, method = self.request, self.folder, self.method
        previous = folder.previous(None if method is None else method.identity(), self.benchmark.name,
                                   request.eval_only, changes=identity_changes, console=console)
        dataset, limit, shard = request.dataset, request.limit, request.shard
        pairs = list(dataset)[:limit] if limit else list(dataset)
        if shard is not None:
            pairs = pairs[shard_slice(len(pairs), shard)]
        # (pair, problem): the dataset's bad pairs (listed by the first shard only, so that a merge
        # counts them once), then those that fail to decode while matching.
        self.skipped = list(dataset.skipped) if shard is None or shard[0] == 1 else []
        self.cache, self.todo = folder.resume(pairs, console)
        self.pairs = pairs
        if request.eval_only:
            self._check_eval_only(previous)
        self.config = self._record(previous)
        name, where = self.benchmark.name, escape(str(folder.matches_path))
        if self.todo:
            console.print(method.describe(), markup=False)
            console.print(f"[bold]{name}[/]: {len(pairs)} pairs, {len(pairs) - len(self.todo)} already in {where}")
        else:
            console.print(f"[bold]{name}[/]: all {len(pairs)} pairs found in {where}; evaluating only")

    def _check_eval_only(self, previous: RunConfig | None) -> None:
        if previous is None:
            raise ValueError(
                f"{self.folder.config_path}: not found; --eval-only needs a finished or resumed run in --out"
            )
        if self.todo:
            raise ValueError(
                f"{self.folder.matches_path}: {len(self.todo)} of {len(self.pairs)} pairs have no matches "
                f"(first: {self.todo[0].name}); run without --eval-only to match them")

    def _record(self, previous: RunConfig | None) -> RunConfig:
        """The run's record: what the matches are comes from the folder when only evaluating, else
        from the method; the counts of earlier (resumed) stages are kept."""
        request, method, shard = self.request, self.method, self.request.shard
        source = previous if request.eval_only else None
        previous = previous or RunConfig.from_dict({})
        return RunConfig(
            benchmark=self.benchmark.name,
            method=source.method if source else method.label,
            identity=source.identity if source else method.identity(),
            matcher=previous.matcher,
            device=source.record.get("device", request.device) if source else request.device,
            dataset={**request.dataset.describe(), "limit": request.limit, "n_pairs_evaluated": len(self.pairs)},
            evaluation=self.ev.record(),
            environment=RunConfig.environment_now(),
            timing=previous.timing,
            feature_reuse=previous.feature_reuse or None,  # earlier stages' counts; add_stats adds this one's
            given=request.given if request.given is not None else previous.given,
            dataset_load=request.dataset_load or previous.dataset_load,
            shard=None if shard is None else {"index": shard[0], "count": shard[1], "n_pairs": len(self.pairs),
                                              "complete": False, "command": shard_command(shard)},
        )

    def record(self) -> None:
        if self.todo:  # before the model loads: the folder is claimed and described
            self.folder.write_config(self.config)

    @classmethod
    def produce(cls, runs: list[BenchmarkRun], console: Console) -> None:
        matching = [run for run in runs if run.todo]
        if matching:
            jobs = [run.job() for run in matching]
            request = matching[0].request
            with machine_load() as load:  # beside the time: how busy the machine was (ground/cost.py)
                match_jobs(jobs, request.device, console, request.options)
            for run, job in zip(matching, jobs):
                run.add_stats({**job.stats, "load": load})

    def title(self, summary: dict) -> str:
        return f"{self.benchmark.name} - {self.config.method} ({self.evaluated} pairs) -> {self.folder.path}"

    def job(self) -> MatchJob:
        def record_matcher(matcher: Matcher) -> None:
            # what it says of itself (a plugin that says nothing: what it was built from), checked to be writable
            now = describe_matcher(matcher, built_settings(self.method.matcher, self.method.settings_dict()))
            if len(self.todo) < len(self.pairs):  # resuming: the folder holds matches already
                self.folder.check_resolved(self.config.matcher, now)
            self.config.matcher = now
            self.folder.write_config(self.config)

        return MatchJob(
            self.method, self.todo, self.cache, self.skipped if self.request.dataset.skip_bad else None, record_matcher
        )

    def add_stats(self, spent: dict) -> None:
        """A match stage's time and feature reuse, added to those of earlier (resumed) stages."""
        config, spent = self.config, dict(spent)
        load = spent.pop("load", None)
        if load is not None:  # a resumed run: its most loaded stage's load averages, all stages' seconds
            config.timing["load"] = worse_load(config.timing.get("load"), load)
        reuse = spent.pop("feature_reuse", None)
        if reuse is not None:  # how often an image's maps served several pairs (no effect on results)
            before, reuse = config.feature_reuse or {}, dict(reuse)
            for key in (
                "backbone_passes",
                "extractions",
                "reused",
                "distinct_images",
                "read_from_disk",
                "written_to_disk",
                "disk_full",
                "dropped_from_disk",
                "products_reused",
                "batches_run",
            ):
                if key in reuse:  # counts of a resumed run add up over its stages
                    reuse[key] += before.get(key, 0)
            for key in ("images_alive_at_most", "peak_memory_mb", "peak_disk_mb", "largest_batch"):
                if key in reuse:  # highs: the highest stage's
                    reuse[key] = max(reuse[key], before.get(key, 0))
            if reuse.get("distinct_images"):
                reuse["passes_per_image"] = round(reuse["backbone_passes"] / reuse["distinct_images"], 4)
            config.feature_reuse = reuse
        timing = config.timing
        for key, value in spent.items():
            timing[key] = timing.get(key, 0) + value
        timing["pairs_per_minute"] = 60.0 * timing["pairs_matched"] / max(timing["match_seconds"], 1e-9)
