"""Synthetic stereo sequences in the KITTI odometry layout, for rig self-calibration.

A stereo rig moves forward through the room scene (scene.room_scene). Its right camera is
the left one moved by a baseline and turned by a small drift in yaw, pitch and roll (about
1 degree each, signs random), as a rig whose calibration has drifted. The truth is written
as KITTI does: ``calib.txt`` with ``P0 = K [I | 0]`` and ``P1 = K [R | t]``; ``poses.txt``
holds the left camera's pose per frame (camera-to-world, 3x4, row-major).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from e3cm_bench.ground.files import write_atomically
from e3cm_bench.apps.synth.layouts import SCENE_SIZE, _write_rgb, seeded_room
from e3cm_bench.apps.synth.scene import look_at, render

BASELINE_M = 0.54  # KITTI's


def rig_extrinsics(rng: np.random.Generator, drift_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(R, t), left -> right: a baseline along x, and a drift of about drift_deg in each angle."""
    angles = np.radians(drift_deg * rng.uniform(0.7, 1.3, 3) * rng.choice([-1, 1], 3))
    R = cv2.Rodrigues(angles)[0]
    centre_right = np.array([BASELINE_M, rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01)])  # in left coordinates
    return R, -R @ centre_right


def write_stereo_sequence(root: str | Path, frames: int = 20, seed: int = 0, drift_deg: float = 1.0) -> Path:
    """image_0/, image_1/, calib.txt and poses.txt under `root`; returns `root`."""
    if frames < 1:
        raise ValueError(f"--frames must be at least 1, got {frames}")
    root = Path(root)
    rng, planes, K = seeded_room(seed)
    R_rig, t_rig = rig_extrinsics(rng, drift_deg)
    poses = []
    for i in range(frames):
        # The left camera drives forward with a little sway, looking down the room.
        centre = np.array([0.4 * np.sin(0.5 * i) - 0.8, rng.uniform(-0.1, 0.1), 0.3 + 0.3 * i])
        target = centre + np.array([0.4 * np.cos(0.3 * i), 0.35, 6.0])
        R_left, t_left = look_at(centre, target)
        R_right, t_right = R_rig @ R_left, R_rig @ t_left + t_rig
        name = f"{i:06d}.png"
        _write_rgb(root / "image_0" / name, render(planes, K, R_left, t_left, SCENE_SIZE).image)
        _write_rgb(root / "image_1" / name, render(planes, K, R_right, t_right, SCENE_SIZE).image)
        pose = np.hstack([R_left.T, (-R_left.T @ t_left)[:, None]])  # camera-to-world
        poses.append(" ".join(f"{v:.9e}" for v in pose.ravel()))
    P0 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = K @ np.hstack([R_rig, t_rig[:, None]])
    calib = "".join(f"{key}: {' '.join(f'{v:.12e}' for v in P.ravel())}\n" for key, P in (("P0", P0), ("P1", P1)))
    write_atomically(root / "calib.txt", lambda tmp: tmp.write_text(calib))
    write_atomically(root / "poses.txt", lambda tmp: tmp.write_text("\n".join(poses) + "\n"))
    return root
