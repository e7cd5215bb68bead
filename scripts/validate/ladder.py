"""Matchers made worse on purpose, to check that a score orders them (docs/own-images.md,
Validation): SIFT+NN with its keypoints moved by Gaussian noise and a share of its matches
replaced by random points, as a `module:factory` matcher:

    cd scripts/validate && e3cm-bench sfm ... --matcher ladder:degraded_sift --set noise_px=2 --set outliers=0.1

The noise of a keypoint is a function of the image and of the keypoint's own position, the same in
every pair the image is in (a detector that localizes worse, whose repeated detections still chain
into tracks); the outliers are drawn per pair from the two images' contents (the same on a rerun).
"""

from __future__ import annotations

import hashlib

import numpy as np

import e3cm_bench as eb


def _digest(image: np.ndarray) -> int:
    return int.from_bytes(hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=8).digest(), "little")


def _noise(points: np.ndarray, image_seed: int, sd: float) -> np.ndarray:
    """Gaussian noise (sd px per axis), a function of each point's position (1/16 px) and the image."""
    if sd <= 0 or len(points) == 0:
        return points
    cells = np.round(points.astype(np.float64) * 16).astype(np.int64)
    out = points.astype(np.float64).copy()
    for k, (x, y) in enumerate(cells):
        rng = np.random.default_rng([image_seed, int(x) & 0xFFFFFFFF, int(y) & 0xFFFFFFFF])
        out[k] += rng.normal(0.0, sd, 2)
    return out.astype(np.float32)


class DegradedSift(eb.Matcher):
    name = "degraded-sift"

    def __init__(self, noise_px: float, outliers: float):
        self.sift = eb.build_matcher("sift")
        self.noise_px, self.outliers = float(noise_px), float(outliers)

    def settings(self) -> dict:
        return {"noise_px": self.noise_px, "outliers": self.outliers}

    def match(self, image0, image1):
        found = self.sift.match(image0, image1)
        seed0, seed1 = _digest(image0), _digest(image1)
        x0, x1 = _noise(found.keypoints0, seed0, self.noise_px), _noise(found.keypoints1, seed1, self.noise_px)
        x0, x1 = (np.clip(x, 0, [image.shape[1] - 1, image.shape[0] - 1]).astype(np.float32)
                  for x, image in ((x0, image0), (x1, image1)))
        if self.outliers > 0 and len(x1):
            rng = np.random.default_rng([seed0, seed1])
            chosen = rng.random(len(x1)) < self.outliers
            x1[chosen] = (rng.random((int(chosen.sum()), 2)) * [image1.shape[1] - 1, image1.shape[0] - 1]).astype(np.float32)
        return eb.Matches(x0, x1, found.scores)


def degraded_sift(noise_px: float = 0.0, outliers: float = 0.0) -> DegradedSift:
    """SIFT+NN with `noise_px` of keypoint noise and `outliers` (a share) of random matches."""
    if not noise_px >= 0 or not 0 <= outliers < 1:
        raise ValueError(f"noise_px must be >= 0 and outliers in [0, 1), got {noise_px!r}, {outliers!r}")
    return DegradedSift(noise_px, outliers)


# The rungs by name, for a command that takes matchers without settings (e3cm-bench rank --matchers
# sift,ladder:noise_2px,...): each the same degraded_sift, its settings fixed.
def noise_1px() -> DegradedSift:
    return degraded_sift(noise_px=1.0)


def noise_2px() -> DegradedSift:
    return degraded_sift(noise_px=2.0)


def noise_4px() -> DegradedSift:
    return degraded_sift(noise_px=4.0)


def outliers_10() -> DegradedSift:
    return degraded_sift(outliers=0.1)


def outliers_30() -> DegradedSift:
    return degraded_sift(outliers=0.3)
