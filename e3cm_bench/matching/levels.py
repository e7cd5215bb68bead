"""Cell <-> pixel bookkeeping shared by the matching steps.

A cell (x, y) of level l covers original pixels [x*2^l, (x+1)*2^l) x [y*2^l, (y+1)*2^l);
its centre is ((x + 0.5) * 2^l - 0.5, (y + 0.5) * 2^l - 0.5) in the pixel-centre convention.
"""

from __future__ import annotations

import math

import torch


def cell_centres(cells: torch.Tensor, level: int) -> torch.Tensor:
    """N x 2 integer cells (x, y) of `level` -> N x 2 float64 centres in original pixels (on the CPU).

    Centres feed OpenCV's estimators and the outputs; float64 on the CPU also avoids MPS,
    which has no float64.
    """
    stride = 2**level
    return (cells.cpu().to(torch.float64) + 0.5) * stride - 0.5


def valid_extent(image_size: tuple[int, int], level: int) -> tuple[int, int]:
    """(width, height) in cells of the part of a level whose cell centres lie inside the image.

    Cells beyond it sit in the right/bottom padding and never take part in a match.
    """
    w, h = image_size
    stride = 2**level
    return (math.floor((w - 0.5) / stride - 0.5) + 1, math.floor((h - 0.5) / stride - 0.5) + 1)


def inside(cells: torch.Tensor, extent: tuple[int, int], margin: int = 0) -> torch.Tensor:
    """Mask of cells lying in [margin, extent - margin) on both axes."""
    w, h = extent
    x, y = cells[:, 0], cells[:, 1]
    return (x >= margin) & (y >= margin) & (x < w - margin) & (y < h - margin)
