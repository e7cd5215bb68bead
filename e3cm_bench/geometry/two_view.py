"""Two-view geometry shared by the matchers and the metrics.

Everything is numpy in, numpy out. Points are N x 2 float arrays in pixel-centre
coordinates (the centre of the top-left pixel is (0, 0)). Fundamental and essential
matrices follow OpenCV's convention: ``x1^T F x0 = 0`` for a point x0 of image 0
and its match x1 in image 1. Estimation is delegated to OpenCV; this module only
adds the conventions, the failure handling and the distances OpenCV lacks in
vectorised form. Every estimator's points pass through perturb.perturb_correspondences, the
identity except in a draw of the regression gate's noise ensemble.
"""

from __future__ import annotations

import cv2
import numpy as np

from e3cm_bench.stats.perturb import perturb_correspondences


def to_homogeneous(points: np.ndarray) -> np.ndarray:
    """N x 2 -> N x 3 with a trailing column of ones."""
    points = np.asarray(points, dtype=np.float64)
    return np.concatenate([points, np.ones((len(points), 1))], axis=1)


# --------------------------------------------------------------------------- F


# OpenCV's method flag for each way of estimating F.
_F_METHODS = {"8point": cv2.FM_8POINT, "ransac": cv2.FM_RANSAC, "prosac": cv2.USAC_PROSAC, "magsac": cv2.USAC_MAGSAC}


def estimate_fundamental(
    x0: np.ndarray,
    x1: np.ndarray,
    method: str = "8point",
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 2000,
) -> np.ndarray | None:
    """Fundamental matrix from >= 8 correspondences; None when too few or degenerate.

    method: '8point' (normalised 8-point on all points, rank 2), 'ransac' (OpenCV RANSAC,
    Sampson threshold in pixels), 'prosac' (PROSAC: the points must come best first) or
    'magsac' (OpenCV's USAC MAGSAC++, locally optimised; the threshold bounds its noise scale).
    """
    x0, x1, _ = perturb_correspondences(x0, x1, keep_order=method == "prosac")
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    x1 = np.ascontiguousarray(x1, dtype=np.float64)
    if len(x0) < 8:
        return None
    try:
        if method == "8point":
            F, _ = cv2.findFundamentalMat(x0, x1, cv2.FM_8POINT)
        else:
            F, _ = cv2.findFundamentalMat(x0, x1, _F_METHODS[method], threshold_px, confidence, max_iters)
    except cv2.error:  # USAC asserts on some degenerate samples (an empty model) instead of finding none
        return None
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        return None
    return F


def local_distortion(H: np.ndarray, point: tuple[float, float]) -> tuple[float, float, float]:
    """How H distorts a neighbourhood of `point`: the rotation (degrees) and the two scales
    (largest first) of its local affine map (the Jacobian, split by SVD)."""
    x, y = point
    p = np.float64([[x, y], [x + 1.0, y], [x, y + 1.0]])
    q = warp_points(H, p)
    jacobian = np.stack([q[1] - q[0], q[2] - q[0]], 1)
    u, scales, vt = np.linalg.svd(jacobian)
    rotation = u @ vt
    return float(np.degrees(np.arctan2(rotation[1, 0], rotation[0, 0]))), float(scales[0]), float(scales[1])


def sampson_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """First-order geometric error of each match w.r.t. F, in squared pixels (paper Eq. 4)."""
    p0 = to_homogeneous(x0)
    p1 = to_homogeneous(x1)
    Fp0 = p0 @ F.T  # rows: F p0
    Ftp1 = p1 @ F  # rows: F^T p1
    numerator = np.sum(p1 * Fp0, axis=1) ** 2
    denominator = Fp0[:, 0] ** 2 + Fp0[:, 1] ** 2 + Ftp1[:, 0] ** 2 + Ftp1[:, 1] ** 2
    return numerator / np.maximum(denominator, 1e-300)


# --------------------------------------------------------------------------- E and pose


def skew(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def essential_from_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """E = [t]_x R for the transform x_1 = R x_0 + t (camera 0 to camera 1)."""
    return skew(t) @ np.asarray(R, dtype=np.float64)


def normalize_keypoints(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels -> normalised image coordinates (K^-1 x), N x 2."""
    points = np.asarray(points, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    return (points - K[[0, 1], [2, 2]][None]) / K[[0, 1], [0, 1]][None]


def symmetric_epipolar_distance(E: np.ndarray, x0n: np.ndarray, x1n: np.ndarray) -> np.ndarray:
    """Squared symmetric epipolar distance of normalised points w.r.t. E (PROTOCOLS §3)."""
    p0 = to_homogeneous(x0n)
    p1 = to_homogeneous(x1n)
    Ep0 = p0 @ E.T
    Etp1 = p1 @ E
    algebraic = np.sum(p1 * Ep0, axis=1) ** 2
    return algebraic * (
        1.0 / np.maximum(Ep0[:, 0] ** 2 + Ep0[:, 1] ** 2, 1e-300)
        + 1.0 / np.maximum(Etp1[:, 0] ** 2 + Etp1[:, 1] ** 2, 1e-300)
    )


def estimate_relative_pose(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    threshold_px: float = 0.5,
    confidence: float = 0.99999,
    method: str = "ransac",
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Essential-matrix RANSAC on normalised points, then the best cheirality check. method:
    OpenCV's robust method (_E_METHODS: ransac, magsac = USAC_MAGSAC, accurate = USAC_ACCURATE).

    Returns (R, t, inlier_mask) or None (fewer than 5 matches or no E). The pixel
    threshold is turned into normalised units by the mean focal length of both cameras.
    """
    if len(kpts0) < 5:
        return None
    K0 = np.asarray(K0, dtype=np.float64)
    K1 = np.asarray(K1, dtype=np.float64)
    kpts0, kpts1, order = perturb_correspondences(kpts0, kpts1)
    x0 = normalize_keypoints(kpts0, K0)
    x1 = normalize_keypoints(kpts1, K1)
    norm_threshold = threshold_px / np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]])
    E, mask = cv2.findEssentialMat(
        x0, x1, np.eye(3), threshold=norm_threshold, prob=confidence, method=_E_METHODS[method]
    )
    if E is None:
        return None
    best = None
    best_count = 0
    # findEssentialMat may stack several solutions (3k x 3); keep the one with most inliers.
    for candidate in np.split(E, len(E) // 3):
        count, R, t, _ = cv2.recoverPose(candidate, x0, x1, np.eye(3), 1e9, mask=mask.copy())
        if count > best_count:
            best_count = count
            best = (R, t[:, 0], mask.ravel() > 0)
    if best is not None and order is not None:
        best = (best[0], best[1], unshuffle(best[2], order))
    return best


def unshuffle(values: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Per-correspondence values computed on points taken in `order`, back in the points' own order."""
    out = np.empty_like(values)
    out[order] = values
    return out


# How a rotation error is measured (method/protocols.py picks one per protocol):
# "nearest-rotation": each matrix that is not orthonormal (beyond ORTHONORMAL_TOLERANCE) is
# first replaced by its nearest rotation (SVD), then the angle of R_est^T R_gt is taken;
# "reference": that angle from the matrices as given, arccos((trace - 1) / 2) clipped to
# [-1, 1], as SuperGlue's, LoFTR's and glue-factory's angle_error_mat compute it. With ground
# truth that is slightly off orthonormal (poses stored in float32, or scaled: det 1.00045 in a
# real RGB-D sequence) (trace - 1) / 2 can exceed 1 and the reference formula reads 0 for
# every estimate within a degree or so of the truth; the nearest rotation gives their angle.
ROTATION_ERRORS = ("nearest-rotation", "reference")
# Below this, |R^T R - I| is float64 rounding (a product of exact rotations: about 1e-15), and
# the matrix is used as it is, so that clean ground truth gives the same numbers either way.
ORTHONORMAL_TOLERANCE = 1e-9


def rotation_deviation(R: np.ndarray) -> float:
    """How far R is from orthonormal: the largest entry of |R^T R - I|."""
    R = np.asarray(R, dtype=np.float64)
    return float(np.abs(R.T @ R - np.eye(3)).max())


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest R in the Frobenius norm (U diag(1, 1, det(U V^T)) V^T of R's SVD)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def rotation_angle_deg(R_est: np.ndarray, R_gt: np.ndarray, formula: str = "nearest-rotation") -> float:
    """Angle of the rotation R_est^T R_gt, in degrees, measured by `formula` (ROTATION_ERRORS)."""
    if formula not in ROTATION_ERRORS:
        raise ValueError(f"rotation error formula must be one of {', '.join(ROTATION_ERRORS)}, got {formula!r}")
    R_est, R_gt = np.asarray(R_est, dtype=np.float64), np.asarray(R_gt, dtype=np.float64)
    if formula == "nearest-rotation":
        R_est, R_gt = (
            nearest_rotation(R) if rotation_deviation(R) > ORTHONORMAL_TOLERANCE else R for R in (R_est, R_gt)
        )
    cos = (np.trace(R_est.T @ R_gt) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def translation_angle_deg(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle between translation directions, folded to [0, 90] (the sign of t is unobservable)."""
    t_est = np.asarray(t_est, dtype=np.float64).ravel()
    t_gt = np.asarray(t_gt, dtype=np.float64).ravel()
    n = np.linalg.norm(t_est) * np.linalg.norm(t_gt)
    if n < 1e-12:
        return 0.0 if np.linalg.norm(t_gt) < 1e-12 else 90.0
    angle = float(np.degrees(np.arccos(np.clip(np.dot(t_est, t_gt) / n, -1.0, 1.0))))
    return min(angle, 180.0 - angle)


# --------------------------------------------------------------------------- H


def estimate_homography(
    x0: np.ndarray,
    x1: np.ndarray,
    threshold_px: float = 3.0,
    max_iters: int = 5000,
    confidence: float = 0.9999,
    method: str = "ransac",
) -> np.ndarray | None:
    """Robust homography mapping image-0 pixels to image-1 pixels, or None. method: 'ransac'
    (cv2.RANSAC) or 'magsac' (OpenCV's USAC MAGSAC++, wxbs-benchmark's estimator)."""
    if len(x0) < 4:
        return None
    x0, x1, _ = perturb_correspondences(x0, x1)
    try:
        H, _ = cv2.findHomography(
            np.ascontiguousarray(x0, dtype=np.float64),
            np.ascontiguousarray(x1, dtype=np.float64),
            _H_METHODS[method],
            threshold_px,
            maxIters=max_iters,
            confidence=confidence,
        )
    except cv2.error:  # USAC asserts on some degenerate samples instead of finding no model
        return None
    if H is None or not np.all(np.isfinite(H)):
        return None
    return H


# OpenCV's method flag for each way of estimating E (the sweep's estimators, issue 69).
_E_METHODS = {"ransac": cv2.RANSAC, "magsac": cv2.USAC_MAGSAC, "accurate": cv2.USAC_ACCURATE}

# OpenCV's method flag for each way of estimating H.
_H_METHODS = {"ransac": cv2.RANSAC, "magsac": cv2.USAC_MAGSAC}


def warp_points(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to N x 2 points."""
    p = to_homogeneous(points) @ np.asarray(H, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]
