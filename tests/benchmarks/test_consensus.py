"""The ground-truth-free score (sfm/consensus.py) on poses whose truth is known: a matcher's error is
its distance to the other matchers' medoid, never to its own pose; a wrong minority does not move
the reference; noisier matchers score lower, in order; a missing pose is a failure."""

from __future__ import annotations

import numpy as np
import pytest

from e3cm_bench.sfm.consensus import BETTER, RelativePose, consensus_errors, pose_distance, rank, robust_mean, score
from e3cm_bench.stats.paired import NO_DIFFERENCE


def rotation(axis, degrees):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def truth(n, rng):
    return [RelativePose(rotation(rng.normal(size=3), rng.uniform(2, 20)), rng.normal(size=3)) for _ in range(n)]


def noisy(pose, degrees, rng):
    turn = rotation(rng.normal(size=3), rng.normal(0, degrees))
    return RelativePose(turn @ pose.R, rotation(rng.normal(size=3), rng.normal(0, degrees)) @ pose.t)


def test_the_distance_is_the_pose_error_and_the_median_ignores_a_wrong_minority():
    rng = np.random.default_rng(0)
    good = truth(1, rng)[0]
    far = RelativePose(rotation([0, 0, 1], 40) @ good.R, -good.t)  # the sign of t is unobservable: 0 degrees
    assert pose_distance(good, far) == pytest.approx(40.0, abs=1e-6)
    near = [noisy(good, 0.3, rng) for _ in range(4)]
    assert pose_distance(robust_mean([far, *near]), good) < 0.5
    assert pose_distance(robust_mean([far]), far) == 0.0


def test_noisier_matchers_score_lower_in_order_and_the_verdicts_read_the_interval():
    rng = np.random.default_rng(1)
    poses = truth(60, rng)
    ladder = {"exact": 0.05, "1deg": 1.0, "3deg": 3.0, "8deg": 8.0}
    given = {name: [noisy(p, sd, rng) for p in poses] for name, sd in ladder.items()}
    errors = consensus_errors(given)
    rows = rank(errors)
    assert [r["method"] for r in rows] == list(ladder)
    assert all(r["score_lo"] <= r["score"] <= r["score_hi"] for r in rows)
    assert rows[0]["vs_next"] in (BETTER, NO_DIFFERENCE) and rows[-1]["vs_next"] == ""
    assert rows[1]["vs_next"] == BETTER and rows[1]["diff_next_lo"] > 0  # 1 vs 3 degrees on 60 pairs


def test_a_missing_pose_is_a_failure_and_a_pair_nobody_else_placed_tells_nothing():
    rng = np.random.default_rng(2)
    poses = truth(3, rng)
    given = {"a": [poses[0], None, poses[2]], "b": [poses[0], poses[1], None], "c": [poses[0], poses[1], None]}
    errors = consensus_errors(given)
    assert errors["a"][1] == np.inf  # b and c placed it: a's failure counts
    assert np.isnan(errors["a"][2]) and errors["b"][2] == errors["c"][2] == np.inf  # only a placed it
    assert score(np.array([0.0, np.nan, np.inf])) == pytest.approx(50.0)


def test_a_matcher_never_votes_for_itself():
    """One matcher far from three agreeing others: its error is its distance to them, and theirs are
    small although its pose is among those their references are made of."""
    rng = np.random.default_rng(3)
    poses = truth(5, rng)
    wrong = [RelativePose(rotation([1, 0, 0], 30) @ p.R, p.t) for p in poses]
    errors = consensus_errors({"x": poses, "y": [noisy(p, 0.1, rng) for p in poses],
                               "z": [noisy(p, 0.1, rng) for p in poses], "wrong": wrong})
    assert (errors["wrong"] > 25).all() and (errors["x"] < 2).all()
    with pytest.raises(ValueError, match="same pairs"):
        consensus_errors({"a": poses, "b": poses[:2]})


def test_a_planar_sets_homographies_are_judged_by_their_corners():
    """Planar: the corners a homography maps image 0's to, their median, the corner distance; a
    matcher whose H is off by 5 px scores below two within 1 px, judged by the other two."""
    from e3cm_bench.sfm.consensus import Planar

    rng = np.random.default_rng(4)
    truths = [np.array([[1, 0.05 * rng.normal(), 20 * rng.normal()], [0.05 * rng.normal(), 1, 10], [0, 0, 1]])
              for _ in range(20)]
    given = {}
    for name, sd in (("good", 0.3), ("fine", 0.5), ("off", 5.0)):
        given[name] = [Planar.corners(H, 640, 480) + rng.normal(0, sd, (4, 2)) for H in truths]
    planar = Planar()
    errors = consensus_errors(given, planar.reference, planar.distance)
    # about 6 px off: some credit under the AUC up to 10 px, below the two within 1 px (two
    # matchers: half of each one's reference is the one 6 px off, so theirs are some 3 px)
    assert planar.score(errors["off"]) < 50 < planar.score(errors["fine"]) <= 100
    # the AUC up to 10 px: the recall 1/3 from 1 px, 2/3 from 4 px (linear between), the inf a miss
    assert planar.score(np.array([1.0, 4.0, np.inf, np.nan])) == pytest.approx(100 * (1 / 6 + 1.5 + 4) / 10)


def test_the_planar_score_orders_homographies_a_share_within_3_px_tied():
    """Two matchers 4 and 7 px off beside three close ones: the share within 3 px gives both 0 (the
    HPatches ladder's tie between its 2 and 4 px rungs), the AUC up to 10 px orders them, and a
    matcher 12 px off, past the threshold, scores 0."""
    from e3cm_bench.sfm.consensus import Planar

    rng = np.random.default_rng(5)
    truths = [np.array([[1, 0.05 * rng.normal(), 20 * rng.normal()], [0.05 * rng.normal(), 1, 10], [0, 0, 1]])
              for _ in range(20)]
    # every corner moved by `offset` (px), each off matcher in its own direction, so that the
    # three close ones hold every reference (a median, whatever the off ones say)
    offsets = {"good": (0, 0), "fine": (0, 0), "close": (0, 0), "four": (4, 0), "seven": (0, 7), "twelve": (-12, 0)}
    given = {name: [Planar.corners(H, 640, 480) + np.array(offset) + rng.normal(0, 0.1, (4, 2)) for H in truths]
             for name, offset in offsets.items()}
    planar = Planar()
    errors = consensus_errors(given, planar.reference, planar.distance)
    assert all((errors[name] > 3).all() for name in ("four", "seven"))  # the old score's 0 for both
    assert planar.score(errors["fine"]) > planar.score(errors["four"]) > planar.score(errors["seven"]) + 20
    assert planar.score(errors["seven"]) > 0 == planar.score(errors["twelve"])
