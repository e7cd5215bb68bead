"""A two-stage matcher run from the feature cache: each image's `features` computed once per
run, every pair matched from what the cache holds (matchers/base.py `splits`).

The match stage wraps each two-stage matcher in `ReusedFeatures` (pipeline/stage.py), which
speaks the cache's protocol as a deep matcher does (uses_feature_cache, feature_identity,
share_features_of, image_key, prefetch): the same budget, Belady order, spill to disk and
release after an image's last pair. Everything else is the matcher's own (name, config,
settings, keypoints_in_image), so that the run records it as it is.
"""

from __future__ import annotations

import json

import numpy as np

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers.base import Features, splits
from e3cm_bench.matchers.feature_cache import FeatureCache
from e3cm_bench.matchers.spill import SpillStore


def matcher_identity(matcher) -> str:
    """Everything a two-stage matcher's features depend on besides the image: its class, its
    recorded settings (config(), and a plugin's settings()) and its device."""
    settings = getattr(matcher, "settings", None)
    own = settings() if callable(settings) else None
    config = matcher.config() if callable(getattr(matcher, "config", None)) else None
    cls = type(matcher)
    return json.dumps({"class": f"{cls.__module__}.{cls.__qualname__}", "config": config, "settings": own,
                       "device": str(getattr(matcher, "device", "cpu"))}, sort_keys=True, default=repr)


class ReusedFeatures:
    """`matcher` (two-stage) with its per-image features kept in a FeatureCache for the pairs
    that share an image. Without a cache (budget 0) it is the matcher itself: match()."""

    uses_feature_cache = True

    def __init__(self, matcher) -> None:
        if not splits(matcher):
            raise ValueError(f"{getattr(matcher, 'name', type(matcher).__name__)} is not a two-stage matcher")
        self.matcher = matcher
        self.feature_cache: FeatureCache | None = None
        self._identity = matcher_identity(matcher)

    def __getattr__(self, name: str):  # the matcher's own name, config, settings, keypoints_in_image, ...
        return getattr(self.__dict__["matcher"], name)

    def reuse_features(self, max_mb: float, spill: SpillStore | None = None) -> None:
        self.feature_cache = FeatureCache(max_mb, spill) if max_mb > 0 else None

    def feature_identity(self) -> str:
        return self._identity

    def share_features_of(self, other: ReusedFeatures, max_mb: float, spill: SpillStore | None = None) -> None:
        """Take other's cache (made if it has none): the two then extract each image once between them."""
        if other.feature_identity() != self.feature_identity():
            raise ValueError("matchers with different settings cannot share features")
        if other.feature_cache is None:
            other.reuse_features(max_mb, spill)
        self.feature_cache = other.feature_cache

    def image_key(self, image: np.ndarray) -> str:
        """The cache's key: the image's content and the matcher's identity."""
        return FeatureCache.key(image, self._identity)

    def prefetch(self, images: list, batch: int) -> list[int]:
        return []  # extraction runs image by image, at the image's first pair

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        if self.feature_cache is None:
            return self.matcher.match(image0, image1)
        return self.matcher.match_features(self._features(image0, 0), self._features(image1, 1))

    def _features(self, image: np.ndarray, which: int) -> Features:
        cache = self.feature_cache
        key = self.image_key(image)
        cache.belongs_to(key, which)
        features = cache.get(key, str(getattr(self.matcher, "device", "cpu")))
        if features is None:
            features = self.matcher.features(image)
            cache.put(key, features)
        return features


def reusing(built: list) -> list:
    """Each two-stage matcher of `built` wrapped to take its features from the feature cache."""
    return [ReusedFeatures(matcher) if splits(matcher) else matcher for matcher in built]
