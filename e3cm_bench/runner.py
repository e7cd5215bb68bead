"""The one loop where datasets, matchers, the match cache and the metrics meet.

pairs -> (cached? skip : load, resize, match, map back to original pixels, cache) ->
evaluate every pair from matches.h5 -> per_pair.csv, summary.csv, plots, config.yaml.

Everything that reaches a CSV is recomputed from matches.h5 plus the ground truth, so
`--eval-only` (new RANSAC or precision settings) needs no matcher, and an interrupted run
resumes at the first pair missing from the cache.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pandas as pd
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.text import Text

from . import geometry, metrics, report
from .cache import MatchCache
from .config import load_yaml, package_versions, save_yaml
from .datasets.base import Pair
from .images import load_image, resize_max_side, to_original_pixels
from .matchers.base import Matcher, Matches
from .viz import draw_matches, save_image

DEFAULT_MAX_SIDE = {"hpatches": None, "megadepth": 1200, "yfcc": 1200}
CONFIG_FILE = "config.yaml"
CACHE_FILE = "matches.h5"


@dataclass
class EvalSettings:
    """Estimator settings of the metrics (PROTOCOLS §2-3); changeable with --eval-only."""

    seed: int = 0
    homography_ransac_px: float = 3.0
    homography_max_iters: int = 5000
    homography_confidence: float = 0.9999
    pose_ransac_px: float = 0.5
    pose_confidence: float = 0.99999
    precision_thresholds: tuple[float, ...] = metrics.PRECISION_THRESHOLDS
    correct_px: float = 3.0  # --viz: a HPatches match is drawn green within this reprojection error


@dataclass
class RunSpec:
    """One benchmark run. `match_options` identify the matches (what the cache depends on)."""

    benchmark: str
    out: Path
    method: str
    match_options: dict
    max_side: int | None = None
    limit: int | None = None
    overwrite: bool = False
    eval_only: bool = False
    viz: int = 0
    device: str = "cpu"  # recorded, not part of match_options: it does not change what is matched
    eval: EvalSettings = field(default_factory=EvalSettings)


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


def match_pair(matcher: Matcher, pair: Pair, max_side: int | None, seed: int) -> tuple[Matches, dict]:
    """Load, resize, match and map back to original pixels; attrs for the cache."""
    image0, image1 = load_image(pair.image0), load_image(pair.image1)
    small0, scale0 = resize_max_side(image0, max_side)
    small1, scale1 = resize_max_side(image1, max_side)
    cv2.setRNGSeed(seed)  # robust estimators inside a matcher (cascade RANSAC, DFM) repeat per pair
    t = time.perf_counter()
    m = matcher.match(small0, small1)
    elapsed = time.perf_counter() - t
    matches = Matches(to_original_pixels(m.keypoints0, scale0), to_original_pixels(m.keypoints1, scale1), m.scores, m.info)
    attrs = {
        "size0": (image0.shape[1], image0.shape[0]),
        "size1": (image1.shape[1], image1.shape[0]),
        "match_size0": (small0.shape[1], small0.shape[0]),
        "match_size1": (small1.shape[1], small1.shape[0]),
        "match_seconds": elapsed,
    }
    return matches, attrs


def evaluate_pair(benchmark: str, pair: Pair, matches: Matches, attrs: dict, ev: EvalSettings) -> dict:
    """One per_pair.csv row from cached matches and the ground truth."""
    k0, k1 = matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64)
    if benchmark == "hpatches":
        width, height = (int(v) for v in attrs["size0"])
        row = metrics.evaluate_homography_pair(
            k0, k1, pair.H, width, height, seed=ev.seed, ransac_threshold=ev.homography_ransac_px,
            max_iters=ev.homography_max_iters, confidence=ev.homography_confidence,
        )
        return {"pair": pair.name, "sequence": pair.meta.get("sequence", ""), **row}
    row = metrics.evaluate_pose_pair(
        k0, k1, pair.K0, pair.K1, pair.T_0to1, seed=ev.seed,
        ransac_threshold=ev.pose_ransac_px, confidence=ev.pose_confidence,
    )
    return {"pair": pair.name, **row}


def correct_mask(benchmark: str, pair: Pair, matches: Matches, ev: EvalSettings) -> np.ndarray:
    """Which matches are right by the ground truth (for --viz; green/red like the paper's Fig. 6)."""
    if benchmark == "hpatches":
        err = np.linalg.norm(geometry.warp_points(pair.H, matches.keypoints0) - matches.keypoints1, axis=1)
        return err <= ev.correct_px
    R, t = pair.T_0to1[:3, :3], pair.T_0to1[:3, 3]
    d = geometry.symmetric_epipolar_distance(
        geometry.essential_from_pose(R, t),
        geometry.normalize_keypoints(matches.keypoints0, pair.K0),
        geometry.normalize_keypoints(matches.keypoints1, pair.K1),
    )
    return d < ev.precision_thresholds[0]


def _check_previous_run(out: Path, spec: RunSpec) -> dict | None:
    """The config of matches already in `out`; refuse to mix matches made differently."""
    path = out / CONFIG_FILE
    if not path.exists():
        return None
    previous = load_yaml(path)
    before = previous.get("match_options")
    if spec.eval_only or before is None:
        return previous
    changed = [k for k in sorted(set(before) | set(spec.match_options)) if before.get(k) != spec.match_options.get(k)]
    if previous.get("benchmark") != spec.benchmark:
        changed.insert(0, "benchmark")
    if changed:
        raise ValueError(
            f"{path}: the matches in this folder were made with other settings ({', '.join(changed)}); "
            "pass --overwrite to replace them or choose another --out"
        )
    return previous


def run_benchmark(
    spec: RunSpec,
    dataset,
    make_matcher: Callable[[], Matcher],
    console: Console | None = None,
) -> dict:
    """Run (or resume, or only evaluate) one benchmark; returns the summary row."""
    console = console or Console()
    out = Path(spec.out)
    if spec.overwrite and out.exists():
        for name in (CACHE_FILE, CONFIG_FILE, "per_pair.csv", "summary.csv"):
            (out / name).unlink(missing_ok=True)
        shutil.rmtree(out / "viz", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    previous = _check_previous_run(out, spec)
    pairs = list(dataset)[: spec.limit] if spec.limit else list(dataset)
    cache = MatchCache(out / CACHE_FILE)
    done = set(cache.names())  # one pass over the file, not one open per pair
    todo = [p for p in pairs if p.name not in done]

    match_options = spec.match_options
    matcher_config = (previous or {}).get("matcher")
    if spec.eval_only:
        if previous is None:
            raise ValueError(f"{out / CONFIG_FILE}: not found; --eval-only needs a finished or resumed run in --out")
        if todo:
            raise ValueError(
                f"{out / CACHE_FILE}: {len(todo)} of {len(pairs)} pairs have no matches (first: {todo[0].name}); "
                "run without --eval-only to match them"
            )
        match_options = previous.get("match_options", match_options)

    config = {
        "benchmark": spec.benchmark,
        "method": spec.method if not spec.eval_only else previous.get("method", spec.method),
        "match_options": match_options,
        "matcher": matcher_config,
        "max_side": match_options.get("max_side", spec.max_side),
        "device": spec.device if not spec.eval_only else previous.get("device", spec.device),
        "dataset": {**dataset.describe(), "limit": spec.limit, "n_pairs_evaluated": len(pairs)},
        "evaluation": asdict(spec.eval),
        "versions": package_versions(),
        "timing": (previous or {}).get("timing", {}),
    }

    if todo:
        console.print(f"[bold]{spec.benchmark}[/]: {len(pairs)} pairs, {len(pairs) - len(todo)} already in {out / CACHE_FILE}")
        matcher = make_matcher()
        config["matcher"] = matcher.config()
        save_yaml(config, out / CONFIG_FILE)  # before matching: an interrupted run is still described
        t0 = time.perf_counter()
        with progress_bar(console) as progress:
            task = progress.add_task(f"matching ({spec.method})", total=len(todo))
            for pair in todo:
                matches, attrs = match_pair(matcher, pair, spec.max_side, spec.eval.seed)
                cache.write(pair.name, matches, attrs)
                progress.advance(task)
        elapsed = time.perf_counter() - t0
        timing = config["timing"]
        timing["match_seconds"] = timing.get("match_seconds", 0.0) + elapsed
        timing["pairs_matched"] = timing.get("pairs_matched", 0) + len(todo)
        timing["pairs_per_minute"] = 60.0 * timing["pairs_matched"] / max(timing["match_seconds"], 1e-9)
    else:
        console.print(f"[bold]{spec.benchmark}[/]: all {len(pairs)} pairs found in {out / CACHE_FILE}; evaluating only")

    rows = []
    for pair in pairs:
        matches = cache.read(pair.name)
        rows.append(evaluate_pair(spec.benchmark, pair, matches, matches.info, spec.eval))
    if spec.benchmark == "hpatches":
        per_pair = pd.DataFrame(rows, columns=metrics.HPATCHES_PAIR_COLUMNS)
        summary = metrics.summarize_hpatches(rows)
    else:
        per_pair = pd.DataFrame(rows, columns=metrics.POSE_PAIR_COLUMNS)
        summary = metrics.summarize_pose(rows)
    report.write_csv(per_pair, out / "per_pair.csv")
    report.write_csv(pd.DataFrame([summary]), out / "summary.csv")
    label = config["method"]
    if spec.benchmark == "hpatches":
        report.plot_mma_curves({label: summary}, out / "mma.png")
    else:
        report.plot_pose_error_cdf({label: per_pair}, out / "pose_error_cdf.png")
    for pair in pairs[: spec.viz]:
        matches = cache.read(pair.name)
        canvas = draw_matches(
            load_image(pair.image0), load_image(pair.image1), matches.keypoints0, matches.keypoints1,
            correct=correct_mask(spec.benchmark, pair, matches, spec.eval), max_lines=400,
        )
        save_image(out / "viz" / (pair.name.replace("/", "__") + ".png"), canvas)
    save_yaml(config, out / CONFIG_FILE)
    report.print_summary(summary, f"{spec.benchmark} - {label} ({len(pairs)} pairs) -> {out}", console=console)
    return summary
