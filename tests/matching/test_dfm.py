"""The DFM baseline with EfficientNet-Lite0 (genuine ImageNet weights, offline) on real images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from e3cm_bench.backbones.loading import load_backbone
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.ground.images import load_image, resize_max_side, to_original_pixels
from e3cm_bench.matchers.dfm import DFMMatcher


@pytest.fixture(scope="module")
def matcher() -> DFMMatcher:
    return DFMMatcher(load_backbone("efficientnet_lite0"), variant="bench")


def corner_error(H_est: np.ndarray, H_true: np.ndarray, size: tuple[int, int]) -> float:
    """Mean distance between the image corners mapped by two homographies."""
    w, h = size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    return float(np.linalg.norm(warp_points(H_est, corners) - warp_points(H_true, corners), axis=1).mean())


def to_resized(scale_xy: tuple[float, float]) -> np.ndarray:
    """Original -> resized pixels (pixel-centre convention), the inverse of to_original_pixels."""
    sx, sy = scale_xy
    return np.array([[1 / sx, 0, 0.5 / sx - 0.5], [0, 1 / sy, 0.5 / sy - 0.5], [0, 0, 1]])


def assert_inside(points: np.ndarray, image: np.ndarray) -> None:
    h, w = image.shape[:2]
    assert np.all(points >= -0.5) and np.all(points[:, 0] <= w - 0.5) and np.all(points[:, 1] <= h - 0.5)


def match(matcher: DFMMatcher, image0: np.ndarray, image1: np.ndarray):
    cv2.setRNGSeed(0)  # the stage-0 RANSAC is seeded by the caller, as the runner does
    return matcher.match(image0, image1)


def test_graffiti_matches_agree_with_ground_truth(matcher, shared_data):
    sequence = shared_data / "hpatches-sequences-release" / "v_graffiti"
    image0, scale0 = resize_max_side(load_image(sequence / "1.ppm"), 640)
    image1, scale1 = resize_max_side(load_image(sequence / "2.ppm"), 640)
    H_12 = np.loadtxt(sequence / "H_1_2")

    matches = match(matcher, image0, image1)
    kpts0 = to_original_pixels(matches.keypoints0, scale0)
    kpts1 = to_original_pixels(matches.keypoints1, scale1)
    errors = np.linalg.norm(warp_points(H_12, kpts0) - kpts1, axis=1)
    mma = {t: float(np.mean(errors <= t)) for t in (1, 3, 5)}
    info = matches.info
    print(f"DFM v_graffiti 1-2 @640: {len(matches)} matches, MMA@1/3/5 = {mma}, stage 0: "
          f"{info['stage0_matches']} matches, {info['stage0_inliers']} inliers, "
          f"timings {info['timings']}")
    # Measured (800x640 -> 640x512, CPU): 9022 matches, MMA@1/3/5 = 0.442 / 0.878 / 0.961;
    # stage 0: 540 matches, 528 inliers. Direct matching (no warp) on the same pair: 2378
    # matches, MMA@3 = 0.555.
    assert len(matches) >= 6000
    assert mma[3] >= 0.78
    assert mma[5] >= 0.88

    assert info["homography_found"] and info["homography_fallback"] is None
    assert info["stage0_matches"] >= 300 and info["stage0_inliers"] >= 300
    # H_BA maps resized-B pixels to resized-A pixels: compare with the ground truth in that frame.
    H_BA_true = to_resized(scale0) @ np.linalg.inv(H_12) @ np.linalg.inv(to_resized(scale1))
    assert corner_error(info["H_BA"], H_BA_true, image1.shape[1::-1]) <= 10.0  # measured 3.5 px
    assert set(info["timings"]) == {"backbone", "stage0", "warp", "stage1"}
    assert info["stage1"]["matches_before_mapping"] >= len(matches)
    assert_inside(matches.keypoints0, image0)
    assert_inside(matches.keypoints1, image1)
    assert np.all((matches.scores > 0) & (matches.scores <= 1 + 1e-6))


def test_synthetic_warp_is_recovered(matcher, shared_data):
    boat = load_image(shared_data / "hpatches-sequences-release" / "v_boat" / "1.ppm")
    image0, _ = resize_max_side(boat, 400)
    h, w = image0.shape[:2]
    # 30 degrees of rotation, 0.9 scale about the centre, and a little perspective.
    H_AB = np.vstack([cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), 30, 0.9), [3e-4, 0, 1]])
    image1 = cv2.warpPerspective(image0, H_AB, (w, h))

    matches = match(matcher, image0, image1)
    errors = np.linalg.norm(warp_points(H_AB, matches.keypoints0) - matches.keypoints1, axis=1)
    mma3 = float(np.mean(errors <= 3))
    print(f"DFM synthetic v_boat 1 (400x320): {len(matches)} matches, MMA@3 = {mma3:.3f}")
    # Measured: 4654 matches, MMA@1/3 = 0.913 / 0.993, stage-0 H within 2 px at the corners.
    assert len(matches) >= 3000
    assert mma3 >= 0.95
    assert matches.info["homography_found"]
    assert corner_error(matches.info["H_BA"], np.linalg.inv(H_AB), (w, h)) <= 6.0
    # B's black corners (outside the rotated A) never take part in a match.
    assert_inside(matches.keypoints1, image1)


@pytest.mark.parametrize(
    "shape0, shape1, reason",
    [
        ((240, 320), (200, 300), "RANSAC inliers"),  # measured: 7 inliers from 15-28 matches
        ((48, 64), (48, 64), "fewer than 4"),  # 3 x 4 cells: at most 2 inside the border ring
    ],
)
def test_unrelated_images_fall_back_to_identity(matcher, shape0, shape1, reason):
    rng = np.random.default_rng(0)
    image0 = rng.integers(0, 256, (*shape0, 3), dtype=np.uint8)
    image1 = rng.integers(0, 256, (*shape1, 3), dtype=np.uint8)

    matches = match(matcher, image0, image1)
    info = matches.info
    print(f"DFM noise {shape0} vs {shape1}: {len(matches)} matches, stage 0: "
          f"{info['stage0_matches']} matches, {info['stage0_inliers']} inliers, "
          f"fallback: {info['homography_fallback']}")
    assert not info["homography_found"]
    assert info["homography_fallback"].startswith("identity") and reason in info["homography_fallback"]
    assert np.array_equal(info["H_BA"], np.eye(3))
    assert set(info["timings"]) == {"backbone", "stage0", "warp", "stage1"}
    assert_inside(matches.keypoints0, image0)
    assert_inside(matches.keypoints1, image1)


def test_config_lists_every_setting(matcher):
    config = matcher.config()
    assert config["matcher"] == "dfm" and config["backbone"] == "efficientnet_lite0"
    assert config["ratio"] == [0.9, 0.9, 0.9, 0.9, 0.95]
    assert config["weights"].startswith("/") and "sha256:" in config["weights"]
    # 1.5 cells of the deepest level (stride 16).
    assert config["homography_ransac"]["threshold_px"] == 24.0
    assert config["homography_ransac"]["min_inliers"] == 15 and "seed" not in config["homography_ransac"]
    custom = DFMMatcher(matcher.backbone, variant="bench", ratio=(0.8,) * 5, homography_threshold_px=5.0, name="dfm-tight")
    assert custom.config()["homography_ransac"]["threshold_px"] == 5.0
    assert custom.config()["ratio"] == [0.8] * 5 and custom.config()["matcher"] == "dfm-tight"
    with pytest.raises(ValueError):
        DFMMatcher(matcher.backbone, ratio=(0.9, 0.9))
