"""Initial matching at the deepest level: dense mutual nearest neighbours + ratio test (Eq. 1-2).

The full similarity matrix of a 1600x1200 pair at stride 16 is ~7500 x 7500 (and 30000 x
30000 at stride 8); `top2_both_ways` builds it in row chunks.
"""

from __future__ import annotations

import torch

from e3cm_bench.matching.levels import inside


def _top2(sim: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-2 similarities and indices along `dim`; a single candidate gets a -inf runner-up."""
    if sim.shape[dim] >= 2:
        return sim.topk(2, dim=dim)
    pad_shape = list(sim.shape)
    pad_shape[dim] = 1
    vals = torch.cat([sim, torch.full(pad_shape, -float("inf"), dtype=sim.dtype, device=sim.device)], dim)
    idx = torch.cat(
        [torch.zeros_like(sim, dtype=torch.long), torch.zeros(pad_shape, dtype=torch.long, device=sim.device)], dim
    )
    return vals, idx


def passes_ratio(best_dist: torch.Tensor, second_dist: torch.Tensor, ratio: float) -> torch.Tensor:
    """best / second < ratio, written without division so that 0/0 (ambiguous) fails.

    1 - cos of identical unit vectors can round to a tiny negative number; clamping at 0
    keeps such a tie ambiguous instead of letting -a < -0.9a pass it.
    """
    return best_dist.clamp_min(0) < ratio * second_dist.clamp_min(0)


def top2_both_ways(
    desc0: torch.Tensor, desc1: torch.Tensor, chunk: int = 2048
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Top-2 cosine similarities of unit descriptors (N0 x C, N1 x C) in both directions.

    Returns vals0, idx0 (N0 x 2: for each row of desc0, over desc1) and vals1, idx1 (N1 x 2).
    The similarity matrix is built in row chunks with a running top-2 per column, so memory
    stays at chunk x N1.
    """
    n0, n1 = len(desc0), len(desc1)
    idx0 = torch.empty(n0, 2, dtype=torch.long, device=desc0.device)
    vals0 = torch.empty(n0, 2, dtype=desc0.dtype, device=desc0.device)
    col_vals = torch.full((2, n1), -float("inf"), dtype=desc0.dtype, device=desc0.device)
    col_idx = torch.zeros((2, n1), dtype=torch.long, device=desc0.device)
    for start in range(0, n0, chunk):
        sim = desc0[start : start + chunk] @ desc1.T
        vals0[start : start + chunk], idx0[start : start + chunk] = _top2(sim, dim=1)
        if n0 <= chunk:
            col_vals, col_idx = _top2(sim, dim=0)
            break
        cvals, cidx = _top2(sim, dim=0)
        merged_vals = torch.cat([col_vals, cvals], 0)
        merged_idx = torch.cat([col_idx, cidx + start], 0)
        col_vals, order = merged_vals.topk(2, dim=0)
        col_idx = merged_idx.gather(0, order)
    return vals0, idx0, col_vals.T, col_idx.T


def mutual_nn_ratio(
    desc0: torch.Tensor, desc1: torch.Tensor, ratio: float, chunk: int = 2048
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual nearest neighbours of L2-normalised descriptors (N0 x C, N1 x C).

    Distance is 1 - cos. A pair is kept when it is mutual and passes the ratio test in
    both directions. Returns (idx0, idx1, distance).
    """
    if len(desc0) == 0 or len(desc1) == 0:
        empty = torch.zeros(0, dtype=torch.long, device=desc0.device)
        return empty, empty, torch.zeros(0, device=desc0.device)
    vals0, nn0, vals1, nn1 = top2_both_ways(desc0, desc1, chunk)
    dist0, dist1 = 1 - vals0, 1 - vals1
    best01 = nn0[:, 0]
    idx0 = torch.arange(len(desc0), device=desc0.device)
    keep = nn1[best01, 0] == idx0
    keep &= passes_ratio(dist0[:, 0], dist0[:, 1], ratio)
    keep &= passes_ratio(dist1[best01, 0], dist1[best01, 1], ratio)
    return idx0[keep], best01[keep], dist0[keep, 0]


def match_dense_level(
    feat0: torch.Tensor,
    feat1: torch.Tensor,
    extent0: tuple[int, int],
    extent1: tuple[int, int],
    ratio: float,
    drop_border: bool = True,
    chunk: int = 2048,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Match every valid cell of two L2-normalised maps (C x H x W).

    Only cells inside the image (extent, in cells) take part; matches touching the outer
    ring of valid cells are dropped. Returns cells0, cells1 (N x 2, integer x, y) and distance.
    """

    def flat(feat: torch.Tensor, extent: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        w, h = extent
        ys, xs = torch.meshgrid(torch.arange(h, device=feat.device), torch.arange(w, device=feat.device), indexing="ij")
        cells = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
        return feat[:, :h, :w].reshape(feat.shape[0], -1).T, cells

    desc0, cells0 = flat(feat0, extent0)
    desc1, cells1 = flat(feat1, extent1)
    i0, i1, dist = mutual_nn_ratio(desc0, desc1, ratio, chunk)
    c0, c1 = cells0[i0], cells1[i1]
    if drop_border:
        keep = inside(c0, extent0, margin=1) & inside(c1, extent1, margin=1)
        c0, c1, dist = c0[keep], c1[keep], dist[keep]
    return c0, c1, dist
