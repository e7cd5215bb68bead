"""Stereo rig self-calibration from matches (paper Sec. 4.4): arrays in, arrays out.

The rig's extrinsics map left-camera coordinates to right-camera coordinates,
``x_right = R x_left + t``; with known intrinsics only R and the direction of t can be
recovered from matches. `estimate_extrinsics` starts from RANSAC on the essential matrix
(OpenCV) and minimises the Sampson error of all pooled matches over R and the unit t with
a robust loss (SciPy's least_squares), as the self-calibration pipeline the paper follows
(Ling and Shen 2016) optimises the extrinsics under the epipolar constraint.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares

from e3cm_bench.geometry.two_view import essential_from_pose, estimate_fundamental

ERROR_COLUMNS = ("yaw", "pitch", "roll", "tx", "ty", "tz")


def fundamental_from_extrinsics(K0: np.ndarray, K1: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.linalg.inv(K1).T @ essential_from_pose(R, t) @ np.linalg.inv(K0)


def _normalised(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(np.asarray(points, np.float64).reshape(-1, 1, 2), K, None).reshape(-1, 2)


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """Two unit vectors orthogonal to t: the unit translation moves on the sphere along them."""
    helper = np.eye(3)[np.argmin(np.abs(t))]
    e1 = np.cross(t, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(t, e1)])


def estimate_extrinsics(
    x0: np.ndarray, x1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
    ransac_px: float = 1.0, loss: str = "cauchy", loss_scale_px: float = 1.0, robust: bool = True,
) -> dict | None:
    """R and unit t (left -> right) from matches x0 (left) and x1 (right) in pixels.

    RANSAC on the essential matrix (threshold ransac_px) gives the start; then the Sampson
    errors (pixels) of all matches are minimised over the rotation (3 parameters, a
    rotation vector applied to the start) and the translation direction (2 parameters on
    the unit sphere). `loss`/`loss_scale_px`: the robust loss of least_squares ('linear'
    for plain least squares). Cauchy, because a loss with a linear tail is not robust enough
    here: moving the epipole towards the image shrinks the Sampson errors of wrong matches,
    so with Huber (or soft-L1) a few percent of wrong SIFT matches pulled a synthetic rig's
    estimate 3-4 degrees from a correct RANSAC start; Cauchy kept it within 0.06 degrees. robust=False starts from the
    8-point E on all matches
    instead of RANSAC (to show what the robust steps are worth). None without 8 matches or
    an estimate. The caller seeds OpenCV's RNG for a repeatable RANSAC.
    """
    x0, x1 = np.asarray(x0, np.float64).reshape(-1, 2), np.asarray(x1, np.float64).reshape(-1, 2)
    if len(x0) < 8:
        return None
    n0, n1 = _normalised(x0, K0), _normalised(x1, K1)
    focal = float(np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]]))
    if robust:
        E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), cv2.RANSAC, 0.9999, ransac_px / focal)
        if E is None or E.shape[0] < 3:
            return None
        E = E[:3]
    else:
        F = estimate_fundamental(x0, x1, "8point")
        if F is None:
            return None
        E, mask = K1.T @ F @ K0, np.full((len(x0), 1), 255, np.uint8)
    n_inliers, R0, t0, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask.copy())
    t0 = t0.ravel() / np.linalg.norm(t0)
    basis = _tangent_basis(t0)

    def extrinsics(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = cv2.Rodrigues(p[:3])[0] @ R0
        t = t0 + p[3:] @ basis
        return R, t / np.linalg.norm(t)

    def residuals(p: np.ndarray) -> np.ndarray:
        R, t = extrinsics(p)
        return signed_sampson_error(fundamental_from_extrinsics(K0, K1, R, t), x0, x1)

    start = np.zeros(5)
    fit = least_squares(residuals, start, loss=loss if robust else "linear", f_scale=loss_scale_px, x_scale=1e-2)
    R, t = extrinsics(fit.x)
    final = np.abs(residuals(fit.x))
    return {"R": R, "t": t, "R_start": R0, "t_start": t0, "n_matches": len(x0), "n_ransac_inliers": int(n_inliers),
            "median_sampson_px": float(np.median(final)), "inliers_1px": int(np.sum(final <= 1.0))}


def signed_sampson_error(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """x1^T F x0 over the norm of its gradient: the Sampson error in pixels with its sign.

    Its square is geometry.sampson_distance; unlike that distance's square root it is smooth
    at zero, which the least-squares solver needs (its Jacobian is taken numerically).
    """
    h0 = np.concatenate([x0, np.ones((len(x0), 1))], 1)
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    Fx0 = h0 @ F.T
    Ftx1 = h1 @ F
    algebraic = np.sum(h1 * Fx0, axis=1)
    return algebraic / np.sqrt(Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2)


def extrinsic_errors(R: np.ndarray, t: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray) -> dict[str, float]:
    """Rotation error as yaw / pitch / roll in degrees (the rotation vector of R R_gt^T about the
    camera's y, x and z axes, which for small errors are its Euler angles), and the error of
    the unit translation, component by component."""
    rvec = cv2.Rodrigues(R @ R_gt.T)[0].ravel()
    pitch, yaw, roll = np.degrees(rvec)  # x right, y down, z forward
    dt = t / np.linalg.norm(t) - t_gt / np.linalg.norm(t_gt)
    return {"yaw": float(yaw), "pitch": float(pitch), "roll": float(roll),
            "tx": float(dt[0]), "ty": float(dt[1]), "tz": float(dt[2])}


def vertical_disparity(x0: np.ndarray, x1: np.ndarray, K0: np.ndarray, K1: np.ndarray, R: np.ndarray, t: np.ndarray,
                       size: tuple[int, int]) -> tuple[float, float]:
    """Median |y_left - y_right| of the matches as they are, and after rectifying both images
    (OpenCV stereoRectify) with the extrinsics (R, t): a good calibration brings the second
    to a fraction of a pixel. The median, so that a matcher's wrong matches (which no
    calibration aligns) do not hide the quality of the calibration."""
    x0, x1 = np.asarray(x0, np.float64).reshape(-1, 2), np.asarray(x1, np.float64).reshape(-1, 2)
    before = float(np.median(np.abs(x0[:, 1] - x1[:, 1])))
    R0r, R1r, P0r, P1r, *_ = cv2.stereoRectify(K0, None, K1, None, size, R, t.reshape(3, 1), alpha=0)
    r0 = cv2.undistortPoints(x0.reshape(-1, 1, 2), K0, None, R=R0r, P=P0r).reshape(-1, 2)
    r1 = cv2.undistortPoints(x1.reshape(-1, 1, 2), K1, None, R=R1r, P=P1r).reshape(-1, 2)
    return before, float(np.median(np.abs(r0[:, 1] - r1[:, 1])))
