"""What a benchmark is: a dataset, a default resize, how one pair is scored, how runs are reported.

Each benchmark is one `Benchmark` object in the registry (`benchmarks/__init__.py`). The
runner and the reports ask it, never a benchmark name, what to do.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.datasets.base import Pair, PairList
from e3cm_bench.ground.matches import Matches
from e3cm_bench.ground.moved import moved_name
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.ground.values import DATASET_KINDS, Range, check_value
from e3cm_bench.method.options import METHOD_OPTIONS, SEEDS


# How a dataset option reads on the command line: a switch, one path, several paths (the option
# repeated), several names (repeated), or one word (options.KINDS says how each is typed and checked).
OPTION_KINDS = DATASET_KINDS

# The per_pair.csv column of the correspondences a matcher returned more than once for a pair:
# the evaluation scores each correspondence once (matches.distinct), and this says how many
# repeats it set aside, so that a count that shrank is explained on the row that shows it.
DUPLICATES = "n_duplicates"


def with_duplicates(columns: Sequence[str]) -> list[str]:
    """A benchmark's per_pair.csv columns with DUPLICATES right after n_matches (at the end
    where there is no n_matches); unchanged where it is already there."""
    columns = list(columns)
    if DUPLICATES in columns:
        return columns
    at = columns.index("n_matches") + 1 if "n_matches" in columns else len(columns)
    return [*columns[:at], DUPLICATES, *columns[at:]]


@dataclass(frozen=True)
class DatasetOption:
    """One option of a benchmark's dataset: the dataset class's keyword, and how it reads as a
    command-line option (``--exclude-large``, ``--scene-info``) and in an experiment's
    ``dataset:`` mapping. The benchmark's command gets one option per entry (cli/benchmarks.py)."""

    name: str
    kind: str
    help: str

    def __post_init__(self) -> None:
        if self.kind not in OPTION_KINDS:
            raise ValueError(f"dataset option {self.name}: kind {self.kind!r} is not one of {', '.join(OPTION_KINDS)}")

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")


@dataclass(frozen=True)
class Benchmark:
    """One benchmark, the unit everything else asks: its dataset and that dataset's options,
    where its data comes from, its default resize, and (subclasses) how a pair is scored
    (`evaluate_pair`, `summarize`) and how runs are reported. The benchmark's command
    (`e3cm-bench NAME`), `import`, `reproduce` and the report are made from this object.

    dataset: the PairList class, built by ``build_dataset`` (as ``dataset(root, skip_bad=..., **options)``).
    dataset_options: the options it takes besides the root (config files are checked against
    them); a DatasetOption becomes an option of the benchmark's command, a plain name is for
    the Python API only.
    summary: the command's help line. Where its data comes from (the default --root) is its
    entry in datasets/sources.py, which names the benchmark it serves.
    default_max_side: longer image side for matching when the user gives none (0, options.FULL_RESOLUTION:
    full size; None, the older spelling, too).
    ransac_field: the EvalSettings field that ``--ransac-px`` sets.
    paper_table: the paper's numbers, a file shipped in e3cm_bench/paper/ (None: the paper has none).
    table_metrics: paper-table column -> summary.csv column; table_extras: measured-only columns.
    """

    name: str
    dataset: type[PairList]
    dataset_options: tuple[str | DatasetOption, ...] = ()
    summary: str = ""
    default_max_side: int | None = 0  # options.FULL_RESOLUTION
    ransac_field: str = "homography_ransac_px"
    paper_table: str | None = None
    table_metrics: Mapping[str, str] = field(default_factory=dict)
    table_extras: tuple[str, ...] = ("n_pairs",)
    # The report page (reporting/site.py): the per_pair.csv columns shown for each method, and the
    # column and threshold above which a pair counts as failed (a NaN or inf value fails too).
    report_columns: tuple[str, ...] = ("n_matches",)
    failure: tuple[str, float] | None = None
    # Summary metrics that are the fraction of pairs whose per_pair column is <= a threshold:
    # metric -> (column, threshold). The regression gate's noise model counts them exactly.
    count_metrics: Mapping[str, tuple[str, float]] = field(default_factory=dict)
    # `compare` (reporting/compare.py): per_pair.csv columns compared pair by pair, each with whether
    # higher is better (a lower-is-better error the run could not compute counts as +inf); each
    # count metric is compared too, as pass/fail. Homography and pose benchmarks have their own.
    paired_columns: tuple[tuple[str, bool], ...] = ()
    # The protocol a run gets when none is named (method/protocols.py): the reference code's
    # where the benchmark has one (WxBS, EVD: wxbs-benchmark's), else e3cm-bench's own.
    default_protocol: str = "default"
    # How many RANSAC seeds a run's interval holds when neither the user nor the protocol says
    # (EvalSettings.interval_seeds): measured beside the pairs' spread, RANSAC's is not negligible
    # on any shared two-view set (docs/sweep.md). A reference's protocol keeps its one evaluation
    # (ReferenceProtocol.interval_seeds); sfm and reconstruct hold their mapper's seeds instead (1).
    default_interval_seeds: int = 3
    # Whether its dataset takes the run's --limit (`first`) and builds no pair beyond it (sfm: a
    # set's exhaustive graph grows with the square of its images).
    builds_to_limit: bool = False
    # Evaluation options it refuses, by name: (the values it still takes, why) (sfm: its mapper's seeds
    # are its repeats and its interval).
    refused_eval: Mapping[str, tuple[tuple, str]] = field(default_factory=dict)
    # The defaults of its own evaluation options (EvalOption.benchmarks: a reconstruction's protocol),
    # by EvalSettings field: filled where the user gives none, so that the record holds them.
    eval_defaults: Mapping[str, object] = field(default_factory=dict)

    @property
    def eval_option_names(self) -> tuple[str, ...]:
        """The evaluation options it takes (EVAL_OPTIONS': every benchmark's and its own)."""
        return tuple(name for name, option in EVAL_OPTIONS.items() if option.applies_to(self.name))

    @property
    def option_names(self) -> tuple[str, ...]:
        return tuple(o.name if isinstance(o, DatasetOption) else o for o in self.dataset_options)

    def command_options(self) -> tuple[DatasetOption, ...]:
        """The dataset options its command line offers."""
        return tuple(o for o in self.dataset_options if isinstance(o, DatasetOption))

    def load_dataset(self, root: str | Path, skip_bad: bool = False, limit: int | None = None, **options) -> PairList:
        # --sample N [--sample-seed S] holds for every benchmark (datasets/base.py stratified_sample);
        # kept among the options so that dataset_load reloads the same sample (shards, export).
        self.check_dataset_values(options)
        sample, sample_seed = options.pop("sample", None), options.pop("sample_seed", None)
        unknown = set(options) - set(self.option_names)
        if unknown:
            raise ValueError(f"dataset option(s) {', '.join(sorted(unknown))} do not apply to {self.name}")
        options = {k: v for k, v in options.items() if v is not None}
        if limit and sample is None and self.builds_to_limit:  # the run's --limit: built no further (sfm's graph)
            options["first"] = int(limit)
        try:
            dataset = self.build_dataset(root, skip_bad, options)
        except (ValueError, FileNotFoundError) as error:  # DatasetError is a ValueError
            hint = self.root_hint(root)
            if not hint:
                raise
            raise type(error)(f"{str(error).splitlines()[0]}; {hint}") from error
        return dataset if sample is None else dataset.sampled(int(sample), int(sample_seed or 0))

    def check_dataset_values(self, options: Mapping, where: str = "") -> None:
        """Each dataset option given (not None) of its kind, --sample and --sample-seed whole numbers
        in their ranges (a command's, a config's ``dataset:``, the Python API's and a record's
        dataset_load for rerun all load here): one line naming the flag (after `where`) otherwise."""
        checks = {o.name: (o.kind, None, o.flag) for o in self.command_options()}
        checks.update(sample=("whole", Range(1, None), "--sample"), sample_seed=("whole", SEEDS, "--sample-seed"))
        for name, (kind, bounds, flag) in checks.items():
            if options.get(name) is not None:
                check_value(options[name], kind, bounds, where + flag)

    def build_dataset(self, root: str | Path, skip_bad: bool, options: dict) -> PairList:
        """The dataset of `root` with its options (checked names, None left out; `first` where
        it builds to the run's limit): ``dataset(root, skip_bad=..., **options)``; a benchmark
        whose dataset takes its options grouped (sfm: SetOptions) builds it its own way."""
        return self.dataset(root, skip_bad=skip_bad, **options)

    def root_hint(self, root: str | Path) -> str:
        """For a --root one level too high: 'ROOT holds hpatches-sequences-release/: did you mean
        --root ROOT/hpatches-sequences-release?' (the folder this benchmark's download makes,
        datasets/sources.py), else ''."""
        from e3cm_bench.datasets.sources import SOURCES

        folders = [s.folder for s in SOURCES.values() if s.benchmark == self.name and s.folder]
        found = next((f for f in folders if (Path(root) / f).is_dir()), None)
        if found is None:
            return ""
        return f"{root} holds {found}/: did you mean --root {Path(root) / found}?"

    def max_side(self, option: int | None) -> int | None:
        """The resize of a run: the option as given (0 = full size), or this benchmark's default
        (method.protocols.resolve_max_side, under its default protocol; options.resolved_side:
        None is full size in the spec)."""
        from e3cm_bench.method.options import resolved_side
        from e3cm_bench.method.protocols import resolve_max_side

        return resolved_side(resolve_max_side(self, option), "--max-side")

    def eval_settings(self, seed: int = 0, ransac_px: float | None = None, **values) -> EvalSettings:
        if ransac_px is not None:
            values[self.ransac_field] = float(ransac_px)
        return EvalSettings(seed=seed, **values)

    # ---- what a command's options mean here: shared by the command line and experiment configs
    def resolve_method(self, matcher: str, *, protocol: str | None = None, available: bool = True, **options):
        """The MethodSpec of a matcher on this benchmark under `protocol` (None: its
        default_protocol); `options`: the other method options by name (options.METHOD_OPTIONS:
        backbone, weights, estimator, sampson_px, ratio, max_side, seed, label, settings, ...).

        The one path, method.build_method: max_side None takes the protocol's side for this
        benchmark, else the benchmark's default; 0 is full size. The protocol's matcher
        settings (num_levels, channel order) apply to deep matchers where `settings` gives
        none; its resize and upright rule apply to every matcher."""
        from e3cm_bench.method.spec import build_method

        return build_method({"matcher": matcher, "protocol": protocol, **options}, benchmark=self, available=available)

    def resolve_eval(self, protocol: str | None = None, seed: int = 0, given: Mapping | None = None,
                     **named) -> EvalSettings:
        """The evaluation settings of a run: the protocol's, then the evaluation options given, by their
        names (EVAL_OPTIONS: ransac_px, pose_estimator, repeats, interval_seeds; None: the protocol's,
        else the benchmark's) in `given` (a command's flags, a config's ``evaluation:``, a record's) or
        as keywords (the Python API). A name this benchmark refuses (`refused_eval`) is one line."""
        from e3cm_bench.benchmarks.eval_options import check_eval_given
        from e3cm_bench.method.protocols import get_protocol, resolve_protocol

        # every value by its flag's own check (kind and range) before any is used: a command's, a
        # config's ``evaluation:``, a record's and the Python API's all come through here
        METHOD_OPTIONS["seed"].check(seed)
        values = check_eval_given({**(given or {}), **named}, self.refused_eval, benchmark=self.name)
        chosen = get_protocol(resolve_protocol(self, protocol), self.name)
        settings = {**self.eval_defaults, **chosen.eval_fields(self.name)}
        settings.update({EVAL_OPTIONS[name].field: value for name, value in values.items() if value != ""})
        if settings.get("interval_seeds") is None:
            settings["interval_seeds"] = (chosen.interval_seeds if chosen.interval_seeds is not None
                                          else self.default_interval_seeds)
        return self.eval_settings(seed=seed, **settings)

    # ---- scoring: subclasses
    def pair_columns(self, ev: EvalSettings) -> list[str]:  # pragma: no cover - abstract
        raise NotImplementedError

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:  # pragma: no cover
        """One per_pair.csv row from the pair's matches (original pixels) and its ground truth."""
        raise NotImplementedError

    def two_view_geometry(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict | None:
        """The estimate this benchmark's evaluation makes from the matches, with its inliers
        ({"H", "inliers"} or {"R", "t", "inliers"}), for an export that stores it; None where the
        evaluation estimates no two-view geometry COLMAP can hold, or where it fails."""
        return None

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:  # pragma: no cover
        raise NotImplementedError

    # A benchmark that scores the pairs together (sfm: one reconstruction from all of them) sets
    # this and defines evaluate_set; the others are scored pair by pair through evaluate_pair.
    evaluates_set = False

    def evaluate_set(self, pairs: Sequence[Pair], matches: Sequence[Matches], ev: EvalSettings,
                     workdir: Path | None, matcher: str | None = None) -> tuple[list[dict], dict]:  # pragma: no cover
        """Every pair's row from all the pairs' matches at once, and the set's own numbers
        (summary columns that no pair bootstrap can resample: they get no interval). workdir:
        a folder of the run the benchmark may write its products in (None: a temporary one);
        matcher: the run's registered matcher (its configuration's), None where unknown."""
        raise NotImplementedError

    def indexed_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], dict]:
        """`summarize` of rows picked by index: f(idx) == summarize([rows[i] for i in idx], ev).

        The bootstrap calls it once per resample; a subclass may read the rows into arrays once
        and summarise each resample from those (the caller checks that f(range(n)) gives the
        summary itself before trusting it). This default builds the rows of each resample.
        """
        rows = list(rows)
        return lambda idx: self.summarize([rows[i] for i in idx], ev)

    def interval_summary(self, rows: Sequence[Mapping], ev: EvalSettings) -> Callable[[Sequence[int]], Mapping] | None:
        """The summary of a bootstrap resample of pairs (by index) where a benchmark resamples
        more than its pairs (sfm: the mapper's seeds too); None: indexed_summary's, pairs only."""
        return None

    def row_columns(self, ev: EvalSettings, rows: Sequence[Mapping]) -> list[str]:
        """per_pair.csv's columns for these rows (sfm adds one set per mapper seed)."""
        return self.pair_columns(ev)

    def notes(self, pairs: Sequence[Pair], per_pair: pd.DataFrame, ev: EvalSettings) -> list[str]:
        """What a run should say once about its ground truth and how it was scored (one line each)."""
        return []

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:  # pragma: no cover
        """Which matches the ground truth calls right (green in --viz drawings)."""
        raise NotImplementedError

    def required_summary_columns(self) -> list[str]:
        """Columns a run's summary.csv must have to be reported at all."""
        return ["n_pairs", "n_matches", *self.table_metrics.values()]

    # ---- reports: subclasses
    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:  # pragma: no cover
        raise NotImplementedError

    def plot_comparison(
        self, runs: Mapping[str, tuple[dict, pd.DataFrame]], stem: Path
    ) -> list[Path]:  # pragma: no cover
        """Plots comparing runs (label -> (summary, per_pair)) next to a table at `stem`."""
        raise NotImplementedError


def __getattr__(name: str):
    return moved_name(__name__, name)  # EvalSettings' bounds moved to eval_settings.py (ground/moved.py MOVED_NAMES)
