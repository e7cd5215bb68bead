"""COLMAP's own SIFT and matching (pycolmap), as a matcher: the reference row of the multi-view
tables (issue 69). With ``sfm --verification colmap`` a run of it is COLMAP's pipeline end to
end (its extraction, its exhaustive matcher's pairs, its verification, then the benchmark's
mapper and metrics), so that a table shows the toolkit's SIFT (OpenCV) beside COLMAP's.

Extraction and matching are pycolmap's in-memory ones with COLMAP's defaults
(FeatureExtractionOptions: up to 8192 SIFT features, DSP off, L1-root normalisation;
FeatureMatchingOptions: ratio 0.8, max distance 0.7, cross check on), on the CPU. COLMAP's
keypoints are in its corner convention (the first pixel's centre at 0.5): they are moved into
ours here. The images come at the run's --max-side, as every matcher's do; --max-side 0 gives
COLMAP's full resolution (its command line's default cap is 3200 px)."""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from e3cm_bench.matchers.base import Features, Matcher, Matches

KEEP_IMAGES = 8  # extractions kept: a pair graph visits each image in several pairs
# COLMAP's first pixel's centre (its corner convention, interchange/pixels.py); ours is at 0
COLMAP_FIRST_CENTRE = 0.5


@dataclass(frozen=True)
class ColmapSiftSettings:
    """max_keypoints: COLMAP's SiftExtractionOptions.max_num_features; ratio, max_distance and
    cross_check: its SiftMatchingOptions."""

    max_keypoints: int = 8192
    ratio: float = 0.8
    max_distance: float = 0.7
    cross_check: bool = True

    def __post_init__(self) -> None:
        if (
            not isinstance(self.max_keypoints, int)
            or isinstance(self.max_keypoints, bool)
            or not 1 <= self.max_keypoints <= 10**6
        ):
            raise ValueError(f"max_keypoints must be a whole number from 1 to 1000000, got {self.max_keypoints!r}")
        for name in ("ratio", "max_distance"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {value!r}")
        if not isinstance(self.cross_check, bool):
            raise ValueError(f"cross_check must be true or false, got {self.cross_check!r}")


class ColmapSiftMatcher(Matcher):
    """pycolmap's SIFT extractor and brute-force matcher on the grayscale images."""

    name = "colmap-sift"

    def __init__(self, settings: ColmapSiftSettings = ColmapSiftSettings()) -> None:
        from e3cm_bench.ground.pycolmap import pycolmap_module

        pycolmap = self.pycolmap = pycolmap_module()
        self.settings = settings
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = settings.max_keypoints
        extraction.num_threads = 1  # the run's workers are the parallelism
        matching = pycolmap.FeatureMatchingOptions()
        matching.sift.max_ratio, matching.sift.max_distance = settings.ratio, settings.max_distance
        matching.sift.cross_check = settings.cross_check
        matching.num_threads = 1
        self._extractor = pycolmap.FeatureExtractor.create(extraction, pycolmap.Device.cpu)
        self._matcher = pycolmap.FeatureMatcher.create(matching, pycolmap.Device.cpu)
        self._seen: OrderedDict = OrderedDict()

    def config(self) -> dict:
        return {"matcher": self.name, "max_keypoints": self.settings.max_keypoints, "ratio": self.settings.ratio,
                "max_distance": self.settings.max_distance, "cross_check": self.settings.cross_check,
                "pycolmap": self.pycolmap.__version__}

    def features(self, image: np.ndarray) -> Features:
        """COLMAP's SIFT of the grey image: keypoints in our convention and the uint8
        descriptors (COLMAP's matcher reads keypoints only for guided matching, which is off)."""
        import cv2

        gray = np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image, np.uint8)
        keypoints, descriptors = self._extractor.extract_from_uint8_array(gray)
        points = np.asarray([[k.x, k.y] for k in keypoints], np.float64).reshape(-1, 2)
        return Features(points=(points - COLMAP_FIRST_CENTRE).astype(np.float32),
                        descriptors=np.asarray(descriptors.data, np.uint8).reshape(len(points), -1))

    def _remembered(self, image: np.ndarray) -> Features:
        # match() pair by pair (--no-feature-reuse, the API): the last few images' features kept
        key = (image.shape, hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest())
        if key not in self._seen:
            self._seen[key] = self.features(image)
            while len(self._seen) > KEEP_IMAGES:
                self._seen.popitem(last=False)
        return self._seen[key]

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        return self.match_features(self._remembered(image0), self._remembered(image1))

    def match_features(self, features0: Features, features1: Features) -> Matches:
        points0, points1 = features0["points"], features1["points"]
        info = {"n_keypoints0": len(points0), "n_keypoints1": len(points1)}
        if len(points0) == 0 or len(points1) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info=info)
        sift, none = self.pycolmap.FeatureExtractorType.SIFT, self.pycolmap.FeatureKeypoints()
        descriptors0 = self.pycolmap.FeatureDescriptors(sift, features0["descriptors"])
        descriptors1 = self.pycolmap.FeatureDescriptors(sift, features1["descriptors"])
        index = np.asarray(self._matcher.match(none, descriptors0, none, descriptors1), np.int64).reshape(-1, 2)
        # COLMAP's matcher gives no score: every match 1 (its ratio test has passed them all)
        return Matches(points0[index[:, 0]], points1[index[:, 1]], np.ones(len(index)), info=info)
