"""The one run driver: every kind of run (a benchmark run, an import, a calibration, a merge of
shards, the noise ensemble's reruns) goes open -> produce matches -> evaluate -> finish here.

- open (`open_run`): lock the folder before anything in it is read or written, clear it on
  --overwrite, make sure it exists. Whether its matches may be kept (the identity check) is
  RunFolder's (RunFolder.previous, check_resolved, check_imported, check_frames, check_shards).
- produce matches: the caller's hook (the match stage, an import source, shards' caches).
- evaluate and finish (`finish_run`): the per-pair evaluation and, where the benchmark scores
  the whole set, the set's (evaluate.evaluate_stage), the CSVs and plots, then config.yaml's
  record and the printed summary.

Like glue-factory's evaluation pipeline, one driver holds the order of the steps and the kinds
of run differ only in how their matches are made.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console

from e3cm_bench.storage.record import RunConfig
from e3cm_bench.storage.folder import RunFolder


@contextmanager
def open_run(folder: RunFolder, overwrite: bool = False) -> Iterator[RunFolder]:
    """The folder locked (then cleared on --overwrite, and there) for the time of the block."""
    with folder.lock():  # taken before anything in the folder is read or written
        if overwrite and folder.path.exists():
            folder.clear()
        folder.path.mkdir(parents=True, exist_ok=True)
        yield folder


def finish_run(benchmark, folder: RunFolder, config: RunConfig, pairs: list, skipped: list, cache, ev, viz: int,
               console: Console, title: Callable[[int], str], count_evaluated: bool = False) -> tuple[list, dict]:
    """Evaluate the matches in `cache` (per pair, and per set where the benchmark has one),
    write the CSVs and the config record, print the summary under `title(n_pairs_evaluated)`;
    returns the pairs evaluated and the summary. count_evaluated: record how many pairs were
    evaluated (a merge's record is made from its shards', which counted their own)."""
    from e3cm_bench.pipeline.evaluate import evaluate_and_report
    from e3cm_bench.reporting.tables import print_summary

    pairs, summary = evaluate_and_report(benchmark, folder, config.method, pairs, skipped, cache, ev, viz, console)
    if count_evaluated:
        config.dataset["n_pairs_evaluated"] = len(pairs)
    config.dataset["n_skipped"] = len(skipped)
    if config.shard is not None:
        config.shard["complete"] = True  # written before the merge check (shards.merge_when_complete)
    folder.write_config(config)
    print_summary(summary, title(len(pairs)), console=console)
    return pairs, summary
