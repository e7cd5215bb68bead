"""The epipolar-constrained cascade (paper Sec. 3.2): confidence score, F per level, Sampson rejection."""

from __future__ import annotations

import numpy as np
import torch

from .. import geometry
from . import ESTIMATORS


def confidence_scores(
    level0_feat0: torch.Tensor,
    level0_feat1: torch.Tensor,
    cells0: torch.Tensor,
    cells1: torch.Tensor,
    level: int,
    eps: float = 1e-3,
    budget: int = 1 << 25,
) -> torch.Tensor:
    """Confidence c (Eq. 3) of matches at `level` from their 2^l x 2^l pixel patches.

    level0_feat*: L2-normalised level-0 maps (C x H x W, one cell per original pixel).
    m_ij = 1 when pixel (i, j) of patch A and pixel (i, j) of patch B are mutual nearest
    neighbours among the pixels of the two patches; d_ij = 1 - cos of those two pixels,
    floored at eps; c = sum m_ij / d_ij. `budget` bounds the similarity block in elements.
    """
    device = level0_feat0.device
    side = 2**level
    p = side * side
    ys, xs = torch.meshgrid(torch.arange(side, device=device), torch.arange(side, device=device), indexing="ij")
    offsets = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)  # P x 2, same order in A and B
    diag = torch.arange(p, device=device)
    scores = torch.zeros(len(cells0), dtype=level0_feat0.dtype, device=device)
    chunk = max(1, budget // (p * p))
    for start in range(0, len(cells0), chunk):
        px0 = cells0[start : start + chunk, None, :] * side + offsets[None]  # n x P x 2
        px1 = cells1[start : start + chunk, None, :] * side + offsets[None]
        a = level0_feat0[:, px0[..., 1], px0[..., 0]].permute(1, 2, 0)  # n x P x C
        b = level0_feat1[:, px1[..., 1], px1[..., 0]].permute(1, 2, 0)
        sim = a @ b.transpose(1, 2)  # n x P x P
        mutual = (sim.argmax(dim=2) == diag) & (sim.argmax(dim=1) == diag)
        d = (1 - sim.diagonal(dim1=1, dim2=2)).clamp_min(eps)
        scores[start : start + chunk] = (mutual.to(d.dtype) / d).sum(1)
    return scores


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
    """
    if len(x0) < 8:
        return None
    if estimator == "top8":
        top = np.argsort(-confidence, kind="stable")[:8]
        return geometry.estimate_fundamental(x0[top], x1[top], "8point")
    if estimator == "ransac":
        return geometry.estimate_fundamental(x0, x1, "ransac", ransac_threshold_px)
    if estimator == "prosac":
        order = np.argsort(-confidence, kind="stable")
        return geometry.estimate_fundamental(x0[order], x1[order], "prosac", ransac_threshold_px)
    raise ValueError(f"unknown cascade estimator {estimator!r}; choose one of {', '.join(ESTIMATORS)}")


def epipolar_inliers(F: np.ndarray, x0: np.ndarray, x1: np.ndarray, threshold_px: float) -> np.ndarray:
    """Mask of matches whose Sampson distance to F is at most threshold_px (compared in pixels)."""
    return np.sqrt(geometry.sampson_distance(F, x0, x1)) <= threshold_px
