"""What the peer matchers share: images as the networks take them, and their device."""

from __future__ import annotations

import numpy as np
import torch

SUPERPOINT_REPO = "magic-leap-community/superpoint"  # transformers' SuperPoint (Magic Leap's weights)


def grey(image: np.ndarray, device: str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 1 x H x W float in [0, 1] (ITU-R 601 luma, as OpenCV's)."""
    rgb = torch.from_numpy(np.ascontiguousarray(image)).to(device=device, dtype=torch.float32) / 255.0
    luma = rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114
    return luma[None, None]


def rgb(image: np.ndarray, device: str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 3 x H x W float in [0, 1]."""
    return (torch.from_numpy(np.ascontiguousarray(image)).to(device=device, dtype=torch.float32) / 255.0).permute(
        2, 0, 1
    )[None]


def numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().float().cpu().numpy()


def superpoint_keypoints(out, image: np.ndarray, device: str):
    """transformers' SuperPoint output for one image -> (keypoints N x 2 at the pixel indices
    they came from, i.e. pixel centres; scores N; descriptors N x D). transformers returns
    positions relative to the image size."""
    keep = out.mask[0] > 0
    size = torch.tensor([image.shape[1], image.shape[0]], device=out.keypoints.device)
    return (out.keypoints[0][keep] * size).round(), out.scores[0][keep], out.descriptors[0][keep]
