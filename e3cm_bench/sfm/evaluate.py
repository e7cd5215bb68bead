"""A set's pairs scored under a protocol: per bag (a connected component of the pair graph,
views.ViewPair.bag) and per seed, one database verified with that seed
and the mapper run on it with the same seed; each pair scored in its bag's reconstruction of
each seed.

Each seed verifies the pairs again (the estimator's RANSAC or COLMAP's, seeded evaluation.seed
+ K) before its mapper runs: a verification drawn once and shared by every seed would leave its
draw out of the interval, which resamples seeds (issue 69: one shared draw at --seed 0 and
another at --seed 1 ranked direct and sift in opposite orders, each outside the other's interval).

Products under WHERE (the run folder's sfm/): database.db, mapper.log, models/ (the first
seed), seed-K/ (the same for seed evaluation.seed + K); with several bags the same under
bag-B/; and per_seed.csv, the summary of each seed (the pairs' AUC and mAA, the models' own
numbers).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.sfm import metrics as sfm_metrics
from e3cm_bench.ground.folders import fresh_folder
from e3cm_bench.sfm.mapper import MODELS, Reconstruction, run_mapper, write_database

NUMBERS = ("n_images", "registered_images", "n_models", "points", "mean_track_length", "mean_reprojection_error")
TRACKS = ("repeat_share", "track_length_database", "merge_displacement_px")


def bags(pairs: Sequence) -> dict:
    """bag -> indices of its pairs (views.ViewPair.bag), in the pairs' order."""
    found: dict = {}
    for i, pair in enumerate(pairs):
        found.setdefault(pair.bag, []).append(i)
    return found


def _images(pairs: Sequence) -> list[str]:
    images = []
    for pair in pairs:
        for name in (pair.view0, pair.view1):
            if name not in images:
                images.append(name)
    return images


def image_root(pairs: Sequence) -> Path | None:
    """The folder the views' names are relative to (pair.image0 = ROOT/view0), which the mapper
    reads the images from (their colours); None where the names are not such paths."""
    for pair in pairs:
        path, name = Path(pair.image0).as_posix(), str(pair.view0)
        if path.endswith("/" + name):
            return Path(path[:-len(name) - 1])
    return None


def reconstruct_set(pairs: Sequence, matches: Sequence, ev, where: Path, protocol) -> tuple[list[dict], dict]:
    """Per-pair rows (the first seed's columns, then each seed's) and the set's numbers (the
    mean over seeds of each seed's, the tracks' numbers, the spread of the metrics over seeds,
    the protocol) of `pairs` under a resolved protocol.ReconstructionProtocol."""
    # a rerun replaces every product of the last (bags may differ); a link there is refused, never followed
    where = fresh_folder(where, "the reconstruction's files go there")
    grouped = bags(pairs)
    k = protocol.mapper_seeds
    rows = [{} for _ in pairs]
    per_seed = [[] for _ in range(k)]  # per seed, each bag's Reconstruction
    tracks = []
    for bag, index in grouped.items():
        folder = where if len(grouped) == 1 else where / f"bag-{bag}"
        chosen = [pairs[i] for i in index]
        images, root = _images(chosen), image_root(chosen)  # the bag's: the same for every seed
        for s in range(k):
            seeded = dataclasses.replace(ev, seed=ev.seed + s)
            workdir = folder if s == 0 else folder / f"seed-{s}"
            verified, numbers = write_database(chosen, [matches[i] for i in index], seeded, workdir, protocol)
            if s == 0:  # the tracks are the merge's: the same for every seed
                tracks.append((len(index), numbers))
            found = run_mapper(workdir, images, seeded.seed, protocol.mapper, MODELS, root=root)
            per_seed[s].append(found)
            for i, pair, check in zip(index, chosen, verified):
                placed = found.placed(pair.view0, pair.view1, protocol.score_model == "largest")
                errors = sfm_metrics.pair_errors(pair.T_0to1, *placed)
                rows[i].update({f"{name}_s{s}": errors[name] for name in sfm_metrics.SEED_COLUMNS})
                if s == 0:
                    rows[i].update({"pair": pair.name, "bag": int(bag), "n_matches": len(matches[i]),
                                    "n_inliers": check["n_inliers"], "registered0": int(placed[0] is not None),
                                    "registered1": int(placed[1] is not None), **errors})
    seeds = _per_seed(rows, per_seed, ev.seed)
    write_per_seed(seeds, where / "per_seed.csv")
    return rows, set_numbers(seeds, tracks, protocol)


def _per_seed(rows: list[dict], per_seed: list[list[Reconstruction]], first: int) -> pd.DataFrame:
    table = []
    n_matches = np.asarray([float(r["n_matches"]) for r in rows], np.float64)
    for s, found in enumerate(per_seed):
        errors = np.asarray([float(r[f"err_pose_s{s}"]) for r in rows], np.float64)
        whole = Reconstruction([name for f in found for name in f.images], [m for f in found for m in f.models])
        table.append({"seed": first + s, **sfm_metrics.summarize_sfm(errors, n_matches), **whole.numbers()})
    return pd.DataFrame(table)


def write_per_seed(table: pd.DataFrame, path: Path) -> None:
    from e3cm_bench.ground.files import write_csv

    write_csv(table, path)


def set_numbers(seeds: pd.DataFrame, tracks: list, protocol) -> dict:
    """The summary's facts of the reconstructions: the mean over seeds of the models' numbers,
    each pair metric's standard deviation over seeds (``m_sd``, no interval of its own), the
    tracks' numbers (the database's: the same for every seed; bags weighted by their pairs) and
    the protocol that made them."""
    out = {key: float(seeds[key].mean()) for key in NUMBERS}
    for key in sfm_metrics.SPREAD_KEYS:
        out[f"{key}_sd"] = float(seeds[key].std(ddof=1)) if len(seeds) > 1 else 0.0
    weights = np.asarray([n for n, _ in tracks], np.float64)
    for key in TRACKS:
        values = np.asarray([numbers[key] for _, numbers in tracks], np.float64)
        ok = np.isfinite(values)
        out[key] = float(np.average(values[ok], weights=weights[ok])) if ok.any() else float("nan")
    out.update({"mapper": protocol.mapper, "mapper_seeds": protocol.mapper_seeds, "merge": protocol.merge_label(),
                "verification": protocol.verification, "score_model": protocol.score_model})
    return out
