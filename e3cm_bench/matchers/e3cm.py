"""E3CM (Zhou et al. 2023) and its cascade-off ablation `direct`."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..backbones import Backbone
from ..matching.pipeline import E3CMSettings, match_pyramids
from .base import Matcher, Matches


def image_to_tensor(image: np.ndarray, device: torch.device | str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 3 x H x W float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).to(device).permute(2, 0, 1)[None].float() / 255.0


class E3CMMatcher(Matcher):
    """Backbone pyramids -> mutual NN + ratio -> DFM refinement, with or without the cascade."""

    def __init__(self, backbone: Backbone, settings: E3CMSettings | None = None, name: str | None = None):
        self.backbone = backbone
        self.settings = settings or E3CMSettings()
        self.name = name or ("e3cm" if self.settings.cascade else "direct")

    @property
    def device(self) -> torch.device:
        return self.backbone.mean.device

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        t = time.perf_counter()
        feats0 = self.backbone(image_to_tensor(image0, self.device))
        feats1 = self.backbone(image_to_tensor(image1, self.device))
        t_backbone = time.perf_counter() - t
        size0 = (image0.shape[1], image0.shape[0])
        size1 = (image1.shape[1], image1.shape[0])
        out = match_pyramids(feats0, feats1, size0, size1, self.settings)
        info = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
        info["timings"] = {"backbone": t_backbone, **out["timings"]}
        return Matches(out["keypoints0"], out["keypoints1"], out["scores"], info)

    def config(self) -> dict:
        return {
            "matcher": self.name,
            **self.backbone.describe(),
            **self.settings.to_dict(),
        }
