"""A run: the stages of run/ put together. The one place where datasets, matchers, the match
cache and the metrics meet.

run_benchmark = open the folder (run.driver.open_run; RunFolder checks its identity) ->
match stage (run/stage.py: pairs -> matches.h5) -> evaluate stage (evaluate.py: matches.h5 +
ground truth -> per-pair rows -> summary) -> reports (CSVs, plots, --viz, config.yaml:
run.driver.finish_run). Everything that reaches a CSV is
recomputed from matches.h5 plus the ground truth, so `--eval-only` is the same run without the
match stage, and an interrupted run resumes at the first pair missing from the cache.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path

import pandas as pd
from rich.console import Console
from rich.markup import escape

from .benchmarks import Benchmark, EvalSettings, get_benchmark
from .cache import MatchCache
from .datasets.base import Pair, PairList
from .devices import check_device, keep_freed_memory
from .matchers.base import Matcher
from .matchers import built_settings
from .matchers.guards import describe_matcher
from .method import MethodSpec, identity_changes
from .run import RunConfig, RunFolder, driver
from .run.pair import match_pair
from .run.stage import MatchJob, MatchOptions, match_jobs
from .run.shards import check_shard_count, merge_when_complete, shard_command, shard_dir, shard_slice

__all__ = ["MatchOptions", "match_pair", "run_benchmark", "run_methods"]


# --------------------------------------------------------------------------- a run


def run_benchmark(
    benchmark: str | Benchmark,
    out: str | Path,
    method: MethodSpec | None = None,
    *,
    root: str | Path | None = None,
    dataset: PairList | None = None,
    dataset_options: dict | None = None,
    skip_bad: bool = False,
    ev: EvalSettings | None = None,
    limit: int | None = None,
    overwrite: bool = False,
    eval_only: bool = False,
    viz: int = 0,
    device: str = "cpu",
    shard: tuple[int, int] | None = None,
    dataset_load: dict | None = None,
    console: Console | None = None,
    options: MatchOptions | None = None,
) -> pd.DataFrame:
    """Run (or resume, or only evaluate) one method on one benchmark; returns summary.csv's row.

    options: how the match stage runs (feature cache, batching, what a failing matcher does:
    run.stage.MatchOptions).
    The pairs come from `dataset`, or from the benchmark's dataset at `root` with
    `dataset_options`. `method` may be None only with eval_only (the folder's own is used).
    shard=(K, N): only the K-th of N slices of the pairs, as a run in OUT/shards/K-of-N/;
    the last shard to finish merges all of them into OUT (shards.merge_run).
    """
    console = console or Console()
    benchmark = get_benchmark(benchmark)
    ev = ev or EvalSettings()
    out = Path(out)
    if method is None and not eval_only:
        raise ValueError("run_benchmark: a method is needed unless eval_only")
    if limit is not None and limit < 1:
        raise ValueError(f"--limit must be at least 1, got {limit}")
    if method is not None and method.backbone is not None:
        check_device(device)
    dataset, load = _dataset(benchmark, dataset, root, dataset_options, skip_bad, dataset_load, limit, console)

    if shard is not None:
        if eval_only:
            raise ValueError("--eval-only applies to a whole run: use e3cm-bench merge on a sharded one")
        run_dir = shard_dir(out, shard)
    else:
        run_dir = out
    summary, = _run_folders(benchmark, [(run_dir, method)], dataset, ev, limit, overwrite, eval_only, viz, device,
                            console, shard, load, options)
    if shard is not None and merge_when_complete(out, console, known=(benchmark,)):
        return pd.read_csv(RunFolder(out).summary_path)
    return pd.DataFrame([summary])


def _dataset(benchmark: Benchmark, dataset: PairList | None, root, dataset_options: dict | None, skip_bad: bool,
             dataset_load: dict | None, limit: int | None, console: Console) -> tuple[PairList, dict | None]:
    """The run's pairs (given, or loaded from `root`) and how to load them again; says how many."""
    if dataset is None:
        if root is None:
            raise ValueError("run_benchmark: give the dataset or its root")
        dataset = benchmark.load_dataset(root, skip_bad=skip_bad, limit=limit, **(dataset_options or {}))
        load = RunConfig.dataset_load_of(root, skip_bad, dataset_options)
    else:
        load = dataset_load  # given with a dataset object, so that its shards can be merged
    n_total = len(dataset) + dataset.n_skipped
    console.print(
        f"{benchmark.name}: {len(dataset)} pairs"
        + (f" ({dataset.n_skipped} of {n_total} skipped: {dataset.skip_reason()})" if dataset.n_skipped else "")
        + (f", limited to the first {limit}" if limit else "")
        + (f"; {dataset.preamble()}" if dataset.preamble() else ""),
        markup=False,
    )
    return dataset, load


def run_methods(
    benchmark: str | Benchmark,
    runs: list[tuple[Path, MethodSpec]],
    dataset: PairList,
    *,
    dataset_load: dict | None = None,
    ev: EvalSettings | None = None,
    limit: int | None = None,
    viz: int = 0,
    device: str = "cpu",
    console: Console | None = None,
    options: MatchOptions | None = None,
) -> list[dict]:
    """Run (or resume) several methods on the same pairs, each into its own folder (OUT, METHOD).

    The same as one run_benchmark per method, result for result, but the pairs are matched
    in one pass (match_jobs): each image is decoded once, and passes through a backbone once
    for all the methods that share its settings. Returns each run's summary row.
    """
    console = console or Console()
    benchmark = get_benchmark(benchmark)
    if any(method.backbone is not None for _, method in runs):
        check_device(device)
    if limit is not None and limit < 1:
        raise ValueError(f"--limit must be at least 1, got {limit}")
    console.print(f"{benchmark.name}: {len(dataset)} pairs" + (f", limited to the first {limit}" if limit else "")
                  + (f"; {dataset.preamble()}" if dataset.preamble() else "")
                  + f"; {len(runs)} methods matched together", markup=False)
    return _run_folders(benchmark, runs, dataset, ev or EvalSettings(), limit, False, False, viz, device, console,
                        None, dataset_load, options)


def _run_folders(
    benchmark: Benchmark, runs: list[tuple[Path, MethodSpec | None]], dataset: PairList, ev: EvalSettings,
    limit: int | None, overwrite: bool, eval_only: bool, viz: int, device: str, console: Console,
    shard: tuple[int, int] | None = None, load: dict | None = None, options: MatchOptions | None = None,
) -> list[dict]:
    """Lock every folder, open each run, match what they still need in one stage, then
    evaluate and report each."""
    if viz < 0:
        raise ValueError(f"--viz must be 0 (no drawings) or more, got {viz}")
    if shard is not None:  # before any folder is opened: N shards of fewer pairs leave some with none
        check_shard_count(shard, min(len(dataset), limit) if limit else len(dataset))
    keep_freed_memory()  # a run's passes reuse the pages of the one before (docs/speed.md); recorded in config.yaml
    with ExitStack() as locks:
        opened = []
        for out, method in runs:
            locks.enter_context(driver.open_run(RunFolder(out), overwrite))
            opened.append(_open_run(benchmark, out, method, dataset, ev, limit, eval_only, device, console, shard, load))
        matching = [run for run in opened if run.todo]
        if matching:
            jobs = [run.job() for run in matching]
            match_jobs(jobs, device, console, options)
            for run, job in zip(matching, jobs):
                run.add_stats(job.stats)
        return [_finish_run(run, viz, console) for run in opened]


@dataclass
class _OpenRun:
    """A run whose folder is locked and described, between its match and evaluate stages."""

    benchmark: Benchmark
    folder: RunFolder
    method: MethodSpec | None
    pairs: list[Pair]
    todo: list[Pair]
    skipped: list[tuple[str, str]]
    skip_bad: bool
    cache: MatchCache
    config: RunConfig
    ev: EvalSettings

    def job(self) -> MatchJob:
        def record_matcher(matcher: Matcher) -> None:
            # what it says of itself (a plugin that says nothing: what it was built from), checked to be writable
            now = describe_matcher(matcher, built_settings(self.method.matcher, self.method.settings_dict()))
            if len(self.todo) < len(self.pairs):  # resuming: the folder holds matches already
                self.folder.check_resolved(self.config.matcher, now)
            self.config.matcher = now
            self.folder.write_config(self.config)

        return MatchJob(self.method, self.todo, self.cache, self.skipped if self.skip_bad else None, record_matcher)

    def add_stats(self, spent: dict) -> None:
        """A match stage's time and feature reuse, added to those of earlier (resumed) stages."""
        config, spent = self.config, dict(spent)
        reuse = spent.pop("feature_reuse", None)
        if reuse is not None:  # how often an image's maps served several pairs (no effect on results)
            before, reuse = config.feature_reuse or {}, dict(reuse)
            for key in ("backbone_passes", "reused", "distinct_images", "read_from_disk", "written_to_disk", "disk_full",
                        "dropped_from_disk", "products_reused", "batches_run"):
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


def _open_run(
    benchmark: Benchmark, out: Path, method: MethodSpec | None, dataset: PairList, ev: EvalSettings,
    limit: int | None, eval_only: bool, device: str, console: Console,
    shard: tuple[int, int] | None = None, load: dict | None = None,
) -> _OpenRun:
    """Describe a run whose folder driver.open_run holds: the previous record (RunFolder checks
    its identity), the pairs still to match, the RunConfig."""
    folder = RunFolder(out)
    previous = folder.previous(None if method is None else method.identity(), benchmark.name, eval_only,
                               changes=identity_changes, console=console)
    pairs = list(dataset)[:limit] if limit else list(dataset)
    if shard is not None:
        pairs = pairs[shard_slice(len(pairs), shard)]
    # (pair, problem): the dataset's bad pairs (listed by the first shard only, so that a merge
    # counts them once), then those that fail to decode while matching.
    skipped = list(dataset.skipped) if shard is None or shard[0] == 1 else []
    cache, todo = folder.resume(pairs, console)

    if eval_only:
        if previous is None:
            raise ValueError(f"{folder.config_path}: not found; --eval-only needs a finished or resumed run in --out")
        if todo:
            raise ValueError(
                f"{folder.matches_path}: {len(todo)} of {len(pairs)} pairs have no matches (first: {todo[0].name}); "
                "run without --eval-only to match them"
            )
    # What the matches are comes from the folder when only evaluating, else from the method.
    source = previous if eval_only else None
    previous = previous or {}
    config = RunConfig(
        benchmark=benchmark.name,
        method=source["method"] if source else method.label,
        identity=source.get("identity") if source else method.identity(),
        matcher=previous.get("matcher"),
        device=source.get("device", device) if source else device,
        dataset={**dataset.describe(), "limit": limit, "n_pairs_evaluated": len(pairs)},
        evaluation=asdict(ev),
        environment=RunConfig.environment_now(),
        timing=previous.get("timing", {}),
        feature_reuse=previous.get("feature_reuse") or None,  # counts of earlier stages; add_stats adds this one's
        dataset_load=load or previous.get("dataset_load"),
        shard=None if shard is None else {"index": shard[0], "count": shard[1], "n_pairs": len(pairs), "complete": False,
                                          "command": shard_command(shard)},
    )
    if todo:
        console.print(method.describe(), markup=False)
        console.print(f"[bold]{benchmark.name}[/]: {len(pairs)} pairs, {len(pairs) - len(todo)} already in {escape(str(folder.matches_path))}")
        folder.write_config(config)  # before the model loads: the folder is claimed and described
    else:
        console.print(f"[bold]{benchmark.name}[/]: all {len(pairs)} pairs found in {escape(str(folder.matches_path))}; evaluating only")
    return _OpenRun(benchmark, folder, method, pairs, todo, skipped, dataset.skip_bad, cache, config, ev)


def _finish_run(run: _OpenRun, viz: int, console: Console) -> dict:
    config, name = run.config, run.benchmark.name
    _, summary = driver.finish_run(run.benchmark, run.folder, config, run.pairs, run.skipped, run.cache, run.ev, viz,
                                   console, lambda n: f"{name} - {config.method} ({n} pairs) -> {run.folder.path}")
    return summary
