"""Two-view geometry (e3cm_bench.geometry.two_view) on synthetic scenes and hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from e3cm_bench.geometry import two_view as geometry
from helpers import rotation

K0 = np.array([[520.0, 0.0, 310.0], [0.0, 515.0, 245.0], [0.0, 0.0, 1.0]])
K1 = np.array([[480.0, 0.0, 330.0], [0.0, 490.0, 235.0], [0.0, 0.0, 1.0]])




R_01 = rotation("y", 12.0) @ rotation("x", -5.0) @ rotation("z", 3.0)
T_01 = np.array([0.8, -0.15, 0.3])


def project(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = X @ K.T
    return p[:, :2] / p[:, 2:3]


def scene_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n random 3D points in front of both cameras, projected into both (exact pixels)."""
    rng = np.random.default_rng(seed)
    X0 = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 12, n)])
    X1 = X0 @ R_01.T + T_01
    assert np.all(X1[:, 2] > 0)
    return project(X0, K0), project(X1, K1)


def true_F() -> np.ndarray:
    # x1^T F x0 = 0 with F = K1^-T [t]_x R K0^-1.
    return np.linalg.inv(K1).T @ geometry.skew(T_01) @ R_01 @ np.linalg.inv(K0)


def unit(F: np.ndarray) -> np.ndarray:
    F = F / np.linalg.norm(F)
    return F * np.sign(F.flat[np.argmax(np.abs(F))])


def algebraic(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    return np.sum(geometry.to_homogeneous(x1) * (geometry.to_homogeneous(x0) @ F.T), axis=1)


# --------------------------------------------------------------------------- 8-point


@pytest.mark.parametrize("n, tol_px2", [(8, 1e-4), (30, 1e-8)])
def test_fundamental_8point_fits_fit_points_and_fresh_points(n, tol_px2):
    x0, x1 = scene_points(n, seed=1)
    F = geometry.estimate_fundamental(x0, x1, "8point")
    assert F is not None and F.shape == (3, 3)
    y0, y1 = scene_points(200, seed=2)  # fresh points of the same scene, never seen by the fit
    for p0, p1 in ((x0, x1), (y0, y1)):
        # x1^T F x0 ~ 0, made scale-free: divided by |x1| |F x0| (the sine of the angle
        # between x1 and its epipolar line's normal, ~1e-3 for a 1 px error here).
        res = algebraic(F, p0, p1)
        scale = np.linalg.norm(geometry.to_homogeneous(p1), axis=1) * np.linalg.norm(
            geometry.to_homogeneous(p0) @ F.T, axis=1
        )
        assert np.max(np.abs(res) / scale) < 1e-6
        # and in pixels: Sampson distance (squared px) at rounding level
        # (measured 1e-8 / 1.3e-5 px^2 with 8 points, 6e-11 / 1.2e-10 with 30).
        assert np.max(geometry.sampson_distance(F, p0, p1)) < tol_px2
    # Exact, generic data determine F up to scale: it is the true one (compared as the
    # essential matrix K1^T F K0, whose entries are all O(1)), and of rank 2.
    E = K1.T @ F @ K0
    np.testing.assert_allclose(unit(E), unit(geometry.essential_from_pose(R_01, T_01)), atol=1e-3)
    s = np.linalg.svd(F, compute_uv=False)
    assert s[2] < 1e-9 * s[0]
    # A wrong correspondence is not on its epipolar line.
    assert geometry.sampson_distance(F, y0[:1], y1[:1] + [0.0, 5.0])[0] > 1.0


def test_fundamental_8point_needs_8_points():
    x0, x1 = scene_points(7, seed=3)
    assert geometry.estimate_fundamental(x0, x1, "8point") is None
    assert geometry.estimate_fundamental(x0[:0], x1[:0], "8point") is None
    assert geometry.estimate_fundamental(x0, x1, "ransac", 1.0) is None


def test_fundamental_ransac_ignores_outliers():
    x0, x1 = scene_points(100, seed=4)
    rng = np.random.default_rng(5)
    x1 = x1.copy()
    x1[:20] += rng.uniform(20, 60, (20, 2)) * rng.choice([-1, 1], (20, 2))
    import cv2

    cv2.setRNGSeed(0)
    F = geometry.estimate_fundamental(x0, x1, "ransac", threshold_px=0.5)
    assert F is not None
    d = geometry.sampson_distance(F, x0, x1)
    assert np.max(d[20:]) < 0.25  # inliers within the 0.5 px threshold
    assert np.min(d[:20]) > 1.0


# --------------------------------------------------------------------------- distances by hand


def test_sampson_distance_hand_value_horizontal_translation():
    # Identity K, camera moved along x: F = [t]_x with t = (1, 0, 0)
    #   F = [[0, 0, 0], [0, 0, -1], [0, 1, 0]]
    # x0 = (x, y, 1): F x0 = (0, -1, y); x1 = (x', y', 1): F^T x1 = (0, 1, -y')
    # x1^T F x0 = -y' + y = y - y'          (epipolar lines are horizontal)
    # denominator = (F x0)_1^2 + (F x0)_2^2 + (F^T x1)_1^2 + (F^T x1)_2^2 = 0 + 1 + 0 + 1 = 2
    # Sampson = (y - y')^2 / 2: a match off by dy = 3 px vertically -> 9 / 2 = 4.5 px^2
    # (the optimal correction moves each point by 1.5 px: 1.5^2 + 1.5^2 = 4.5).
    F = geometry.skew([1.0, 0.0, 0.0])
    np.testing.assert_array_equal(F, [[0, 0, 0], [0, 0, -1], [0, 1, 0]])
    x0 = np.array([[10.0, 20.0], [-7.0, 3.0], [100.0, 50.0], [4.0, 4.0]])
    x1 = np.array([[35.0, 23.0], [-50.0, 3.0], [90.0, 49.0], [4.0, 4.0]])
    d = geometry.sampson_distance(F, x0, x1)
    np.testing.assert_allclose(d, [4.5, 0.0, 0.5, 0.0], atol=1e-12)
    # Scale-invariant in F.
    np.testing.assert_allclose(geometry.sampson_distance(-7.0 * F, x0, x1), d, atol=1e-12)


def test_symmetric_epipolar_distance_hand_values():
    # Same E = [(1,0,0)]_x (R = I): algebraic error y0 - y1, both line norms 1:
    # d = (y0 - y1)^2 * (1/1 + 1/1) = 2 * 0.01^2 = 2e-4.
    E = geometry.essential_from_pose(np.eye(3), [1.0, 0.0, 0.0])
    d = geometry.symmetric_epipolar_distance(E, np.array([[0.1, 0.2]]), np.array([[0.3, 0.21]]))
    np.testing.assert_allclose(d, [2e-4], rtol=1e-12)
    # Forward motion, t = (0, 0, 1), R = I: E = [[0, -1, 0], [1, 0, 0], [0, 0, 0]].
    # x0 = (0.1, 0): E x0 = (0, 0.1, 0); x1 = (0.2, 0.05): E^T x1 = (0.05, -0.2, 0)
    # x1^T E x0 = 0.05 * 0.1 = 0.005 -> squared 2.5e-5
    # d = 2.5e-5 * (1 / 0.01 + 1 / (0.0025 + 0.04)) = 2.5e-5 * (100 + 23.5294118) = 3.0882353e-3
    E = geometry.essential_from_pose(np.eye(3), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(E, [[0, -1, 0], [1, 0, 0], [0, 0, 0]])
    d = geometry.symmetric_epipolar_distance(E, np.array([[0.1, 0.0]]), np.array([[0.2, 0.05]]))
    np.testing.assert_allclose(d, [2.5e-5 * (100.0 + 1.0 / 0.0425)], rtol=1e-12)
    assert abs(d[0] - 3.0882353e-3) < 1e-9


def test_symmetric_epipolar_distance_zero_on_true_pose():
    x0, x1 = scene_points(50, seed=6)
    E = geometry.essential_from_pose(R_01, T_01)
    d = geometry.symmetric_epipolar_distance(
        E, geometry.normalize_keypoints(x0, K0), geometry.normalize_keypoints(x1, K1)
    )
    assert np.max(d) < 1e-20


# --------------------------------------------------------------------------- homography


def test_estimate_homography_recovers_known_h():
    H = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
    rng = np.random.default_rng(7)
    x0 = rng.uniform(0, 640, (60, 2))
    x1 = geometry.warp_points(H, x0)
    x1[:10] += rng.uniform(30, 80, (10, 2))  # outliers
    import cv2

    cv2.setRNGSeed(0)
    H_est = geometry.estimate_homography(x0, x1)
    assert H_est is not None
    np.testing.assert_allclose(H_est / H_est[2, 2], H, rtol=1e-6, atol=1e-8)
    assert geometry.estimate_homography(x0[:3], x1[:3]) is None


def test_warp_points_identity_and_translation():
    pts = np.array([[0.0, 0.0], [3.5, -2.0]])
    np.testing.assert_allclose(geometry.warp_points(np.eye(3), pts), pts)
    T = np.array([[1.0, 0, 5], [0, 1, -1], [0, 0, 1]])
    np.testing.assert_allclose(geometry.warp_points(T, pts), pts + [5, -1])


# --------------------------------------------------------------------------- angles


def test_translation_angle_folds_sign():
    t = np.array([0.3, -0.2, 0.9])
    assert geometry.translation_angle_deg(t, t) == pytest.approx(0.0, abs=1e-6)
    assert geometry.translation_angle_deg(-t, t) == pytest.approx(0.0, abs=1e-6)
    assert geometry.translation_angle_deg(5 * t, -0.1 * t) == pytest.approx(0.0, abs=1e-6)
    assert geometry.translation_angle_deg([1, 0, 0], [0, 1, 0]) == pytest.approx(90.0)
    assert geometry.translation_angle_deg([1, 0, 0], [1, 1, 0]) == pytest.approx(45.0)
    assert geometry.translation_angle_deg([1, 0, 0], [-1, 1, 0]) == pytest.approx(45.0)  # 135 folded
    assert geometry.translation_angle_deg([1, 0, 0], [-1, math.tan(math.radians(30)), 0]) == pytest.approx(30.0)


def test_rotation_angle():
    assert geometry.rotation_angle_deg(np.eye(3), rotation("z", 25.0)) == pytest.approx(25.0)
    assert geometry.rotation_angle_deg(rotation("x", 10.0), rotation("x", -20.0)) == pytest.approx(30.0)


def test_essential_and_pose_recovered_from_synthetic_scene():
    x0, x1 = scene_points(200, seed=8)
    import cv2

    cv2.setRNGSeed(0)
    out = geometry.estimate_relative_pose(x0, x1, K0, K1)
    assert out is not None
    R, t, mask = out
    assert geometry.rotation_angle_deg(R, R_01) < 0.01
    assert geometry.translation_angle_deg(t, T_01) < 0.01
    assert mask.sum() >= 190
    assert geometry.estimate_relative_pose(x0[:4], x1[:4], K0, K1) is None


def test_an_opencv_assertion_in_the_f_estimator_reads_as_no_f(monkeypatch):
    """USAC (MAGSAC++) asserts on some degenerate samples ('!model.empty()', seen on a demo
    pair) instead of returning no model: that must read as 'no F', as RANSAC's None does."""
    import cv2

    from e3cm_bench.geometry import two_view as geometry

    def asserts(*args, **kwargs):
        raise cv2.error("OpenCV(5.0.0) estimator.cpp:418: error: (-215:Assertion failed) !model.empty()")

    monkeypatch.setattr(geometry.cv2, "findFundamentalMat", asserts)
    x = np.random.default_rng(0).uniform(0, 100, (20, 2))
    assert geometry.estimate_fundamental(x, x + 1, "magsac", 1.0) is None
