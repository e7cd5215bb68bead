"""Matches between two images: the one value every matcher returns and the cache stores.

numpy only (no torch), so that the cache, the metrics and the reports import it cheaply.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Matches:
    """Correspondences between two images.

    keypoints0, keypoints1: N x 2 float32, pixels of the images given to the matcher,
    pixel-centre convention (the centre of the top-left pixel is (0, 0)).
    scores: N float32, higher is more confident.
    info: diagnostics (per-level counts, the F used at each level, stage timings).
    """

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Arrays of the right shapes and lengths, or a one-line MatchesError (scores None:
        every match scores 1)."""
        self.keypoints0 = _points(self.keypoints0, "keypoints0")
        self.keypoints1 = _points(self.keypoints1, "keypoints1")
        if len(self.keypoints0) != len(self.keypoints1):
            raise MatchesError(f"keypoints0 has {len(self.keypoints0)} points, keypoints1 {len(self.keypoints1)}")
        if self.scores is None:
            self.scores = np.ones(len(self.keypoints0), np.float32)
        try:
            scores = np.asarray(self.scores, dtype=np.float32)
        except (TypeError, ValueError):
            raise MatchesError(f"scores: not numbers ({type(self.scores).__name__})") from None
        if scores.size != len(self.keypoints0) or scores.ndim > 1 and scores.size != scores.shape[0]:
            raise MatchesError(f"scores has shape {scores.shape}, expected ({len(self.keypoints0)},)")
        self.scores = scores.reshape(-1)
        if not isinstance(self.info, dict):
            raise MatchesError(f"info must be a dict, got {type(self.info).__name__}")

    def __len__(self) -> int:
        return len(self.keypoints0)


class MatchesError(ValueError):
    """Matches that cannot be what they claim: wrong shapes or lengths, NaN, outside the image."""


def _points(values, name: str) -> np.ndarray:
    try:
        points = np.asarray(values, dtype=np.float32)
    except (TypeError, ValueError):
        raise MatchesError(f"{name}: not numbers ({type(values).__name__})") from None
    if points.size == 0:
        return points.reshape(0, 2)
    if points.ndim != 2 or points.shape[1] != 2:
        raise MatchesError(f"{name} has shape {points.shape}, expected N x 2")
    return points


# A keypoint may sit on the image's outer edge: pixel-centre convention, the image spans
# [-0.5, w - 0.5] x [-0.5, h - 0.5]; a hair of slack for float32 rounding.
EDGE_SLACK_PX = 1e-3


def check_in_image(matches: Matches, size0: tuple[int, int], size1: tuple[int, int], bounded: bool = True) -> None:
    """A MatchesError naming the first problem: a keypoint that is not finite, or (bounded)
    outside its image of size (w, h)."""
    for i, (points, (w, h)) in enumerate(((matches.keypoints0, size0), (matches.keypoints1, size1))):
        bad = ~np.isfinite(points).all(axis=1)
        if bad.any():
            raise MatchesError(
                f"keypoints{i}: {int(bad.sum())} point(s) not finite (first: row {int(np.flatnonzero(bad)[0])})"
            )
        if not bounded:
            continue
        lo = -0.5 - EDGE_SLACK_PX
        outside = (points[:, 0] < lo) | (points[:, 1] < lo) | (points[:, 0] > w - 0.5 + EDGE_SLACK_PX) \
            | (points[:, 1] > h - 0.5 + EDGE_SLACK_PX)
        if outside.any():
            x, y = points[np.flatnonzero(outside)[0]]
            raise MatchesError(f"keypoints{i}: {int(outside.sum())} point(s) outside the {w}x{h} image "
                               f"(first: {x:.1f}, {y:.1f})")
    if not np.isfinite(matches.scores).all():
        raise MatchesError("scores: not all finite")


def distinct(matches: Matches) -> tuple[Matches, int]:
    """The matches with each correspondence (x0, y0, x1, y1) kept once, at its first occurrence
    (with that occurrence's score), and how many repeats were dropped.

    The evaluation counts a correspondence once: a matcher returning one correct match 5000
    times has one correct match, not an MMA of 1.0 over 5000. Repeats are common and harmless
    otherwise (SIFT returns a keypoint once per orientation, so about a tenth of SIFT+NN's
    matches repeat another exactly); refusing them would refuse SIFT.
    """
    if len(matches) < 2:
        return matches, 0
    both = np.concatenate([matches.keypoints0, matches.keypoints1], axis=1)
    _, first = np.unique(both, axis=0, return_index=True)
    dropped = len(matches) - len(first)
    if dropped == 0:
        return matches, 0
    keep = np.sort(first)
    info = {**matches.info, "n_duplicates": dropped}
    return Matches(matches.keypoints0[keep], matches.keypoints1[keep], matches.scores[keep], info), dropped
