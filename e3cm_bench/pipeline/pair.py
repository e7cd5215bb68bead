"""One pair through a matcher: the images as the matcher gets them (upright, resized), what
it returns checked, the keypoints brought back to the stored images' pixels."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.cost import measured
from e3cm_bench.ground.devices import is_out_of_memory
from e3cm_bench.ground.images import load_image, resize_max_side, to_original_pixels
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.guards import PairTimeout, StoppableWorker, WorkerDied, no_exit, pair_time_limit
from e3cm_bench.ground.matches import Matches, MatchesError, check_in_image
from e3cm_bench.method.spec import MethodSpec

# What match_pair adds to a result's info and the cache keeps next to each pair's matches.
PAIR_ATTRS = ("size0", "size1", "match_size0", "match_size1", "match_seconds")
# The cost of the pair beside its time (ground/cost.py): the matching process's peak resident
# memory during the pair, whether that peak was the pair's own, and on CUDA the allocator's peak;
# and the part of it the run's feature cache held when the pair was matched (pipeline/stage.py).
COST_ATTRS = ("match_peak_mb", "match_peak_own", "match_gpu_peak_mb", "match_cache_mb")


@dataclass(frozen=True)
class TimeLimit:
    """--pair-timeout for one pair: the seconds the matcher may take (None: no limit) and the
    worker, a StoppableWorker made by `match_worker(matcher)`, whose child process runs the
    matcher and is killed when they pass; without a worker the matcher runs in this process
    under an alarm (matchers/guards.py pair_time_limit)."""

    seconds: float | None = None
    worker: StoppableWorker | None = None


NO_TIME_LIMIT = TimeLimit()


def match_pair(
    matcher: Matcher, image0: str | Path | np.ndarray, image1: str | Path | np.ndarray,
    max_side: int | None = None, seed: int = 0, rotations: tuple[int, int] = (0, 0),
    resize: str = "shrink", limit: TimeLimit = NO_TIME_LIMIT,
) -> Matches:
    """Match two images (paths or H x W x 3 RGB uint8 arrays); keypoints in original pixels.

    rotations: quarter turns (np.rot90, counter-clockwise) that make each image upright, as
    a YFCC/ScanNet pair list's rot0/rot1 give them; the images are matched upright (CNN
    features are not rotation invariant) and the keypoints mapped back to the stored images.
    The images are resized by their longer side to `max_side` (None: full size; `resize`:
    how, images.RESIZE_MODES, by default shrunk to at most max_side), matched, and the
    keypoints mapped back. OpenCV's RNG is seeded with `seed` first, so
    matchers with a RANSAC inside give the same matches every time. ``info`` holds the
    matcher's diagnostics plus size0/size1 (original w, h), match_size0/1 and match_seconds.
    limit: --pair-timeout (TimeLimit): with its worker the matcher runs in the worker's child
    process, killed when the seconds pass; else in this process.
    """
    image0 = load_image(image0) if not isinstance(image0, np.ndarray) else image0
    image1 = load_image(image1) if not isinstance(image1, np.ndarray) else image1
    small0, scale0 = matcher_input(image0, rotations[0], max_side, resize)
    small1, scale1 = matcher_input(image1, rotations[1], max_side, resize)
    t = time.perf_counter()
    if limit.worker is not None:
        m = stoppable_match(limit.worker, matcher, small0, small1, seed, limit.seconds)
    else:
        cv2.setRNGSeed(int(seed))
        m = checked_match(matcher, small0, small1, limit.seconds)
    info = {
        **m.info,
        "size0": (image0.shape[1], image0.shape[0]),
        "size1": (image1.shape[1], image1.shape[0]),
        "match_size0": (small0.shape[1], small0.shape[0]),
        "match_size1": (small1.shape[1], small1.shape[0]),
        "match_seconds": time.perf_counter() - t,
    }
    if any(rotations):
        info["rotations"] = tuple(int(r) for r in rotations)
    keypoints0 = unrotate_points(to_original_pixels(m.keypoints0, scale0), rotations[0], info["size0"])
    keypoints1 = unrotate_points(to_original_pixels(m.keypoints1, scale1), rotations[1], info["size1"])
    return Matches(keypoints0, keypoints1, m.scores, info)


def matcher_input(image: np.ndarray, quarter_turns: int, max_side: int | None, resize: str) -> tuple[np.ndarray, float]:
    """An image as match_pair hands it to the matcher (upright, resized by its longer side),
    and the scale of that resize."""
    return resize_max_side(np.ascontiguousarray(np.rot90(image, quarter_turns)), max_side, resize)


class MatcherError(ValueError):
    """A matcher that raised, or returned something that is not sound matches."""


def checked_match(matcher: Matcher, image0: np.ndarray, image1: np.ndarray, time_limit: float | None = None) -> Matches:
    """matcher.match, with what it returns checked: a Matches of N x 2 keypoints and N scores,
    all finite, inside the images (unless the matcher says its points may leave them). A
    matcher that raises or returns anything else gives a MatcherError naming it; running out
    of memory is left as it is (the runner says what to do about it). A matcher that calls
    sys.exit, or takes more than `time_limit` seconds (--pair-timeout), fails the same way
    (matchers/guards.py)."""
    name = getattr(matcher, "name", type(matcher).__name__)
    try:
        with no_exit("match()"), pair_time_limit(time_limit, f"matcher {name}"), measured() as cost:
            m = matcher.match(image0, image1)
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as error:  # noqa: BLE001 - whatever a plugin raises ends in one line
        if is_out_of_memory(error):
            raise
        raise MatcherError(f"matcher {name} raised {type(error).__name__}: {error}") from error
    if not isinstance(m, Matches):
        raise MatcherError(f"matcher {name} returned {type(m).__name__}, expected e3cm_bench.Matches")
    most = max(image0.shape[0] * image0.shape[1], image1.shape[0] * image1.shape[1])
    if len(m) > most:  # 10^7 matches of two 1 MP images would be 160 MB a pair in the cache
        raise MatcherError(f"matcher {name} returned {len(m):,} matches, more than the {most:,} pixels of the larger "
                           "image (at most one match per pixel)")
    try:
        m = Matches(m.keypoints0, m.keypoints1, m.scores, m.info)  # shapes and lengths, again: fields may be reassigned
        check_in_image(m, (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0]),
                       bounded=getattr(matcher, "keypoints_in_image", True))
    except MatchesError as error:
        raise MatcherError(f"matcher {name} returned bad matches: {error}") from None
    m.info.update(cost.attrs())
    return m


def match_worker(matcher: Matcher) -> StoppableWorker:
    """A child process that runs `matcher` (forked when first used: it holds the matcher as
    built here) and can be killed with all it started (matchers/guards.py)."""
    name = getattr(matcher, "name", type(matcher).__name__)
    return StoppableWorker(lambda small0, small1, seed: _seeded_match(matcher, small0, small1, seed), f"matcher {name}",
                           errors=(MatcherError,))


def _seeded_match(matcher: Matcher, image0: np.ndarray, image1: np.ndarray, seed: int) -> Matches:
    # In the child: its OpenCV RNG is its own, so the seed is set there, as match_pair does here.
    cv2.setRNGSeed(int(seed))
    return checked_match(matcher, image0, image1)


def stoppable_match(worker: StoppableWorker, matcher: Matcher, image0: np.ndarray, image1: np.ndarray, seed: int,
                    time_limit: float | None) -> Matches:
    """checked_match in the worker's child, bounded by time_limit: a child without an answer
    by then is killed (with whatever it forked) and the pair fails as a MatcherError."""
    name = getattr(matcher, "name", type(matcher).__name__)
    try:
        m = worker.call((image0, image1, int(seed)), time_limit, f"matcher {name}")
    except (PairTimeout, WorkerDied) as error:
        raise MatcherError(f"matcher {name} raised {type(error).__name__}: {error}") from None
    if not isinstance(m, Matches):  # checked in the child; what comes back is checked for its kind
        raise MatcherError(f"matcher {name} returned {type(m).__name__}, expected e3cm_bench.Matches")
    return m


def unrotate_points(points: np.ndarray, quarter_turns: int, stored_size: tuple[int, int]) -> np.ndarray:
    """Points of np.rot90(image, k) -> points of the stored image (w, h), pixel-centre convention.

    One counter-clockwise turn sends stored pixel (x, y) to (y, w - 1 - x); undone one turn
    at a time.
    """
    points = np.asarray(points, dtype=np.float64).copy()
    w, h = stored_size
    for turn in range(quarter_turns % 4, 0, -1):
        # The image rotated (turn - 1) times has width w or h; its turn-th rotation is undone.
        width = w if (turn - 1) % 2 == 0 else h
        x, y = points[:, 0].copy(), points[:, 1].copy()
        points[:, 0], points[:, 1] = width - 1 - y, x
    return points.astype(np.float32)


def pair_rotations(pair: Pair, method: MethodSpec) -> tuple[int, int]:
    """The quarter turns that make the pair upright (`Pair.rotations`, from its list), unless the method
    matches images as stored."""
    if not method.upright:
        return (0, 0)
    return pair.rotations

