"""Runs that outgrow one process: shards of a run, merging them, and launching them.

A run with ``--shard K/N`` takes the K-th of N contiguous, near-equal slices of the pair
list (contiguous: pairs of one scene or sequence stay together) and is an ordinary run in
``OUT/shards/K-of-N/`` with its own cache, identity check and lock. HDF5 files are never
shared between processes. `merge_run` checks that all N shards exist, are complete and
share one identity, evaluates every pair from the shards' caches, and writes the usual
CSVs, plots and config.yaml into OUT. The last shard to finish merges automatically.
Launching is left to the cluster's scheduler (SLURM arrays, scripts/slurm/) or to
`pipeline.launch.run_shards` (one local process per worker or device; submitit for SLURM).
"""

from __future__ import annotations

import os
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from rich.console import Console

from e3cm_bench.pipeline.driver import PairRun, run_pipeline
from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
from e3cm_bench.storage.run_config import RunConfig
from e3cm_bench.ground.files import refuse_link
from e3cm_bench.storage.folder import RunFolder

# The most shards one run may have: a merge lists every one of them (E3CM_SHARDS=1000000000
# must not make it list a billion); each shard holds at least one pair too (check_shard_count).
MAX_SHARDS = 100_000


def parse_shard(text: str) -> tuple[int, int]:
    """'2/3' -> (2, 3): the 2nd of 3 shards (1-based)."""
    try:
        k, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise ValueError(f"--shard: expected K/N (e.g. 2/8), got {text!r}") from None
    return check_shard((k, n))


def check_shard(shard) -> tuple[int, int]:
    """A shard (K, N) as --shard K/N or the Python API's shard=(K, N) gives it: two whole numbers,
    K from 1 to N, N at most MAX_SHARDS; a one-line ValueError otherwise."""
    whole = isinstance(shard, (tuple, list)) and len(shard) == 2 and all(
        isinstance(v, int) and not isinstance(v, bool) for v in shard)
    if not whole:
        raise ValueError(f"shard must be (K, N), two whole numbers (the K-th of N shards), got {shard!r}")
    k, n = shard
    if not 1 <= k <= n:
        raise ValueError(f"--shard {k}/{n}: K must be between 1 and N")
    check_shard_count((k, n))
    return k, n


def check_shard_count(shard: tuple[int, int], n_pairs: int | None = None, option: str | None = None) -> None:
    """A one-line ValueError for N shards over MAX_SHARDS, or (n_pairs given) over the pairs of the run."""
    k, n = shard
    option = option or f"--shard {k}/{n}"
    if n > MAX_SHARDS:
        raise ValueError(f"{option}: at most {MAX_SHARDS:,} shards")
    if n_pairs is not None and n > n_pairs:
        raise ValueError(f"{option}: {n} shards of {n_pairs} pair(s) would leave some with none; "
                         f"choose N of at most {n_pairs}")

def shard_slice(n_pairs: int, shard: tuple[int, int]) -> slice:
    """The K-th of N contiguous slices of n_pairs items; sizes differ by at most one."""
    k, n = shard
    return slice(n_pairs * (k - 1) // n, n_pairs * k // n)

# The options that say how a run's shards run; a shard's own command line has only --shard K/N.
LAUNCH_OPTIONS = {"--shard": 1, "--workers": 1, "--devices": 1, "--launcher": 1, "--shards": 1}


def shard_command(shard: tuple[int, int], argv: list[str] | None = None, cwd: str | None = None,
                  device: str | None = None) -> str | None:
    """The command line that runs (or resumes) shard K/N of the run this process's command makes:
    ``cd CWD && e3cm-bench ARGS --shard K/N``, the launch options (--workers, --devices,
    --launcher, --shards, --shard) removed; device: a --device to add (a --devices worker's).
    None where argv is not the e3cm-bench command line (the Python API). Recorded in each
    shard's config.yaml (shard: command), so that merge can name it for a shard that is missing or unfinished."""
    argv = list(sys.argv if argv is None else argv)
    program = Path(argv[0]) if argv else Path()
    if not (program.name == "e3cm-bench" or program.parts[-3:] == ("e3cm_bench", "cli", "__main__.py")
            or program.parts[-2:] == ("e3cm_bench", "__main__.py")):
        return None
    args, rest = [], argv[1:]
    while rest:
        arg = rest.pop(0)
        name = arg.split("=", 1)[0]
        if name in LAUNCH_OPTIONS:
            if "=" not in arg:
                del rest[:LAUNCH_OPTIONS[name]]
            continue
        args.append(arg)
    args += ["--shard", f"{shard[0]}/{shard[1]}"] + (["--device", device] if device else [])
    return f"cd {shlex.quote(cwd or os.getcwd())} && " + shlex.join(["e3cm-bench", *args])


def rerun_commands(configs: dict[tuple[int, int], RunConfig], shards: list[tuple[int, int]]) -> str:
    """': CMD1; CMD2' for the shards named (from their own recorded command, or
    another shard's with its --shard K/N replaced), or '' where no shard recorded one."""
    commands = {key: c.rerun_command for key, c in configs.items()}
    known = {key: command for key, command in commands.items() if command}
    if not known:
        return ""
    (k0, n0), template = next(iter(sorted(known.items())))
    commands = [known.get(shard) or template.replace(f"--shard {k0}/{n0}", f"--shard {shard[0]}/{shard[1]}")
                for shard in shards]
    return ": " + "; ".join(commands)


def shard_dir(out: Path, shard: tuple[int, int]) -> Path:
    """The folder a shard's run writes: OUT/shards/K-of-N, never through a link at OUT/shards."""
    refuse_link(RunFolder(out).shards_dir)
    return RunFolder(out).shard(shard).path

class ShardedCache:
    """Reads a pair's matches from whichever shard's cache holds it."""

    def __init__(self, folders: list[RunFolder]) -> None:
        self.where = {}
        for folder in folders:
            cache = folder.cache()
            for name in cache.names():
                self.where[name] = cache

    def names(self) -> list[str]:
        return sorted(self.where)

    def read(self, name: str):
        if name not in self.where:
            raise KeyError(f"pair {name!r} is in no shard's cache")
        return self.where[name].read(name)

def shard_configs(out: Path) -> dict[tuple[int, int], RunConfig]:
    """(K, N) -> the record of each shard folder of OUT that holds a shard's config.yaml."""
    configs = {}
    for folder in RunFolder(out).shard_folders():
        config = RunConfig.read_if_present(folder.config_path)
        if config is not None and config.shard_key is not None:
            configs[config.shard_key] = config
    return configs

def all_shards_complete(out: Path) -> bool:
    configs = shard_configs(out)
    if not configs:
        return False
    n = next(iter(configs))[1]
    # counted, not listed: N comes from a shard's record (a crafted one may say a billion)
    return (len(configs) == n and all(m == n and 1 <= k <= n for k, m in configs)
            and all(c.shard_complete for c in configs.values()))

def merge_run(out: str | Path, viz: int = 0, console: Console | None = None) -> pd.DataFrame:
    """Evaluate all shards of the run in OUT as one run; writes OUT's CSVs, plots and config.yaml."""
    console = console or Console()
    out = Path(out)
    configs = shard_configs(out)
    if not configs:
        raise ValueError(f"{RunFolder(out).shards_dir}: no shards to merge (run with --shard K/N first)")
    counts = {n for _, n in configs}
    if len(counts) > 1:
        raise ValueError(
            f"{RunFolder(out).shards_dir}: shards of different layouts "
            f"({', '.join(f'N={n}' for n in sorted(counts))}); "
            "keep one and delete the others"
        )
    n = counts.pop()
    check_shard_count((1, n), option=f"{RunFolder(out).shards_dir}: shards of N={n}")
    missing = [(k, n) for k in range(1, n + 1) if (k, n) not in configs]
    unfinished = [key for key, c in sorted(configs.items()) if not c.shard_complete]
    if missing or unfinished:
        names = lambda shards: ", ".join(f"{k}-of-{n}" for k, _ in shards)  # noqa: E731
        problems = ([f"{names(missing)} missing"] if missing else []) + \
                   ([f"{names(unfinished)} not finished (stopped, or still running)"] if unfinished else [])
        raise ValueError(f"{RunFolder(out).shards_dir}: shard(s) {'; '.join(problems)}; run each with --shard K/{n}, "
                         "it resumes what it matched" + rerun_commands(configs, sorted(missing + unfinished)))
    RunFolder(out).check_shards(configs)
    first = configs[(1, n)]
    if not first.dataset_load:
        raise ValueError(
            f"{RunFolder(out).shard((1, n)).config_path}: no dataset_load (shards made from a dataset object "
            "cannot be merged from the command line)"
        )
    loaded = load_run_pairs(RunFolder(out).shard((1, n)).config_path)
    run = MergeRun(loaded.benchmark, RunFolder(out), evaluation_of(loaded.config), viz, pairs=loaded.pairs,
                   count_evaluated=True, configs=configs, n=n)
    summary, = run_pipeline([run], console)
    return pd.DataFrame([summary])


@dataclass
class MergeRun(PairRun):
    """The merge hook: the matches are the shards' caches, read as one; the record is made from
    the first shard's (every shard's timing kept)."""

    configs: dict = field(default_factory=dict)
    n: int = 0

    def open(self, console: Console) -> None:
        first, n = self.configs[(1, self.n)], self.n
        timings = {f"{k}-of-{n}": self.configs[(k, n)].timing for k in range(1, n + 1)}
        self.config = RunConfig(
            benchmark=first.benchmark, method=first.method, identity=first.identity,
            matcher=first.matcher, device=first.device,
            dataset=dict(first.dataset),  # its counts are the merge's own (PairRun.evaluate)
            evaluation=first.evaluation, environment=first.environment,
            timing={"match_seconds": sum(t.get("match_seconds", 0.0) for t in timings.values()),
                    "pairs_matched": sum(t.get("pairs_matched", 0) for t in timings.values())},
            dataset_load=first.dataset_load,
            shards={"count": n, "layout": "contiguous slices of the pair list", "timing": timings},
        )

    def record(self) -> None:
        """Nothing before the merge's own evaluation: OUT is written when it is whole."""

    @classmethod
    def produce(cls, runs: list[MergeRun], console: Console) -> None:
        for run in runs:
            run.cache, run.skipped = _merged_matches(run.folder.path, run.n, run.pairs)

    def title(self, summary: dict) -> str:
        return (f"{self.benchmark.name} - {self.config.method} ({self.evaluated} pairs, {self.n} shards merged) "
                f"-> {self.folder.path}")


def _merged_matches(out: Path, n: int, pairs: list) -> tuple[ShardedCache, list]:
    """The produce-matches hook of a merge: the shards' caches read as one, and their skipped
    pairs (each once); every pair must be in one of them."""
    folders = [RunFolder(out).shard((k, n)) for k in range(1, n + 1)]
    cache = ShardedCache(folders)
    skipped = []
    for folder in folders:
        if folder.skipped_path.is_file():
            skipped += [tuple(r) for r in pd.read_csv(folder.skipped_path).itertuples(index=False)]
    skipped = list(dict.fromkeys(skipped))
    failed = {name for name, _ in skipped}
    absent = [p.name for p in pairs if p.name not in cache.where and p.name not in failed]
    if absent:
        raise ValueError(
            f"{RunFolder(out).shards_dir}: {len(absent)} pair(s) are in no shard's cache (first: {absent[0]}); "
            "the shards were made from another pair list"
        )
    return cache, skipped


def merge_when_complete(out: Path, console: Console) -> bool:
    """Merge if every shard is finished; False when some are not, or another process is merging.

    Each shard marks itself complete before calling this, so of shards finishing together at
    least the last one sees all of them complete; the folder lock keeps two from merging at once.
    """
    if not all_shards_complete(out):
        return False
    try:
        merge_run(out, console=console)
    except ValueError as error:
        if "another run is using this folder" in str(error):
            return False
        raise
    return True
