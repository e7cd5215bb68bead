"""The sfm benchmark's metrics: each evaluated pair's pose error read from the reconstruction,
and the set's AUC and mAA over the pairs. Pure functions of arrays.

A pair's relative pose is that of its two images' cameras in the model that registered both:
R = R1 R0^T, t = t1 - R t0 (world-to-camera poses), scored against the ground truth as the pose
benchmarks score an estimate (metrics.pose_error: the rotation angle, and the angle between
translation directions folded to [0, 90] degrees; err_pose the larger). A pair whose images are
not both registered, or are registered in different models, has no relative pose: error inf.

mAA is the Image Matching Challenge 2020's (the definition IMC 2021 kept), as its reference
code computes it (github.com/ubc-vision/image-matching-benchmark, utils/pack_helper.py,
``compute_qt_auc_colmap``): each pair's error is the larger of its rotation error and its
translation-direction error, in degrees; the accuracy at threshold k is the fraction of pairs
that ``np.histogram(err, np.arange(11))`` puts in the bins below k, i.e. error < k for k = 1..9 and
error <= 10 for k = 10 (numpy's last bin is closed); mAA is the mean of the ten accuracies. The
reference's errors (utils/eval_helper.py ``evaluate_R_t``) are the quaternion angle between the
rotations and the arccos of |cos| between the translations: the same angles as ours, the
translation folded the same way (tests/benchmarks/test_sfm_metrics.py checks both on recorded poses).
Where the reference evaluates a bag's pairs in the model with the most images only
(utils/colmap_helper.py ``get_best_colmap_index``), this benchmark takes a pair from whichever
model holds both of its images (the issue's rule: a pair in two different models fails); the
per-pair ``model`` column says which.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from e3cm_bench.geometry import metrics

MAA_THRESHOLDS = tuple(range(1, 11))  # degrees, IMC 2020
MAA = "maa"


def relative_from_absolute(pose0: np.ndarray, pose1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of camera 1 relative to camera 0 from world-to-camera 4x4 poses."""
    R = pose1[:3, :3] @ pose0[:3, :3].T
    return R, pose1[:3, 3] - R @ pose0[:3, 3]


def pair_errors(T_0to1: np.ndarray, placed0, placed1) -> dict:
    """err_R, err_t, err_pose (degrees) and model of a pair, from where the reconstruction put
    its images ((model index, pose) or None each); inf and model -1 where it has no pose."""
    if placed0 is None or placed1 is None or placed0[0] != placed1[0]:
        return {"model": -1, "err_R": float("inf"), "err_t": float("inf"), "err_pose": float("inf")}
    R, t = relative_from_absolute(placed0[1], placed1[1])
    err_R, err_t = metrics.pose_error(T_0to1, R, t)
    return {"model": int(placed0[0]), "err_R": err_R, "err_t": err_t, "err_pose": max(err_R, err_t)}


def accuracy_imc(errors: Iterable[float], thresholds: Sequence[int] = MAA_THRESHOLDS) -> list[float]:
    """Fraction of pairs accurate at each threshold, IMC 2020's way (error < k, <= at the last
    threshold: np.histogram's closed last bin); inf and NaN are misses."""
    errors = np.asarray(list(errors), np.float64)
    if errors.size == 0:
        return [float("nan")] * len(thresholds)
    last = len(thresholds) - 1
    return [float(np.mean(errors <= k if i == last else errors < k)) for i, k in enumerate(thresholds)]


def maa(errors: Iterable[float]) -> float:
    curve = accuracy_imc(errors)
    return float(np.mean(curve)) if curve and not np.isnan(curve[0]) else float("nan")


def summarize_sfm(errors: np.ndarray, n_matches: np.ndarray) -> dict:
    """The pair-level summary: n_pairs, n_matches, n_failures, auc@5/10/20, maa."""
    errors = np.asarray(errors, np.float64)
    summary = {"n_pairs": int(errors.size),
               "n_matches": float(np.mean(n_matches)) if errors.size else float("nan"),
               "n_failures": int(np.count_nonzero(~np.isfinite(errors)))}
    for threshold, auc in zip(metrics.POSE_AUC_THRESHOLDS, metrics.pose_auc(errors, metrics.POSE_AUC_THRESHOLDS)):
        summary[f"auc@{threshold}"] = auc
    summary[MAA] = maa(errors)
    return summary


# ----------------------------------------------------------------------------- the mapper's seeds
# per_pair.csv keeps the first seed's err_R, err_t, err_pose and model as before, then each seed
# k's (evaluation seed + k) as err_R_sK, err_t_sK, err_pose_sK, model_sK.
SEED_COLUMNS = ("model", "err_R", "err_t", "err_pose")
SPREAD_KEYS = ("auc@5", "auc@10", "auc@20", MAA)


def seed_columns(k: int) -> list[str]:
    return [f"{name}_s{s}" for s in range(k) for name in SEED_COLUMNS]


def seeds_in(rows: Sequence) -> int:
    """How many seeds the rows hold (0: rows of one reconstruction, without seed columns)."""
    rows = list(rows)
    k = 0
    while rows and f"err_pose_s{k}" in rows[0]:
        k += 1
    return k


def seed_errors(rows: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """(pairs x seeds err_pose, n_matches) of sfm rows (a single column without seeds)."""
    rows = list(rows)
    k = seeds_in(rows)
    names = [f"err_pose_s{s}" for s in range(k)] or ["err_pose"]
    errors = np.asarray([[float(r[n]) for n in names] for r in rows], np.float64).reshape(len(rows), len(names))
    return errors, np.asarray([float(r["n_matches"]) for r in rows], np.float64)


def summarize_seeds(errors: np.ndarray, n_matches: np.ndarray, seeds: Sequence[int] | None = None) -> dict:
    """The mean over the seeds (columns of errors; `seeds` picks them, repeats allowed) of each
    seed's summarize_sfm (n_failures too: the mean count)."""
    errors = np.asarray(errors, np.float64)
    columns = range(errors.shape[1]) if seeds is None else seeds
    each = [summarize_sfm(errors[:, s], n_matches) for s in columns]
    summary = dict(each[0])
    for key in summary:
        if key not in ("n_pairs", "n_matches"):
            summary[key] = float(np.mean([e[key] for e in each]))
    return summary


def bags_of(rows: Sequence) -> np.ndarray | None:
    """Each row's bag (None: rows without the column, written before bags were recorded)."""
    rows = list(rows)
    if not rows or "bag" not in rows[0]:
        return None
    bags = np.asarray([float(r["bag"]) for r in rows], np.float64)
    return bags.astype(np.int64) if np.isfinite(bags).all() else None


def two_level_summary(errors: np.ndarray, n_matches: np.ndarray, seed: int = 0, bags: np.ndarray | None = None):
    """summarize(idx) for the bootstrap over pairs (idx) that, with each resample of pairs,
    resamples the mapper's seeds too (with replacement, from its own generator, so that the
    sequence of resamples is a pure function of `seed`): the interval then holds both the pairs'
    and the seeds' randomness (each seed is a verification draw and a mapper run). With several
    bags the pairs are drawn in two stages instead, the bags and then each drawn bag's pairs
    (stats.bootstrap.nested_resample, from the same generator; `idx` is then unused): a bag's
    pairs share one reconstruction. With one seed and one bag it is the pairs' bootstrap."""
    from e3cm_bench.stats.bootstrap import groups_of, nested_resample

    errors = np.asarray(errors, np.float64)
    k = errors.shape[1]
    rng = np.random.default_rng(seed)
    groups = groups_of(bags)

    def summarize(idx) -> dict:
        idx = (nested_resample(groups, rng) if groups is not None
               else np.asarray(idx, dtype=np.int64).reshape(-1))
        return summarize_seeds(errors[idx], n_matches[idx], rng.integers(0, k, k) if k > 1 else None)

    return summarize
