"""What the deep matchers share: a backbone on a device, and image -> feature pyramid."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..backbones import Backbone
from .base import Matcher


def image_to_tensor(image: np.ndarray, device: torch.device | str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 3 x H x W float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).to(device).permute(2, 0, 1)[None].float() / 255.0


class DeepMatcher(Matcher):
    """A matcher built on the feature pyramid of an ImageNet CNN (`backbones.Backbone`)."""

    def __init__(self, backbone: Backbone, name: str):
        self.backbone = backbone
        self.name = name

    @property
    def device(self) -> torch.device:
        return self.backbone.mean.device

    def features(self, image: np.ndarray) -> list[torch.Tensor]:
        """The image's pyramid: level l is C_l x H_l x W_l at stride 2^l."""
        return self.backbone(image_to_tensor(image, self.device))

    def pyramids(self, image0: np.ndarray, image1: np.ndarray) -> tuple[list[torch.Tensor], list[torch.Tensor], float]:
        """Both images' pyramids and the seconds the backbone took."""
        t = time.perf_counter()
        feats0, feats1 = self.features(image0), self.features(image1)
        return feats0, feats1, time.perf_counter() - t

    def settings_dict(self) -> dict:  # pragma: no cover - each subclass says what it depends on
        raise NotImplementedError

    def config(self) -> dict:
        return {"matcher": self.name, **self.backbone.describe(), **self.settings_dict()}
