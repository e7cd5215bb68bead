"""The page of `e3cm-bench rank` (OUT/index.html): the ranking as verdict.csv holds it, the cost-score
plot (OUT/cost_score.png) and a few match drawings per matcher (OUT/drawings/LABEL/), beside the
run folders they come from. A static page, as the report's: no script, nothing fetched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.reporting.escape import html_text

PLOT, DRAWINGS = "cost_score.png", "drawings"
DRAWN_PAIRS = 2  # per matcher: its first pairs, in the folder's pair order
SHOWN = ("rank", "method", "score", "score_lo", "score_hi", "vs_next", "seconds_per_image", "peak_memory_mb",
         "registered_images", "n_images", "n_models", "points", "mean_track_length", "mean_reprojection_error",
         "failed")
STYLE = ("body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse}"
         "td,th{border:1px solid #ccc;padding:3px 6px;font-size:13px}td.n{text-align:right}img{max-width:100%}")


def _cell(value, column: str) -> str:
    if isinstance(value, float):
        if np.isnan(value):
            return "<td></td>"
        digits = 0 if column in ("peak_memory_mb", "points") else 2 if column.startswith("seconds") else 1
        return f'<td class="n">{value:.{digits}f}</td>'
    return f"<td>{html_text('' if value is None else value)}</td>"


def cost_score_plot(table: pd.DataFrame, path: Path) -> Path | None:
    """Score (with its interval) against seconds per image, through drawing/plots' cost figure."""
    from e3cm_bench.drawing.plots import plot_cost_accuracy

    ranked = table[table["failed"].fillna("") == ""]
    if ranked.empty:
        return None
    runs = {row.method: {"seconds_per_pair": row.seconds_per_image, "consensus score": row.score,
                         "consensus score_lo": row.score_lo, "consensus score_hi": row.score_hi}
            for row in ranked.itertuples()}
    return plot_cost_accuracy(runs, "consensus score", path, x_label="seconds per image (matching and mapping; log)")


def draw_run(run: Path, folder: Path) -> list[Path]:
    """The run's first DRAWN_PAIRS pairs, their matches drawn on the images (colour by height)."""
    from e3cm_bench.benchmarks.from_record import load_run_pairs
    from e3cm_bench.drawing.matches import draw_matches, save_image
    from e3cm_bench.ground.images import load_image
    from e3cm_bench.storage.cache import MatchCache
    from e3cm_bench.storage.folder import RunFolder

    cache, written = MatchCache(RunFolder(run).matches_path), []
    for k, pair in enumerate(load_run_pairs(run).pairs[:DRAWN_PAIRS]):
        matches = cache.read(pair.name)
        canvas = draw_matches(load_image(pair.image0), load_image(pair.image1), matches.keypoints0,
                              matches.keypoints1, max_lines=300)
        written.append(save_image(folder / f"pair{k}.jpg", canvas))
    return written


def write_rank_page(table: pd.DataFrame, out: Path, page: Path) -> Path:
    header = "".join(f"<th>{html_text(c)}</th>" for c in SHOWN)
    rows = "".join("<tr>" + "".join(_cell(row.get(c), c) for c in SHOWN) + "</tr>"
                   for row in table.to_dict("records"))
    plot = cost_score_plot(table, out / PLOT)
    body = [f"<h1>Which matcher for these images</h1><p>Ranked by the consensus score: each matcher's relative "
            f"poses against the other matchers' reconstructions, AUC up to 10 degrees, 95% interval over the pairs; "
            f"'{html_text('vs_next')}' reads the paired interval against the next row (docs/own-images.md).</p>",
            f"<table><tr>{header}</tr>{rows}</table>"]
    if plot is not None:
        body.append(f'<h2>Cost and score</h2><img src="{PLOT}" alt="score against seconds per image">')
    for row in table.to_dict("records"):
        if row.get("failed") or not row.get("run"):
            continue
        try:
            drawn = draw_run(Path(row["run"]), out / DRAWINGS / str(row["method"]))
        except (OSError, ValueError, KeyError) as error:  # a drawing is no reason to lose the page
            body.append(f"<p>{html_text(row['method'])}: no drawing ({html_text(error)})</p>")
            continue
        images = "".join(f'<img src="{html_text(p.relative_to(out).as_posix())}" alt="matches">' for p in drawn)
        body.append(f"<h2>{html_text(row['method'])}</h2>{images}")
    text = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>rank</title>'
            f"<style>{STYLE}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    from e3cm_bench.ground.files import write_atomically

    return write_atomically(page, lambda tmp: tmp.write_text(text))
