"""Metrics against values computed by hand (PROTOCOLS §2-3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import rotation
from e3cm_bench.geometry.metrics import (
    HPATCHES_PAIR_COLUMNS,
    MMA_THRESHOLDS,
    POSE_PAIR_COLUMNS,
    epipolar_precision,
    evaluate_homography_pair,
    evaluate_pose_pair,
    homography_corner_error,
    mma_per_pair,
    pose_auc,
    pose_error,
    precision_key,
    summarize_hpatches,
    summarize_pose,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])




def rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def project(points3d: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = points3d @ K.T
    return p[:, :2] / p[:, 2:3]


def synthetic_scene(T_0to1: np.ndarray, n: int = 200, seed: int = 0):
    """n random points 4..8 m in front of camera 0, seen by both cameras; pixel matches."""
    rng = np.random.default_rng(seed)
    points = np.column_stack(
        [rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 8, n)]
    )
    points1 = points @ T_0to1[:3, :3].T + T_0to1[:3, 3]
    return project(points, K), project(points1, K)


# --------------------------------------------------------------------------- homography


def test_mma_counts_errors_against_each_threshold():
    H = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 5.0], [0.0, 0.0, 1.0]])  # translation (10, 5)
    kpts0 = np.array([[0.0, 0.0], [10.0, 10.0], [20.0, 20.0]])
    # Errors of 0.5, 2.5 and 12 px along x: within t for t >= 1, t >= 3, never.
    kpts1 = kpts0 + [10.0, 5.0] + np.array([[0.5, 0], [2.5, 0], [12.0, 0]])
    expected = [1 / 3, 1 / 3] + [2 / 3] * 8  # t = 1, 2 | t = 3..10
    np.testing.assert_allclose(mma_per_pair(kpts0, kpts1, H), expected)


def test_mma_is_zero_without_matches():
    no_matches = np.zeros((0, 2))
    np.testing.assert_array_equal(mma_per_pair(no_matches, no_matches, np.eye(3)), np.zeros(10))


def test_corner_error_of_a_known_offset():
    shifted = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, 4.0], [0.0, 0.0, 1.0]])
    # Every corner is off by (3, 4): 5 px.
    assert homography_corner_error(shifted, np.eye(3), 640, 480) == pytest.approx(5.0)


def test_corner_error_uses_the_last_pixel_centres():
    doubled = np.diag([2.0, 2.0, 1.0])
    # Corners (0,0), (10,0), (10,10), (0,10) move by 0, 10, sqrt(200), 10.
    expected = (0 + 10 + math.sqrt(200) + 10) / 4
    assert homography_corner_error(doubled, np.eye(3), 11, 11) == pytest.approx(expected)


def test_corner_error_without_estimate_is_inf():
    assert homography_corner_error(None, np.eye(3), 640, 480) == math.inf


def test_homography_pair_recovers_exact_homography():
    H = np.array([[0.9, 0.05, 20.0], [-0.03, 1.1, 10.0], [1e-5, 2e-5, 1.0]])
    xs, ys = np.meshgrid(np.arange(0, 600, 40.0), np.arange(0, 400, 40.0))
    grid = np.column_stack([xs.ravel(), ys.ravel()])
    target = grid @ H[:2, :2].T + H[:2, 2]
    target = target / (grid @ H[2, :2] + H[2, 2])[:, None]
    row = evaluate_homography_pair(grid, target, H, 640, 480, seed=0)
    assert list(row) == HPATCHES_PAIR_COLUMNS[2:]
    assert row["n_matches"] == len(grid)
    assert row["mma@1"] == pytest.approx(1.0)
    assert row["h_error"] < 1e-4


def test_homography_pair_fails_with_fewer_than_four_matches():
    kpts = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    row = evaluate_homography_pair(kpts, kpts, np.eye(3), 100, 100, seed=0)
    assert row["n_matches"] == 3
    assert row["mma@1"] == 1.0
    assert row["h_error"] == math.inf


def test_homography_pair_without_matches_has_zero_mma_and_fails():
    row = evaluate_homography_pair(np.zeros((0, 2)), np.zeros((0, 2)), np.eye(3), 100, 100, seed=0)
    assert row["n_matches"] == 0
    assert all(row[f"mma@{t}"] == 0.0 for t in MMA_THRESHOLDS)
    assert row["h_error"] == math.inf


def test_homography_pair_is_reproducible_per_seed():
    rng = np.random.default_rng(1)
    kpts0 = rng.uniform(0, 500, (300, 2))
    kpts1 = kpts0 + rng.normal(0, 1.0, kpts0.shape)
    kpts1[:120] = rng.uniform(0, 500, (120, 2))  # 40 % outliers make RANSAC's sampling matter
    first = evaluate_homography_pair(kpts0, kpts1, np.eye(3), 500, 500, seed=7)
    evaluate_homography_pair(kpts0, kpts1, np.eye(3), 500, 500, seed=8)  # moves the global RNG
    assert evaluate_homography_pair(kpts0, kpts1, np.eye(3), 500, 500, seed=7) == first


# --------------------------------------------------------------------------- pose


def test_pose_error_known_rotation_and_translation():
    T = rigid(rotation("z", 10.0), [1.0, 0.0, 0.0])
    assert pose_error(T, np.eye(3), np.array([0.0, 1.0, 0.0])) == pytest.approx((10.0, 90.0))
    assert pose_error(T, np.eye(3), np.array([1.0, 1.0, 0.0])) == pytest.approx((10.0, 45.0))
    # The sign of t is unobservable: the opposite direction is no error.
    opposite = np.array([-2.0, 0.0, 0.0])
    assert pose_error(T, rotation("z", 10.0), opposite) == pytest.approx((0.0, 0.0))
    assert pose_error(T, None, None) == (math.inf, math.inf)


def test_precision_is_one_for_exact_matches():
    T = rigid(rotation("y", 8.0) @ rotation("x", 3.0), [0.5, 0.1, 0.2])
    kpts0, kpts1 = synthetic_scene(T)
    assert epipolar_precision(kpts0, kpts1, K, K, T) == {1e-4: 1.0, 5e-4: 1.0}


def test_precision_counts_perturbed_matches():
    # R = I, t = (1, 0, 0): E = [t]x, epipolar lines are the image rows and the squared
    # symmetric distance of normalised points is exactly 2 (v0 - v1)^2. A vertical shift of
    # d px (f = 500) gives 2 (d / 500)^2: 2 px -> 3.2e-5, 5 px -> 2e-4, 10 px -> 8e-4.
    T = rigid(np.eye(3), [1.0, 0.0, 0.0])
    kpts0, kpts1 = synthetic_scene(T, n=10)
    kpts1[7:, 1] += [2.0, 5.0, 10.0]
    precision = epipolar_precision(kpts0, kpts1, K, K, T)
    assert precision[1e-4] == pytest.approx(8 / 10)  # 7 exact + the 2 px one
    assert precision[5e-4] == pytest.approx(9 / 10)  # ... + the 5 px one
    assert epipolar_precision(np.zeros((0, 2)), np.zeros((0, 2)), K, K, T) == {1e-4: 0.0, 5e-4: 0.0}


def test_pose_pair_recovers_pose_from_exact_matches():
    T = rigid(rotation("y", 8.0) @ rotation("x", 3.0), [0.5, 0.1, 0.2])
    kpts0, kpts1 = synthetic_scene(T)
    row = evaluate_pose_pair(kpts0, kpts1, K, K, T, seed=0)
    assert list(row) == POSE_PAIR_COLUMNS[1:]
    assert row["n_matches"] == 200
    assert row["err_R"] < 1e-3 and row["err_t"] < 1e-3
    assert row["err_pose"] == max(row["err_R"], row["err_t"])
    assert row["precision@1e-4"] == 1.0


def test_pose_pair_fails_with_fewer_than_five_matches():
    T = rigid(rotation("y", 8.0), [0.5, 0.1, 0.2])
    kpts0, kpts1 = synthetic_scene(T, n=4)
    row = evaluate_pose_pair(kpts0, kpts1, K, K, T, seed=0)
    assert row["n_matches"] == 4
    assert row["err_R"] == row["err_t"] == row["err_pose"] == math.inf
    assert row["precision@1e-4"] == 1.0  # precision needs no estimate
    empty = evaluate_pose_pair(np.zeros((0, 2)), np.zeros((0, 2)), K, K, T, seed=0)
    assert empty["err_pose"] == math.inf and empty["precision@5e-4"] == 0.0


def test_precision_key_matches_paper_notation():
    assert precision_key(1e-4) == "precision@1e-4"
    assert precision_key(5e-4) == "precision@5e-4"
    assert precision_key(2.5e-3) == "precision@2.5e-3"


def test_pose_auc_by_hand():
    # Errors 1, 3, 6, inf (N = 4): curve (0,0) (1,.25) (3,.5) (6,.75); inf never arrives.
    # @5:  0.125 + 2*0.375 + (5-3)*0.5                      = 1.875  -> /5  = 37.5 %
    # @10: 0.125 + 0.75 + 3*0.625 + (10-6)*0.75             = 5.75   -> /10 = 57.5 %
    # @20: 0.125 + 0.75 + 1.875 + (20-6)*0.75               = 13.25  -> /20 = 66.25 %
    assert pose_auc([6.0, math.inf, 1.0, 3.0]) == pytest.approx([37.5, 57.5, 66.25])


def test_pose_auc_equals_the_reference_convention_on_random_errors_with_ties():
    """SuperGlue's / LoFTR's pose_auc, restated: sort all errors (failures as inf), put (0, 0)
    first with recall k / N at the k-th, keep the points whose error is below the threshold
    (searchsorted, left side), hold the last recall to the threshold, trapezoid, divide."""
    def reference(errors, threshold):
        e = np.concatenate([[0.0], np.sort(errors)])
        r = np.concatenate([[0.0], np.arange(1, len(errors) + 1) / len(errors)])
        last = np.searchsorted(e, threshold)
        x, y = np.append(e[:last], threshold), np.append(r[:last], r[last - 1])
        return 100 * float(np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2)) / threshold

    rng = np.random.default_rng(0)
    for _ in range(500):
        errors = rng.integers(0, 25, rng.integers(1, 30)).astype(float)  # whole numbers: ties at 5, 10, 20
        errors[rng.random(len(errors)) < 0.2] = np.inf
        if rng.random() < 0.5:
            errors[np.isfinite(errors)] += rng.random(np.isfinite(errors).sum())
        assert pose_auc(list(errors)) == pytest.approx([reference(errors, t) for t in (5, 10, 20)], abs=1e-12)


def test_pose_auc_edge_cases():
    # An error exactly at the threshold does not count (SuperGlue's and LoFTR's pose_auc);
    # just below it, the curve (0,0) -> (5,1) has area 2.5 -> 50 %.
    assert pose_auc([5.0], thresholds=(5,)) == pytest.approx([0.0])
    assert pose_auc([5.0 - 1e-9], thresholds=(5,)) == pytest.approx([50.0])
    # Ties at a threshold: of [5, 5, 10] only errors below 5 count for AUC@5, the two 5s count for AUC@10.
    assert pose_auc([5.0, 5.0, 10.0], thresholds=(5, 10)) == pytest.approx([0.0, 100 * (5 * (1 / 3) / 2 + 5 * (2 / 3)) / 10])
    assert pose_auc([math.inf, float("nan")]) == [0.0, 0.0, 0.0]
    assert pose_auc([0.0, 0.0]) == pytest.approx([100.0, 100.0, 100.0])
    assert all(math.isnan(v) for v in pose_auc([]))


# --------------------------------------------------------------------------- summaries


def hpatches_row(sequence: str, n_matches: int, mma: float, h_error: float) -> dict:
    row = {"pair": f"{sequence}/1-2", "sequence": sequence, "n_matches": n_matches}
    row.update({f"mma@{t}": mma for t in MMA_THRESHOLDS})
    row["h_error"] = h_error
    return row


def test_summarize_hpatches_counts_failed_pairs():
    rows = [
        hpatches_row("i_a", 10, 0.5, 0.5),
        hpatches_row("v_b", 20, 1.0, 2.0),
        hpatches_row("v_c", 0, 0.0, math.inf),  # failed: no matches, no H
    ]
    summary = summarize_hpatches(rows)
    mma = [f"mma@{t}" for t in MMA_THRESHOLDS]
    expected_order = (
        ["n_pairs", "n_matches", *mma]
        + ["n_pairs_i", "n_matches_i", *[f"{m}_i" for m in mma]]
        + ["n_pairs_v", "n_matches_v", *[f"{m}_v" for m in mma]]
        + ["h_acc@1", "h_acc@3", "h_acc@5"]
    )
    assert list(summary) == expected_order
    assert summary["n_pairs"] == 3 and summary["n_matches"] == pytest.approx(10.0)
    assert summary["mma@3"] == pytest.approx(0.5)
    assert (summary["n_pairs_i"], summary["mma@3_i"]) == (1, pytest.approx(0.5))
    assert (summary["n_pairs_v"], summary["mma@3_v"], summary["n_matches_v"]) == (2, 0.5, 10.0)
    accuracy = [summary["h_acc@1"], summary["h_acc@3"], summary["h_acc@5"]]
    assert accuracy == pytest.approx([1 / 3, 2 / 3, 2 / 3])


def test_summarize_hpatches_empty_split_is_nan():
    summary = summarize_hpatches([hpatches_row("v_b", 20, 1.0, 2.0)])
    assert summary["n_pairs_i"] == 0
    assert math.isnan(summary["mma@1_i"]) and math.isnan(summary["n_matches_i"])
    assert summary["mma@1_v"] == 1.0


def test_summarize_pose_counts_failed_pairs():
    errors = [6.0, math.inf, 1.0, 3.0]  # the AUC example above
    rows = [
        {
            "pair": str(k),
            "n_matches": 100 * k,
            "err_pose": e,
            "precision@1e-4": 0.5 * (k % 2),
            "precision@5e-4": 1.0,
        }
        for k, e in enumerate(errors)
    ]
    summary = summarize_pose(rows)
    assert list(summary) == [
        "n_pairs", "n_matches", "n_failures", "auc@5", "auc@10", "auc@20", "precision@1e-4", "precision@5e-4",
    ]
    assert summary["n_pairs"] == 4
    assert summary["n_matches"] == pytest.approx(150.0)
    aucs = [summary["auc@5"], summary["auc@10"], summary["auc@20"]]
    assert aucs == pytest.approx([37.5, 57.5, 66.25])
    assert summary["precision@1e-4"] == pytest.approx(25.0)  # (0 + .5 + 0 + .5) / 4, in percent
    assert summary["precision@5e-4"] == pytest.approx(100.0)
