"""The evaluate stage of a run: cached matches + ground truth -> per-pair rows, the summary,
and the reports (CSVs, the run's plot, --viz drawings). Shared by the runner, merged shards
and imported matches; it never matches."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

import pandas as pd
from rich.console import Console

from e3cm_bench import stats
from e3cm_bench.benchmarks import Benchmark, EvalSettings
from e3cm_bench.benchmarks.base import DUPLICATES, with_duplicates
from e3cm_bench.storage.cache import MatchCache, check_free_space
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.cost import SHARED_PEAK
from e3cm_bench.ground.files import CSV_FLOAT_FORMAT, write_csv
from e3cm_bench.ground.images import header_size, load_image
from e3cm_bench.benchmarks.intervals import INTERVAL_SEEDS, metric_keys, summary_intervals
from e3cm_bench.ground.matches import Matches, distinct
from e3cm_bench.storage import FAILED_ATTR
from e3cm_bench.drawing.matches import draw_matches, drawn, drawn_pairs, save_image


def evaluate_stage(
    benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings, workdir: Path | None = None,
    matcher: str | None = None,
) -> tuple[pd.DataFrame, dict, list[tuple[str, str]]]:
    """Every pair's row from its cached matches and ground truth, the summary of the rows, and
    (pair, message) of the pairs stored as the matcher's failures (--on-matcher-error fail-pair),
    each pair read from the cache once. matcher: the run's (its configuration's), for a benchmark
    that scores the set together and whose defaults follow the matcher's kind (sfm's merge).

    The summary holds each metric's bootstrap interval over the pairs beside it (``<metric>_lo``,
    ``<metric>_hi``, and the bootstrap's samples, seed and confidence: intervals.py).
    """
    rows, failures, read, costs = [], [], [], []
    for pair in pairs:
        matches = cache.read(pair.name)
        costs.append(pair_cost(matches))
        if benchmark.evaluates_set:  # scored together below, from every pair's matches
            read.append(matches)
        else:
            rows.append(evaluate_pair(benchmark, pair, matches, ev))
        if FAILED_ATTR in matches.info:
            failures.append((pair.name, str(matches.info[FAILED_ATTR])))
    set_numbers = {}
    if benchmark.evaluates_set:
        rows, set_numbers = benchmark.evaluate_set(pairs, read, ev, workdir, matcher)
    if ev.repeats > 1:
        summary = repeated_summary(benchmark, pairs, cache, ev, rows)
    else:
        summary = benchmark.summarize(rows, ev)
        indexed = benchmark.interval_summary(rows, ev)
        if ev.interval_seeds > 1 and not benchmark.evaluates_set:
            indexed = seeded_interval_summary(benchmark, pairs, cache, ev, rows)
            summary[INTERVAL_SEEDS] = ev.interval_seeds
        summary.update(summary_intervals(benchmark, rows, ev, summary=summary, indexed=indexed))
    summary.update(set_numbers)  # after the intervals: facts of the one set, not resampled
    summary.update(cost_summary(costs))
    # with_duplicates: a benchmark that does not list the column still gets it, the rows hold it
    return pd.DataFrame(rows, columns=with_duplicates(benchmark.row_columns(ev, rows))), summary, failures


def cost_table(pairs: list[Pair], cache: MatchCache) -> pd.DataFrame:
    """cost.csv: each pair's cost (pair_cost), apart from per_pair.csv, whose numbers are a pure
    function of the matches and the ground truth (reruns, shards and imports reproduce it byte
    for byte); time and memory are measurements, and move with the machine."""
    rows = [{"pair": pair.name, **pair_cost(cache.read(pair.name))} for pair in pairs]
    table = pd.DataFrame(rows, columns=("pair", *COST_COLUMNS))
    return table.dropna(axis=1, how="all") if len(table) else table


# A pair's cost as cost.csv holds it: the matcher's wall time and the matching process's peak
# resident memory during the pair (ground/cost.py); NaN for matches imported or failed. A pair
# matched in a process that held other methods too (demo, reproduce: ground/cost.py SHARED_PEAK) has no
# peak of its own: its peak_memory_mb is blank, and the process's peak, marked shared, is in
# shared_peak_memory_mb (in demo and reproduce every method showed the same peak). cache_memory_mb: how
# much of the pair's peak the feature cache held (features and pyramids of images with pairs left).
COST_COLUMNS = ("match_seconds", "peak_memory_mb", "gpu_peak_memory_mb", "shared_peak_memory_mb", "cache_memory_mb")
# The run's cost in summary.csv: the mean seconds per pair (with its bootstrap interval over the
# pairs, as every number), the highest per-pair peak, on CUDA the allocator's highest peak, and
# the highest shared peak, the cache's highest share. A benchmark that maps the set (reconstruct) adds
# its mapping's seconds and the whole run's per image.
COST_KEYS = ("seconds_per_pair", "peak_memory_mb", "gpu_peak_memory_mb", "shared_peak_memory_mb", "cache_memory_mb",
             "mapping_seconds", "seconds_per_image")


def pair_cost(matches: Matches) -> dict:
    info = matches.info
    peak, gpu_peak = float(info.get("match_peak_mb", np.nan)), float(info.get("match_gpu_peak_mb", np.nan))
    shared = bool(info.get(SHARED_PEAK, False))
    return {"match_seconds": float(info.get("match_seconds", np.nan)),
            "peak_memory_mb": np.nan if shared else peak,
            "gpu_peak_memory_mb": np.nan if shared else gpu_peak,
            "shared_peak_memory_mb": peak if shared else np.nan,
            "cache_memory_mb": float(info.get("match_cache_mb", np.nan))}


def cost_summary(costs: list[dict]) -> dict:
    """The run's cost from its pairs' (pair_cost): empty where no pair was timed (imported matches)."""
    seconds = np.array([c["match_seconds"] for c in costs], float)
    timed = seconds[np.isfinite(seconds)]
    if not len(timed):
        return {}
    out = {"seconds_per_pair": float(timed.mean())}
    bounds = stats.bootstrap_interval(list(timed), lambda picked: {"s": float(np.mean(picked))}, keys=["s"])
    out["seconds_per_pair_lo"], out["seconds_per_pair_hi"] = (float(v) for v in bounds["s"])
    for key in COST_KEYS[1:]:
        values = np.array([c.get(key, np.nan) for c in costs], float)
        if np.isfinite(values).any():
            out[key] = float(np.nanmax(values))
    return out


def evaluate_pair(benchmark: Benchmark, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
    """The pair's row, each correspondence scored once, and how many repeats were set aside.

    Every consumer of a run's per-pair numbers goes through here (and `drawn`), so that a
    matcher cannot raise its MMA or precision by returning a correct match many times."""
    kept, repeats = distinct(matches)
    return {**benchmark.evaluate_pair(pair, kept, ev), DUPLICATES: repeats}


def seeded_rows(benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings,
                first: list[dict], k: int) -> list[list[dict]]:
    """Every pair's row under each of the K seeds ev.seed + 0..K-1, no rematching; `first` is
    seed ev.seed's (the run's own rows, not scored again)."""
    return [first] + [[evaluate_pair(benchmark, pair, cache.read(pair.name), replace(ev, seed=ev.seed + r))
                       for pair in pairs] for r in range(1, k)]


def repeated_summary(benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings,
                     first: list[dict]) -> dict:
    """--repeats K: the summary of each of K evaluations (seeds ev.seed + r; the first is
    `first`, the run's own), their mean as the run's numbers, each metric's standard deviation
    over the repeats (``<metric>_sd``), and the two-level bootstrap interval of that mean (the
    pairs resampled, and with them the repeats).
    per_pair.csv keeps the first repeat's rows."""
    repeats = seeded_rows(benchmark, pairs, cache, ev, first, ev.repeats)
    each = [benchmark.summarize(rows, ev) for rows in repeats]
    keys = metric_keys(each[0])
    summary = dict(each[0])
    for key in keys:
        values = np.array([s[key] for s in each], float)
        summary[key] = float(np.mean(values))
        summary[f"{key}_sd"] = float(np.std(values, ddof=1))
    summary["repeats"] = ev.repeats
    indexed = [benchmark.indexed_summary(rows, ev) for rows in repeats]
    # Two levels, as sfm's mapper seeds: with each resample of pairs the repeats are drawn too
    # (with replacement, from a generator of their own), so that the interval holds RANSAC's
    # spread as well as the pairs' (docs/sweep.md measured it: up to 0.7 of the pairs' half-width
    # on KITTI, more than all of it on ScanNet)
    draw = np.random.default_rng(ev.seed)

    def mean_over_repeats(idx) -> dict:
        picked = [indexed[r](idx) for r in draw.integers(0, len(indexed), len(indexed))]
        # a resample may hold no pair of a group (a WxBS category): its keys are then absent, as
        # from one evaluation's resample, and the bootstrap counts them as NaN
        return {key: float(np.mean([p[key] for p in picked])) for key in keys if all(key in p for p in picked)}

    summary.update(summary_intervals(benchmark, first, ev, summary=summary, indexed=mean_over_repeats))
    return summary


def seeded_interval_summary(benchmark: Benchmark, pairs: list[Pair], cache: MatchCache, ev: EvalSettings,
                            first: list[dict]):
    """The resample summary of an interval that holds RANSAC's spread (ev.interval_seeds K): the
    pairs scored again with the seeds ev.seed + 1 .. K-1 (`first` is the run's own seed's rows),
    and each bootstrap resample of the pairs summarised under one of the K seeds, drawn from a
    generator of its own. The run's numbers stay its own seed's: the interval is that of one
    evaluation, a draw of the pairs and of the estimator's seed alike."""
    indexed = [benchmark.indexed_summary(rows, ev)
               for rows in seeded_rows(benchmark, pairs, cache, ev, first, ev.interval_seeds)]
    draw = np.random.default_rng(ev.seed)

    def one_seed(idx) -> dict:
        return indexed[int(draw.integers(0, len(indexed)))](idx)

    return one_seed


def write_reports(run, per_pair: pd.DataFrame, summary: dict, pairs: list[Pair]) -> None:
    """per_pair.csv, summary.csv, the run's plot, and drawings of `run.viz` of `pairs` spread over
    them (drawing.matches.drawn_pairs); run: the pipeline's PairRun (benchmark, folder, cache, ev)."""
    from e3cm_bench.storage.fingerprint import FINGERPRINT, of_config

    benchmark, folder = run.benchmark, run.folder
    write_csv(per_pair, folder.per_pair_path)
    summary = {**summary, FINGERPRINT: of_config(run.config)}  # what the numbers were scored under
    write_csv(pd.DataFrame([summary]), folder.summary_path)
    costs = cost_table(pairs, run.cache)
    if "match_seconds" in costs.columns:  # matches made here; imported ones have no cost
        write_csv(costs, folder.cost_path)
    else:
        folder.cost_path.unlink(missing_ok=True)
    benchmark.plot_run(run.config.method, summary, per_pair, folder.path)
    for pair in drawn_pairs(pairs, run.viz):
        matches = drawn(run.cache.read(pair.name))
        canvas = draw_matches(
            load_image(pair.image0), load_image(pair.image1), matches.keypoints0, matches.keypoints1,
            correct=benchmark.correct_mask(pair, matches, run.ev), max_lines=400,
        )
        save_image(folder.drawing_path(pair.name), canvas)


# The reports' room, checked before the first of them is written, follows what they hold: the
# CSVs as write_csv renders them, a bound on the run's plot, and each drawing's canvas
# uncompressed (PNG stores a photograph in fewer bytes, plus a filter byte per row and a header).
PLOT_BYTES = 1 << 20     # the run's plot: the demo's are about 50 KiB each
DRAWING_BYTES = 8 << 20  # a drawing of images whose sizes neither the cache nor their headers give
PNG_HEADER_BYTES = 4096


def report_bytes(per_pair: pd.DataFrame, summary: dict, skipped: list[tuple[str, str]],
                 failures: list[tuple[str, str]], drawings: list[tuple[Pair, Matches]]) -> int:
    """About how many bytes write_skipped, write_failures and write_reports will write."""
    tables = [per_pair, pd.DataFrame([summary]), pd.DataFrame(skipped), pd.DataFrame(failures)]
    need = sum(len(t.to_csv(index=False, float_format=CSV_FLOAT_FORMAT).encode()) for t in tables if len(t))
    need += PLOT_BYTES
    for pair, matches in drawings:
        sizes = [matches.info.get(f"size{i}") for i in (0, 1)]
        if any(size is None for size in sizes):
            sizes = [header_size(path) for path in (pair.image0, pair.image1)]
        if any(size is None for size in sizes):
            need += DRAWING_BYTES
            continue
        (w0, h0), (w1, h1) = ((int(v) for v in size) for size in sizes)
        height = max(h0, h1)
        need += height * ((w0 + w1) * 3 + 1) + PNG_HEADER_BYTES
    return need


def evaluate_and_report(run, console: Console) -> tuple[list[Pair], dict]:
    """The evaluate stage and the reports of a run (the pipeline's PairRun: benchmark, folder,
    pairs, skipped, cache, ev, viz; a run or merged shards) over its pairs but the skipped ones;
    returns the pairs evaluated and the summary."""
    benchmark, folder, skipped, cache, ev = run.benchmark, run.folder, run.skipped, run.cache, run.ev
    out = folder.path
    failed = {name for name, _ in skipped}
    pairs = [p for p in run.pairs if p.name not in failed]
    if not pairs:
        raise ValueError(f"{out}: no pair could be matched ({skipped[0][1]})")
    per_pair, summary, failures = evaluate_stage(
        benchmark, pairs, cache, ev, workdir=out, matcher=run.config.matcher_name
    )
    if skipped:  # a clean run keeps the usual columns; a run with holes says so in its summary
        summary["n_skipped"] = len(skipped)
    if failures:  # scored as failures (no matches); the count says how many were the matcher's
        summary["n_failed"] = len(failures)
    repeats = int(per_pair[DUPLICATES].sum()) if len(per_pair) else 0
    if repeats:
        console.print(f"{repeats} repeated correspondence(s) in {int((per_pair[DUPLICATES] > 0).sum())} pair(s) "
                      f"counted once (per_pair.csv: {DUPLICATES})", markup=False)
    for note in benchmark.notes(pairs, per_pair, ev):
        console.print(f"warning: {note}", markup=False, soft_wrap=True)
    drawings = [(pair, cache.read(pair.name)) for pair in drawn_pairs(pairs, run.viz)]
    check_free_space(out, report_bytes(per_pair, summary, skipped, failures, drawings), "the run's reports")
    write_skipped(skipped, folder.skipped_path, console)
    write_failures(failures, folder.failures_path, console)
    write_reports(run, per_pair, summary, pairs)
    return pairs, summary


def write_skipped(skipped: list[tuple[str, str]], path: Path, console: Console) -> None:
    """skipped.csv (pair, reason) when pairs were skipped; no stale file when none were."""
    if not skipped:
        path.unlink(missing_ok=True)
        return
    write_csv(pd.DataFrame(skipped, columns=["pair", "reason"]), path)
    console.print(
        f"{len(skipped)} pair(s) skipped for bad input, listed in {path} (first: {skipped[0][1]})", markup=False
    )


def write_failures(failures: list[tuple[str, str]], path: Path, console: Console) -> None:
    """failures.csv (pair, error) when the matcher failed on pairs; no stale file when it did not."""
    if not failures:
        path.unlink(missing_ok=True)
        return
    write_csv(pd.DataFrame(failures, columns=["pair", "error"]), path)
    console.print(f"{len(failures)} pair(s) failed in the matcher and count as failures, listed in {path} "
                  f"(first: {failures[0][1]})", markup=False)
