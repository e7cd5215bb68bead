"""The two reference implementations' matching, step by step, for rows that claim to be theirs.

`e3cm-release` is the E3CM authors' `match_large_img` / `match_small_img` followed by their
`refinement_pose_ransac`; `dfm` is the DFM release's two-stage `match`. Both differ from the
paper text and from this project's own pipeline (pipeline.py) in ways that change results;
../shared/parity/README.md lists them and tests/matching/test_parity.py proves that these functions
reproduce the releases' outputs on its four pairs. What each step keeps from the release:

- dense matching runs over the whole padded map (padding cells included) and drops the
  outer ring of the padded map; distances are 2 - 2 cos, ratios d1 / (d2 + 1e-8) <= r;
- refinement compares the 2x2 children in the release's order (x, y) + (0,0), (0,1), (1,0),
  (1,1); the B->A ratio is read at the B child with the A child's index (`ratio_at="own"`,
  an evident slip: `"matched"` reads it at the B child actually matched); a parent keeps at
  most its two best children; when fewer than 4 children survive in all, the parents come
  back (at the finer level's even cells);
- the E3CM release then removes repeated A, then repeated B points (first occurrence kept,
  rows sorted), the DFM release does not;
- the E3CM release's cascade: RANSAC F (1 px, 0.99) on all deepest matches, each next level's
  uncascaded list filtered by |x_B^T F x_A| < 0.01 (F as OpenCV returns it, F[2,2] = 1), a
  new RANSAC F on the survivors; nothing passing keeps all; fewer than 8 matches or no F
  returns the unfiltered finest list. Rejections never feed back into refinement. A level
  with fewer than 8 matches is skipped and the F before it filters the next level; 7
  survivors give OpenCV's stacked 7-point solutions, of which the first filters the next
  level (`release_fundamental_solutions`).

Cells are N x 2 int64 (x, y) tensors; point lists are N x 2 float64 arrays in pixels,
(c + 0.5) 2^l - 0.5 at level l (pixel-centre convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.stats.perturb import perturb_correspondences
from e3cm_bench.matching.dense import top2_both_ways
from e3cm_bench.matching.refine import first_of_each

# The release's children: offsets (dx, dy) in this order.
RELEASE_CHILD_OFFSETS = torch.tensor([[0, 0], [0, 1], [1, 0], [1, 1]])
RATIO_AT = ("own", "matched")


def unit_rows(x: torch.Tensor) -> torch.Tensor:
    """Each row divided by its L2 norm, as the releases do (no epsilon)."""
    return x / x.square().sum(1, keepdim=True).sqrt()


def release_dense(map0: torch.Tensor, map1: torch.Tensor, ratio: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mutual NN + symmetric ratio test over two whole (padded) maps C x H x W -> cells0, cells1.

    Matches touching the outer ring of either padded map are dropped. Order: by A's
    row-major index, as the release returns them.
    """
    c, h0, w0 = map0.shape
    _, h1, w1 = map1.shape
    desc0 = unit_rows(map0.reshape(c, -1).T)
    desc1 = unit_rows(map1.reshape(c, -1).T)
    vals0, idx0, vals1, idx1 = top2_both_ways(desc0, desc1)
    dist0, dist1 = 2 - 2 * vals0, 2 - 2 * vals1
    ratio01 = dist0[:, 0] / (dist0[:, 1] + 1e-8)
    ratio10 = dist1[:, 0] / (dist1[:, 1] + 1e-8)
    nn01, nn10 = idx0[:, 0], idx1[:, 0]
    ids = torch.arange(len(desc0), device=desc0.device)
    keep = (nn10[nn01] == ids) & (ratio01 <= ratio) & (ratio10[nn01] <= ratio)
    i0, i1 = ids[keep], nn01[keep]
    cells0 = torch.stack([i0 % w0, i0 // w0], 1)
    cells1 = torch.stack([i1 % w1, i1 // w1], 1)
    on_ring = _on_ring(cells0, w0, h0) | _on_ring(cells1, w1, h1)
    return cells0[~on_ring], cells1[~on_ring]


def _on_ring(cells: torch.Tensor, w: int, h: int) -> torch.Tensor:
    x, y = cells[:, 0], cells[:, 1]
    return (x == 0) | (x == w - 1) | (y == 0) | (y == h - 1)


def release_refine(
    map0: torch.Tensor,
    map1: torch.Tensor,
    cells0: torch.Tensor,
    cells1: torch.Tensor,
    ratio: float,
    ratio_at: str = "own",
    dedup: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One refinement step into the finer maps map0/map1 (C x H x W, padded) -> child cells.

    ratio_at: "own" = the releases' indexing, "matched" = corrected. dedup: the E3CM
    release's removal of repeated points (the DFM release has none).
    """
    n = len(cells0)
    if n == 0:
        return cells0, cells1
    if ratio_at not in RATIO_AT:
        raise ValueError(f"ratio_at must be one of {RATIO_AT}, got {ratio_at!r}")
    offsets = RELEASE_CHILD_OFFSETS.to(cells0.device)
    parents0, parents1 = 2 * cells0, 2 * cells1
    kids0 = parents0[:, None, :] + offsets[None]  # N x 4 x 2
    kids1 = parents1[:, None, :] + offsets[None]
    keep, best_b = _kept_children(_children_similarity(map0, map1, kids0, kids1), ratio, ratio_at)
    keep = keep.to(cells0.device)
    best_b = best_b.to(cells0.device)
    out0 = kids0[keep]
    out1 = (parents1[:, None, :] + offsets[best_b])[keep]
    if len(out0) < 4 and n > len(out0):
        out0, out1 = parents0, parents1
    if dedup:  # the release's torch.unique + np.unique(return_index): first occurrence, rows sorted
        first = first_of_each(out0)
        out0, out1 = out0[first], out1[first]
        first = first_of_each(out1)
        out0, out1 = out0[first], out1[first]
    return out0, out1


def _children_similarity(map0: torch.Tensor, map1: torch.Tensor, kids0: torch.Tensor,
                         kids1: torch.Tensor) -> torch.Tensor:
    """N x 4 (A children) x 4 (B children) cosine similarities of the children (N x 4 x 2
    cells) in the maps normalised whole, on the CPU."""
    norm0 = map0 / map0.square().sum(0, keepdim=True).sqrt()
    norm1 = map1 / map1.square().sum(0, keepdim=True).sqrt()
    # N x 4 (A children) x 4 (B children) similarities, each summed over channels of C x N
    # slices as the releases do: exact ties (saturated regions) then break the same way.
    # (Each child's C x N slice is gathered once, not once per pair of children.)
    sim = torch.zeros(len(kids0), 4, 4, dtype=torch.float32, device=kids0.device)
    a = [norm0[:, kids0[:, i, 1], kids0[:, i, 0]] for i in range(4)]
    b = [norm1[:, kids1[:, j, 1], kids1[:, j, 0]] for j in range(4)]
    for i in range(4):
        for j in range(4):
            sim[:, i, j] = (a[i] * b[j]).sum(0).float()
    return sim.cpu()


def _kept_children(sim: torch.Tensor, ratio: float, ratio_at: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(keep: N x 4, which A children are kept; best_b: N x 4, the B child each matched), from
    their similarities: mutual, past the ratio test, and at most two per parent."""
    n = len(sim)
    sim_ab, nn_ab = sim.topk(2, dim=2)
    dist_ab = 2 - 2 * sim_ab
    ratio_ab = dist_ab[..., 0] / (dist_ab[..., 1] + 1e-8)
    best_b = nn_ab[..., 0]
    sim_ba, nn_ba = sim.transpose(2, 1).topk(2, dim=2)
    dist_ba = 2 - 2 * sim_ba
    ratio_ba = dist_ba[..., 0] / (dist_ba[..., 1] + 1e-8)
    best_a = nn_ba[..., 0]
    if ratio_at == "matched":
        ratio_ba = ratio_ba.gather(1, best_b)
    mutual = best_a.gather(1, best_b) == torch.arange(4)[None]
    keep = (torch.maximum(ratio_ab, ratio_ba) < ratio) & mutual
    # At most two children per parent: the two worst of the four are dropped (failures
    # count as distance 5, above any real one).
    score = dist_ab[..., 0].masked_fill(~keep, 5.0)
    worst = score.topk(2, dim=1).indices
    rows = torch.arange(n)
    keep[rows, worst[:, 0]] = False
    keep[rows, worst[:, 1]] = False
    return keep, best_b


def level_points(cells: torch.Tensor, level: int) -> np.ndarray:
    """Cells of `level` -> pixel coordinates (float64), (c + 0.5) 2^l - 0.5."""
    return (cells.cpu().to(torch.float64).numpy() + 0.5) * 2**level - 0.5


def release_levels(
    maps0: list[torch.Tensor], maps1: list[torch.Tensor], ratio: tuple[float, ...], ratio_at: str = "own",
    dedup: bool = True,
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The E3CM release's `match_large_img` (or `match_small_img` when given 4 maps): dense
    matching at the deepest map with its ratio, then refinement down to level 0 with
    ratio[l]. Returns the cells of every level, deepest first."""
    top = len(maps0) - 1
    cells0, cells1 = release_dense(maps0[top], maps1[top], ratio[top])
    levels0, levels1 = [cells0], [cells1]
    for level in range(top - 1, -1, -1):
        cells0, cells1 = release_refine(maps0[level], maps1[level], cells0, cells1, ratio[level], ratio_at, dedup)
        levels0.append(cells0)
        levels1.append(cells1)
    return levels0, levels1


@dataclass(frozen=True)
class ReleaseCascade:
    """The E3CM release's `refinement_pose_ransac` settings (its eval scripts' values)."""

    residual: float = 0.01  # |x_B^T F x_A| below this survives
    ransac_px: float = 1.0
    confidence: float = 0.99


def release_fundamental_solutions(x0: np.ndarray, x1: np.ndarray, cascade: ReleaseCascade) -> np.ndarray | None:
    """cv2.findFundamentalMat(FM_RANSAC) as the release calls it, its output as OpenCV gives it:
    3 x 3, or 3k x 3 (k = 2, 3) for exactly 7 matches, where OpenCV runs its 7-point algorithm
    alone and stacks every real solution. None where OpenCV finds none (fewer than 7
    matches, or no solution) or refuses the input (the release would stop there; here the
    fallback applies)."""
    x0, x1, _ = perturb_correspondences(x0, x1)  # the identity but in a noise-ensemble draw
    try:
        F, _ = cv2.findFundamentalMat(
            np.ascontiguousarray(x0), np.ascontiguousarray(x1), cv2.FM_RANSAC, cascade.ransac_px, cascade.confidence
        )
    except cv2.error:
        return None
    if F is None or F.ndim != 2 or F.shape[1] != 3 or F.shape[0] < 3 or F.shape[0] % 3:
        return None
    return F


def algebraic_residual(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """x1^T F x0 per match in float64, in the release's order ((x1^T F) x0) and evaluated
    term by term, each product and sum rounded on its own (numpy's elementwise operations,
    no fused multiply-add). With an ill-conditioned F (entries ~1e11 when F[2,2] is
    normalised to 1) the residual is mostly cancellation, so the order decides which
    matches pass: a BLAS matrix product sums in an order (and with FMA) that depends on the
    CPU's kernels (AVX-512 vs AVX2: 281 vs 278 survivors on the parity file's kitti_640 L2),
    while this order gives the reference's survivors on every CPU."""
    x0 = np.asarray(x0, np.float64)
    x1 = np.asarray(x1, np.float64)
    u, v = x1[:, 0], x1[:, 1]
    t = [u * F[0, j] + v * F[1, j] + F[2, j] for j in range(3)]  # (x1^T F)_j, x1 = (u, v, 1)
    return t[0] * x0[:, 0] + t[1] * x0[:, 1] + t[2]


def release_cascade(
    points0: list[np.ndarray], points1: list[np.ndarray], cascade: ReleaseCascade = ReleaseCascade()
) -> dict:
    """The release's cascade over per-level point lists (deepest first) -> the finest level's
    survivors, with each list's survivors, count and F (the 3 x 3 it filters with), the number
    of solutions OpenCV stacked where it gave several, a note per list where the release
    departs from "filter, then fit", and which fallback (if any) decided the result. Keys
    are list indices (0 = deepest)."""
    finest = len(points0) - 1
    out = {"counts": {}, "survivors": {}, "fundamentals": {}, "solutions": {}, "notes": {}, "fallback": None}
    if len(points0[0]) < 8:
        out["fallback"] = "fewer than 8 deepest matches: unfiltered finest level"
        out["notes"][0] = f"{len(points0[0])} matches, fewer than 8: no F"
        out["points0"], out["points1"] = points0[finest], points1[finest]
        return out

    def fit(i: int, x0: np.ndarray, x1: np.ndarray) -> np.ndarray | None:
        stacked = release_fundamental_solutions(x0, x1, cascade)
        # The release's outlier_rejection cuts any F that is not 3 x 3 to its first three
        # rows: of OpenCV's stacked 7-point solutions, the first filters the next list.
        out["fundamentals"][i] = None if stacked is None else stacked[:3]
        if stacked is None:
            out["notes"][i] = f"no F from {len(x0)} matches"
        elif len(stacked) > 3:
            out["solutions"][i] = len(stacked) // 3
            out["notes"][i] = (f"{len(x0)} matches: OpenCV's 7-point algorithm stacked {len(stacked) // 3} solutions;"
                               " the release uses the first")
        return out["fundamentals"][i]

    F = fit(0, points0[0], points1[0])
    x0, x1 = points0[finest], points1[finest]
    for i in range(1, finest + 1):
        if F is None:
            x0, x1 = points0[finest], points1[finest]
            out["fallback"] = f"no F at list {i - 1}: unfiltered finest level"
            continue
        x0, x1 = points0[i], points1[i]
        if len(x0) < 8:
            # The release skips this list (were it the last, its result is the unfiltered
            # finest list) and keeps the F it had: that F filters the next list.
            x0, x1 = points0[finest], points1[finest]
            out["fallback"] = f"fewer than 8 matches at list {i}: unfiltered finest level"
            out["notes"][i] = (f"{len(points0[i])} matches, fewer than 8: not filtered, no F"
                               + ("" if i == finest else "; the last F filters the next level"))
            continue
        passed = np.abs(algebraic_residual(F, x0, x1)) < cascade.residual
        if passed.any():
            x0, x1 = x0[passed], x1[passed]
        out["counts"][i] = len(x0)
        out["survivors"][i] = (x0, x1)
        F = fit(i, x0, x1)
        out["fallback"] = None
    out["points0"], out["points1"] = x0, x1
    return out


# ---------------------------------------------------------------------------------------------
# The DFM release's two-stage match.

DFM_STAGE0_THRESHOLD_PX = 16 * math.sqrt(2) + 1
DFM_FINAL_MARGIN_PX = 16


@dataclass(frozen=True)
class DFMRelease:
    """The DFM release's settings. ratio: levels 0..3 refinement and [4] the stage-1 dense
    ratio (its config: 0.9, 0.9, 0.9, 0.9, 0.95); stage0_ratio: 1.0 (plain mutual NN).
    fixes: which of its evident slips to correct ("ratio_at": the refinement's B->A ratio
    index; "border_y": the final filter compares B's y with the padded width)."""

    ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.95)
    stage0_ratio: float = 1.0
    homography_threshold_px: float = DFM_STAGE0_THRESHOLD_PX
    fixes: tuple[str, ...] = ()


DFM_FIXES = ("ratio_at", "border_y")


def dfm_release_stage0(
    top0: torch.Tensor, top1: torch.Tensor, level: int, settings: DFMRelease
) -> tuple[np.ndarray, int]:
    """Plain mutual NN at the deepest map and the homography B -> A (identity when RANSAC
    gives none; no minimum of inliers). Returns H and the number of stage-0 matches."""
    cells0, cells1 = release_dense(top0, top1, settings.stage0_ratio)
    H = None
    if len(cells0) >= 4:
        H = dfm_stage0_homography(level_points(cells0, level), level_points(cells1, level), settings)
    return (np.eye(3) if H is None else H), len(cells0)


def dfm_stage0_homography(points0: np.ndarray, points1: np.ndarray, settings: DFMRelease) -> np.ndarray | None:
    """The release's stage-0 homography B -> A from its matches (None where RANSAC finds none)."""
    x1, x0, _ = perturb_correspondences(points1, points0)
    H, _ = cv2.findHomography(x1, x0, cv2.RANSAC, settings.homography_threshold_px, maxIters=5000, confidence=0.9999)
    return H


def dfm_release_stage1(
    maps0: list[torch.Tensor], maps_w: list[torch.Tensor], stage1_top0: torch.Tensor, stage1_top_w: torch.Tensor,
    settings: DFMRelease,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense matching on the stage-1 maps (VGG19: conv5_2, stride 16) of A and warped B, then
    refinement through maps 3..0. Returns level-0 cells."""
    ratio_at = "matched" if "ratio_at" in settings.fixes else "own"
    cells0, cells1 = release_dense(stage1_top0, stage1_top_w, settings.ratio[4])
    for level in range(3, -1, -1):
        cells0, cells1 = release_refine(maps0[level], maps_w[level], cells0, cells1, settings.ratio[level], ratio_at)
    return cells0, cells1


def dfm_release_final(
    cells0: torch.Tensor, cells_w: torch.Tensor, H_init: np.ndarray, size0: tuple[int, int], size1: tuple[int, int],
    settings: DFMRelease,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warped-B points back to B (zero-based, as the release), then its border filter: points
    within 16 px of the right/bottom edge are dropped (no test at the left/top edge).
    Returns the kept points of A and B and the mask over the input."""
    x0 = cells0.cpu().to(torch.float64).numpy()
    x1 = warp_points(np.linalg.inv(H_init), cells_w.cpu().to(torch.float64).numpy())
    (w0, h0), (w1, h1) = size0, size1
    pad_right1, pad_bottom1 = (-w1) % 16, (-h1) % 16
    # The release compares B's y with (padded width - bottom padding); "border_y" uses the height.
    limit_y1 = (
        h1 - DFM_FINAL_MARGIN_PX
        if "border_y" in settings.fixes
        else w1 + pad_right1 - pad_bottom1 - DFM_FINAL_MARGIN_PX
    )
    with np.errstate(invalid="ignore"):
        keep = (x0[:, 0] < w0 - DFM_FINAL_MARGIN_PX) & (x0[:, 1] < h0 - DFM_FINAL_MARGIN_PX)
        keep &= (x1[:, 0] < w1 - DFM_FINAL_MARGIN_PX) & (x1[:, 1] < limit_y1)
    return x0[keep], x1[keep], keep
