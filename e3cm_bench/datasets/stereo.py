"""Stereo sequences for rig self-calibration: frames (left, right) and the rig's true extrinsics.

Layouts read:
- KITTI odometry (and `e3cm-bench synth stereo`): ``image_0/NNNNNN.png`` (left),
  ``image_1/NNNNNN.png`` (right), ``calib.txt`` with ``P0:`` and ``P1:`` (3x4, row-major),
  optional ``poses.txt``. Pass the sequence folder (``dataset/sequences/00``).
- KITTI raw: ``image_00/data/*.png``, ``image_01/data/*.png``, and ``calib_cam_to_cam.txt``
  in the drive folder or its parent (the date folder). The synced downloads are rectified:
  the truth is then ``P_rect_00``/``P_rect_01``; ``unrectified=True`` takes ``K_00``,
  ``K_01``, ``R_01``, ``T_01`` (relative to ``R_00``, ``T_00``) for the unsynced images.

The extrinsics map left-camera to right-camera coordinates: ``x_right = R x_left + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from e3cm_bench.datasets.base import DatasetError, require_directory
from e3cm_bench.datasets.truth import check_intrinsics, check_rotation, check_translation


@dataclass
class StereoSequence:
    root: Path
    layout: str
    left: list[Path]
    right: list[Path]
    K0: np.ndarray
    K1: np.ndarray
    R: np.ndarray  # ground truth, left -> right
    t: np.ndarray
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.left)

    def describe(self) -> dict:
        return {"root": str(self.root), "layout": self.layout, "n_frames": len(self), **self.meta}


def read_calibration_file(path: Path) -> dict[str, np.ndarray]:
    """'KEY: numbers' lines; lines whose values are not numbers (calib_time) are left out. A key
    given twice is refused: which of the two the file's author meant cannot be told."""
    if not path.is_file():
        raise DatasetError(f"{path}: calibration file not found")
    values, lines = {}, {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        key = key.strip()
        if key in lines:
            raise DatasetError(f"{path}: '{key}:' is given twice (lines {lines[key]} and {number})")
        lines[key] = number
        try:
            values[key] = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue
    return values


# The baseline below which two cameras are taken as one (the file's units: metres in KITTI).
MIN_BASELINE = 1e-9


def _rotation(values: dict, key: str, path: Path) -> np.ndarray:
    R = _entry(values, key, 9, path).reshape(3, 3)
    check_rotation(R, str(path), f"'{key}:'")
    return R


def _baseline(t: np.ndarray, path: Path, keys: str) -> np.ndarray:
    """A rig's t, refused when the two cameras sit at one place (nothing to rectify or triangulate)."""
    check_translation(t, str(path), f"the baseline of {keys}")
    if not np.linalg.norm(t) > MIN_BASELINE:
        raise DatasetError(f"{path}: {keys} put both cameras at the same place (no baseline); a stereo rig needs two")
    return t


def _entry(values: dict, key: str, size: int, path: Path) -> np.ndarray:
    if key not in values or values[key].size != size or not np.all(np.isfinite(values[key])):
        raise DatasetError(f"{path}: needs '{key}:' with {size} finite numbers")
    return values[key]


def _from_projections(
    P0: np.ndarray, P1: np.ndarray, path: Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """K0, K1 and the extrinsics of camera 1 relative to camera 0 from two 3x4 projections."""
    K0, R0, c0 = cv2.decomposeProjectionMatrix(P0)[:3]
    K1, R1, c1 = cv2.decomposeProjectionMatrix(P1)[:3]
    if abs(c0[3, 0]) < 1e-12 or abs(c1[3, 0]) < 1e-12:
        raise DatasetError(f"{path}: a projection matrix has its camera at infinity")
    C0, C1 = c0[:3, 0] / c0[3, 0], c1[:3, 0] / c1[3, 0]
    t0, t1 = -R0 @ C0, -R1 @ C1
    R = R1 @ R0.T
    K0, K1 = K0 / K0[2, 2], K1 / K1[2, 2]
    # OpenCV's RQ decomposition leaves a focal negative where the 3x3 part has a negative determinant
    for K, which in ((K0, "the first"), (K1, "the second")):
        check_intrinsics(K, f"{path}: {which} projection matrix")
    return K0, K1, R, t1 - R @ t0


def _frames(left_dir: Path, right_dir: Path) -> tuple[list[Path], list[Path]]:
    left = sorted(p for p in left_dir.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".ppm"))
    if not left:
        raise DatasetError(f"{left_dir}: no images")
    right = [right_dir / p.name for p in left]
    missing = [p for p in right if not p.is_file()]
    if missing:
        raise DatasetError(f"{missing[0]}: right image missing ({len(missing)} of {len(left)})")
    return left, right


def load_stereo_sequence(root: str | Path, unrectified: bool = False) -> StereoSequence:
    root = require_directory(root, "stereo sequence")
    if (root / "image_0").is_dir():
        path = root / "calib.txt"
        values = read_calibration_file(path)
        K0, K1, R, t = _from_projections(_entry(values, "P0", 12, path).reshape(3, 4),
                                         _entry(values, "P1", 12, path).reshape(3, 4), path)
        t = _baseline(t, path, "P0 and P1")
        left, right = _frames(root / "image_0", root / "image_1")
        return StereoSequence(root, "kitti-odometry", left, right, K0, K1, R, t, {"calib": str(path)})
    if (root / "image_00").is_dir():
        path = next((p / "calib_cam_to_cam.txt" for p in (root, root.parent) if (p / "calib_cam_to_cam.txt").is_file()),
                    root.parent / "calib_cam_to_cam.txt")
        values = read_calibration_file(path)
        if unrectified:
            K0, K1 = _entry(values, "K_00", 9, path).reshape(3, 3), _entry(values, "K_01", 9, path).reshape(3, 3)
            check_intrinsics(K0, f"{path}: 'K_00:'")
            check_intrinsics(K1, f"{path}: 'K_01:'")
            R00, R01 = _rotation(values, "R_00", path), _rotation(values, "R_01", path)
            T00, T01 = _entry(values, "T_00", 3, path), _entry(values, "T_01", 3, path)
            R = R01 @ R00.T
            t = _baseline(T01 - R @ T00, path, "R_00, T_00 and R_01, T_01")
        else:
            K0, K1, R, t = _from_projections(_entry(values, "P_rect_00", 12, path).reshape(3, 4),
                                             _entry(values, "P_rect_01", 12, path).reshape(3, 4), path)
            t = _baseline(t, path, "P_rect_00 and P_rect_01")
        left, right = _frames(root / "image_00" / "data", root / "image_01" / "data")
        layout = "kitti-raw" + ("" if unrectified else "-rectified")
        return StereoSequence(root, layout, left, right, K0, K1, R, t, {"calib": str(path)})
    raise DatasetError(f"{root}: not a stereo sequence (expected image_0/ + image_1/ + calib.txt, "
                       "or image_00/data + image_01/data + calib_cam_to_cam.txt)")
