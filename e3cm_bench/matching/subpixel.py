"""Sub-pixel refinement of final matches on the images themselves (training-free).

Level-0 keypoints of the cascade sit on whole pixels of the level-0 map; this moves each
match's point in image B to where a Lucas-Kanade fit of the patch around A's point says it
is, and keeps the move only where it is consistent:

- LK (OpenCV's pyramidal `calcOpticalFlowPyrLK`) starts at the match (initial flow), in a
  `window` x `window` patch, on one pyramid level above the image;
- forward-backward: B's refined point tracked back into A must land within `fb_px` of A's
  point;
- the move is at most `max_move` pixels (a refinement, never a new match).

A match whose fit fails either check keeps its point (`drop=False`) or is dropped
(`drop=True`: the strict variant). No match is ever added. Arrays in, arrays out; pixel-centre
coordinates (OpenCV's too). Deterministic: LK has no randomness.
"""

from __future__ import annotations

import cv2
import numpy as np

REFINE_MODES = ("none", "lk", "lk-strict")


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def refine_lk(image0: np.ndarray, image1: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray, window: int = 9,
              max_move: float = 1.5, fb_px: float = 0.3, drop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(kpts1 refined, keep): kpts1 moved by LK where consistent; keep[i] False only for a
    match the strict variant drops. kpts0 never moves."""
    kpts0 = np.asarray(kpts0, np.float32).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, np.float32).reshape(-1, 2)
    keep = np.ones(len(kpts0), bool)
    if len(kpts0) == 0:
        return kpts1.copy(), keep
    grey0, grey1 = _grey(image0), _grey(image1)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    options = dict(winSize=(window, window), maxLevel=1, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(grey0, grey1, kpts0.reshape(-1, 1, 2), kpts1.reshape(-1, 1, 2).copy(), **options)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(grey1, grey0, moved, kpts0.reshape(-1, 1, 2).copy(), **options)
    moved, back = moved.reshape(-1, 2), back.reshape(-1, 2)
    consistent = (status.ravel() == 1) & (status_back.ravel() == 1) \
        & (np.linalg.norm(back - kpts0, axis=1) <= fb_px) \
        & (np.abs(moved - kpts1).max(axis=1) <= max_move) & np.isfinite(moved).all(axis=1)
    h, w = grey1.shape[:2]
    consistent &= (moved[:, 0] >= 0) & (moved[:, 0] <= w - 1) & (moved[:, 1] >= 0) & (moved[:, 1] <= h - 1)
    refined = np.where(consistent[:, None], moved, kpts1)
    if drop:
        keep = consistent
    return refined.astype(np.float32), keep
