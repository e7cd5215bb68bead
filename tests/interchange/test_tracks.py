"""One keypoint list per image from pairwise matches: exact repeats always merged, near ones
within a radius merged to the first seen, the matches' order and every coordinate kept."""

from __future__ import annotations

import numpy as np
import pytest

from e3cm_bench.interchange.tracks import merge_keypoints, track_lengths


def test_exact_repeats_across_pairs_become_one_keypoint_and_chain_a_track():
    a = np.array([[10.0, 20.0], [30.5, 40.25]])
    b = np.array([[11.0, 21.0], [31.5, 41.25]])
    c = np.array([[12.0, 22.0], [5.0, 5.0]])
    items = [("A", "B", a, b), ("B", "C", b[::-1], c[::-1])]
    keypoints, pairs = merge_keypoints(items)
    assert [len(keypoints[n]) for n in "ABC"] == [2, 2, 2]  # B's 4 occurrences are 2 locations
    for (n0, n1, k0, k1), index in zip(items, pairs):
        assert np.array_equal(keypoints[n0][index[:, 0]], k0) and np.array_equal(keypoints[n1][index[:, 1]], k1)
    assert pairs[1].tolist() == [[1, 0], [0, 1]]  # the pair's own match order; each list in first-seen order
    lengths = track_lengths({n: len(k) for n, k in keypoints.items()}, [("A", "B"), ("B", "C")], pairs)
    assert sorted(lengths.tolist()) == [3, 3]


def test_without_a_radius_a_point_a_float_step_away_stays_distinct():
    p = np.array([[100.0, 100.0]])
    q = np.nextafter(p, 200.0)
    keypoints, _ = merge_keypoints([("A", "B", p, p), ("A", "C", q, p)])
    assert len(keypoints["A"]) == 2 and len(keypoints["B"]) == 1


def test_a_radius_merges_to_the_first_seen_location_and_does_not_chain():
    first = np.array([[0.0, 0.0]])
    items = [("A", "B", first, first), ("A", "C", np.array([[0.3, 0.0]]), first),
             ("A", "D", np.array([[0.6, 0.0]]), first), ("A", "E", np.array([[1.2, 0.0]]), first)]
    keypoints, pairs = merge_keypoints(items, merge_px=0.5)
    # 0.3 joins 0.0; 0.6 is 0.6 from the first representative: a new one, which 1.2 does not reach
    assert keypoints["A"].tolist() == [[0.0, 0.0], [0.6, 0.0], [1.2, 0.0]]
    assert [int(p[0, 0]) for p in pairs] == [0, 0, 1, 2]
    for (n0, _, k0, _), index in zip(items, pairs):
        assert np.all(np.linalg.norm(keypoints[n0][index[:, 0]] - k0, axis=1) <= 0.5)


@pytest.mark.parametrize("radius", [-1.0, float("nan")])
def test_a_negative_or_nan_radius_is_refused(radius):
    with pytest.raises(ValueError, match="merge_px"):
        merge_keypoints([("A", "B", np.zeros((1, 2)), np.zeros((1, 2)))], radius)
