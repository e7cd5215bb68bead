"""One keypoint list per image out of a run's pairwise matches, so that a multi-view tool can
chain them into tracks.

A run stores each pair's matches as coordinates. COLMAP's mapper (and hloc, which feeds it)
builds a track from keypoint *indices*: a point seen in images A, B and C becomes one track only
if the keypoint of B matched to A is the same index as the keypoint of B matched to C. Writing
each pair's keypoints as its own block gives every track exactly two views, and the mapper
reconstructs nothing; so the keypoints of an image are merged across its pairs here:

- exact duplicates always (the same float coordinates: what a detector-based matcher gives,
  since every pair of an image sees the same detections);
- with ``merge_px > 0`` also locations within that radius, for dense and semi-dense matchers
  whose point for one feature moves by a fraction of a pixel from pair to pair. The merge is
  greedy in first-seen order: the first occurrence of a location is its representative and
  keeps its coordinates; a later location joins the earliest representative within the radius
  (Euclidean, inclusive), else it becomes a new one. A chain of points each within the radius
  of the next is therefore not merged into one, which keeps a merged point within ``merge_px``
  of every location it stands for.

- with ``cell`` (hloc's dense quantization, as ``--merge quantize`` presets it: cell 4 px, max
  error 4 px) every location falls in a square grid cell of that size; the first location seen
  in a cell represents it, and a later one in the same cell joins it when within ``max_error``
  of it, else stays its own keypoint (merged only with its exact repeats). The radius merge is
  not applied then.

The keypoints of an image are listed in the order their representatives are first seen, pairs
in the run's order and within a pair in match order, so the lists and the index arrays are a
pure function of the run and the radius.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np


def _representatives(points: np.ndarray, merge_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(index of each point's representative in the kept list, kept points' positions in
    ``points``), kept in first-seen order."""
    n = len(points)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = np.ravel(inverse)
    order = np.argsort(first, kind="stable")  # distinct locations in first-seen order
    rank = np.empty(len(first), np.int64)
    rank[order] = np.arange(len(first))
    distinct_first = first[order]  # position in `points` of each distinct location
    if merge_px <= 0 or len(distinct_first) < 2:
        return rank[inverse], distinct_first
    from scipy.spatial import cKDTree  # only the radius merge needs it

    locations = points[distinct_first]
    neighbours = cKDTree(locations).query_ball_point(locations, r=float(merge_px))
    leader = np.full(len(locations), -1, np.int64)
    kept: list[int] = []
    for i in range(len(locations)):  # first-seen order: an earlier location leads
        if leader[i] >= 0:
            continue
        leader[i] = len(kept)
        kept.append(i)
        for j in neighbours[i]:
            if leader[j] < 0:
                leader[j] = leader[i]
    return leader[rank[inverse]], distinct_first[np.asarray(kept, np.int64)]


def _quantized(points: np.ndarray, cell: float, max_error: float) -> tuple[np.ndarray, np.ndarray]:
    """_representatives' result for the grid merge (module docstring): per distinct location,
    in first-seen order, the first location of its cell if within max_error, else itself."""
    index, kept = _representatives(points, 0.0)
    locations = points[kept]
    cells = np.floor(locations / float(cell)).astype(np.int64)
    _, first_in_cell = np.unique(cells, axis=0, return_index=True)
    _, cell_of = np.unique(cells, axis=0, return_inverse=True)
    leader_of_cell = first_in_cell[np.ravel(cell_of)]  # distinct-location index of its cell's first
    near = np.linalg.norm(locations - locations[leader_of_cell], axis=1) <= max_error
    leader = np.where(near, leader_of_cell, np.arange(len(locations)))
    # renumber the leaders in first-seen order (a leader is always first of its own group)
    leaders = np.unique(leader)
    rank = np.full(len(locations), -1, np.int64)
    rank[leaders] = np.arange(len(leaders))
    return rank[leader][index], kept[leaders]


def merge_keypoints(items: Iterable[tuple[str, str, np.ndarray, np.ndarray]], merge_px: float = 0.0,
                    cell: float | None = None, max_error: float | None = None
                    ) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """Per image one keypoint list, per pair its matches as indices into those lists.

    ``items``: (image name 0, image name 1, keypoints0 (N, 2), keypoints1 (N, 2)) per pair, in
    the run's order (row i of keypoints0 matched to row i of keypoints1). Returns
    ({image name: (K, 2) float64 keypoints}, [per pair an (N, 2) int64 array of (index in image
    0's list, index in image 1's list)]), the matches in each pair's own order. With
    ``merge_px == 0`` every returned keypoint equals, bit for bit, the coordinates it replaces.
    """
    if not merge_px >= 0:  # also refuses NaN
        raise ValueError(f"merge_px must be a radius of 0 or more pixels, got {merge_px!r}")
    items = list(items)
    blocks: dict[str, list[np.ndarray]] = {}
    where: list[tuple[tuple[str, int, int], ...]] = []  # per pair, per side: (image, start, stop)
    for name0, name1, k0, k1 in items:
        k0, k1 = (np.asarray(k, np.float64).reshape(-1, 2) for k in (k0, k1))
        if len(k0) != len(k1):
            raise ValueError(f"pair {name0} - {name1}: {len(k0)} keypoints in the first image, {len(k1)} in the second")
        sides = []
        for name, points in ((name0, k0), (name1, k1)):
            listed = blocks.setdefault(name, [])
            start = sum(len(b) for b in listed)
            listed.append(points)
            sides.append((name, start, start + len(points)))
        where.append(tuple(sides))
    keypoints: dict[str, np.ndarray] = {}
    index: dict[str, np.ndarray] = {}
    for name, listed in blocks.items():
        points = np.concatenate(listed) if listed else np.zeros((0, 2))
        index[name], kept = (_quantized(points, cell, cell if max_error is None else max_error) if cell
                             else _representatives(points, merge_px))
        keypoints[name] = points[kept]
    pairs = [np.stack([index[n0][a0:b0], index[n1][a1:b1]], axis=1).astype(np.int64)
             for (n0, a0, b0), (n1, a1, b1) in where]
    return keypoints, pairs


def merge_displacement(items: Sequence[tuple[str, str, np.ndarray, np.ndarray]], keypoints: dict[str, np.ndarray],
                       pairs: Sequence[np.ndarray]) -> float:
    """Mean distance (px) between each matched location and the keypoint the merge put in its
    place, over both sides of every match: what the merge moved the matches by (0 when exact)."""
    moved, count = 0.0, 0
    for (name0, name1, k0, k1), index in zip(items, pairs):
        for name, points, side in ((name0, k0, 0), (name1, k1, 1)):
            points = np.asarray(points, np.float64).reshape(-1, 2)
            if len(points):
                moved += float(np.linalg.norm(keypoints[name][index[:, side]] - points, axis=1).sum())
                count += len(points)
    return moved / count if count else float("nan")


def repeat_share(items: Sequence[tuple[str, str, np.ndarray, np.ndarray]], radius: float) -> float:
    """Share of the matched locations of an image that another pair of the same image also
    matched within `radius` px (0: exactly), over every image: how much the pairs' keypoints
    can chain into tracks before any merge."""
    from scipy.spatial import cKDTree

    blocks: dict[str, list[np.ndarray]] = {}
    for name0, name1, k0, k1 in items:
        for name, points in ((name0, k0), (name1, k1)):
            blocks.setdefault(name, []).append(np.unique(np.asarray(points, np.float64).reshape(-1, 2), axis=0))
    repeated, total = 0, 0
    for listed in blocks.values():
        total += sum(len(b) for b in listed)
        for b, points in enumerate(listed):
            others = [o for k, o in enumerate(listed) if k != b and len(o)]
            if not others or not len(points):
                continue
            # the nearest location of the image's other pairs, within the radius (inclusive)
            distance, _ = cKDTree(np.concatenate(others)).query(points, k=1)
            repeated += int(np.count_nonzero(distance <= max(float(radius), 0.0)))
    return repeated / total if total else float("nan")


def track_lengths(
    n_keypoints: dict[str, int], names: Sequence[tuple[str, str]], pairs: Sequence[np.ndarray]
) -> np.ndarray:
    """Number of images in each connected track (the connected components of the keypoints
    joined by the matches), for tracks of two images or more: a figure to say what a merge did."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    offsets, total = {}, 0
    for name, count in n_keypoints.items():
        offsets[name] = total
        total += int(count)
    ends = [np.asarray(m, np.int64).reshape(-1, 2) + [offsets[n0], offsets[n1]] for (n0, n1), m in zip(names, pairs)]
    ends = np.concatenate(ends) if ends else np.zeros((0, 2), np.int64)
    graph = coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(total, total))
    _, roots = connected_components(graph, directed=False)
    image_of = np.repeat(np.arange(len(offsets)), [int(c) for c in n_keypoints.values()])
    seen = np.unique(np.stack([roots, image_of], axis=1), axis=0)
    _, counts = np.unique(seen[:, 0], return_counts=True)
    return counts[counts >= 2]
