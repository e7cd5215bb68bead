"""E3CM (Zhou et al. 2023) and its cascade-off ablation `direct`."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from e3cm_bench.backbones.pyramid import Backbone
from e3cm_bench.matching.pipeline import E3CMSettings, match_pyramids
from e3cm_bench.matching.subpixel import refine_matches
from e3cm_bench.matchers.base import Matches
from e3cm_bench.matchers.deep import DeepMatcher


@dataclass
class DirectSettings(E3CMSettings):
    """E3CMSettings with the cascade off: `direct` is that ablation and nothing else."""

    cascade: bool = False

    def __post_init__(self) -> None:
        if self.cascade:
            raise ValueError("direct is e3cm without the cascade: cascade stays false (--matcher e3cm has it)")
        super().__post_init__()


class E3CMMatcher(DeepMatcher):
    """Backbone pyramids -> mutual NN + ratio -> DFM refinement, with or without the cascade."""

    def __init__(self, backbone: Backbone, settings: E3CMSettings | None = None, name: str | None = None,
                 channel_order: str = "rgb"):
        settings = settings or E3CMSettings()
        super().__init__(backbone, name or ("e3cm" if settings.cascade else "direct"), channel_order)
        self.settings = settings
        # The top-8 and PROSAC cascades read level 0 by pixels (matching/cascade.py UnitPixels).
        self.wants_pixel_rows = settings.reads_level0
        # The releases' handling (valid_cells_only false) keeps points of padding cells.
        self.keypoints_in_image = bool(settings.valid_cells_only)

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        feats0, feats1, t_backbone = self.pyramids(image0, image1)
        size0 = (image0.shape[1], image0.shape[0])
        size1 = (image1.shape[1], image1.shape[0])
        out = match_pyramids(feats0, feats1, size0, size1, self.settings, memo=self.image_product)
        info = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
        info["timings"] = {"backbone": t_backbone, **out["timings"]}
        k0, k1, scores = out["keypoints0"], out["keypoints1"], out["scores"]
        if self.settings.refine != "none":
            t = time.perf_counter()
            k1, keep = refine_matches(image0, image1, k0, k1, self.settings.refine, self.settings.refine_window)
            k0, k1, scores = k0[keep], k1[keep], scores[keep]
            info["timings"]["refine"] = time.perf_counter() - t
        return Matches(k0, k1, scores, info)

    def settings_dict(self) -> dict:
        return self.settings.to_dict()
