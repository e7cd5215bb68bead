"""A score of each matcher's reconstruction without ground truth: how well its relative poses agree
with what the OTHER matchers' reconstructions of the same images say. Pure functions of arrays.

Each matcher reconstructed the same folder. For every pair of images that were matched, a matcher's
model gives a relative pose (R, t) when it registered both images in one model (sfm.metrics: the
ground truth's rule), else none. For matcher m and a pair, the reference is the geometric median of
the other matchers' relative poses of that pair (`robust_mean`), and m's error is its distance to
it: the larger of the rotation angle and the folded angle between translation directions, in
degrees (the sfm benchmark's pose error). That error is inf where m has no relative pose (a
failure, as the ground truth counts it), NaN where no other matcher has one (the pair tells
nothing about m). m never votes for itself: a
matcher that keeps wrong matches and still registers every image disagrees with the rest.

The score is the AUC of those errors up to 10 degrees (percent), the sfm benchmark's auc@10 with
the leave-one-out consensus in place of the ground truth, so that where ground truth exists the two
are read on one scale. Its interval resamples the pairs (every matcher with the same draws: the
verdict between neighbours is a paired difference, read as `compare` reads its intervals).

docs/own-images.md says how it was validated against ground truth and where it must not be trusted.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from e3cm_bench.geometry import metrics
from e3cm_bench.geometry.two_view import rotation_angle_deg, translation_angle_deg
from e3cm_bench.stats.bootstrap import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, CONFIDENCE, percentile_interval, \
    resample_indices
from e3cm_bench.stats.paired import NO_DIFFERENCE

SCORE_THRESHOLD = 10.0  # degrees: the sfm benchmark's headline auc@10
BETTER = "better than the next"
WEISZFELD_ITERATIONS = 30


@dataclass(frozen=True)
class RelativePose:
    """Camera 1 relative to camera 0: x1 = R x0 + t (t's length is the model's, its direction counts)."""

    R: np.ndarray
    t: np.ndarray


def pose_distance(a: RelativePose, b: RelativePose) -> float:
    """The larger of the rotation angle between a and b and the folded angle of their translations."""
    return max(rotation_angle_deg(a.R, b.R), translation_angle_deg(a.t, b.t))


def _weiszfeld(points: np.ndarray, iterations: int = WEISZFELD_ITERATIONS) -> np.ndarray:
    """The geometric median of the rows of `points` (Weiszfeld's iteration from their mean)."""
    estimate = points.mean(axis=0)
    for _ in range(iterations):
        distance = np.maximum(np.linalg.norm(points - estimate, axis=1), 1e-12)
        weights = 1.0 / distance
        estimate = (weights[:, None] * points).sum(axis=0) / weights.sum()
    return estimate


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def robust_mean(poses: Sequence[RelativePose]) -> RelativePose:
    """The poses' geometric median: the rotations' in chordal space (the 3x3 matrices as vectors,
    projected back onto SO(3)), the translation directions' on the sphere, each direction's sign
    taken to agree with their mean's (the sign of t is unobservable).

    A median and not a pick: the medoid, a pick, judges the best matcher against the second best
    and the second against the best, so that the two trade places at random; the median of the
    others averages their errors down, so that the better of two matchers, whose reference the
    worse one's errors enter, is still judged against the closer reference (the expected squared
    distance to the others' mean differs by the two variances' difference times 1 - 1/(N-1)^2).
    And a median and not a mean: a minority of wrong poses moves it little."""
    if len(poses) == 1:
        return poses[0]
    R = _nearest_rotation(_weiszfeld(np.stack([np.asarray(p.R, np.float64).ravel() for p in poses])).reshape(3, 3))
    directions = np.stack([np.asarray(p.t, np.float64).ravel() / max(np.linalg.norm(p.t), 1e-12) for p in poses])
    axis = np.linalg.svd(directions, full_matrices=False)[2][0]  # the principal direction, up to sign
    directions *= np.where(directions @ axis < 0, -1.0, 1.0)[:, None]
    t = _weiszfeld(directions)
    return RelativePose(R, t / max(np.linalg.norm(t), 1e-12))


def consensus_errors(poses: Mapping[str, Sequence], reference: Callable[[Sequence], object] | None = None,
                     distance: Callable[[object, object], float] | None = None) -> dict[str, np.ndarray]:
    """Each matcher's error per pair against the reference made of the other matchers' estimates (the
    module's rule): inf where it has none, NaN where no other matcher has one. poses: matcher -> its
    estimate of each pair (None: none), pairs in one order; by default relative poses, judged by
    `robust_mean` and `pose_distance` (a planar set's homographies: `Planar`)."""
    reference, distance = reference or robust_mean, distance or pose_distance
    names = list(poses)
    counts = {len(v) for v in poses.values()}
    if len(counts) > 1:
        raise ValueError(f"every matcher must give a pose (or None) for the same pairs, got {sorted(counts)} pairs")
    n = counts.pop() if counts else 0
    errors = {name: np.full(n, np.nan) for name in names}
    for k in range(n):
        for name in names:
            others = [poses[o][k] for o in names if o != name and poses[o][k] is not None]
            if not others:
                continue
            own = poses[name][k]
            errors[name][k] = float("inf") if own is None else distance(own, reference(others))
    return errors


@dataclass(frozen=True)
class Planar:
    """A planar set's estimates (HPatches): each pair's homography as where it maps image 0's
    corners (4 x 2), the reference their geometric median, the distance the mean corner distance in
    pixels (the homography benchmark's corner error), the score the AUC (percent) of those
    distances up to `threshold` px, the pose score's form with pixels for degrees.

    An AUC and not the share within a cutoff: a share gives every matcher past the cutoff the same
    0, so that matchers 4 and 6 px off tie (the HPatches ladder's two worst rungs did at 3 px); the
    AUC gives each pair credit falling linearly to 0 at `threshold`. 10 px, the widest of the
    usual corner-error AUC thresholds (3, 5, 10 px), so that errors a few px apart still differ."""

    threshold: float = 10.0

    @staticmethod
    def corners(H: np.ndarray, width: int, height: int) -> np.ndarray:
        from e3cm_bench.geometry.two_view import warp_points

        box = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], np.float64)
        return warp_points(np.asarray(H, np.float64), box)

    @staticmethod
    def reference(estimates: Sequence[np.ndarray]) -> np.ndarray:
        return _weiszfeld(np.stack([np.asarray(e, np.float64).ravel() for e in estimates])).reshape(4, 2)

    @staticmethod
    def distance(a: np.ndarray, b: np.ndarray) -> float:
        error = float(np.mean(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1)))
        return error if np.isfinite(error) else float("inf")

    def score(self, errors: np.ndarray) -> float:
        return score(errors, self.threshold)


def score(errors: np.ndarray, threshold: float = SCORE_THRESHOLD) -> float:
    """AUC (percent) of the errors up to `threshold` (degrees; `Planar`'s, px); the NaN pairs (no
    reference) left out, the inf ones (no estimate) counted as misses."""
    errors = np.asarray(errors, np.float64)
    return metrics.pose_auc(errors[~np.isnan(errors)], (threshold,))[0]


@dataclass(frozen=True)
class Ranking:
    """The bootstrap behind a ranking: how many resamples of the pairs, their seed, the confidence."""

    n_samples: int = BOOTSTRAP_SAMPLES
    seed: int = BOOTSTRAP_SEED
    confidence: float = CONFIDENCE


def rank(errors: Mapping[str, np.ndarray], ranking: Ranking | None = None) -> list[dict]:
    """One row per matcher, best first: method, score, score_lo, score_hi (the pairs resampled),
    rank, and the paired verdict against the next row (its difference and interval), `BETTER`
    where the interval of this row's score minus the next's lies above 0, else no difference."""
    ranking = ranking or Ranking()
    names = list(errors)
    n = len(next(iter(errors.values()))) if names else 0
    idx = resample_indices(n, ranking.n_samples, ranking.seed)
    full = {name: score(errors[name]) for name in names}
    drawn = {name: np.array([score(errors[name][row]) for row in idx]) for name in names}
    order = sorted(names, key=lambda name: (-np.nan_to_num(full[name], nan=-np.inf), names.index(name)))
    rows = []
    for position, name in enumerate(order):
        lo, hi = percentile_interval(drawn[name], ranking.confidence)
        row = {"method": name, "score": full[name], "score_lo": lo, "score_hi": hi, "rank": position + 1,
               "vs_next": "", "diff_next": float("nan"), "diff_next_lo": float("nan"), "diff_next_hi": float("nan")}
        if position + 1 < len(order):
            following = order[position + 1]
            d_lo, d_hi = percentile_interval(drawn[name] - drawn[following], ranking.confidence)
            row.update({"diff_next": full[name] - full[following], "diff_next_lo": d_lo, "diff_next_hi": d_hi,
                        "vs_next": BETTER if d_lo > 0 else NO_DIFFERENCE})
        rows.append(row)
    return rows
