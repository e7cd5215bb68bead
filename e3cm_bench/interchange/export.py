"""A run's matches out to another tool: ``export_run(RUN, FORMAT, OUT)``.

The run's pairs are loaded again as the run loaded them (run.config.load_run_pairs: its
config.yaml's dataset_load, else its dataset block, its skip_bad and --limit); every pair of the run
with matches in its cache is written (pairs it skipped have none), in the run's pair order.
COLMAP and hloc get one keypoint list per image (tracks.py; ``merge_px`` merges within a
radius). OUT is never a run folder nor inside one: export writes beside a run, so that it
cannot replace what a run holds (an OUT that holds the run is allowed, since no file it
writes can land in the run: each is checked).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console

from ..files import writable_folder
from ..run import RunFolder, load_run_pairs
from ..images import load_image
from ..matches import Matches, distinct
from .base import image_name
from .pixels import check_origin

FORMATS = ("colmap", "hloc", "gluefactory", "npz")
OUTPUTS = {"colmap": ("database.db",), "hloc": ("features.h5", "matches.h5", "pairs.txt"), "gluefactory": ("predictions.h5",),
           "npz": ()}
DEFAULT_ORIGINS = {"colmap": "corner", "hloc": "center", "gluefactory": "corner", "npz": "center"}
MERGING = ("colmap", "hloc")  # the formats with one keypoint list per image


@dataclass
class ExportItem:
    """One pair on its way out: its names in the dataset, its images' sizes (w, h) and
    intrinsics where the benchmark has them, its matches, and (colmap) the geometry the
    evaluation estimates from them."""

    name: str
    pair: object
    name0: str
    name1: str
    size0: tuple[int, int]
    size1: tuple[int, int]
    matches: Matches
    K0: np.ndarray | None = None
    K1: np.ndarray | None = None
    geometry: dict | None = None


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
    """The evaluation's own estimate on these matches (H where the pair has one, else the relative
    pose where the benchmark has a RANSAC threshold) and its inliers; None where it fails."""
    from .. import estimators
    from ..geometry import warp_points

    k0, k1 = matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64)
    if getattr(pair, "H", None) is not None:
        H = estimators.homography(k0, k1, ev.homography_ransac_px, ev.homography_max_iters, ev.homography_confidence,
                                  estimator=ev.estimator, seed=ev.seed)
        if H is None:
            return None
        with np.errstate(invalid="ignore"):
            error = np.linalg.norm(warp_points(H, k0) - k1, axis=1)
        return {"H": H, "inliers": np.nan_to_num(error, nan=np.inf) <= ev.homography_ransac_px}
    if getattr(pair, "K0", None) is not None and hasattr(benchmark, "ransac_px"):
        sizes = (tuple(matches.info["size0"]), tuple(matches.info["size1"])) if "size0" in matches.info else None
        found = estimators.relative_pose(k0, k1, pair.K0, pair.K1, benchmark.ransac_px(pair, matches, ev),
                                         ev.pose_confidence, estimator=ev.estimator, seed=ev.seed, sizes=sizes)
        if found is None:
            return None
        R, t, inliers = found
        return {"R": np.asarray(R, np.float64), "t": np.asarray(t, np.float64).ravel(), "inliers": np.asarray(inliers, bool)}
    return None


def _run_folder_holding(folder: Path, run_dir: Path) -> Path | None:
    """The run folder that `folder` is or lies in (the run being exported, or any folder with a
    run's config.yaml and its matches or tables), else None; links resolved."""
    run_dir = run_dir.resolve()
    folder = folder.resolve()
    for place in (folder, *folder.parents):
        if place == run_dir:
            return place
        here = RunFolder(place)
        if here.config_path.is_file() and any(p.is_file() for p in (here.matches_path, here.per_pair_path, here.summary_path)):
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


def export_run(run_dir: str | Path, fmt: str, out: str | Path, origin: str | None = None, overwrite: bool = False,
               console: Console | None = None, merge_px: float = 0.0) -> dict:
    """Write RUN's matches to OUT in FORMAT (colmap, hloc, gluefactory, npz); returns what was
    written. An existing output file is refused unless overwrite; files are written beside
    their name and renamed into place, never through a link. merge_px (colmap, hloc): keypoints
    of an image within this radius are written as one (tracks.py); exact repeats always are."""
    console = console or Console()
    if fmt not in FORMATS:
        raise ValueError(f"--to must be one of {', '.join(FORMATS)}, got {fmt!r}")
    merge_px = float(merge_px)
    if not merge_px >= 0:  # also refuses NaN
        raise ValueError(f"--merge-px must be a radius of 0 or more pixels, got {merge_px:g}")
    if merge_px > 0 and fmt not in MERGING:
        raise ValueError(f"--merge-px applies to --to {' and '.join(MERGING)} (one keypoint list per image); "
                         f"{fmt} keeps each pair's own keypoints")
    origin = check_origin(origin or DEFAULT_ORIGINS[fmt])
    run_dir, out = Path(run_dir), Path(out)
    refuse_run_folder(run_dir, out)
    benchmark, config, root, pairs, options, _ = load_run_pairs(run_dir)
    if fmt == "npz":  # a pair's name may hold folders, which could reach into a run under OUT
        refuse_run_folder(run_dir, out, [out / f"{p.name}.npz" for p in pairs])
    ev = None
    if fmt == "colmap":
        from .colmap import pycolmap_module

        pycolmap_module()  # before any work: one line if the extra is not installed
        ev = config.eval_settings()  # the evaluation's own, so that the stored inliers are the ones it found
    writable_folder(out)
    if not overwrite:
        taken = [out / name for name in OUTPUTS[fmt] if (out / name).exists()]
        if fmt == "npz":
            taken = [out / f"{p.name}.npz" for p in pairs if (out / f"{p.name}.npz").exists()][:1]
        if taken:
            raise ValueError(f"{taken[0]}: already exists; pass --overwrite to replace it or choose another OUT")
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
            item = ExportItem(pair.name, pair, image_name(pair.image0, root), image_name(pair.image1, root), size0, size1,
                              matches, getattr(pair, "K0", None), getattr(pair, "K1", None))
            if ev is not None:
                item.geometry = _geometry(benchmark, pair, matches, ev)
            items.append(item)
    if not items:
        raise ValueError(f"{run_dir}: no matched pairs in its cache to export")
    merged = layout = None
    if fmt in MERGING:
        from .tracks import merge_keypoints

        merged = merge_keypoints(((item.name0, item.name1, item.matches.keypoints0, item.matches.keypoints1)
                                  for item in items), merge_px)
    if fmt == "hloc":
        from .hloc import hloc_layout, write_hloc

        layout = hloc_layout(items, merged)
        written = write_hloc(out, items, origin, merge_px, layout=layout)
    elif fmt == "npz":
        from .npz import write_npz

        written = write_npz(out, items, origin)
    elif fmt == "colmap":
        from .colmap import write_colmap

        written = write_colmap(out, items, origin, merge_px, merged=merged)
    else:
        from .gluefactory import write_gluefactory

        written = write_gluefactory(out, items, origin, benchmark=benchmark.name, root=root,
                                    ignore_large=bool(options.get("exclude_large")))
    n_matches = sum(len(item.matches) for item in items)
    console.print(f"export: {len(items)} pairs ({n_matches} matches) of {run_dir} -> {fmt} in {out} "
                  f"(pixel origin: {origin})", markup=False, highlight=False, soft_wrap=True)
    if fmt == "colmap":
        verified = sum(item.geometry is not None for item in items)
        console.print(f"export: {verified} of {len(items)} pairs with a two-view geometry (the evaluation's inliers)",
                      markup=False, highlight=False)
    found = {"format": fmt, "n_pairs": len(items), "n_matches": n_matches, "files": [str(p) for p in written],
             "pixel_origin": origin}
    if merged is not None:
        found.update(_merge_figures(items, merged, layout, merge_px))
        how = "exact repeats merged" if merge_px == 0 else f"exact repeats and points within {merge_px:g} px merged"
        console.print(f"export: one keypoint list per image: {2 * n_matches} matched keypoints -> "
                      f"{found['n_keypoints_merged']} ({how}); {found['n_tracks']} tracks, "
                      f"{found['mean_track_length']:.2f} images each on average", markup=False, highlight=False,
                      soft_wrap=True)
        if layout is not None:
            console.print(f"export: {found['n_keypoints_appended']} keypoints appended where a pair matched one keypoint "
                          "of its first image more than once (hloc's matches0 holds one match per keypoint)",
                          markup=False, highlight=False, soft_wrap=True)
    return found


def _merge_figures(items, merged, layout, merge_px: float) -> dict:
    """What the one-keypoint-list-per-image export did: keypoints kept, tracks and their mean
    length (images per track), and hloc's appended keypoints."""
    from .tracks import track_lengths

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
