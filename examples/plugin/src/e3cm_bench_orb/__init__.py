"""ORB + mutual nearest neighbour: a complete e3cm-bench matcher plugin.

A plugin is a `MatcherEntry`: a name, one line of description, a settings dataclass (its
defaults are what `e3cm-bench matchers` lists; a bad value raises a one-line ValueError),
and a function building the matcher from the settings. The matcher is written in two stages:
``features(image) -> Features`` per image and ``match_features(features0, features1) ->
Matches`` per pair (a matcher may instead define one method, ``match(image0, image1)``).
Images are H x W x 3 uint8 RGB arrays; keypoints come out in those images' pixels
(pixel-centre convention: the top-left pixel's centre is (0, 0)). The benchmark resizes the
images first and maps the keypoints back itself; it extracts each image once per run and
matches every pair of it from the kept features (``--no-feature-reuse``: pair by pair).

A run records the plugin by its code (the sha256 of this package's .py files: an edit, even
in an editable install, is a new identity) and its settings by ``OrbMatcher.settings()``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from e3cm_bench import Features, Matcher, MatcherEntry, Matches


@dataclass(frozen=True)
class OrbSettings:
    """max_keypoints: ORB's strongest corners kept per image; scale_factor, n_levels: its
    pyramid; fast_threshold: the FAST corner threshold."""

    max_keypoints: int = 5000
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20

    def __post_init__(self) -> None:
        if not isinstance(self.max_keypoints, int) or self.max_keypoints < 1:
            raise ValueError(f"max_keypoints must be a whole number >= 1, got {self.max_keypoints!r}")
        if not 1.0 < float(self.scale_factor) <= 2.0:
            raise ValueError(f"scale_factor must be in (1, 2], got {self.scale_factor!r}")
        if not isinstance(self.n_levels, int) or not 1 <= self.n_levels <= 16:
            raise ValueError(f"n_levels must be a whole number 1..16, got {self.n_levels!r}")


class OrbMatcher(Matcher):
    """ORB on the grey images; a match is a pair of mutual nearest neighbours in Hamming
    distance. Scores: 1 - distance / 256 (higher is better). OpenCV places the corners of
    coarser pyramid levels by scaling alone; they are kept as OpenCV gives them."""

    name = "orb"

    def __init__(self, settings: OrbSettings) -> None:
        self.options = settings
        self._orb = cv2.ORB_create(nfeatures=settings.max_keypoints, scaleFactor=float(settings.scale_factor),
                                   nlevels=settings.n_levels, fastThreshold=settings.fast_threshold)

    def settings(self) -> dict:
        """Every setting its matches depend on, defaults included: what a run's config.yaml
        records under `matcher` (without it, e3cm-bench records the settings dataclass)."""
        return asdict(self.options)

    def features(self, image: np.ndarray) -> Features:
        """One image's corners and descriptors: the benchmark computes them once per image of a
        run and keeps them for the image's other pairs."""
        points, descriptors = self._detect(image)
        return Features(points=points, descriptors=descriptors)

    def match_features(self, features0: Features, features1: Features) -> Matches:
        """One pair's matches from its images' features (read, never changed: they are reused)."""
        points0, descriptors0 = features0["points"], features0["descriptors"]
        points1, descriptors1 = features1["points"], features1["descriptors"]
        info = {"n_keypoints0": len(points0), "n_keypoints1": len(points1)}
        if descriptors0 is None or descriptors1 is None:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info)
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(descriptors0, descriptors1)
        index0 = np.array([m.queryIdx for m in pairs], int)
        index1 = np.array([m.trainIdx for m in pairs], int)
        scores = np.array([1.0 - m.distance / 256.0 for m in pairs])
        return Matches(points0[index0], points1[index1], scores, info)

    def _detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        keypoints, descriptors = self._orb.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
        return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors


ENTRY = MatcherEntry(
    name="orb",
    description="ORB + mutual nearest neighbour (OpenCV): the example plugin",
    build=OrbMatcher,
    settings=OrbSettings,
)
