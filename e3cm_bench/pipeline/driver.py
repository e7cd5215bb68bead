"""The one run pipeline: every kind of run (a benchmark run, an import, a merge of shards, a
calibration; the noise ensemble's draws are benchmark runs) goes through `run_pipeline`:

1. open: lock the folder before anything in it is read or written, clear it on --overwrite,
   then the kind's `open` hook: the identity check against the folder's previous record
   (RunFolder.previous and its checks), the pairs still to match, the new record.
2. record: config.yaml written (the folder is claimed and described before any model loads).
3. produce matches: the kind's `produce` hook, once for all the runs of that kind (the match
   stage matches several methods' pairs in one pass; an import reads a source; a merge reads
   the shards' caches).
4. evaluate: the kind's `evaluate` hook (PairRun's: the per-pair evaluation, the set's where
   the benchmark scores it, the CSVs and plots; a calibration's: its windows).
5. finish: the record again (with what the stages counted), and the printed summary.

Like glue-factory's EvalPipeline, one driver holds the order of the steps; the kinds of run
are small hook objects that differ only in how they open, make their matches and score them.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field

from rich.console import Console

from e3cm_bench.benchmarks import Benchmark, EvalSettings
from e3cm_bench.pipeline.evaluate import evaluate_and_report
from e3cm_bench.reporting.tables import print_summary
from e3cm_bench.storage import RunConfig, RunFolder


@contextmanager
def open_run(folder: RunFolder, overwrite: bool = False) -> Iterator[RunFolder]:
    """The folder locked (then cleared on --overwrite, and there) for the time of the block."""
    with folder.lock():  # taken before anything in the folder is read or written
        if overwrite and folder.path.exists():
            folder.clear()
        folder.path.mkdir(parents=True, exist_ok=True)
        yield folder


class RunHook:
    """A kind of run as the pipeline drives it. A subclass sets `folder` and `overwrite`, makes
    `config` in `open`, and overrides the steps that differ from these defaults."""

    folder: RunFolder
    overwrite: bool = False
    config: RunConfig

    def open(self, console: Console) -> None:
        """The identity check and the new record (self.config), the folder held."""
        raise NotImplementedError

    def record(self) -> None:
        """config.yaml before the matches are made."""
        self.folder.write_config(self.config)

    @classmethod
    def produce(cls, runs: Sequence[RunHook], console: Console) -> None:
        """Make the matches the runs of this kind lack (one call for all of them)."""

    def evaluate(self, console: Console) -> dict | None:
        """Score the matches and write the run's tables; returns the summary to print (or None)."""
        raise NotImplementedError

    def title(self, summary: dict) -> str:
        return str(self.folder.path)


def run_pipeline(runs: Sequence[RunHook], console: Console) -> list[dict | None]:
    """Every run through open -> record -> produce -> evaluate -> finish; each run's summary."""
    with ExitStack() as locks:
        for run in runs:
            locks.enter_context(open_run(run.folder, run.overwrite))
            run.open(console)
            run.record()
        kinds: dict[type, list[RunHook]] = {}
        for run in runs:
            kinds.setdefault(type(run), []).append(run)
        for kind, group in kinds.items():
            kind.produce(group, console)
        return [finish_run(run, run.evaluate(console), console) for run in runs]


def finish_run(run: RunHook, summary: dict | None, console: Console) -> dict | None:
    if run.config.shard is not None:
        run.config.shard["complete"] = True  # written before the merge check (shards.merge_when_complete)
    run.folder.write_config(run.config)
    if summary is not None:
        print_summary(summary, run.title(summary), console=console)
    return summary


@dataclass
class PairRun(RunHook):
    """A run scored pair by pair against a benchmark's ground truth: a benchmark run, an import,
    a merge. `pairs`, `skipped` and `cache` are filled by its `open` hook."""

    benchmark: Benchmark
    folder: RunFolder
    ev: EvalSettings
    viz: int = 0
    overwrite: bool = False
    pairs: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    cache: object = None
    count_evaluated: bool = False  # a merge's count is its own; a run's is recorded when it opens
    evaluated: int = field(default=0, init=False)  # the pairs its evaluation scored (the summary's title)

    def evaluate(self, console: Console) -> dict:
        pairs, summary = evaluate_and_report(self, console)
        if self.count_evaluated:
            self.config.dataset["n_pairs_evaluated"] = len(pairs)
        self.config.dataset["n_skipped"] = len(self.skipped)
        self.evaluated = len(pairs)
        return summary
