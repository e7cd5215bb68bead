"""`e3cm-bench rank IMAGES --matchers a,b,c --out OUT`: which matcher for one's own images, at what cost.

Each matcher reconstructs the folder as `reconstruct` does (the same RECONSTRUCT benchmark, run by
run_benchmark into OUT/runs/LABEL: cache, resume, the same verification and mapper), one after the
other; then the runs are judged together without ground truth (apps/rank_verdict.py,
sfm/consensus.py) into OUT/verdict.csv and a page, OUT/index.html. A matcher that fails is
recorded with its reason and the others go on; an interrupted rank resumes run by run (each run
folder resumes by itself). What the verdict depends on is recorded in OUT/rank.yaml.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import pandas as pd
from rich.console import Console

from e3cm_bench.apps.rank_verdict import VERDICT, verdict_table, write_verdict
from e3cm_bench.sfm.consensus import SCORE_THRESHOLD, Ranking

RUNS, RECORD, LOG, PAGE = "runs", "rank.yaml", "rank.log", "index.html"
# Method options that only a matcher on a backbone takes: given once for the rank, each passes to
# the matchers that take it (sift has no backbone to set).
BACKBONE_ONLY = ("backbone", "weights", "precision", "channel_order")
MIN_MATCHERS = 3


@dataclass(frozen=True)
class RankRequest:
    """One rank: the folder, where it goes, the matchers (names or module:factory), the method
    options they share (build_method's names), reconstruct's dataset and evaluation options (the
    mapper, its seeds), the seed, the device."""

    images: Path
    out: Path
    matchers: tuple[str, ...]
    method: dict = field(default_factory=dict)
    dataset_options: dict = field(default_factory=dict)
    evaluation: dict = field(default_factory=dict)
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        if len(self.matchers) < MIN_MATCHERS:  # with two, each is only the other's distance from it
            raise ValueError(f"--matchers: a rank needs at least {MIN_MATCHERS} matchers (each is judged by the "
                             f"others), got {len(self.matchers)}")
        labels = [label_of(m) for m in self.matchers]
        twice = sorted({label for label in labels if labels.count(label) > 1})
        if twice:
            raise ValueError(f"--matchers: {', '.join(twice)} given twice")


def label_of(matcher: str) -> str:
    """The run folder's and the table's name of a matcher: its name, a module:factory's factory
    with the module (`mine.akaze:ENTRY` -> `mine.akaze-ENTRY`), nothing a path could misread."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "-", matcher.replace(":", "-"))


def method_given(request: RankRequest, matcher: str) -> dict:
    from e3cm_bench.matchers.registry import get_matcher

    deep = get_matcher(matcher, allow_import=True).needs_backbone
    given = {k: v for k, v in request.method.items() if v is not None and (deep or k not in BACKBONE_ONLY)}
    return {**given, "matcher": matcher}


def run_one(request: RankRequest, matcher: str, console: Console) -> Path:
    """The matcher's reconstruct run of the folder, into OUT/runs/LABEL (resumed where it stopped),
    resolved from its options by section as `reconstruct`'s are (pipeline/resolve.py)."""
    from e3cm_bench.pipeline.resolve import resolve_request
    from e3cm_bench.pipeline.runner import run_benchmark
    from e3cm_bench.sfm.own_images import RECONSTRUCT

    folder = Path(request.out) / RUNS / label_of(matcher)
    given = {"method": method_given(request, matcher),
             "dataset": {k: v for k, v in request.dataset_options.items() if v is not None},
             "evaluation": {k: v for k, v in request.evaluation.items() if v is not None},
             "run": {"out": folder, "root": request.images, "device": request.device}}
    run_benchmark(resolve_request(RECONSTRUCT, given), console=console)
    return folder


def record(request: RankRequest) -> dict:
    """OUT/rank.yaml: the request and how the verdict is made (score, threshold, resampling)."""
    from e3cm_bench.ground.machine import package_versions, run_environment

    given = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(request).items()}
    ranking = Ranking()
    return {"versions": package_versions(), "environment": run_environment(),
            "request": {**given, "matchers": list(request.matchers)},
            "verdict": {"score": "consensus auc", "threshold_deg": SCORE_THRESHOLD,
                        "reference": "geometric median of the other matchers' relative poses (sfm/consensus.py)",
                        "resampled": "pairs", "bootstrap_samples": ranking.n_samples,
                        "bootstrap_seed": ranking.seed, "confidence": ranking.confidence}}


def rank_folder(request: RankRequest, console: Console | None = None) -> pd.DataFrame:
    """Every matcher's run (a failing one recorded), then the verdict; returns verdict.csv's table."""
    from e3cm_bench.ground.files import save_yaml
    from e3cm_bench.ground.locks import FolderLock

    from e3cm_bench.sfm.own_images import RECONSTRUCT

    console = console or Console()
    out = Path(request.out)
    # the folder and the pair options checked once, before a matcher starts: a folder of no images
    # is one line and a non-zero exit, not three failed rows
    RECONSTRUCT.build_dataset(request.images, False, {k: v for k, v in request.dataset_options.items()
                                                      if v is not None})
    with FolderLock(out), (out / LOG).open("a") as log:
        save_yaml(record(request), out / RECORD)
        quiet = Console(file=log, width=100, soft_wrap=True)
        runs, failed = {}, {}
        for k, matcher in enumerate(request.matchers, 1):
            label = label_of(matcher)
            console.print(f"[{k}/{len(request.matchers)}] {label}: matching and reconstructing "
                          f"(its log: {out / LOG})", markup=False, highlight=False)
            try:
                runs[label] = run_one(request, matcher, quiet)
            except Exception as error:  # noqa: BLE001 - one matcher's failure is its row, not the rank's end
                failed[label] = " ".join(f"{type(error).__name__}: {error}".split())
                console.print(f"    {label} failed: {failed[label]}", markup=False, highlight=False)
        table = verdict_table(runs, failed)
        modelled = int((table.get("registered_images", pd.Series(dtype=float)).fillna(0) > 0).sum())
        if modelled < MIN_MATCHERS:
            console.print(f"warning: only {modelled} of the {len(request.matchers)} matchers made a reconstruction: "
                          "each is judged by fewer than two others, which says little of which is right "
                          "(docs/own-images.md)", markup=False, highlight=False)
        write_verdict(table, out)
        write_page(table, out)
    return table


def write_page(table: pd.DataFrame, out: Path) -> Path:
    """OUT/index.html: the ranking and the cost-score plot (OUT/cost_score.png)."""
    from e3cm_bench.apps.rank_page import write_rank_page

    return write_rank_page(table, Path(out), Path(out) / PAGE)


def print_verdict(table: pd.DataFrame, out: Path, console: Console) -> None:
    """The ranking on the console (80 columns): rank, method, score [interval], the verdict against
    the next row, seconds per image; then where the files are."""
    from rich.table import Table

    shown = Table(title="ranked without ground truth (consensus score, 95% interval over the pairs)")
    for column in ("rank", "method", "score [lo, hi]", "vs next", "s/image"):
        shown.add_column(column, justify="left" if column in ("method", "vs next") else "right")
    for row in table.to_dict("records"):
        if row.get("failed"):
            shown.add_row("", str(row["method"]), "failed", str(row["failed"])[:60], "")
            continue
        shown.add_row(f"{int(row['rank'])}", str(row["method"]),
                      f"{row['score']:.1f} [{row['score_lo']:.1f}, {row['score_hi']:.1f}]", str(row["vs_next"]),
                      f"{row['seconds_per_image']:.2f}")
    console.print(shown)
    console.print(f"wrote {out / VERDICT}, {out / PAGE}; each matcher's run in {out / RUNS}", markup=False,
                  highlight=False)


__all__ = ["RankRequest", "VERDICT", "label_of", "print_verdict", "rank_folder"]
