"""What the deep matchers share: a backbone on a device, and image -> feature pyramid."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..backbones import Backbone
from .base import Matcher

CHANNEL_ORDERS = ("rgb", "bgr")


def image_to_tensor(image: np.ndarray, device: torch.device | str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 3 x H x W float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).to(device).permute(2, 0, 1)[None].float() / 255.0


class DeepMatcher(Matcher):
    """A matcher built on the feature pyramid of an ImageNet CNN (`backbones.Backbone`).

    channel_order "bgr" feeds the network the channels reversed, as the E3CM release's
    evaluation scripts do (cv2.imread without conversion); the networks were trained on RGB.
    """

    def __init__(self, backbone: Backbone, name: str, channel_order: str = "rgb"):
        if channel_order not in CHANNEL_ORDERS:
            raise ValueError(f"channel_order must be one of {', '.join(CHANNEL_ORDERS)}, got {channel_order!r}")
        self.backbone = backbone
        self.name = name
        self.channel_order = channel_order

    @property
    def device(self) -> torch.device:
        return self.backbone.mean.device

    def network_input(self, image: np.ndarray) -> torch.Tensor:
        if self.channel_order == "bgr":
            image = image[..., ::-1]
        return image_to_tensor(image, self.device)

    def features(self, image: np.ndarray) -> list[torch.Tensor]:
        """The image's pyramid: level l is C_l x H_l x W_l at stride 2^l."""
        return self.backbone(self.network_input(image))

    def pyramids(self, image0: np.ndarray, image1: np.ndarray) -> tuple[list[torch.Tensor], list[torch.Tensor], float]:
        """Both images' pyramids and the seconds the backbone took."""
        t = time.perf_counter()
        feats0, feats1 = self.features(image0), self.features(image1)
        return feats0, feats1, time.perf_counter() - t

    def settings_dict(self) -> dict:  # pragma: no cover - each subclass says what it depends on
        raise NotImplementedError

    def config(self) -> dict:
        return {"matcher": self.name, **self.backbone.describe(), "channel_order": self.channel_order,
                **self.settings_dict()}
