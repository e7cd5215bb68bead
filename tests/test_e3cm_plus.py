"""e3cm-plus: its sub-pixel step, its settings, and its quality on shared pairs (margins measured)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from e3cm_bench.matchers.e3cm_plus import E3CMPlusSettings
from e3cm_bench.matching.pipeline import subpixel_offsets
from e3cm_bench.method import MethodSpec


def smooth_field(c: int, h: int, w: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(1, c, h // 4 + 3, w // 4 + 3, generator=gen, dtype=torch.float64)
    return F.interpolate(noise, size=(h + 12, w + 12), mode="bicubic", align_corners=False)[0]


@pytest.mark.parametrize("shift", [(0.3, -0.2), (-0.4, 0.1), (0.0, 0.0)])
def test_subpixel_offsets_recover_a_known_fractional_shift(shift):
    # B's map is A's smooth field sampled shift pixels further (B(x) = A(x + shift)... read at
    # the same integer pixel B sees A's content from x - shift): A's pixel p then matches B at
    # p - shift, whose nearest pixel is p; the offsets must point from p towards p - shift.
    field = smooth_field(16, 40, 48, seed=1)
    h, w = 40, 48
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")

    def sample(dx: float, dy: float) -> torch.Tensor:
        gx = (xs + 6 + dx) / (w + 12 - 1) * 2 - 1
        gy = (ys + 6 + dy) / (h + 12 - 1) * 2 - 1
        grid = torch.stack([gx, gy], -1)[None]
        return F.grid_sample(field[None], grid, mode="bilinear", align_corners=True)[0]

    map0 = sample(0.0, 0.0)
    map1 = sample(shift[0], shift[1])  # B at p shows A's content at p + shift
    cells = torch.stack(torch.meshgrid(torch.arange(4, w - 4), torch.arange(4, h - 4), indexing="xy"), -1).reshape(-1, 2)
    offsets = subpixel_offsets(map0.float(), map1.float(), cells, cells).numpy()
    # A's pixel p sits at B's p - shift.
    # A parabola through three similarities pulls large shifts towards 0 (measured: 0.29 for
    # 0.4); it must still remove most of the error of staying on the pixel.
    want = -np.asarray(shift)
    got = np.median(offsets, axis=0)
    assert np.all(np.abs(got - want) <= 0.35 * np.abs(want) + 0.05), got
    assert np.all(np.abs(offsets) <= 0.5)


def test_subpixel_offsets_are_zero_at_the_border_and_for_no_matches():
    map0 = torch.randn(8, 5, 6)
    cells = torch.tensor([[0, 2], [5, 0]])
    off = subpixel_offsets(map0, map0, cells, cells).numpy()
    assert off[0, 0] == 0 and off[1, 0] == 0 and off[1, 1] == 0  # x at 0 / 5 = w - 1; y at 0
    assert subpixel_offsets(map0, map0, cells[:0], cells[:0]).shape == (0, 2)


def test_settings_are_checked_and_the_label_says_e3cm_plus():
    with pytest.raises(ValueError, match="prewarp must be true or false"):
        E3CMPlusSettings(prewarp="maybe")
    with pytest.raises(ValueError, match="unknown cascade estimator"):
        E3CMPlusSettings(estimator="magic")
    spec = MethodSpec.create("e3cm-plus", "efficientnet_lite0")
    assert spec.label == "e3cm-plus-efficientnet_lite0" and spec.seed == 0  # random: MAGSAC++, stage 0
    with pytest.raises(ValueError, match="e3cm-plus"):
        MethodSpec.create("e3cm-plus", "efficientnet_lite0", options={"cascade": False})
