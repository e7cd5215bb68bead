"""The epipolar-constrained cascade (paper Sec. 3.2): confidence score, F per level, Sampson rejection."""

from __future__ import annotations

import functools

import numpy as np
import torch

from e3cm_bench.geometry import two_view as geometry
from e3cm_bench.matching import ESTIMATORS
from e3cm_bench.matching.norms import channel_norm


class UnitPixels:
    """Level 0 read by pixels and L2-normalised as read: `rows` ((H W) x C, a map's pixels;
    any float dtype that widens to the float32 map exactly, such as a bf16 backbone's own
    channels-last output) divided by `norms` ((H W), the pixels' channel norms clamped at
    1e-12) as they are gathered. A gathered row is bit for bit that pixel of
    F.normalize(map, dim=0): the same division of the same two numbers. The confidence score
    reads most of level 0 patch by patch; dividing what it gathers, in cache, replaced writing
    a normalised copy of the whole map (docs/speed.md)."""

    def __init__(self, rows: torch.Tensor, norms: torch.Tensor, width: int):
        self.rows, self.norms, self.width = rows, norms, width

    @classmethod
    def of(
        cls, level0_feat: torch.Tensor, rows: torch.Tensor | None = None, norms: torch.Tensor | None = None
    ) -> "UnitPixels":
        """level0_feat: C x H x W; rows / norms: those of it where already in hand (pixel_rows, pixel_norms)."""
        return cls(pixel_rows(level0_feat) if rows is None else rows,
                   pixel_norms(level0_feat) if norms is None else norms, level0_feat.shape[2])

    @property
    def channels(self) -> int:
        return self.rows.shape[1]

    def gather(self, index: torch.Tensor) -> torch.Tensor:
        """len(index) x C: the normalised pixels at flat positions `index` (y W + x)."""
        rows = self.rows.index_select(0, index)
        # bf16 rows widen to float32 exactly, so widening them first and dividing in place
        # gives the bits of dividing the bf16 rows by the float32 norms, and spares torch
        # widening element by element inside the division (the cost: docs/speed.md).
        rows = rows.to(self.norms.dtype)
        return rows.div_(self.norms.index_select(0, index)[:, None])

    def patch_index(self, cells: torch.Tensor, side: int) -> torch.Tensor:
        """(n P): flat positions of the pixels of the side x side patches at `cells` (n x 2
        cells (x, y) of a level of stride `side`), each patch's in row-major order."""
        xy = cells[:, None, :] * side + _patch_offsets(side, cells.device)[None]
        return (xy[..., 1] * self.width + xy[..., 0]).reshape(-1)

    def patches(self, cells: torch.Tensor, side: int) -> torch.Tensor:
        """n x P x C: the normalised pixels of the patches at `cells`."""
        return self.gather(self.patch_index(cells, side)).reshape(len(cells), side * side, -1)


def pixel_rows(level0_feat: torch.Tensor) -> torch.Tensor:
    """C x H x W -> (H W) x C rows (a view when the map is channels-last, else a copy)."""
    c = level0_feat.shape[0]
    return level0_feat.permute(1, 2, 0).reshape(-1, c)


def pixel_norms(level0_feat: torch.Tensor) -> torch.Tensor:
    """(H W): each pixel's channel norm as F.normalize takes it (torch's norm, clamped at 1e-12)."""
    return channel_norm(level0_feat).clamp_min_(1e-12).reshape(-1)


def confidence_scores(
    unit0: UnitPixels,
    unit1: UnitPixels,
    cells0: torch.Tensor,
    cells1: torch.Tensor,
    level: int,
    eps: float = 1e-3,
    budget: int = 1 << 25,
    top: int | None = None,
) -> torch.Tensor:
    """Confidence c (Eq. 3) of matches at `level` from their 2^l x 2^l pixel patches.

    unit0 / unit1: the two images' level 0 (one cell per original pixel), read L2-normalised.
    m_ij = 1 when pixel (i, j) of patch A and pixel (i, j) of patch B are mutual nearest
    neighbours among the pixels of the two patches; d_ij = 1 - cos of those two pixels,
    floored at eps; c = sum m_ij / d_ij. `budget` bounds the similarity block in elements.

    top: only the `top` most confident matches are wanted (the paper's top-8). Each match's
    c is at most a bound that costs 5 P dot products instead of P^2 (`_confidence_bound`);
    only matches whose bound reaches the top-th score found so far are scored, in decreasing
    bound order, and the rest are left at -inf. The top matches and their scores are exactly
    those of the full computation.
    """
    n, side = len(cells0), 2**level
    p = side * side

    def score(rows):
        return _patch_confidence(unit0.patches(cells0[rows], side), unit1.patches(cells1[rows], side), eps)

    scores = torch.full((n,), -torch.inf, dtype=unit0.norms.dtype, device=unit0.norms.device)
    chunk = max(1, budget // (p * p))
    if top is None or n <= top:
        for start in range(0, n, chunk):
            scores[start : start + chunk] = score(slice(start, start + chunk))
        return scores
    bound = _confidence_bounds(unit0, unit1, cells0, cells1, side, eps)
    order = torch.argsort(-bound, stable=True)
    bound = bound[order]
    # The `top` highest bounds are scored first; their lowest score is the first threshold.
    # Then, in bound order, only matches whose bound reaches the top-th score found so far:
    # the others cannot enter the top (nor tie with it). The steps start at `top` matches
    # and double, so that the threshold stays fresh, up to 64 matches where a score costs
    # most (level 4, P = 256) and 1024 elsewhere.
    scores[order[:top]] = score(order[:top])
    most = min(chunk, 64 if p >= 256 else 1024)
    start, step = top, min(top, most)
    while start < n:
        count = int((bound[start : start + step] >= scores.topk(top).values[-1]).sum())
        if count:
            rows = order[start : start + count]
            scores[rows] = score(rows)
        if count < step:
            break
        start, step = start + step, min(2 * step, most)
    return scores


def _confidence_bounds(unit0: UnitPixels, unit1: UnitPixels, cells0: torch.Tensor, cells1: torch.Tensor,
                       side: int, eps: float) -> torch.Tensor:
    """Each match's bound on its confidence (`_confidence_bound`), computed block by block."""
    n, p = len(cells0), side * side
    # The bound's temporaries are n x P x C: blocks of them small enough to stay in cache
    # (at level 4, P = 256, C = 64: blocks of 128 matches took 0.4-0.6x the time of blocks of 512).
    block = max(1, _BOUND_BLOCK // (p * unit0.channels))
    return torch.cat([
        _confidence_bound(unit0.patches(cells0[start : start + block], side),
                          unit1.patches(cells1[start : start + block], side), side, eps)
        for start in range(0, n, block)
    ])


@functools.lru_cache(maxsize=None)
def _patch_offsets(side: int, device) -> torch.Tensor:
    """P x 2 pixel offsets (x, y) inside a side x side patch, row-major."""
    ys, xs = torch.meshgrid(torch.arange(side, device=device), torch.arange(side, device=device), indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)


def _patch_confidence(a: torch.Tensor, b: torch.Tensor, eps: float) -> torch.Tensor:
    """c of n patch pairs (n x P x C each)."""
    sim = a @ b.transpose(1, 2)  # n x P x P
    d = (1 - sim.diagonal(dim1=1, dim2=2)).clamp_min(eps)
    return (_mutual_diagonal(sim).to(d.dtype) / d).sum(1)


def _mutual_diagonal(sim: torch.Tensor) -> torch.Tensor:
    """n x P: sim.argmax(2) == i and sim.argmax(1) == i for each diagonal entry i, exactly.

    argmax is slow on the CPU; a maximum is not. Entry i is the argmax of its row when it
    beats every other entry of the row, and not when another beats it. Where another equals
    it, argmax's rule (the first of equals) decides: entry i is the argmax when no entry
    before it is equal. Only those tied entries' rows (and columns) are read again, a row
    of P values each. sim is modified (its diagonal is set to -inf).
    """
    diag = sim.diagonal(dim1=1, dim2=2)
    own = diag.clone()
    diag.fill_(-torch.inf)
    row_other, col_other = sim.amax(dim=2), sim.amax(dim=1)
    mutual = (own >= row_other) & (own >= col_other)
    for along_rows, other in ((True, row_other), (False, col_other)):
        patch, i = (mutual & (own == other)).nonzero(as_tuple=True)
        if len(patch):
            # The tied entry's row (sim[patch, i, :]) or column (sim[patch, :, i]).
            line = sim[patch, i] if along_rows else sim[patch, :, i]
            before = torch.arange(sim.shape[1], device=sim.device)[None] < i[:, None]
            mutual[patch, i] = ~((line == own[patch, i][:, None]) & before).any(1)
    return mutual


# Elements of one operand of the bound's products in one block (8 MiB in float32).
_BOUND_BLOCK = 1 << 21

# The bound's dot products are summed in another order than the matrix product's entries;
# this slack (far above fp32 rounding of a unit-vector dot product) keeps it an upper bound.
_BOUND_SLACK = 1e-4


def _confidence_bound(a: torch.Tensor, b: torch.Tensor, side: int, eps: float) -> torch.Tensor:
    """An upper bound of c for n patch pairs (n x P x C each) from 5 P dot products.

    Pixel i can be mutual only if a_i . b_i beats a_i's similarity to B's pixels beside i and
    b_i's similarity to A's pixels beside i (its 4 neighbours in the patch; neighbouring CNN
    features are alike, so this rules out most pixels); every pixel not ruled out is counted
    with its 1 / max(eps, 1 - cos).
    """
    n = len(a)
    a, b = a.reshape(n, side, side, -1), b.reshape(n, side, side, -1)
    diag = (a * b).sum(-1)  # n x s x s
    beaten = torch.zeros_like(diag, dtype=torch.bool)
    for dim in (1, 2) if side > 1 else ():  # neighbours along y (dim 1) and x (dim 2)
        def part(t, first):  # pixels p (first=True) or p + 1 along `dim`
            index = [slice(None)] * t.dim()
            index[dim] = slice(None, -1) if first else slice(1, None)
            return t[tuple(index)]

        forward = (part(a, True) * part(b, False)).sum(-1)  # a at p . b at p + 1
        backward = (part(a, False) * part(b, True)).sum(-1)  # a at p + 1 . b at p
        d_p, d_next = part(diag, True), part(diag, False)
        # a at p prefers b at p + 1, or b at p prefers a at p + 1: p fails a test, and so on.
        beaten_p, beaten_next = part(beaten, True), part(beaten, False)  # views: |= writes into beaten
        beaten_p |= (forward > d_p + _BOUND_SLACK) | (backward > d_p + _BOUND_SLACK)
        beaten_next |= (forward > d_next + _BOUND_SLACK) | (backward > d_next + _BOUND_SLACK)
    d = (1 - diag - _BOUND_SLACK).clamp_min(eps)
    return ((~beaten).to(d.dtype) / d).flatten(1).sum(1)


def estimate_level_fundamental(
    x0: np.ndarray,
    x1: np.ndarray,
    confidence: np.ndarray | None,
    estimator: str,
    ransac_threshold_px: float,
) -> np.ndarray | None:
    """F_l from the matches of one level (cell centres in original pixels).

    top8: the paper's choice, normalised 8-point on the 8 most confident matches.
    ransac: OpenCV RANSAC over all matches. prosac: OpenCV PROSAC, matches ordered by confidence.
    magsac: OpenCV's MAGSAC++ over all matches (e3cm-plus).
    """
    if len(x0) < 8:
        return None
    if estimator == "top8":
        top = np.argsort(-confidence, kind="stable")[:8]
        return geometry.estimate_fundamental(x0[top], x1[top], "8point")
    if estimator in ("ransac", "magsac"):
        return geometry.estimate_fundamental(x0, x1, estimator, ransac_threshold_px)
    if estimator == "prosac":
        order = np.argsort(-confidence, kind="stable")
        return geometry.estimate_fundamental(x0[order], x1[order], "prosac", ransac_threshold_px)
    raise ValueError(f"unknown cascade estimator {estimator!r}; choose one of {', '.join(ESTIMATORS)}")


def epipolar_inliers(F: np.ndarray, x0: np.ndarray, x1: np.ndarray, threshold_px: float) -> np.ndarray:
    """Mask of matches whose Sampson distance to F is at most threshold_px (compared in pixels)."""
    return np.sqrt(geometry.sampson_distance(F, x0, x1)) <= threshold_px
