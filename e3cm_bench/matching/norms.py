"""L2 norms over the channels (dim 0) of feature maps: torch's bits, faster on the CPU.

torch's CPU norm over the outer dimension of a contiguous C x ... tensor adds the squares of
each position's channels one after the other in float32, one position at a time (a scalar
loop), then takes the correctly rounded square root. `ordered_norm` does the same additions
in the same order, a channel at a time over every position (vectorised across positions):
`acc += x[k] * x[k]`, the product rounded before it is added (`addcmul_` fuses the two on
this machine's torch, rounding once, and gives other bits). On a 64-channel level 0 that
takes about 0.4x the time of adding the squares a band of positions at a time, which it
replaced, and a seventh of torch's (the removed A/B script norm_ab.py, in the git history).

That order is torch's choice, not a promise, so the sum is used only after it has given
torch's own norm bit for bit on probe maps of the same channel count, checked once per
process; elsewhere (another torch, a GPU, a channels-last or small map) torch's norm runs.
"""

from __future__ import annotations

import torch

# Below this many positions the Python loop over the channels costs more than it saves.
MIN_POSITIONS = 4096

_checked: dict[tuple[int, int], bool] = {}


def ordered_norm(feat: torch.Tensor) -> torch.Tensor:
    """1 x ...: the L2 norm over dim 0, squares summed channel by channel in order."""
    c = feat.shape[0]
    flat = feat.reshape(c, -1)
    acc = flat[0] * flat[0]
    square = torch.empty_like(acc)
    for k in range(1, c):
        acc.add_(torch.mul(flat[k], flat[k], out=square))
    # The square root in float64 rounded to float32 is the correctly rounded float32 root
    # (torch's vectorised float32 sqrt is not, on some CPUs).
    return acc.double().sqrt_().to(feat.dtype).reshape(1, *feat.shape[1:])


def ordered_is_exact(feat: torch.Tensor) -> bool:
    """Whether ordered_norm gives torch's norm bit for bit for maps like `feat` (and is worth it)."""
    if (feat.device.type != "cpu" or feat.dtype != torch.float32 or not feat.is_contiguous()
            or feat.dim() < 2 or feat[0].numel() < MIN_POSITIONS):
        return False
    key = (feat.shape[0], torch.get_num_threads())
    if key not in _checked:
        gen = torch.Generator().manual_seed(0)
        # Two probe sizes: one below torch's parallel grain and one above it; neither a
        # multiple of a vector's width, so the loops' scalar tails are probed too.
        probes = [torch.randn(feat.shape[0], h, 37, generator=gen).relu_() * 3
                  for h in (5, 1 + 40000 // (37 * feat.shape[0]))]
        _checked[key] = all(torch.equal(ordered_norm(p), p.norm(2, 0, keepdim=True)) for p in probes)
    return _checked[key]


def channel_norm(feat: torch.Tensor) -> torch.Tensor:
    """feat.norm(2, 0, keepdim=True), bit for bit."""
    return ordered_norm(feat) if ordered_is_exact(feat) else feat.norm(2, 0, keepdim=True)


def normalize_channels(feat: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """F.normalize(feat, dim=0), bit for bit: the same norm, clamped at eps, and the same division."""
    return feat / channel_norm(feat).clamp_min_(eps)
