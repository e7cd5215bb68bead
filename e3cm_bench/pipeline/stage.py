"""The match stage: the pairs a run still lacks, through one or several methods' matchers, into
their caches, in one pass over the pairs (each image decoded once, a shared backbone's maps
reused across the pairs that share an image). Nothing here changes a result."""

from __future__ import annotations

import concurrent.futures
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from rich.console import Console

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.cost import SHARED_PEAK
from e3cm_bench.ground.devices import is_out_of_memory
from e3cm_bench.ground.images import ImageError, load_image
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.guards import StoppableWorker, can_fork
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.pair_order import most_alive, reuse_order
from e3cm_bench.pipeline.address_space import check_address_space
from e3cm_bench.ground.folders import fresh_folder, remove_folder
from e3cm_bench.storage.folder import FAILED_ATTR, RunFolder
from e3cm_bench.pipeline.pair import (COST_ATTRS, PAIR_ATTRS, MatcherError, TimeLimit, match_pair, match_worker,
                                      matcher_input, pair_rotations)
from e3cm_bench.pipeline.progress import progress_bar
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.ground.moved import moved_name


def match_cached_pair(
    matcher: Matcher, pair: Pair, method: MethodSpec, cache: MatchCache,
    images: tuple[np.ndarray, np.ndarray] | None = None, time_limit: float | None = None,
    worker: StoppableWorker | None = None, shared: bool = False,
) -> None:
    """Match one pair of a benchmark and store it (the step an interrupted run repeats).

    images: the pair's images already decoded (the match stage decodes ahead), else read here.
    worker: the matcher's stoppable child process (pipeline/pair.py match_worker), where
    --pair-timeout runs it. shared: the process holds other methods too (its peak is theirs too)."""
    image0, image1 = images if images is not None else (pair.image0, pair.image1)
    matches = match_pair(matcher, image0, image1, method.max_side, method.seed_for_matching,
                         pair_rotations(pair, method), method.resize, TimeLimit(time_limit, worker))
    if getattr(matcher, "feature_cache", None) is not None:  # the cache's share of the pair's peak
        matches.info["match_cache_mb"] = matcher.feature_cache.bytes / 2**20
    attrs = {k: matches.info[k] for k in PAIR_ATTRS + COST_ATTRS if k in matches.info}
    cache.write(pair.name, matches, {**attrs, SHARED_PEAK: True} if shared else attrs)


def decoded_ahead(pairs: list[Pair], executor: ThreadPoolExecutor, ahead: int = 1):
    """(pair, future of its two decoded images, [(pair, future)] of the next `ahead` pairs):
    the next pairs' decoding runs in a thread while the current pair is matched (OpenCV
    decodes with the GIL released). A decoding error is raised by the future's result(), at
    its own pair."""
    def read(pair: Pair) -> tuple[np.ndarray, np.ndarray]:
        return load_image(pair.image0), load_image(pair.image1)

    futures = {}
    for i, pair in enumerate(pairs):
        for j in range(i, min(i + 1 + ahead, len(pairs))):
            if j not in futures:
                futures[j] = executor.submit(read, pairs[j])
        yield pair, futures.pop(i), [(pairs[j], futures[j]) for j in range(i + 1, min(i + 1 + ahead, len(pairs)))]


def batch_ahead(job: MatchJob, matcher, batch: int, current: tuple[Pair, object], coming: list[tuple[Pair, object]],
                wanted: dict[str, list[int]], index: int) -> list[int]:
    """When an image of the current pair is not in the feature cache: pass it through the
    backbone together with the images of the coming pairs that the cache lacks, `batch` at a
    time (DeepMatcher.prefetch), as job's method will hand them to the matcher. A pair whose
    images cannot be decoded is left out here (its error comes at its own pair). Returns the
    size of each batch run."""
    if index not in wanted[current[0].name]:
        return []
    items = []
    for pair, images in [current, *coming]:
        if index not in wanted[pair.name]:
            continue
        try:
            decoded = images.result()
        except ImageError:
            continue
        for file, image, turns in zip((pair.image0, pair.image1), decoded, pair_rotations(pair, job.method)):
            small = matcher_input(image, turns, job.method.max_side, job.method.resize)[0]
            items.append((matcher.image_key(small), str(file), small))
        if pair is current[0] and all(matcher.feature_cache.holds(key) for key, _, _ in items):
            return []
    return matcher.prefetch(items, batch)


# --------------------------------------------------------------------------- the stage

@dataclass
class MatchJob:
    """One method's part of a match stage: the pairs it still has to match and where they go.

    skipped: when a list is given, a pair whose image cannot be decoded is appended to it as
    (name, problem) and the stage goes on; otherwise the error ends the stage (the pairs
    matched before it stay in the cache). on_matcher(matcher) runs once the model is loaded
    (the runner records its settings). stats is filled by the stage: seconds spent in this
    method's matcher, pairs matched and, for deep matchers, the feature reuse counts.
    """

    method: MethodSpec
    todo: list[Pair]
    cache: MatchCache
    skipped: list[tuple[str, str]] | None = None
    on_matcher: Callable[[Matcher], None] | None = None
    stats: dict = field(default_factory=dict)


def match_stage(
    method: MethodSpec, todo: list[Pair], cache: MatchCache, device: str, console: Console, on_matcher=None,
    skipped: list[tuple[str, str]] | None = None, options: MatchOptions | None = None,
) -> dict:
    """Build the matcher, match the pairs not yet cached, write each to the cache; returns the
    job's stats (see MatchJob)."""
    job = MatchJob(method, todo, cache, skipped, on_matcher)
    match_jobs([job], device, console, options)
    return job.stats


@dataclass
class _Shared:
    """The matchers of a stage, and the groups of them that share one backbone's feature cache."""

    matchers: list
    groups: dict
    budget: float
    disk: float
    batch: int
    alive: int = 0  # the most images alive at once in the stage's order (pair_order.most_alive)
    workers: list | None = None  # each matcher's StoppableWorker, where --pair-timeout isolates them

    @property
    def feature_caches(self) -> list:
        return [group["matcher"].feature_cache for group in self.groups.values()]


def match_jobs(jobs: list[MatchJob], device: str, console: Console, options: MatchOptions | None = None) -> None:
    """Match the pairs of several methods in one pass over the pairs.

    Each pair's images are decoded once for all methods, and deep matchers with the same
    backbone settings share one backbone and one feature cache, so an image goes through
    the network once for all of them (reproduce's deep methods but dfm). Nothing about a
    result changes: each method's matches go to its own cache. The pairs are matched in
    `reuse_order`; an image's maps are dropped once its last pair is matched.
    """
    options = options or MatchOptions()
    spill_root = RunFolder(jobs[0].cache.path.parent).spill_dir if jobs else None
    if spill_root is not None:
        remove_folder(spill_root)  # what an interrupted stage left; a link there refused, never followed
    shared = _build_matchers(jobs, device, options, spill_root)
    todo = sum(len(job.todo) for job in jobs)
    try:
        if todo:
            check_address_space("before matching", 0)
        if shared.workers is None and options.pair_timeout is not None:
            console.print(
                "--pair-timeout: CUDA is in use, and it cannot run in a forked child, so the limit runs in this "
                "process: a matcher that blocks SIGALRM or never returns from C code is not stopped by it",
                markup=False,
            )
        _pass_over_pairs(jobs, shared, console, options)
    finally:
        for worker in shared.workers or []:
            worker.close()
        for feature_cache in shared.feature_caches:
            feature_cache.close()
        if spill_root is not None:
            remove_folder(spill_root, ignore_errors=True)
    if todo:
        check_address_space("after matching", todo)
    _report_reuse(jobs, shared, console)


def isolates(options: MatchOptions) -> bool:
    """Whether the matchers run in stoppable child processes: with --pair-timeout, where this
    process can fork and has not started CUDA (which cannot be used in a forked child)."""
    if options.pair_timeout is None or not can_fork():
        return False
    torch = sys.modules.get("torch")
    return torch is None or not torch.cuda.is_initialized()


def _build_matchers(jobs: list[MatchJob], device: str, options: MatchOptions, spill_root) -> _Shared:
    """Each job's matcher (one backbone, one weights load, per setting), joined to the feature
    cache of its backbone's group; each in its stoppable child where `isolates`."""
    loaded: dict = {}
    built = [job.method.build(device, loaded=loaded) for job in jobs]
    isolated = isolates(options)
    if isolated:  # a child's feature maps stay in the child: no cache shared through this process
        options = replace(options, feature_cache_mb=0, backbone_batch=options.backbone_batch or 1)
    if options.feature_reuse and not isolated:
        from e3cm_bench.matchers.two_stage import reusing

        built = reusing(built)
    budget, batch, disk = 0.0, int(options.backbone_batch or 1), 0.0
    if any(getattr(matcher, "uses_feature_cache", False) for matcher in built):
        from e3cm_bench.matchers.feature_cache import auto_cache_mb
        from e3cm_bench.matchers.spill import auto_spill_mb

        budget = auto_cache_mb(device) if options.feature_cache_mb is None else float(options.feature_cache_mb)
        if any(hasattr(matcher, "backbone") for matcher in built):
            # torch: imported only for a matcher on a backbone (a classical run's address space stays small)
            from e3cm_bench.matchers.deep import auto_backbone_batch

            batch = auto_backbone_batch(device) if options.backbone_batch is None else int(options.backbone_batch)
        if budget and spill_root is not None:
            disk = auto_spill_mb(spill_root) if options.spill_mb is None else float(options.spill_mb)
    shared = _Shared([], {}, budget, disk, batch)
    for job, matcher in zip(jobs, built):
        if budget and getattr(matcher, "uses_feature_cache", False):
            from e3cm_bench.matchers.spill import SpillStore

            identity = matcher.feature_identity()
            if identity not in shared.groups:
                if disk > 0 and not shared.groups:  # made here, anew: never through a link (remove_folder)
                    fresh_folder(spill_root)
                spill = SpillStore(spill_root / str(len(shared.groups)), disk) if disk > 0 else None
                shared.groups[identity] = {"matcher": matcher, "labels": [], "spill": spill,
                                           "lead": len(shared.matchers), "batches": []}
            group = shared.groups[identity]
            matcher.share_features_of(group["matcher"], budget, group["spill"])
            group["labels"].append(job.method.label)
        if job.on_matcher is not None:
            job.on_matcher(getattr(matcher, "matcher", matcher))  # a two-stage matcher recorded as it is
        shared.matchers.append(matcher)
        job.stats.update(match_seconds=0.0, pairs_matched=0)
    if isolated:
        shared.workers = [match_worker(matcher) for matcher in shared.matchers]
    return shared


def _pass_over_pairs(jobs: list[MatchJob], shared: _Shared, console: Console, options: MatchOptions) -> None:
    """One pass over every pair any job still needs, in reuse order: each pair's images decoded
    once (ahead, in a thread), matched by every job that needs it; an image's maps dropped
    after its last pair."""
    wanted: dict[str, list[int]] = {}
    pairs: dict[str, Pair] = {}
    for i, job in enumerate(jobs):
        for pair in job.todo:
            pairs.setdefault(pair.name, pair)
            wanted.setdefault(pair.name, []).append(i)
    labels = ", ".join(job.method.label for job in jobs)
    feature_caches, batch = shared.feature_caches, shared.batch
    with progress_bar(console) as progress, ThreadPoolExecutor(max_workers=1) as executor:
        task = progress.add_task(f"matching ({labels})", total=sum(len(job.todo) for job in jobs))
        # few images alive at once; the cache is told the order, so it keeps what comes soonest
        order = reuse_order(list(pairs.values()))
        shared.alive = most_alive(order)
        files_in_order = [(str(pair.image0), str(pair.image1)) for pair in order]
        last_use = {file: k for k, files in enumerate(files_in_order) for file in files}
        for feature_cache in feature_caches:
            feature_cache.plan(files_in_order)
        for k, (pair, images, coming) in enumerate(decoded_ahead(order, executor, ahead=batch)):
            files = files_in_order[k]
            for feature_cache in feature_caches:
                feature_cache.at(k, files)
            if batch > 1:
                for group in shared.groups.values():
                    lead = group["lead"]
                    group["batches"] += batch_ahead(jobs[lead], shared.matchers[lead], batch, (pair, images), coming,
                                                    wanted, lead)
            if shared.workers and any(worker.pid is None for worker in shared.workers):
                # A child is forked here (the first, or one after a stop): with the decoding
                # thread idle, so that no lock it holds is copied into the child held.
                concurrent.futures.wait([images, *(future for _, future in coming)])
                for i in wanted[pair.name]:
                    shared.workers[i].start()
            for i in wanted[pair.name]:
                _match_one(jobs[i], shared.matchers[i], pair, images, options,
                           shared.workers[i] if shared.workers else None, len(jobs) > 1)
                progress.advance(task)
            for file in dict.fromkeys(files):
                if last_use[file] == k:  # no pair left: its maps are not needed again
                    for feature_cache in feature_caches:
                        feature_cache.done_with(file)


def _report_reuse(jobs: list[MatchJob], shared: _Shared, console: Console) -> None:
    """Each backbone group's feature reuse, into its jobs' stats and on screen."""
    for group in shared.groups.values():
        reuse = group["matcher"].feature_cache
        stats = {"cache_mb": round(shared.budget), "spill_mb": round(shared.disk),
                 "images_alive_at_most": shared.alive, **reuse.stats(),
                 "shared_by": group["labels"], "backbone_batch": shared.batch, "batches_run": len(group["batches"]),
                 "largest_batch": max(group["batches"], default=0)}
        for job, matcher in zip(jobs, shared.matchers):
            if getattr(matcher, "feature_cache", None) is reuse:
                job.stats["feature_reuse"] = stats
        what = "backbone passes" if hasattr(group["matcher"], "backbone") else "extractions"
        console.print(f"features ({', '.join(group['labels'])}): {stats['extractions']} {what} for "
                      f"{stats['distinct_images']} images ({stats['passes_per_image']:.2f} per image), "
                      f"{stats.get('read_from_disk', 0)} read back from disk", markup=False)  # labels are the user's


def _match_one(job: MatchJob, matcher: Matcher, pair: Pair, images, options: MatchOptions | None = None,
               worker: StoppableWorker | None = None, shared: bool = False) -> None:
    """One method's match of one pair, into its cache (shared: among others in this process);
    errors in one line naming the pair."""
    t = time.perf_counter()
    try:
        options = options or MatchOptions()
        match_cached_pair(matcher, pair, job.method, job.cache, images.result(), options.pair_timeout, worker, shared)
        job.stats["pairs_matched"] += 1
    except (RuntimeError, MemoryError) as error:
        if not (isinstance(error, MemoryError) or is_out_of_memory(error)):
            raise
        raise ValueError(f"pair {pair.name}: {too_big_message(job.method, error)}") from None
    except MatcherError as error:
        if options.on_matcher_error != "fail-pair":
            raise MatcherError(f"pair {pair.name}: {error} (the pairs matched before it are kept; "
                               "--on-matcher-error fail-pair counts such a pair as failed and goes on)") from error
        store_failure(job.cache, pair, images.result(), str(error))
        job.stats["pairs_failed"] = job.stats.get("pairs_failed", 0) + 1
    except ImageError as error:
        if job.skipped is None:
            raise ImageError(f"{error} (pair {pair.name}; the pairs matched before it are kept; "
                             "--skip-bad skips such pairs)") from None
        job.skipped.append((pair.name, str(error)))
    job.stats["match_seconds"] += time.perf_counter() - t


def store_failure(cache: MatchCache, pair: Pair, images: tuple[np.ndarray, np.ndarray], message: str) -> None:
    """A pair the matcher failed on: no matches, and the message, so that it scores as a failure."""
    from e3cm_bench.ground.matches import Matches

    size0, size1 = ((int(image.shape[1]), int(image.shape[0])) for image in images)
    empty = Matches(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros(0, np.float32))
    cache.write(pair.name, empty, {"size0": size0, "size1": size1, "match_size0": size0, "match_size1": size1,
                                   "match_seconds": float("nan"), FAILED_ATTR: message[:2000]})


def too_big_message(method: MethodSpec, error: BaseException) -> str:
    # A MemoryError of DeepMatcher.check_memory says how much is needed and which side fits.
    hint = str(error) if isinstance(error, MemoryError) and "--max-side" in str(error) else \
        "pass a smaller --max-side, e.g. 1600"
    return (
        f"its images at {method.resize_description} do not fit in memory for {method.label} (the pairs matched before "
        "it are "
        f"kept): {hint}"
    )


def __getattr__(name: str):
    return moved_name(__name__, name)  # the match section's table moved to match_options.py (ground/moved.py)
