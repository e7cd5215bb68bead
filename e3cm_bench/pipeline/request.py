"""What a run is asked to do, in one value: `RunRequest`.

`resolve_request` (pipeline/resolve.py) builds every one: from the command line's flags
(cli/benchmarks.py, cli/reconstruct.py), `reproduce`'s per method (pipeline/experiments.py),
the Python API's keywords (`request_from_fields`, for runner.run_benchmark); a launched shard
receives one (pipeline/launch.py). It travels unchanged to the stage that reads each field:
`options` (pair_timeout among them) to the match stage, `ev` to the evaluate stage, the rest to
the pipeline's open step; `given` is what the user gave, by section, as config.yaml keeps it. A
new run option is one field here (or in MatchOptions), one row of the option table and its one
consumer.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from e3cm_bench.benchmarks import Benchmark, EvalSettings, get_benchmark
from e3cm_bench.datasets.base import PairList
from e3cm_bench.ground.values import KindOf, Range
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.shards import check_shard
from e3cm_bench.pipeline.match_options import MatchOptions


@dataclass(frozen=True)
class RunOption(KindOf):
    """A count of the run's request, declared as the method's and the evaluation's options are
    (options.KindOf): its field, its flag, its kind and range, checked by the one check whoever
    gives it (the command, the Python API, a record's dataset.limit for rerun)."""

    name: str
    flag: str
    kind: str
    default: object
    range: Range | None = None


RUN_OPTIONS: dict[str, RunOption] = {o.name: o for o in (
    RunOption("limit", "--limit", "whole", None, Range(1, None)),  # None: every pair
    RunOption("viz", "--viz", "whole", 0, Range(0, None)),  # 0: no drawings
)}


@dataclass
class RunRequest:
    """One run (or, with run_methods, one run per method over the same pairs).

    benchmark: a registered name or a Benchmark. out: the run folder. method: what makes the
    matches (None only with eval_only: the folder's own). The pairs come from `dataset`, or
    from the benchmark's dataset at `root` with `dataset_options`; `dataset_load` says how to
    load them again where a dataset object is given (merging shards, export). shard=(K, N):
    only the K-th of N slices of the pairs, in OUT/shards/K-of-N/. options: how the match
    stage runs (MatchOptions: feature cache, batching, a failing matcher, pair_timeout)."""

    benchmark: str | Benchmark
    out: Path | None = None
    method: MethodSpec | None = None
    root: Path | None = None
    dataset: PairList | None = None
    dataset_options: dict = field(default_factory=dict)
    dataset_load: dict | None = None
    skip_bad: bool = False
    ev: EvalSettings | None = None
    limit: int | None = None
    overwrite: bool = False
    eval_only: bool = False
    viz: int = 0
    device: str = "cpu"
    shard: tuple[int, int] | None = None
    options: MatchOptions = field(default_factory=MatchOptions)
    # what the user gave, by section, in the tables' names (pipeline/resolve.py): config.yaml keeps it
    given: dict | None = None

    def __post_init__(self) -> None:
        # None from a caller means "the default", as every field's own default does
        self.out = None if self.out is None else Path(self.out)
        self.dataset_options = dict(self.dataset_options or {})
        if self.ev is None:  # the benchmark's default protocol's settings, as its command has them
            self.ev = self.bench.resolve_eval()
        self.options = self.options or MatchOptions()
        self.check_counts(self.limit, self.viz)
        if self.shard is not None:  # the Python API's (K, N), as --shard K/N is checked
            check_shard(self.shard)

    @staticmethod
    def check_counts(limit: int | None, viz: int) -> None:
        """The run's counts, each by its RUN_OPTIONS entry (kind and range), one line for the first
        that is not; the command calls it with its flags before anything loads, the request with
        its fields (the Python API, rerun)."""
        RUN_OPTIONS["limit"].check(limit)
        RUN_OPTIONS["viz"].check(viz if viz is not None else 0)

    @property
    def bench(self) -> Benchmark:
        return get_benchmark(self.benchmark)

    def but(self, **changes) -> RunRequest:
        """The same request with some fields changed (a method's folder, a shard, a device)."""
        return replace(self, **changes)
