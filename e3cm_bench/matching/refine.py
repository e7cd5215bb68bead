"""Hierarchical refinement from DFM: a match at level l proposes matches among its 2x2 children.

Each child of the A cell looks for its nearest child of the B cell (and vice versa); pairs
that are mutual and pass the ratio test survive, at most `max_per_parent` per parent
(lowest distances first).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from e3cm_bench.matching.dense import passes_ratio
from e3cm_bench.matching.levels import inside
from e3cm_bench.matching.norms import normalize_channels

CHILD_OFFSETS = torch.tensor([[0, 0], [1, 0], [0, 1], [1, 1]])


@dataclass(frozen=True)
class ChildTest:
    """Which children of a parent match survive at one level: the ratio test's threshold, the
    most kept per parent (lowest distances first), and ratio_at: where the B->A ratio test is
    read, "matched" at the B child the A child matched (the test as Eq. 2 states it), "own" at
    the B child with the A child's index (both releases' indexing; matching/release.py)."""

    ratio: float
    max_per_parent: int = 2
    ratio_at: str = "matched"


def refine_to_children(
    feat0: torch.Tensor,
    feat1: torch.Tensor,
    cells0: torch.Tensor,
    cells1: torch.Tensor,
    extent0: tuple[int, int],
    extent1: tuple[int, int],
    test: ChildTest,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Refine N parent matches to level l-1, the children kept by `test`.

    feat0/feat1: maps of level l-1 (C x H x W; normalised here, as they are read). cells0/cells1: N x 2 parent
    cells (x, y) at level l. extent0/extent1: valid (w, h) of level l-1 in cells.
    Returns child cells0, cells1 (M x 2), distance (M) and the parent index of each child.
    """
    device = feat0.device
    n = len(cells0)
    if n == 0:
        empty = torch.zeros(0, 2, dtype=torch.long, device=device)
        return empty, empty, torch.zeros(0, device=device), torch.zeros(0, dtype=torch.long, device=device)
    offsets = CHILD_OFFSETS.to(device)
    kids0 = (2 * cells0)[:, None, :] + offsets[None]  # N x 4 x 2
    kids1 = (2 * cells1)[:, None, :] + offsets[None]
    # Only the children are read, so only they are L2-normalised (bit for bit what normalising
    # the whole map would give them).
    d0 = normalize_channels(_gather(feat0, kids0)).permute(1, 2, 0)  # N x 4 x C
    d1 = normalize_channels(_gather(feat1, kids1)).permute(1, 2, 0)
    dist = 1 - d0 @ d1.transpose(1, 2)  # N x 4 (children of A) x 4 (children of B)
    child_dist, b_of_a = _children_checked(dist, kids0, kids1, extent0, extent1, test.ratio, test.ratio_at)

    # Keep the best `max_per_parent` children per parent.
    k = min(test.max_per_parent, 4)
    top_dist, top_a = child_dist.topk(k, dim=1, largest=False)
    parent = torch.arange(n, device=device)[:, None].expand(n, k)
    top_b = b_of_a.gather(1, top_a)
    out0 = kids0[parent, top_a].reshape(-1, 2)
    out1 = kids1[parent, top_b].reshape(-1, 2)
    out_dist = top_dist.reshape(-1)
    parent = parent.reshape(-1)
    keep = torch.isfinite(out_dist)
    out0, out1, out_dist, parent = out0[keep], out1[keep], out_dist[keep], parent[keep]
    # Distinct parents have disjoint children, but guard against duplicate input matches.
    key = torch.cat([out0, out1], 1)
    _, first = _unique_rows(key)
    return out0[first], out1[first], out_dist[first], parent[first]


def _children_checked(dist: torch.Tensor, kids0: torch.Tensor, kids1: torch.Tensor, extent0: tuple[int, int],
                      extent1: tuple[int, int], ratio: float, ratio_at: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(each A child's distance to its nearest B child, inf where the pair is not mutual, fails
    the ratio test or lies in the padding: N x 4; that B child's index: N x 4)."""
    n, device = len(dist), dist.device
    best_a, nn_a = dist.topk(2, dim=2, largest=False)  # for each A child, over B children
    best_b, nn_b = dist.topk(2, dim=1, largest=False)  # for each B child, over A children
    a_idx = torch.arange(4, device=device)[None].expand(n, 4)
    b_of_a = nn_a[..., 0]  # N x 4
    mutual = nn_b[:, 0, :].gather(1, b_of_a) == a_idx
    ok_a = passes_ratio(best_a[..., 0], best_a[..., 1], ratio)
    ok_b = passes_ratio(best_b[:, 0, :], best_b[:, 1, :], ratio)
    if ratio_at == "matched":
        ok_b = ok_b.gather(1, b_of_a)
    # Children in the padding are ruled out before the best ones per parent are chosen, so a
    # parent at the image edge still yields its valid children.
    valid = inside(kids0.reshape(-1, 2), extent0).reshape(n, 4) & inside(
        kids1.gather(1, b_of_a[..., None].expand(n, 4, 2)).reshape(-1, 2), extent1
    ).reshape(n, 4)
    child_dist = best_a[..., 0].masked_fill(~(mutual & ok_a & ok_b & valid), float("inf"))
    return child_dist, b_of_a


def _gather(feat: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """C x N x 4, contiguous: feat[:, cells[..., 1], cells[..., 0]], by index_select on the
    flattened map (the same values; 5-6x faster than advanced indexing on the CPU). A
    channels-last map is read by pixel rows, without copying the map."""
    c, _, w = feat.shape
    index = (cells[..., 1] * w + cells[..., 0]).reshape(-1)
    rows = feat.permute(1, 2, 0)
    if not feat.is_contiguous() and rows.is_contiguous():
        picked = rows.reshape(-1, c).index_select(0, index).T.contiguous()
    else:
        picked = feat.reshape(c, -1).index_select(1, index)
    return picked.reshape(c, *cells.shape[:-1])


def _unique_rows(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unique rows and the index of the first occurrence of each (order kept)."""
    first = first_of_each(rows).sort().values
    return rows[first], first


def first_of_each(rows: torch.Tensor) -> torch.Tensor:
    """Index of the first occurrence of each distinct row, in sorted row order (torch.unique's)."""
    if len(rows) == 0:
        return torch.zeros(0, dtype=torch.long, device=rows.device)
    keys = row_keys(rows)
    # torch.unique over rows (dim=0) compares them one pair at a time on the CPU; one integer
    # per row sorts the same way and is unique'd as a flat tensor, far faster (docs/speed.md,
    # "Duplicate children found by one key per row"). Rows whose key could overflow fall back.
    uniq, inverse = (
        torch.unique(rows, dim=0, return_inverse=True) if keys is None else torch.unique(keys, return_inverse=True)
    )
    first = torch.full((len(uniq),), len(rows), dtype=torch.long, device=rows.device)
    return first.scatter_reduce_(0, inverse, torch.arange(len(rows), device=rows.device), reduce="amin")


def row_keys(rows: torch.Tensor) -> torch.Tensor | None:
    """One int64 per row of an N x k integer tensor, in the rows' lexicographic order (equal
    rows, equal keys): each column minus its least value, as the digits of a number whose
    k-th digit runs to that column's range. None where the rows are not integers or the
    number could pass 2^62."""
    if rows.is_floating_point() or rows.is_complex() or rows.dim() != 2:
        return None
    low = rows.amin(0)
    spans = (rows.amax(0) - low + 1).tolist()
    if torch.tensor(spans, dtype=torch.float64).prod() >= 2.0**62:
        return None
    digits = (rows - low).long()
    keys = digits[:, 0].clone()
    for col in range(1, rows.shape[1]):
        keys.mul_(spans[col]).add_(digits[:, col])
    return keys
