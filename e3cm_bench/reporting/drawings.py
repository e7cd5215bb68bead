"""The report's match drawings: which pairs are drawn (those most methods fail, then an even
sample of the rest) and each run's drawing of them, from its cached matches, coloured by the
ground truth of its own pairs (loaded again as the run loaded them: benchmarks.records.load_run_pairs).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
from e3cm_bench.reporting.runs import Run

N_WORST = 8          # pairs drawn because most methods fail there
N_SAMPLE = 8         # pairs drawn as an even sample of the rest
DRAWING_WIDTH = 1280  # px: a drawing (both images side by side) is shrunk to this width
DRAWING_QUALITY = 80  # JPEG


def pair_rows(runs: list[Run]) -> pd.DataFrame:
    """One row per pair (in the first run's order), per method the report columns and `fail`."""
    benchmark = runs[0].benchmark
    frames = []
    for k, run in enumerate(runs):
        columns = [c for c in benchmark.report_columns if c in run.per_pair.columns]
        part = run.per_pair[["pair", *columns]].set_index("pair").add_prefix(f"{k}:")
        if benchmark.failure is not None and benchmark.failure[0] in run.per_pair.columns:
            value = run.per_pair.set_index("pair")[benchmark.failure[0]].astype(float)
            part[f"{k}:fail"] = ~(value <= benchmark.failure[1])  # NaN and inf fail
        frames.append(part)
    order = list(runs[0].per_pair["pair"])
    table = pd.concat(frames, axis=1, join="outer")
    order += [p for p in table.index if p not in set(order)]
    return table.loc[order]


def choose_pairs(pairs: pd.DataFrame, runs: list[Run]) -> list[str]:
    """The N_WORST pairs most methods fail (ties: fewer matches first), then an even sample."""
    fails = pairs[[c for c in pairs.columns if c.endswith(":fail")]].fillna(True).sum(axis=1)
    matches = pairs[[c for c in pairs.columns if c.endswith(":n_matches")]].fillna(0).sum(axis=1)
    ranked = pd.DataFrame({"fails": fails, "matches": matches, "order": range(len(pairs))}, index=pairs.index)
    worst = list(ranked.sort_values(["fails", "matches", "order"], ascending=[False, True, True]).index[:N_WORST])
    rest = [p for p in pairs.index if p not in set(worst)]
    sample = [rest[int(i)] for i in np.linspace(0, len(rest) - 1, min(N_SAMPLE, len(rest)))] if rest else []
    return list(dict.fromkeys(worst + sample))


def draw_pairs(runs: list[Run], chosen: list[str], out: Path, notes: list[str]) -> dict[str, dict[int, str]]:
    """pair -> {run index: drawing path}; matches from each run's cache, colours from the ground
    truth of the run's own dataset (recorded in its config.yaml) when it can be loaded."""
    import cv2

    from e3cm_bench.ground.images import load_image
    from e3cm_bench.drawing.matches import draw_matches, drawn, save_image

    drawings: dict[str, dict[int, str]] = {name: {} for name in chosen}
    for k, run in enumerate(runs):
        cache = run.folder.cache()
        cached = set(cache.names())
        pairs = _dataset_pairs(run, notes)
        ev = evaluation_of(run.run_config)
        for name in chosen:
            if name not in cached or name not in pairs:
                continue
            pair, matches = pairs[name], drawn(cache.read(name))  # the matches its row scored
            try:
                image0, image1 = load_image(pair.image0), load_image(pair.image1)
            except ValueError as error:
                notes.append(f"{run.label}: {error}; no drawing")
                continue
            correct = run.benchmark.correct_mask(pair, matches, ev) if len(matches) else None
            canvas = draw_matches(
                image0, image1, matches.keypoints0, matches.keypoints1, correct=correct, max_lines=400
            )
            scale = min(1.0, DRAWING_WIDTH / canvas.shape[1])
            if scale < 1:
                canvas = cv2.resize(canvas, (round(canvas.shape[1] * scale), round(canvas.shape[0] * scale)),
                                    interpolation=cv2.INTER_AREA)
            path = out / "img" / f"{file_slug(name)}--{k:02d}.jpg"
            save_image(path, canvas, [cv2.IMWRITE_JPEG_QUALITY, DRAWING_QUALITY])
            drawings[name][k] = path.relative_to(out).as_posix()
    return drawings


def _dataset_pairs(run: Run, notes: list[str]) -> dict:
    """The run's pairs with their ground truth, loaded as the run loaded them (load_run_pairs)."""
    try:
        loaded = load_run_pairs(run.run_config)
    except (ValueError, OSError, TypeError) as error:
        notes.append(f"{run.label}: its dataset cannot be read here ({str(error).splitlines()[0]}); no drawings")
        return {}
    return {pair.name: pair for pair in loaded.pairs}


def file_slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)
