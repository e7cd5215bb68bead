"""A run's matches out to another tool: ``export_run(RUN, FORMAT, OUT)``.

The run's pairs are loaded again as the run loaded them (benchmarks.records.load_run_pairs: its
config.yaml's dataset_load, else its dataset block, its skip_bad and --limit); every pair of the run
with matches in its cache is written (pairs it skipped have none), in the run's pair order.
COLMAP and hloc get one keypoint list per image (tracks.py; ``merge_px`` merges within a
radius). OUT is never a run folder nor inside one: export writes beside a run, so that it
cannot replace what a run holds (an OUT that holds the run is allowed, since no file it
writes can land in the run: each is checked).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console

from e3cm_bench.ground.locks import writable_folder
from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
from e3cm_bench.storage import RunFolder
from e3cm_bench.ground.images import load_image
from e3cm_bench.ground.matches import Matches, distinct
from e3cm_bench.interchange.base import ExportItem, image_name
from e3cm_bench.interchange.pixels import resolve_origin
from e3cm_bench.interchange.registry import formats, get_format
from e3cm_bench.drawing.formats import print_wrapped


def _geometry(benchmark, pair, matches: Matches, ev) -> dict | None:
    """The evaluation's own estimate on these matches (the same estimator, threshold and seed,
    on each correspondence once, as the evaluation counts them); the inliers are given for every
    match written, a repeat of an inlier being an inlier."""
    found = estimate_geometry(benchmark, pair, distinct(matches)[0], ev)
    if found is None or len(found["inliers"]) == len(matches):
        return found
    both = np.concatenate([matches.keypoints0, matches.keypoints1], axis=1)
    _, first, inverse = np.unique(both, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))  # distinct keeps the first occurrences in order
    return {**found, "inliers": np.asarray(found["inliers"], bool)[rank[np.ravel(inverse)]]}


def estimate_geometry(benchmark, pair, matches: Matches, ev) -> dict | None:
    """The two-view geometry the run's benchmark estimates in its evaluation (H, or the relative
    pose; Benchmark.two_view_geometry) and its inliers; None where it has none or it fails."""
    return benchmark.two_view_geometry(pair, matches, ev)


def _run_folder_holding(folder: Path, run_dir: Path) -> Path | None:
    """The run folder that `folder` is or lies in (the run being exported, or any folder with a
    run's config.yaml and its matches or tables), else None; links resolved."""
    run_dir = run_dir.resolve()
    folder = folder.resolve()
    for place in (folder, *folder.parents):
        if place == run_dir:
            return place
        here = RunFolder(place)
        if here.config_path.is_file() and any(
            p.is_file() for p in (here.matches_path, here.per_pair_path, here.summary_path)
        ):
            return place
    return None


def refuse_run_folder(run_dir: Path, out: Path, targets=()) -> None:
    """A one-line refusal where OUT, or the folder of one of the files to write, is a run folder
    or inside one: an export there would replace the run's own files (its matches.h5)."""
    for folder in (out, *{Path(t).parent for t in targets}):
        run = _run_folder_holding(folder, run_dir)
        if run is not None:
            where = "is" if run == folder.resolve() else "is inside"
            raise ValueError(f"{folder}: {where} the run folder {run}; export writes beside a run, never into one: "
                             "choose another OUT")


@dataclass
class ExportJob:
    """What a format's writer may need besides the items: the run's benchmark, dataset root and
    options, the merge radius and (formats that merge) the merged keypoints; a writer may leave
    figures for the report here (hloc: its layout)."""

    benchmark: object
    root: Path
    options: dict
    merge_px: float
    merged: tuple | None = None
    layout: tuple | None = None


def export_run(run_dir: str | Path, fmt: str, out: str | Path, origin: str | None = None, overwrite: bool = False,
               console: Console | None = None, merge_px: float = 0.0) -> dict:
    """Write RUN's matches to OUT in FORMAT (registry.formats(): colmap, gluefactory, hloc, npz);
    returns what was written. An existing output file is refused unless overwrite; files are
    written beside their name and renamed into place, never through a link. merge_px (colmap,
    hloc): keypoints of an image within this radius are written as one (tracks.py); exact
    repeats always are."""
    console = console or Console()
    fmt = get_format(fmt)
    merge_px = _check_merge(fmt, merge_px)
    origin = resolve_origin(fmt, origin)
    run_dir, out = Path(run_dir), Path(out)
    refuse_run_folder(run_dir, out)
    benchmark, config, root, pairs, options, _ = load_run_pairs(run_dir)
    targets = fmt.targets(out, [p.name for p in pairs])
    refuse_run_folder(run_dir, out, targets)
    ev = _eval_settings(fmt, config)
    writable_folder(out)
    taken = [path for path in targets if path.exists()]
    if taken and not overwrite:
        raise ValueError(f"{taken[0]}: already exists; pass --overwrite to replace it or choose another OUT")
    items = _items(run_dir, benchmark, root, pairs, ev)
    job = ExportJob(benchmark, root, options, merge_px)
    if fmt.merges:
        from e3cm_bench.interchange.tracks import merge_keypoints

        job.merged = merge_keypoints(((item.name0, item.name1, item.matches.keypoints0, item.matches.keypoints1)
                                      for item in items), merge_px)
    written = fmt.write(out, items, origin, job)
    return _report(console, run_dir, out, fmt, origin, items, written, job)


def _check_merge(fmt, merge_px: float) -> float:
    merge_px = float(merge_px)
    if not merge_px >= 0:  # also refuses NaN
        raise ValueError(f"--merge-px must be a radius of 0 or more pixels, got {merge_px:g}")
    if merge_px > 0 and not fmt.merges:
        merging = [f.name for f in formats().values() if f.merges]
        raise ValueError(f"--merge-px applies to --to {' and '.join(merging)} (one keypoint list per image); "
                         f"{fmt.name} keeps each pair's own keypoints")
    return merge_px


def _eval_settings(fmt, config):
    """The run's evaluation settings (records.evaluation_of) where the format stores each pair's
    geometry (so that the stored inliers are the ones the evaluation found); the format's library
    checked first."""
    fmt.check_available()  # before any work: one line if an extra is not installed
    return evaluation_of(config) if fmt.stores_geometry else None


def _items(run_dir: Path, benchmark, root: Path, pairs: list, ev) -> list[ExportItem]:
    """An ExportItem per pair with matches in the run's cache, in the run's pair order (with its
    geometry where ev is given)."""
    items = []
    folder = RunFolder(run_dir)
    with folder.lock():
        cache = folder.cache()
        done = set(cache.names())
        for pair in pairs:
            if pair.name not in done:
                continue
            matches = cache.read(pair.name)
            size0 = tuple(int(v) for v in matches.info.get("size0", ())) or _size(pair.image0)
            size1 = tuple(int(v) for v in matches.info.get("size1", ())) or _size(pair.image1)
            item = ExportItem(pair.name, pair, *_image_names(pair, root), size0, size1, matches,
                              getattr(pair, "K0", None), getattr(pair, "K1", None))
            if ev is not None:
                item.geometry = _geometry(benchmark, pair, matches, ev)
            items.append(item)
    if not items:
        raise ValueError(f"{run_dir}: no matched pairs in its cache to export")
    return items


def _image_names(pair, root: Path) -> tuple[str, str]:
    """The pair's image names: the set's own where it names its views (sfm: the names of its
    reconstruction's database, absolute paths with --absolute-paths), else each image's path
    under the root."""
    view0, view1 = getattr(pair, "view0", None), getattr(pair, "view1", None)  # a views.ViewPair's
    if view0 and view1:
        return str(view0), str(view1)
    return image_name(pair.image0, root), image_name(pair.image1, root)


def _report(console: Console, run_dir: Path, out: Path, fmt, origin: str, items: list, written: list,
            job: ExportJob) -> dict:
    """Print what the export did and return its figures."""
    n_matches = sum(len(item.matches) for item in items)
    # Within the terminal's width, or 80 columns in a pipe or a log (formats.text_width: rich alone
    # takes the width of a terminal on stdin, so `export ... > log` wrote lines as wide), words whole.
    say = functools.partial(print_wrapped, console)
    say(
        f"export: {len(items)} pairs ({n_matches} matches) of {run_dir} -> {fmt.name} in {out} (pixel origin: {origin})"
    )
    if fmt.stores_geometry:
        verified = sum(item.geometry is not None for item in items)
        say(f"export: {verified} of {len(items)} pairs with a two-view geometry (the evaluation's inliers)")
    found = {"format": fmt.name, "n_pairs": len(items), "n_matches": n_matches, "files": [str(p) for p in written],
             "pixel_origin": origin}
    if job.merged is not None:
        found.update(_merge_figures(items, job.merged, job.layout, job.merge_px))
        how = (
            "exact repeats merged"
            if job.merge_px == 0
            else f"exact repeats and points within {job.merge_px:g} px merged"
        )
        say(f"export: one keypoint list per image: {2 * n_matches} matched keypoints -> {found['n_keypoints_merged']} "
            f"({how}); {found['n_tracks']} tracks, {found['mean_track_length']:.2f} images each on average")
        if job.layout is not None:
            say(f"export: {found['n_keypoints_appended']} keypoints appended where a pair matched one keypoint of its "
                "first image more than once (hloc's matches0 holds one match per keypoint)")
    return found


def _merge_figures(items, merged, layout, merge_px: float) -> dict:
    """What the one-keypoint-list-per-image export did: keypoints kept, tracks and their mean
    length (images per track), and hloc's appended keypoints."""
    from e3cm_bench.interchange.tracks import track_lengths

    keypoints, indices = merged
    lengths = track_lengths({n: len(k) for n, k in keypoints.items()}, [(i.name0, i.name1) for i in items], indices)
    found = {"merge_px": merge_px, "n_keypoints_merged": int(sum(len(k) for k in keypoints.values())),
             "n_tracks": int(len(lengths)), "mean_track_length": float(np.mean(lengths)) if len(lengths) else 0.0}
    if layout is not None:
        found["n_keypoints_appended"] = int(sum(len(k) for k in layout[0].values())) - found["n_keypoints_merged"]
    return found


def _size(path: Path) -> tuple[int, int]:
    image = load_image(path)
    return int(image.shape[1]), int(image.shape[0])
