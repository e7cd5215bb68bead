"""The one place where datasets, matchers, the match cache and the metrics meet.

run_benchmark = check the folder -> match stage (pairs -> matches.h5) -> evaluate stage
(matches.h5 + ground truth -> per-pair rows -> summary) -> reports (CSVs, plots, --viz,
config.yaml). Everything that reaches a CSV is recomputed from matches.h5 plus the ground
truth, so `--eval-only` is the same run without the match stage, and an interrupted run
resumes at the first pair missing from the cache.
"""

from __future__ import annotations

import shutil
import time
from contextlib import ExitStack
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Callable
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.text import Text

from .benchmarks import Benchmark, EvalSettings, get_benchmark
from .cache import MatchCache
from .datasets.base import Pair, PairList
from .devices import check_device, is_out_of_memory, keep_freed_memory
from .evaluate import evaluate_and_report
from .files import absolute_paths
from .images import ImageError, load_image, resize_max_side, to_original_pixels
from .matchers.base import Matcher
from .matches import Matches, MatchesError, check_in_image
from .method import MethodSpec, identity_changes
from .pair_order import most_alive, reuse_order
from .report import print_summary
from .run import RunConfig, RunFolder
from .shards import merge_when_complete, shard_dir, shard_slice
# What match_pair adds to a result's info and the cache keeps next to each pair's matches.
PAIR_ATTRS = ("size0", "size1", "match_size0", "match_size1", "match_seconds")


# --------------------------------------------------------------------------- one pair


def match_pair(
    matcher: Matcher, image0: str | Path | np.ndarray, image1: str | Path | np.ndarray,
    max_side: int | None = None, seed: int = 0, rotations: tuple[int, int] = (0, 0),
    resize: str = "shrink",
) -> Matches:
    """Match two images (paths or H x W x 3 RGB uint8 arrays); keypoints in original pixels.

    rotations: quarter turns (np.rot90, counter-clockwise) that make each image upright, as
    a YFCC/ScanNet pair list's rot0/rot1 give them; the images are matched upright (CNN
    features are not rotation invariant) and the keypoints mapped back to the stored images.
    The images are resized by their longer side to `max_side` (None: full size; `resize`:
    how, images.RESIZE_MODES, by default shrunk to at most max_side), matched, and the
    keypoints mapped back. OpenCV's RNG is seeded with `seed` first, so
    matchers with a RANSAC inside give the same matches every time. ``info`` holds the
    matcher's diagnostics plus size0/size1 (original w, h), match_size0/1 and match_seconds.
    """
    image0 = load_image(image0) if not isinstance(image0, np.ndarray) else image0
    image1 = load_image(image1) if not isinstance(image1, np.ndarray) else image1
    small0, scale0 = matcher_input(image0, rotations[0], max_side, resize)
    small1, scale1 = matcher_input(image1, rotations[1], max_side, resize)
    cv2.setRNGSeed(int(seed))
    t = time.perf_counter()
    m = checked_match(matcher, small0, small1)
    info = {
        **m.info,
        "size0": (image0.shape[1], image0.shape[0]),
        "size1": (image1.shape[1], image1.shape[0]),
        "match_size0": (small0.shape[1], small0.shape[0]),
        "match_size1": (small1.shape[1], small1.shape[0]),
        "match_seconds": time.perf_counter() - t,
    }
    if any(rotations):
        info["rotations"] = tuple(int(r) for r in rotations)
    keypoints0 = unrotate_points(to_original_pixels(m.keypoints0, scale0), rotations[0], info["size0"])
    keypoints1 = unrotate_points(to_original_pixels(m.keypoints1, scale1), rotations[1], info["size1"])
    return Matches(keypoints0, keypoints1, m.scores, info)


def matcher_input(image: np.ndarray, quarter_turns: int, max_side: int | None, resize: str) -> tuple[np.ndarray, float]:
    """An image as match_pair hands it to the matcher (upright, resized by its longer side),
    and the scale of that resize."""
    return resize_max_side(np.ascontiguousarray(np.rot90(image, quarter_turns)), max_side, resize)


class MatcherError(ValueError):
    """A matcher that raised, or returned something that is not sound matches."""


def checked_match(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> Matches:
    """matcher.match, with what it returns checked: a Matches of N x 2 keypoints and N scores,
    all finite, inside the images (unless the matcher says its points may leave them). A
    matcher that raises or returns anything else gives a MatcherError naming it; running out
    of memory is left as it is (the runner says what to do about it)."""
    name = getattr(matcher, "name", type(matcher).__name__)
    try:
        m = matcher.match(image0, image1)
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as error:  # noqa: BLE001 - whatever a plugin raises ends in one line
        if is_out_of_memory(error):
            raise
        raise MatcherError(f"matcher {name} raised {type(error).__name__}: {error}") from error
    if not isinstance(m, Matches):
        raise MatcherError(f"matcher {name} returned {type(m).__name__}, expected e3cm_bench.Matches")
    try:
        m = Matches(m.keypoints0, m.keypoints1, m.scores, m.info)  # shapes and lengths, again: fields may be reassigned
        check_in_image(m, (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0]),
                       bounded=getattr(matcher, "keypoints_in_image", True))
    except MatchesError as error:
        raise MatcherError(f"matcher {name} returned bad matches: {error}") from None
    return m


def unrotate_points(points: np.ndarray, quarter_turns: int, stored_size: tuple[int, int]) -> np.ndarray:
    """Points of np.rot90(image, k) -> points of the stored image (w, h), pixel-centre convention.

    One counter-clockwise turn sends stored pixel (x, y) to (y, w - 1 - x); undone one turn
    at a time.
    """
    points = np.asarray(points, dtype=np.float64).copy()
    w, h = stored_size
    for turn in range(quarter_turns % 4, 0, -1):
        # The image rotated (turn - 1) times has width w or h; its turn-th rotation is undone.
        width = w if (turn - 1) % 2 == 0 else h
        x, y = points[:, 0].copy(), points[:, 1].copy()
        points[:, 0], points[:, 1] = width - 1 - y, x
    return points.astype(np.float32)


def pair_rotations(pair: Pair, method: MethodSpec) -> tuple[int, int]:
    """The quarter turns that make the pair upright (rot0/rot1 of its list), unless the method
    matches images as stored."""
    if not method.upright:
        return (0, 0)
    return int(pair.meta.get("rot0", 0)), int(pair.meta.get("rot1", 0))


def match_cached_pair(
    matcher: Matcher, pair: Pair, method: MethodSpec, cache: MatchCache,
    images: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Match one pair of a benchmark and store it (the step an interrupted run repeats).

    images: the pair's images already decoded (the match stage decodes ahead), else read here."""
    image0, image1 = images if images is not None else (pair.image0, pair.image1)
    matches = match_pair(matcher, image0, image1, method.max_side, method.seed_for_matching,
                         pair_rotations(pair, method), method.resize)
    cache.write(pair.name, matches, {k: matches.info[k] for k in PAIR_ATTRS})


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


# --------------------------------------------------------------------------- progress


class RateColumn(ProgressColumn):
    """Pairs per minute (rich has a speed column for bytes only)."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("-- pairs/min" if speed is None else f"{speed * 60:.1f} pairs/min", style="cyan")


def progress_bar(console: Console) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), RateColumn(),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )


# --------------------------------------------------------------------------- stages


# Memory for the feature pyramids of the run's images (matchers/feature_cache.py): pairs that
# share an image reuse its maps. None: half the memory available when the stage starts, at most
# 16 GiB (feature_cache.auto_cache_mb). VGG19 at 1200 x 900 needs about 0.5 GiB per image,
# Lite0 0.12; bf16 and fp16 maps are held in half of that.
FEATURE_CACHE_MB = None


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
    skipped: list[tuple[str, str]] | None = None, feature_cache_mb: float | None = FEATURE_CACHE_MB,
    spill_mb: float | None = None, backbone_batch: int | None = None,
) -> dict:
    """Build the matcher, match the pairs not yet cached, write each to the cache; returns the
    job's stats (see MatchJob). feature_cache_mb, spill_mb, backbone_batch: see match_jobs."""
    job = MatchJob(method, todo, cache, skipped, on_matcher)
    match_jobs([job], device, console, feature_cache_mb, spill_mb, backbone_batch)
    return job.stats


def match_jobs(jobs: list[MatchJob], device: str, console: Console, feature_cache_mb: float | None = FEATURE_CACHE_MB,
               spill_mb: float | None = None, backbone_batch: int | None = None) -> None:
    """Match the pairs of several methods in one pass over the pairs.

    Each pair's images are decoded once for all methods, and deep matchers with the same
    backbone settings share one backbone and one feature cache, so an image goes through
    the network once for all of them (reproduce's deep methods but dfm). Nothing about a
    result changes: each method's matches go to its own cache.

    feature_cache_mb: memory (MiB) for the feature pyramids of images that have pairs left
    (0: no reuse; None: half the memory available now, at most 16 GiB). spill_mb: disk for
    the pyramids memory cannot hold, in the first job's run folder (0: none; None: half the
    free disk space there, at most 64 GiB). The pairs are matched in `reuse_order`; an
    image's maps are dropped once its last pair is matched. backbone_batch: images passed
    through a shared backbone together when the current pair needs a pass, with the coming
    pairs' images the cache lacks (batch_ahead; None: 8 on a GPU, 1 on a CPU; needs the cache).
    """
    from .matchers.deep import auto_backbone_batch
    from .matchers.feature_cache import SpillStore, auto_cache_mb, auto_spill_mb  # torch: loaded when matching

    budget = auto_cache_mb(device) if feature_cache_mb is None else float(feature_cache_mb)
    batch = auto_backbone_batch(device) if backbone_batch is None else int(backbone_batch)
    if batch < 1:
        raise ValueError(f"--backbone-batch must be at least 1, got {batch}")
    # What memory cannot hold goes to the first job's run folder (removed when the stage ends), up
    # to half the free disk space there, at most 64 GiB (feature_cache.auto_spill_mb); 0: never.
    spill_root = RunFolder(jobs[0].cache.path.parent).spill_dir if jobs else None
    if spill_root is not None:
        shutil.rmtree(spill_root, ignore_errors=True)  # what an interrupted stage left
    disk = 0.0 if not budget or spill_root is None else auto_spill_mb(spill_root) if spill_mb is None else float(spill_mb)
    matchers, groups, loaded = [], {}, {}
    for job in jobs:
        matcher = job.method.build(device, loaded=loaded)  # one backbone (one weights load) per setting
        if budget and getattr(matcher, "uses_feature_cache", False):
            identity = matcher.feature_identity()
            if identity not in groups:
                spill = SpillStore(spill_root / str(len(groups)), disk) if disk > 0 else None
                groups[identity] = {"matcher": matcher, "labels": [], "spill": spill, "lead": len(matchers),
                                    "batches": []}
            group = groups[identity]
            matcher.share_features_of(group["matcher"], budget, group["spill"])
            group["labels"].append(job.method.label)
        if job.on_matcher is not None:
            job.on_matcher(matcher)
        matchers.append(matcher)
        job.stats.update(match_seconds=0.0, pairs_matched=0)
    wanted: dict[str, list[int]] = {}
    pairs: dict[str, Pair] = {}
    for i, job in enumerate(jobs):
        for pair in job.todo:
            pairs.setdefault(pair.name, pair)
            wanted.setdefault(pair.name, []).append(i)
    labels = ", ".join(job.method.label for job in jobs)
    feature_caches = [group["matcher"].feature_cache for group in groups.values()]
    try:
        with progress_bar(console) as progress, ThreadPoolExecutor(max_workers=1) as executor:
            task = progress.add_task(f"matching ({labels})", total=sum(len(job.todo) for job in jobs))
            # few images alive at once; the cache is told the order, so it keeps what comes soonest
            order = reuse_order(list(pairs.values()))
            alive = most_alive(order)
            files_in_order = [(str(pair.image0), str(pair.image1)) for pair in order]
            last_use = {file: k for k, files in enumerate(files_in_order) for file in files}
            for feature_cache in feature_caches:
                feature_cache.plan(files_in_order)
            for k, (pair, images, coming) in enumerate(decoded_ahead(order, executor, ahead=batch)):
                files = files_in_order[k]
                for feature_cache in feature_caches:
                    feature_cache.at(k, files)
                if batch > 1:
                    for group in groups.values():
                        lead = group["lead"]
                        group["batches"] += batch_ahead(jobs[lead], matchers[lead], batch, (pair, images), coming,
                                                        wanted, lead)
                for i in wanted[pair.name]:
                    _match_one(jobs[i], matchers[i], pair, images)
                    progress.advance(task)
                for file in dict.fromkeys(files):
                    if last_use[file] == k:  # no pair left: its maps are not needed again
                        for feature_cache in feature_caches:
                            feature_cache.done_with(file)
    finally:
        for feature_cache in feature_caches:
            feature_cache.close()
        if spill_root is not None:
            shutil.rmtree(spill_root, ignore_errors=True)
    for group in groups.values():
        reuse = group["matcher"].feature_cache
        stats = {"cache_mb": round(budget), "spill_mb": round(disk), "images_alive_at_most": alive, **reuse.stats(),
                 "shared_by": group["labels"], "backbone_batch": batch, "batches_run": len(group["batches"]),
                 "largest_batch": max(group["batches"], default=0)}
        for job, matcher in zip(jobs, matchers):
            if getattr(matcher, "feature_cache", None) is reuse:
                job.stats["feature_reuse"] = stats
        console.print(f"feature maps ({', '.join(group['labels'])}): {stats['backbone_passes']} backbone passes for "
                      f"{stats['distinct_images']} images ({stats['passes_per_image']:.2f} per image), "
                      f"{stats.get('read_from_disk', 0)} read back from disk")


def _match_one(job: MatchJob, matcher: Matcher, pair: Pair, images) -> None:
    """One method's match of one pair, into its cache; errors in one line naming the pair."""
    t = time.perf_counter()
    try:
        match_cached_pair(matcher, pair, job.method, job.cache, images.result())
        job.stats["pairs_matched"] += 1
    except (RuntimeError, MemoryError) as error:
        if not (isinstance(error, MemoryError) or is_out_of_memory(error)):
            raise
        raise ValueError(f"pair {pair.name}: {too_big_message(job.method, error)}") from None
    except MatcherError as error:
        raise MatcherError(f"pair {pair.name}: {error} (the pairs matched before it are kept)") from error
    except ImageError as error:
        if job.skipped is None:
            raise ImageError(f"{error} (pair {pair.name}; the pairs matched before it are kept; "
                             "--skip-bad skips such pairs)") from None
        job.skipped.append((pair.name, str(error)))
    job.stats["match_seconds"] += time.perf_counter() - t


def too_big_message(method: MethodSpec, error: BaseException) -> str:
    # A MemoryError of DeepMatcher.check_memory says how much is needed and which side fits.
    hint = str(error) if isinstance(error, MemoryError) and "--max-side" in str(error) else \
        "pass a smaller --max-side, e.g. 1600"
    return (f"its images at {method.resize_description} do not fit in memory for {method.label} (the pairs matched before it are "
            f"kept): {hint}")


# --------------------------------------------------------------------------- a run


# Settings a matcher resolves when it is built, not in the identity: `auto` there may resolve
# otherwise in another version (VGG19's fp32 layout became channels_last), and the maps with it.
RESOLVED_AT_BUILD = ("memory_format",)


def _check_resolved(before: dict | None, now: dict, path: Path) -> None:
    """Refuse to resume a folder whose matches were made with a setting that resolved otherwise
    (recorded in its config.yaml `matcher`; records without it are not checked)."""
    changed = [f"{key} {before[key]} -> {now[key]}" for key in RESOLVED_AT_BUILD
               if before and key in before and key in now and before[key] != now[key]]
    if changed:
        raise ValueError(
            f"{path}: the matches in this folder were made with the backbone run otherwise ({', '.join(changed)}; "
            "the maps round differently); pass --overwrite to replace them or choose another --out"
        )


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
    feature_cache_mb: float | None = FEATURE_CACHE_MB,
    backbone_batch: int | None = None,
) -> pd.DataFrame:
    """Run (or resume, or only evaluate) one method on one benchmark; returns summary.csv's row.

    feature_cache_mb: memory (MiB) for reusing an image's feature maps across the pairs that
    share it (0: off; None: sized from the memory available, see match_jobs; it never changes
    a result). backbone_batch: images per backbone pass (None: 8 on a GPU, 1 on a CPU; see
    match_jobs).
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
    if dataset is None:
        if root is None:
            raise ValueError("run_benchmark: give the dataset or its root")
        dataset = benchmark.load_dataset(root, skip_bad=skip_bad, **(dataset_options or {}))
        # How to load the same pairs again (merging shards needs the ground truth), with absolute
        # paths: a merge may run in another working directory (a SLURM task's).
        load = {"root": str(Path(root).resolve()), "skip_bad": skip_bad,
                "options": {k: absolute_paths(v) for k, v in (dataset_options or {}).items() if v is not None}}
    else:
        load = dataset_load  # given with a dataset object, so that its shards can be merged
    n_total = len(dataset) + dataset.n_skipped
    console.print(
        f"{benchmark.name}: {len(dataset)} pairs"
        + (f" ({dataset.n_skipped} of {n_total} skipped: {dataset.skip_reason()})" if dataset.n_skipped else "")
        + (f", limited to the first {limit}" if limit else ""),
        markup=False,
    )

    if shard is not None:
        if eval_only:
            raise ValueError("--eval-only applies to a whole run: use e3cm-bench merge on a sharded one")
        run_dir = shard_dir(out, shard)
    else:
        run_dir = out
    summary, = _run_folders(benchmark, [(run_dir, method)], dataset, ev, limit, overwrite, eval_only, viz, device,
                            console, shard, load, feature_cache_mb, backbone_batch)
    if shard is not None and merge_when_complete(out, console):
        return pd.read_csv(RunFolder(out).summary_path)
    return pd.DataFrame([summary])


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
    feature_cache_mb: float | None = FEATURE_CACHE_MB,
    backbone_batch: int | None = None,
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
                  + f"; {len(runs)} methods matched together", markup=False)
    return _run_folders(benchmark, runs, dataset, ev or EvalSettings(), limit, False, False, viz, device, console,
                        None, dataset_load, feature_cache_mb, backbone_batch)


def _run_folders(
    benchmark: Benchmark, runs: list[tuple[Path, MethodSpec | None]], dataset: PairList, ev: EvalSettings,
    limit: int | None, overwrite: bool, eval_only: bool, viz: int, device: str, console: Console,
    shard: tuple[int, int] | None = None, load: dict | None = None, feature_cache_mb: float | None = FEATURE_CACHE_MB,
    backbone_batch: int | None = None,
) -> list[dict]:
    """Lock every folder, open each run, match what they still need in one stage, then
    evaluate and report each."""
    if viz < 0:
        raise ValueError(f"--viz must be 0 (no drawings) or more, got {viz}")
    keep_freed_memory()  # a run's passes reuse the pages of the one before (docs/speed.md); recorded in config.yaml
    with ExitStack() as locks:
        opened = []
        for out, method in runs:
            locks.enter_context(RunFolder(out).lock())  # taken before anything in the folder is read or written
            opened.append(_open_run(benchmark, out, method, dataset, ev, limit, overwrite, eval_only, device,
                                    console, shard, load))
        matching = [run for run in opened if run.todo]
        if matching:
            jobs = [run.job() for run in matching]
            match_jobs(jobs, device, console, feature_cache_mb, backbone_batch=backbone_batch)
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
            # what the matcher says of itself (a plugin's object may have no config())
            describe = getattr(matcher, "config", None)
            now = describe() if callable(describe) else {"matcher": getattr(matcher, "name", type(matcher).__name__)}
            if len(self.todo) < len(self.pairs):  # resuming: the folder holds matches already
                _check_resolved(self.config.matcher, now, self.folder.config_path)
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
    limit: int | None, overwrite: bool, eval_only: bool, device: str, console: Console,
    shard: tuple[int, int] | None = None, load: dict | None = None,
) -> _OpenRun:
    folder = RunFolder(out)
    if overwrite and out.exists():
        folder.clear()
    out.mkdir(parents=True, exist_ok=True)
    previous = folder.previous(None if method is None else method.identity(), benchmark.name, eval_only,
                               changes=identity_changes)
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
        shard=None if shard is None else {"index": shard[0], "count": shard[1], "n_pairs": len(pairs), "complete": False},
    )
    if todo:
        console.print(method.describe(), markup=False)
        console.print(f"[bold]{benchmark.name}[/]: {len(pairs)} pairs, {len(pairs) - len(todo)} already in {folder.matches_path}")
        folder.write_config(config)  # before the model loads: the folder is claimed and described
    else:
        console.print(f"[bold]{benchmark.name}[/]: all {len(pairs)} pairs found in {folder.matches_path}; evaluating only")
    return _OpenRun(benchmark, folder, method, pairs, todo, skipped, dataset.skip_bad, cache, config, ev)


def _finish_run(run: _OpenRun, viz: int, console: Console) -> dict:
    config, folder = run.config, run.folder
    pairs, summary = evaluate_and_report(run.benchmark, folder, config.method, run.pairs, run.skipped, run.cache,
                                         run.ev, viz, console)
    config.dataset["n_skipped"] = len(run.skipped)
    if config.shard is not None:
        config.shard["complete"] = True  # written before the merge check (shards.merge_when_complete)
    folder.write_config(config)
    print_summary(summary, f"{run.benchmark.name} - {config.method} ({len(pairs)} pairs) -> {folder.path}", console=console)
    return summary
