"""Two runs of one benchmark compared pair by pair: `e3cm-bench compare RUN_A RUN_B` and the
report page's comparison section.

Only the pairs both runs hold take part (matched by per_pair.csv's ``pair`` column), so each
pair is its own control. Per metric, one statistic over the same pairs (the mean of bounded
values, the median of an error where a failure is +inf), B - A with its paired-bootstrap
interval, the bootstrap's p and the verdict read from that interval, all from
`stats.compare_paired` (its docstring states the rule). Which per-pair values are compared, by
which statistic, and which way is better, is said once here per kind of benchmark
(`paired_metrics`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from e3cm_bench.geometry import metrics
from e3cm_bench import stats
from e3cm_bench.benchmarks import Benchmark, HomographyBenchmark, PoseBenchmark
from e3cm_bench.ground.files import write_atomically, write_csv
from e3cm_bench.reporting.escape import markdown_text
from e3cm_bench.drawing.formats import format_interval, format_number, text_width
from e3cm_bench.reporting.tables import Run
from e3cm_bench.storage.fingerprint import protocol_items, protocol_notes

HOMOGRAPHY_MMA_DEFAULT = (3,)  # the MMA threshold the tables show
POSE_ERROR_THRESHOLDS = metrics.POSE_AUC_THRESHOLDS  # degrees: err_pose < t, the AUC's thresholds


@dataclass(frozen=True)
class PairedMetric:
    """One per-pair value to compare: its name, how it is read from per_pair.csv, which way is better."""

    name: str
    values: Callable[[pd.DataFrame], np.ndarray]
    higher_is_better: bool
    statistic: str = "mean"  # "median" where a value can be +inf (a failed pair's error)


@dataclass
class Comparison:
    """The result of comparing run A with run B on the pairs both hold."""

    label_a: str
    label_b: str
    benchmark: str
    n_a: int
    n_b: int
    n_common: int
    results: list[stats.PairedResult]
    metrics: list[PairedMetric]
    confidence: float
    n_samples: int
    seed: int
    seeded: bool = False  # values of several reconstructions per pair (sfm's mapper seeds)
    notes: tuple[str, ...] = ()  # where the runs were scored under different protocols (storage/fingerprint.py)

    def table(self) -> pd.DataFrame:
        """compare.csv: one row per metric; a, b: the statistic of A's and B's values over the n
        pairs; d = b - a with its interval [d_lo, d_hi]; p_value and verdict from that interval."""
        rows = []
        for metric, r in zip(self.metrics, self.results):
            rows.append(
                {
                    "metric": r.metric,
                    "statistic": r.statistic,
                    "better": "higher" if metric.higher_is_better else "lower",
                    "n": r.n,
                    "a": r.a,
                    "b": r.b,
                    "d": r.diff,
                    "d_lo": r.lo,
                    "d_hi": r.hi,
                    "p_value": r.p_value,
                    "verdict": r.verdict,
                    "confidence": self.confidence,
                    "bootstrap_samples": self.n_samples,
                    "bootstrap_seed": self.seed,
                }
            )
        return pd.DataFrame(rows)

    def display(self, wide: bool = True) -> tuple[list[str], list[list[str]]]:
        """The table as people read it: header and text rows. wide (Markdown, report page): with
        the statistic, the better direction and p; otherwise (the terminal, 80 columns) metric,
        n, A, B, B - A with its interval and the verdict, the rest said once below the table."""
        interval = f"B - A [{self.confidence:.0%} CI]"
        if wide:
            header = ["metric", "statistic", "better", "n", f"A: {self.label_a}", f"B: {self.label_b}", interval, "p",
                      "verdict"]
        else:
            header = ["metric", "n", "A", "B", interval, "verdict"]
        body = []
        for row in self.table().to_dict("records"):
            cells = {
                "metric": row["metric"],
                "statistic": row["statistic"],
                "better": row["better"],
                "n": str(row["n"]),
                "a": _value(row["a"]),
                "b": _value(row["b"]),
                "d": _difference(row),
                "p": _p_value(row["p_value"], self.n_samples),
                "verdict": row["verdict"],
            }
            keys = (["metric", "statistic", "better", "n", "a", "b", "d", "p", "verdict"] if wide
                    else ["metric", "n", "a", "b", "d", "verdict"])
            body.append([cells[k] for k in keys])
        return header, body

    def heading(self) -> str:
        return (f"{self.benchmark}: A = {self.label_a} ({self.n_a} pairs), B = {self.label_b} ({self.n_b} pairs); "
                f"{self.n_common} pairs in both are compared")

    def explanation(self) -> str:
        """What the numbers are, said once (below the terminal's table and the report's)."""
        medians = [m.name for m in self.metrics if m.statistic == "median"]
        lower = [m.name for m in self.metrics if not m.higher_is_better]
        text = "A, B: the mean over the n pairs" + (" and each run's mapper seeds" if self.seeded else "")
        if medians:
            text += (f", but {', '.join(medians)}: the median, a failed pair counting as +inf (the worst)")
        text += (f". Lower is better for {', '.join(lower)}, higher for the others. " if lower
                 else ". Higher is better. ")
        text += ("B - A: its paired-bootstrap interval (" + ("pairs resampled together, each run's seeds on their own; "
                                                          if self.seeded else "")
                 + f"{self.n_samples} resamples, seed {self.seed}); the verdict "
                 f"names a winner when the interval excludes 0 (bootstrap p < {1 - self.confidence:.2g}).")
        return text


def _value(value: float) -> str:
    return format_number(value, "", decimals=2, fraction_decimals=3)


def _difference(row: dict) -> str:
    """B - A [lo, hi], signed, with the decimals of the values it is the difference of (three
    for fractions, whose differences are small; two for pixels and degrees)."""
    fraction = all(abs(v) < 1.5 for v in (row["a"], row["b"]) if np.isfinite(v))
    places = 3 if fraction else 2
    text = format_interval(row["d"], row["d_lo"], row["d_hi"], "d_", decimals=places)
    bounds = [float(row[k]) for k in ("d_lo", "d_hi")]
    if not text.endswith("]") or all(not np.isfinite(v) or round(v, places) != 0 for v in bounds):
        return text
    # A bound that rounds to 0 decides the verdict: "+0.200 [+0.000, +0.400] no difference
    # detectable" read as a contradiction. A bound of exactly 0 is written 0 and said to touch
    # it; one merely near 0 gets the digits that show its sign.
    shown = [("0" if v == 0 else f"{v:+.2g}") if np.isfinite(v) and round(v, places) == 0 else f"{v:+.{places}f}"
             for v in bounds]
    text = f"{text.split(' [')[0]} [{shown[0]}, {shown[1]}]"
    return text + (" touches 0" if 0.0 in bounds else "")


def _p_value(p: float, n_samples: int) -> str:
    """A bootstrap p below one resample's worth is written as a bound, not as 0."""
    return f"<{1 / n_samples:.2g}" if p < 1 / n_samples else f"{p:.2g}"


def _column(name: str, failure_is_inf: bool = False) -> Callable[[pd.DataFrame], np.ndarray]:
    def read(per_pair: pd.DataFrame) -> np.ndarray:
        # a run of several reconstructions (sfm's mapper seeds: NAME_s0, NAME_s1, ...) gives a
        # pairs x seeds array, compared over both (stats.compare_paired)
        seeds = [f"{name}_s{k}" for k in range(len(per_pair.columns)) if f"{name}_s{k}" in per_pair.columns]
        columns = seeds if len(seeds) > 1 else [name]
        values = per_pair[columns].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=np.float64)
        values = values if len(columns) > 1 else values[:, 0]
        if failure_is_inf:  # an error the run could not compute is a failure: worse than any value
            values = np.where(np.isnan(values), np.inf, values)
        return values
    return read


def _passes(name: str, threshold: float, inclusive: bool) -> Callable[[pd.DataFrame], np.ndarray]:
    error = _column(name, failure_is_inf=True)

    def read(per_pair: pd.DataFrame) -> np.ndarray:
        values = error(per_pair)
        return ((values <= threshold) if inclusive else (values < threshold)).astype(np.float64)
    return read


def parse_mma(option: str | None, available: Sequence[str] = ()) -> tuple[int, ...]:
    """--mma: "3" (default), "1,3,5", or "all" (every mma@k column the runs hold)."""
    if option is None or option == "":
        return HOMOGRAPHY_MMA_DEFAULT
    if option.strip().lower() == "all":
        return tuple(t for t in metrics.MMA_THRESHOLDS if f"mma@{t}" in available) or tuple(metrics.MMA_THRESHOLDS)
    try:
        chosen = tuple(int(part) for part in option.split(",") if part.strip())
    except ValueError:
        raise ValueError(f"--mma {option!r}: give thresholds in pixels such as 3 or 1,3,5, or 'all'") from None
    unknown = [t for t in chosen if t not in metrics.MMA_THRESHOLDS]
    if unknown or not chosen:
        raise ValueError(f"--mma {option!r}: thresholds must be among {', '.join(map(str, metrics.MMA_THRESHOLDS))}")
    return chosen


def paired_metrics(benchmark: Benchmark, mma: Sequence[int] = HOMOGRAPHY_MMA_DEFAULT) -> list[PairedMetric]:
    """The per-pair values compared for a benchmark, in the order they are shown.

    Homography: mma@k (each k of `mma`; mean), h_error (median, lower is better; no estimate =
    +inf), and whether h_error <= t for t = 1, 3, 5 px (0/1 per pair; its mean is h_acc@t).
    Pose: err_pose (median, lower is better; no pose = +inf), whether err_pose < t for t = 5, 10,
    20 degrees (the AUC's thresholds; 0/1, mean), and the table's precision column (mean).
    """
    if isinstance(benchmark, HomographyBenchmark):
        return [
            *(PairedMetric(f"mma@{t}", _column(f"mma@{t}"), higher_is_better=True) for t in mma),
            PairedMetric(
                "h_error", _column("h_error", failure_is_inf=True), higher_is_better=False, statistic="median"
            ),
            *(
                PairedMetric(f"h_acc@{t}", _passes("h_error", t, inclusive=True), higher_is_better=True)
                for t in metrics.HOMOGRAPHY_ACCURACY_THRESHOLDS
            ),
        ]
    if isinstance(benchmark, PoseBenchmark):
        precision = benchmark.table_metrics.get("P", metrics.precision_key(metrics.PRECISION_THRESHOLDS[0]))
        return [
            PairedMetric("err_pose", _column("err_pose", failure_is_inf=True), higher_is_better=False,
                         statistic="median"),
            *(PairedMetric(f"err_pose<{t}", _passes("err_pose", t, inclusive=False), higher_is_better=True)
              for t in POSE_ERROR_THRESHOLDS),
            PairedMetric(precision, _column(precision), higher_is_better=True),
        ]
    # A lower-is-better column is an error, +inf where the pair failed: compared by its median.
    generic = [PairedMetric(name, _column(name, failure_is_inf=not higher), higher_is_better=higher,
                            statistic="mean" if higher else "median")
               for name, higher in benchmark.paired_columns]
    generic += [PairedMetric(metric, _passes(column, threshold, inclusive=True), higher_is_better=True)
                for metric, (column, threshold) in benchmark.count_metrics.items()]
    if generic:
        return generic
    # reconstruct's runs: no ground truth, so no pair holds a score; a count of their own (verified
    # matches, images registered) is no verdict, since wrong matches are counted and registered too
    raise ValueError(f"compare: {benchmark.name} runs have no ground truth, so no pair has a score to compare; "
                     f"e3cm-bench table RUN... --out FILE sets their reconstructions and costs side by side")


def _pairs(run: Run) -> pd.DataFrame:
    per_pair = run.per_pair
    if per_pair.empty or "pair" not in per_pair.columns:
        raise ValueError(
            f"{run.folder.per_pair_path}: missing, empty or without a 'pair' column; compare reads each run's pairs "
            "from it"
        )
    duplicated = per_pair["pair"][per_pair["pair"].duplicated()]
    if len(duplicated):
        raise ValueError(f"{run.folder.per_pair_path}: pair {duplicated.iloc[0]!r} appears more than once")
    return per_pair.set_index("pair")


def _bags(a: pd.DataFrame, b: pd.DataFrame) -> np.ndarray | None:
    """The pairs' bags (sfm: the pairs of one reconstruction resample together), where both runs
    record the same ones; None otherwise."""
    if "bag" not in a.columns or "bag" not in b.columns:
        return None
    bags_a, bags_b = (pd.to_numeric(t["bag"], errors="coerce").to_numpy(np.float64) for t in (a, b))
    if not (np.isfinite(bags_a).all() and np.array_equal(bags_a, bags_b)):
        return None
    return bags_a


def compare_runs(
    run_a: Run, run_b: Run, mma: Sequence[int] = HOMOGRAPHY_MMA_DEFAULT, alpha: float = 1.0 - stats.CONFIDENCE,
    n_samples: int = stats.BOOTSTRAP_SAMPLES, seed: int = stats.BOOTSTRAP_SEED,
) -> Comparison:
    """Compare run A with run B on the pairs both hold (in A's order); ValueError in one line when
    they are of different benchmarks, lack per-pair rows or share no pair."""
    if run_a.benchmark.name != run_b.benchmark.name:
        raise ValueError(f"compare: {run_a.dir} is a {run_a.benchmark.name} run and {run_b.dir} a "
                         f"{run_b.benchmark.name} run; compare two runs of one benchmark")
    a, b = _pairs(run_a), _pairs(run_b)
    common = [name for name in a.index if name in set(b.index)]
    if not common:
        raise ValueError(f"compare: {run_a.dir} and {run_b.dir} have no pair in common")
    a, b = a.loc[common], b.loc[common]
    chosen = paired_metrics(run_a.benchmark, mma)
    groups = _bags(a, b)
    results, seeded = [], False
    for metric in chosen:
        try:
            values_a, values_b = metric.values(a), metric.values(b)
        except KeyError as missing:
            raise ValueError(f"compare: {metric.name} needs per_pair.csv column {missing} in both runs") from None
        seeded = seeded or np.ndim(values_a) == 2 or np.ndim(values_b) == 2
        results.append(stats.compare_paired(values_a, values_b, metric.name, higher_is_better=metric.higher_is_better,
                                            statistic=metric.statistic, alpha=alpha,
                                            resampling=stats.Resampling(n_samples, seed, groups)))
    label_a, label_b = run_a.label, run_b.label
    if label_a == label_b:  # two folders of one method: name them by folder instead
        named = (run_a.dir.name, run_b.dir.name)
        label_a, label_b = named if named[0] != named[1] else (str(run_a.dir), str(run_b.dir))
    return Comparison(label_a, label_b, run_a.benchmark.name, len(run_a.per_pair), len(run_b.per_pair),
                      len(common), results, chosen, 1.0 - alpha, n_samples, seed, seeded,
                      tuple(protocol_notes([(label_a, protocol_items(run_a.run_config)),
                                            (label_b, protocol_items(run_b.run_config))])))


def print_comparison(comparison: Comparison, console: Console | None = None) -> None:
    """The comparison on the terminal, within the console's width (80 columns in a log or a pipe):
    the labels on lines of their own, the narrow table, then what its columns mean; no cell is
    cut (one that cannot fit folds onto a second line)."""
    console = console or Console()
    width = text_width(console)
    header, body = comparison.display(wide=False)
    same_n = all(r.n == comparison.n_common for r in comparison.results)
    if same_n:  # the n column would repeat the heading's number on every row: room for the verdict
        header, body = (
            [h for k, h in enumerate(header) if k != 1],
            [[c for k, c in enumerate(row) if k != 1] for row in body],
        )
    every = ", each row over all of them (n)" if same_n else ""
    console.print(f"{comparison.benchmark}: {comparison.n_common} pairs in both runs are compared{every}", markup=False,
                  highlight=False, width=width)
    for side, label, n in (("A", comparison.label_a, comparison.n_a), ("B", comparison.label_b, comparison.n_b)):
        console.print(f"  {side} = {label} ({n} pairs)", markup=False, highlight=False, width=width)
    # No vertical lines, one space of padding: columns two apart, so the table needs about 76
    # columns where rich's default box needed 100 and cut the names to fit 80.
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, padding=(0, 1, 0, 0))
    for k, column in enumerate(header):
        table.add_column(escape(column), justify="left" if k in (0, len(header) - 1) else "right", overflow="fold",
                         no_wrap=k != len(header) - 1)
    for row in body:
        table.add_row(*(escape(cell) for cell in row))
    console.print(table, width=width)
    console.print(comparison.explanation(), markup=False, highlight=False, width=width)
    for note in comparison.notes:  # a verdict across protocols is no verdict on the matchers alone
        console.print(f"note: {note}", markup=False, highlight=False, soft_wrap=True)  # one line, however long


def to_markdown(comparison: Comparison) -> str:
    header, body = comparison.display()
    widths = [max(len(h), *(len(row[k]) for row in body)) for k, h in enumerate(header)]
    right = {3, 4, 5, 6, 7}

    def line(cells: Sequence[str]) -> str:
        return (
            "| "
            + " | ".join(c.rjust(w) if k in right else c.ljust(w) for k, (c, w) in enumerate(zip(cells, widths)))
            + " |"
        )

    rule = "| " + " | ".join("-" * (w - 1) + ":" if k in right else "-" * w for k, w in enumerate(widths)) + " |"
    # the heading holds the two labels: their characters stay text (no HTML, no link)
    return (f"{markdown_text(comparison.heading())}\n\n" + "\n".join([line(header), rule, *(line(r) for r in body)])
            + f"\n\n{comparison.explanation()}\n"
            + "".join(f"\n- {markdown_text('note: ' + note)}\n" for note in comparison.notes))


def write_comparison(comparison: Comparison, out: Path) -> tuple[Path, Path]:
    """OUT/compare.csv and OUT/compare.md."""
    out = Path(out)
    csv_path = write_csv(comparison.table(), out / "compare.csv")
    text = to_markdown(comparison)
    md_path = write_atomically(out / "compare.md", lambda tmp: tmp.write_text(text))
    return csv_path, md_path
