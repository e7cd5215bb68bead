"""SIFT + nearest neighbour with Lowe's ratio test: the handcrafted baseline ("SIFT+NN")."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from e3cm_bench.matchers.base import Features, Matcher, Matches


# OpenCV SIFT doubles the image first with a half-pixel-aligned bilinear resize (original
# pixel x lands on 2x + 0.5) but maps keypoints back by halving alone, so every keypoint
# comes out 0.25 px right of and below its true pixel-centre position (measured on
# synthetic blobs: +0.24..0.26 px at every octave). Subtracting it keeps OpenCV's usual
# detections. (OpenCV's enable_precise_upscale avoids the shift too, but detects a
# different, slightly worse set of points on HPatches.)
UPSCALE_OFFSET_PX = 0.25


@dataclass(frozen=True)
class SiftSettings:
    """max_keypoints: OpenCV's strongest responses kept (0: all); ratio: Lowe's ratio test;
    cross_check: keep mutual nearest neighbours only."""

    max_keypoints: int = 8000
    ratio: float = 0.8
    cross_check: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.max_keypoints, int) or isinstance(self.max_keypoints, bool) or self.max_keypoints < 0:
            raise ValueError(f"max_keypoints must be a whole number >= 0 (0: no limit), got {self.max_keypoints!r}")
        if not isinstance(self.ratio, (int, float)) or not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio!r}")
        if not isinstance(self.cross_check, bool):
            raise ValueError(f"cross_check must be true or false, got {self.cross_check!r}")


class SiftMatcher(Matcher):
    """OpenCV SIFT on the grayscale images, matched by L2 nearest neighbour.

    A match i -> j is kept when the nearest descriptor distance is below ``ratio`` times
    the second nearest (Lowe's ratio test). With ``cross_check`` (off by default) it must
    also be mutual: i is in turn the nearest neighbour of j. Scores are ``1 - d1/d2``,
    so higher is more distinctive. Keypoints are in the pixel-centre convention. Two-stage:
    an image's keypoints and descriptors (features), then a pair's matching (match_features).
    """

    name = "sift"

    def __init__(self, max_keypoints: int = 8000, ratio: float = 0.8, cross_check: bool = False) -> None:
        if not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        if max_keypoints is not None and max_keypoints < 0:
            raise ValueError(f"max_keypoints must be >= 0 (0 or None: no limit), got {max_keypoints}")
        self.max_keypoints = max_keypoints
        self.ratio = ratio
        self.cross_check = cross_check
        # OpenCV keeps the strongest nfeatures responses; 0 means keep all.
        self._sift = cv2.SIFT_create(nfeatures=max_keypoints or 0)

    def config(self) -> dict:
        return {
            "matcher": self.name,
            "max_keypoints": self.max_keypoints,
            "ratio": self.ratio,
            "cross_check": self.cross_check,
        }

    def features(self, image: np.ndarray) -> Features:
        points, descriptors = self._detect(image)
        return Features(points=points, descriptors=descriptors)

    def match_features(self, features0: Features, features1: Features) -> Matches:
        points0, descriptors0 = features0["points"], features0["descriptors"]
        points1, descriptors1 = features1["points"], features1["descriptors"]
        info = {"n_keypoints0": len(points0), "n_keypoints1": len(points1)}
        # The ratio test needs a second neighbour in image 1; cross-checking needs one in image 0.
        if len(points0) < 2 or len(points1) < 2:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info=info)

        matcher = cv2.BFMatcher(cv2.NORM_L2)
        index0, index1, scores = [], [], []
        for first, second in matcher.knnMatch(descriptors0, descriptors1, k=2):
            # Strict inequality also rejects d1 = d2 = 0 (duplicate descriptors).
            if first.distance < self.ratio * second.distance:
                index0.append(first.queryIdx)
                index1.append(first.trainIdx)
                scores.append(1.0 - first.distance / second.distance)
        index0, index1, scores = np.array(index0, int), np.array(index1, int), np.array(scores)

        if self.cross_check and len(index0):
            backward = matcher.match(descriptors1, descriptors0)  # nearest of each point of image 1
            nearest_in_0 = np.array([m.trainIdx for m in backward])
            mutual = nearest_in_0[index1] == index0
            index0, index1, scores = index0[mutual], index1[mutual], scores[mutual]

        return Matches(points0[index0], points1[index1], scores, info=info)

    def _detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        keypoints, descriptors = self._sift.detectAndCompute(gray, None)
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(-1, 2) - UPSCALE_OFFSET_PX
        return points, descriptors
