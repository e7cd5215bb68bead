"""Benchmark metrics (PROTOCOLS §2-3): arrays in, numbers out.

A failed estimate is an infinite error and stays in every average; pairs are never dropped.
RANSAC is seeded per pair, right before it runs, so that a pair evaluated alone (a resumed
run, ``--eval-only``) gives the same numbers as in a full run.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from e3cm_bench.geometry.estimators import PoseRansac
from e3cm_bench.geometry.estimators import homography as estimate_homography
from e3cm_bench.geometry.estimators import relative_pose as estimate_relative_pose
from e3cm_bench.geometry.two_view import (
    ORTHONORMAL_TOLERANCE,
    essential_from_pose,
    normalize_keypoints,
    rotation_angle_deg,
    rotation_deviation,
    symmetric_epipolar_distance,
    translation_angle_deg,
    warp_points,
)

MMA_THRESHOLDS = tuple(range(1, 11))  # pixels
HOMOGRAPHY_ACCURACY_THRESHOLDS = (1, 3, 5)  # pixels of mean corner error
POSE_AUC_THRESHOLDS = (5, 10, 20)  # degrees
PRECISION_THRESHOLDS = (1e-4, 5e-4)  # squared symmetric epipolar distance, normalised coords


def precision_key(threshold: float) -> str:
    """Column name of a precision threshold, written as in the paper: 1e-4 -> 'precision@1e-4'."""
    mantissa, exponent = f"{threshold:e}".split("e")
    return f"precision@{float(mantissa):g}e{int(exponent)}"


HPATCHES_PAIR_COLUMNS = [
    "pair",
    "sequence",
    "n_matches",
    *[f"mma@{t}" for t in MMA_THRESHOLDS],
    "h_error",
]
POSE_PAIR_COLUMNS = [
    "pair",
    "n_matches",
    "err_R",
    "err_t",
    "err_pose",
    *[precision_key(t) for t in PRECISION_THRESHOLDS],
]


# --------------------------------------------------------------------------- homography


def mma_per_pair(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    H: np.ndarray,
    thresholds: Sequence[float] = MMA_THRESHOLDS,
) -> np.ndarray:
    """Fraction of matches with ||H(x0) - x1|| <= t for each t; zeros for a pair without matches."""
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    if len(kpts0) == 0:
        return np.zeros(len(thresholds))
    distances = np.linalg.norm(warp_points(H, kpts0) - kpts1, axis=1)
    # A point sent to infinity gives a NaN distance, which compares False: counted wrong.
    return np.array([np.mean(distances <= t) for t in thresholds])


def homography_corner_error(
    H_est: np.ndarray | None, H_gt: np.ndarray, width: int, height: int
) -> float:
    """Mean distance between the corners of image 0 mapped by H_est and by H_gt; inf if no H_est."""
    if H_est is None:
        return float("inf")
    corners = np.array(
        [[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], dtype=np.float64
    )
    offsets = warp_points(H_est, corners) - warp_points(H_gt, corners)
    error = float(np.mean(np.linalg.norm(offsets, axis=1)))
    return error if np.isfinite(error) else float("inf")


def symmetric_homography_error(kpts0: np.ndarray, kpts1: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Per match, the mean of ||H x0 - x1|| and ||H^-1 x1 - x0|| (glue-factory's match error on
    HPatches; NaN where a point goes to infinity)."""
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    H = np.asarray(H, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        forward = np.linalg.norm(warp_points(H, kpts0) - kpts1, axis=1)
        backward = np.linalg.norm(warp_points(np.linalg.inv(H), kpts1) - kpts0, axis=1)
    return (forward + backward) / 2.0


def precision_column(threshold: float) -> str:
    """glue-factory's name of its match precision at `threshold` px: 1 -> 'prec@1px'."""
    return f"prec@{threshold:g}px"


@dataclass(frozen=True)
class HomographyScoring:
    """How evaluate_homography_pair estimates H: the RANSAC threshold (pixels), its iterations
    and confidence, and the backend (opencv or poselib, estimators.py); EvalSettings' homography_*
    fields and its estimator."""

    ransac_threshold: float = 3.0
    max_iters: int = 5000
    confidence: float = 0.9999
    estimator: str = "opencv"


def evaluate_homography_pair(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    H_gt: np.ndarray,
    width0: int,
    height0: int,
    seed: int,
    scoring: HomographyScoring = HomographyScoring(),
) -> dict:
    """One HPatches row: n_matches, mma@1..mma@10, h_error (inf when RANSAC finds no H)."""
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    row = {"n_matches": len(kpts0)}
    for t, value in zip(MMA_THRESHOLDS, mma_per_pair(kpts0, kpts1, H_gt)):
        row[f"mma@{t}"] = float(value)
    cv2.setRNGSeed(int(seed))
    H_est = estimate_homography(kpts0, kpts1, scoring.ransac_threshold, scoring.max_iters, scoring.confidence,
                                scoring.estimator, seed)
    row["h_error"] = homography_corner_error(H_est, H_gt, width0, height0)
    return row


# --------------------------------------------------------------------------- relative pose


def pose_error(
    T_0to1: np.ndarray, R: np.ndarray | None, t: np.ndarray | None, rotation_error: str = "nearest-rotation"
) -> tuple[float, float]:
    """(rotation error, folded translation-direction error) in degrees; (inf, inf) without R.
    rotation_error: geometry.ROTATION_ERRORS, how the rotation's angle is measured."""
    if R is None or t is None:
        return float("inf"), float("inf")
    T_0to1 = np.asarray(T_0to1, dtype=np.float64)
    return rotation_angle_deg(R, T_0to1[:3, :3], rotation_error), translation_angle_deg(t, T_0to1[:3, 3])


# Ground truth further than this from orthonormal is said once per run: at 1e-6 the reference
# formula can read 0 for estimates up to about 0.06 degrees off (the angle whose cosine the
# deviation hides grows as its square root); closer, the note would only report rounding (KITTI's
# poses, stored to 7 digits, are 1.6e-7 off).
ROTATION_NOTE_TOLERANCE = 1e-6


def rotation_note(rotations: Sequence[np.ndarray], err_R: Sequence[float], rotation_error: str) -> str | None:
    """One line where ground-truth rotations are not orthonormal, None where they are: how
    many, how far, and what the run's formula (geometry.ROTATION_ERRORS) made of them; under
    the reference formula, how many of their errors read exactly 0 (the clipped cosine: a
    true 0 needs an estimate equal to the truth to the last bit)."""
    deviation = np.array([rotation_deviation(R) for R in rotations], dtype=np.float64)
    off = deviation > ORTHONORMAL_TOLERANCE
    zeros = int(np.count_nonzero(off & (np.asarray(err_R, dtype=np.float64) == 0.0)))
    if not (deviation.max(initial=0.0) > ROTATION_NOTE_TOLERANCE or (rotation_error == "reference" and zeros)):
        return None
    dets = [float(np.linalg.det(R)) for R, o in zip(rotations, off) if o]
    what = (f"{int(off.sum())} of {len(off)} pairs' ground-truth rotations are not orthonormal (|R^T R - I| up to "
            f"{deviation.max():.2g}, det {min(dets):.6f} to {max(dets):.6f})")
    if rotation_error == "reference":
        return (f"{what}; this protocol keeps its reference code's formula, arccos((trace - 1) / 2) clipped, under "
                f"which {zeros} of them read a rotation error of exactly 0 that is not one (the default protocol "
                "measures to the nearest rotation)")
    return f"{what}; their rotation errors are measured to the nearest rotation (docs/benchmarks.md)"


def epipolar_distances(
    kpts0: np.ndarray, kpts1: np.ndarray, K0: np.ndarray, K1: np.ndarray, T_0to1: np.ndarray
) -> np.ndarray:
    """Squared symmetric epipolar distance of each match to the true E, in normalised coordinates."""
    T_0to1 = np.asarray(T_0to1, dtype=np.float64)
    E = essential_from_pose(T_0to1[:3, :3], T_0to1[:3, 3])
    return symmetric_epipolar_distance(E, normalize_keypoints(kpts0, K0), normalize_keypoints(kpts1, K1))


def epipolar_precision(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    T_0to1: np.ndarray,
    thresholds: Sequence[float] = PRECISION_THRESHOLDS,
) -> dict[float, float]:
    """Fraction of matches whose squared symmetric epipolar distance to the true E is < t."""
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    if len(kpts0) == 0:
        return {t: 0.0 for t in thresholds}
    distances = epipolar_distances(kpts0, kpts1, K0, K1, T_0to1)
    return {t: float(np.mean(distances < t)) for t in thresholds}


@dataclass(frozen=True)
class PoseScoring:
    """How evaluate_pose_pair scores a pose pair: the essential-matrix RANSAC's threshold (pixels)
    and confidence, the epipolar precision's thresholds, the backend (opencv or poselib,
    estimators.py) and how err_R is measured (geometry.ROTATION_ERRORS)."""

    ransac_threshold: float = 0.5
    confidence: float = 0.99999
    precision_thresholds: Sequence[float] = PRECISION_THRESHOLDS
    estimator: str = "opencv"
    rotation_error: str = "nearest-rotation"
    method: str = "ransac"  # OpenCV's robust method of E (estimators.POSE_METHODS)


def evaluate_pose_pair(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    T_0to1: np.ndarray,
    seed: int,
    scoring: PoseScoring = PoseScoring(),
    sizes: tuple | None = None,
) -> dict:
    """One pose row: n_matches, err_R, err_t, err_pose (max of both), precision@t for each t.
    sizes: the images' (w, h), for PoseLib's cameras."""
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    row = {"n_matches": len(kpts0)}
    cv2.setRNGSeed(int(seed))
    ransac = PoseRansac(scoring.ransac_threshold, scoring.confidence, scoring.estimator, seed, scoring.method)
    estimate = estimate_relative_pose(kpts0, kpts1, K0, K1, ransac, sizes)
    R, t = (estimate[0], estimate[1]) if estimate is not None else (None, None)
    row["err_R"], row["err_t"] = pose_error(T_0to1, R, t, scoring.rotation_error)
    row["err_pose"] = max(row["err_R"], row["err_t"])
    for threshold, value in epipolar_precision(kpts0, kpts1, K0, K1, T_0to1, scoring.precision_thresholds).items():
        row[precision_key(threshold)] = value
    return row


def pose_error_curve(errors: Iterable[float]) -> tuple[np.ndarray, np.ndarray]:
    """Points of the cumulative pose-error curve: (0, 0), then (e_k, k / N) for finite e_k.

    N counts failures (inf / NaN errors) too, so they lower the curve without ever
    appearing on it. Joined by straight lines, this is the curve whose normalised area
    is the AUC (PROTOCOLS §3); the plots draw the same points.
    """
    errors = np.asarray(list(errors), dtype=np.float64)
    finite = np.sort(errors[np.isfinite(errors)])
    recall = np.arange(1, len(finite) + 1) / max(len(errors), 1)
    return np.concatenate([[0.0], finite]), np.concatenate([[0.0], recall])


def pose_auc(
    errors: Iterable[float], thresholds: Sequence[float] = POSE_AUC_THRESHOLDS
) -> list[float]:
    """Area under the recall-vs-error curve up to each threshold, in percent (PROTOCOLS §3).

    The curve (``pose_error_curve``) is linear between points (trapezoid rule) and flat
    after the last error within the threshold. Failures count in N and never reach any
    threshold. NaN for no errors.
    """
    errors = list(errors)
    if len(errors) == 0:
        return [float("nan")] * len(thresholds)
    curve_errors, curve_recall = pose_error_curve(errors)
    aucs = []
    for threshold in thresholds:
        # Points with error < threshold are on the curve; then hold that recall to the threshold.
        # An error equal to the threshold does not count (SuperGlue's and LoFTR's pose_auc).
        n_within = np.searchsorted(curve_errors, threshold, side="left")
        x = np.concatenate([curve_errors[:n_within], [threshold]])
        y = np.concatenate([curve_recall[:n_within], [curve_recall[n_within - 1]]])
        area = np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2.0)
        aucs.append(float(100.0 * area / threshold))
    return aucs


# --------------------------------------------------------------------------- summaries


def _mean(values: Iterable[float]) -> float:
    values = np.asarray(list(values), dtype=np.float64)
    return float(np.mean(values)) if len(values) else float("nan")


def _hpatches_block(rows: Sequence[Mapping], suffix: str) -> dict:
    block = {
        f"n_pairs{suffix}": len(rows),
        f"n_matches{suffix}": _mean(r["n_matches"] for r in rows),
    }
    for t in MMA_THRESHOLDS:
        block[f"mma@{t}{suffix}"] = _mean(r[f"mma@{t}"] for r in rows)
    return block


def summarize_hpatches(rows: Iterable[Mapping]) -> dict:
    """Mean #matches and MMA overall / illumination (_i) / viewpoint (_v), then homography accuracy.

    The split is the sequence prefix ``i_`` or ``v_``; a sequence with neither counts only
    overall. A split without pairs gets NaN means. h_acc@t is the fraction of all pairs with
    corner error <= t; failed pairs (inf) count as misses.
    """
    rows = list(rows)
    summary = _hpatches_block(rows, "")
    for split in ("i", "v"):
        in_split = [r for r in rows if str(r["sequence"]).startswith(f"{split}_")]
        summary.update(_hpatches_block(in_split, f"_{split}"))
    for t in HOMOGRAPHY_ACCURACY_THRESHOLDS:
        summary[f"h_acc@{t}"] = _mean(float(r["h_error"]) <= t for r in rows)
    return summary


def summarize_pose(
    rows: Iterable[Mapping], precision_thresholds: Sequence[float] = PRECISION_THRESHOLDS, drop_failures: bool = False
) -> dict:
    """n_pairs, mean #matches, AUC@5/10/20 of err_pose and mean precision, both in percent.

    drop_failures: pairs without a pose (error inf) leave the AUC, as the E3CM release's
    eval scripts do (non-standard: it rewards matchers that fail on hard pairs);
    n_failures says how many there were either way.
    """
    rows = list(rows)
    errors = [r["err_pose"] for r in rows]
    failures = [e for e in errors if not np.isfinite(e)]
    summary = {"n_pairs": len(rows), "n_matches": _mean(r["n_matches"] for r in rows), "n_failures": len(failures)}
    if drop_failures:
        errors = [e for e in errors if np.isfinite(e)]
    aucs = pose_auc(errors, POSE_AUC_THRESHOLDS)
    for threshold, auc in zip(POSE_AUC_THRESHOLDS, aucs):
        summary[f"auc@{threshold}"] = auc
    for threshold in precision_thresholds:
        key = precision_key(threshold)
        summary[key] = 100.0 * _mean(r[key] for r in rows)
    return summary
