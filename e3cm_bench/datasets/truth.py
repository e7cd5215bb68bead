"""The ground-truth rule, one for every source: scene_info files, glue-factory's views.txt,
COLMAP models, SuperGlue pair lists, stereo calibration files and homography files.

A value that breaks it is refused in one line, ``WHERE: PROBLEM``, WHERE naming the file and
the entry (``model: image 3.png``, ``pairs.txt:7: K0``), PROBLEM the same words whichever file
the value came from. What the rule asks:

- a rotation is a rotation: R R^T = I and det R = 1 to ROTATION_TOLERANCE, and a quaternion
  has norm 1 to that tolerance (a zero quaternion is refused: read as a matrix it becomes the
  identity, a plausible and wrong pose);
- focal lengths are positive and finite, principal points finite, image sizes positive;
- translations are finite and below MAX_TRANSLATION (a larger one is a unit or parsing slip:
  the largest in the shared data is YFCC100M's, 3.5e5 units, in SfM models of no fixed scale);
- a relative pose has a translation (its direction is half the pose error);
- a homography is finite and invertible.
"""

from __future__ import annotations

import numpy as np

from e3cm_bench.datasets.base import DatasetError

# How far a stored rotation may be from orthonormal with determinant +1, and a quaternion from
# norm 1: files print about seven significant digits (KITTI's calibration, COLMAP's text at 17).
ROTATION_TOLERANCE = 1e-3
MAX_TRANSLATION = 1e7
MIN_TRANSLATION = 1e-9  # below this the translation's direction, half of the pose error, is undefined
MAX_CONDITION = 1e12  # of a homography, relative to its entries' scale: above it H maps the image onto a line


def check_rotation(R: np.ndarray, where: str, what: str = "the rotation") -> None:
    """R (3x3) must be finite, orthonormal and of determinant +1."""
    R = np.asarray(R, np.float64)
    if not np.all(np.isfinite(R)):
        raise DatasetError(f"{where}: {what} has non-finite entries")
    off = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if off > ROTATION_TOLERANCE or abs(det - 1) > ROTATION_TOLERANCE:
        raise DatasetError(f"{where}: {what} is not a rotation (R R^T differs from I by {off:.3g}, det {det:.4f})")


def check_quaternion(q, where: str) -> None:
    """A stored rotation quaternion (any component order) must have norm 1."""
    q = np.asarray(q, np.float64).ravel()
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or abs(norm - 1) > ROTATION_TOLERANCE:
        shown = ", ".join(f"{v:g}" for v in q)
        raise DatasetError(f"{where}: the rotation quaternion ({shown}) has norm {norm:.4g}, not 1 "
                           "(not a rotation)")


def check_translation(t: np.ndarray, where: str, what: str = "the translation") -> None:
    """t (3,) must be finite and of norm below MAX_TRANSLATION."""
    t = np.asarray(t, np.float64).ravel()
    if not np.all(np.isfinite(t)):
        raise DatasetError(f"{where}: {what} has non-finite entries")
    norm = float(np.linalg.norm(t))
    if norm >= MAX_TRANSLATION:
        raise DatasetError(f"{where}: {what} has norm {norm:.4g}, implausibly far (over {MAX_TRANSLATION:g})")


def check_intrinsics(K: np.ndarray, where: str) -> None:
    """K must be a camera matrix: positive finite focal lengths, a finite principal point,
    last row (0, 0, 1)."""
    K = np.asarray(K, np.float64)
    for value in (K[0, 0], K[1, 1]):
        if not np.isfinite(value):
            raise DatasetError(f"{where}: focal length {value:g} is not finite")
        if not value > 0:
            raise DatasetError(f"{where}: focal length {value:g} is not positive")
    if not np.all(np.isfinite(K[:2, 2])):
        raise DatasetError(f"{where}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) is not finite")
    if not np.allclose(K[2], [0, 0, 1]):
        raise DatasetError(f"{where}: intrinsics are not a camera matrix (last row {K[2].tolist()}, not [0, 0, 1])")


def check_image_size(width, height, where: str) -> None:
    if not (np.isfinite(width) and np.isfinite(height) and width > 0 and height > 0):
        raise DatasetError(f"{where}: image size {width:g} x {height:g} is not positive")


def check_world_pose(T: np.ndarray, where: str, what: str = "the pose") -> None:
    """A pose (3x4 or 4x4; world-to-camera, or camera 0 to camera 1): a rotation and a
    plausible translation."""
    T = np.asarray(T, np.float64)
    check_rotation(T[:3, :3], where, f"{what}'s rotation")
    check_translation(T[:3, 3], where, f"{what}'s translation")


def check_pose(T: np.ndarray, where: str) -> None:
    """A relative pose T_0to1 (4x4): a rotation and a translation that is plausible and not
    zero (the pose error compares translation directions, which a zero translation has none
    of: SuperGlue's and LoFTR's evaluations cannot score such a pair either)."""
    check_world_pose(T, where, "the relative pose")
    if not np.linalg.norm(T[:3, 3]) > MIN_TRANSLATION:
        raise DatasetError(f"{where}: the relative pose has no translation (the cameras share a centre), "
                           "so its translation error is undefined")


def check_homography(H: np.ndarray, where: str) -> None:
    """H (3x3) must be finite and invertible (relative to its entries' scale: an H of tiny
    entries is fine, a rank-deficient one is not)."""
    if not np.all(np.isfinite(H)):
        raise DatasetError(f"{where}: the homography has non-finite entries (NaN or inf)")
    if np.linalg.cond(H) > MAX_CONDITION:
        raise DatasetError(f"{where}: the homography is singular (it maps the image onto a line or a point)")
