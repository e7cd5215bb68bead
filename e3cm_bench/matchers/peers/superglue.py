"""`superpoint+superglue`: SuperPoint + SuperGlue (Sarlin et al. 2020), transformers'
implementation of Magic Leap's models and weights (licensed for non-commercial use only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...matches import Matches
from ..base import Matcher
from .common import grey, numpy, superpoint_keypoints

SUPERGLUE_REPOS = {"outdoor": "magic-leap-community/superglue_outdoor",
                   "indoor": "magic-leap-community/superglue_indoor"}


def _normalised_as(points: torch.Tensor, size: tuple[int, int], canvas: tuple[int, int]) -> torch.Tensor:
    """Points of an image of `size` (w, h) moved so that SuperGlue's keypoint normalisation
    for an image of `canvas` gives what it gives them in their own image: SuperGlue
    normalises each image's keypoints by that image's size, transformers' pair by one size."""
    own, other = torch.tensor(size, dtype=points.dtype), torch.tensor(canvas, dtype=points.dtype)
    return other / 2 + (points - own / 2) * (other.max() / own.max())


class SuperGlueMatcher(Matcher):
    """SuperPoint on each grey image (its own size), then SuperGlue's graph network and
    Sinkhorn; mutual matches above match_threshold. Scores: SuperGlue's matching scores.
    weights: a transformers-format SuperGlue model folder or safetensors file."""

    name = "superpoint+superglue"

    def __init__(self, settings, device: str = "cpu", weights: str | Path | None = None, pretrained: bool = True):
        from transformers import SuperGlueConfig, SuperGlueForKeypointMatching, SuperPointConfig

        options = {"sinkhorn_iterations": settings.sinkhorn_iterations, "matching_threshold": settings.match_threshold}
        if weights is not None or pretrained:
            source = str(Path(weights).parent if weights is not None and Path(weights).is_file() else weights) \
                if weights is not None else SUPERGLUE_REPOS[settings.weights]
            self.model = SuperGlueForKeypointMatching.from_pretrained(source, **options)
        else:
            detector = SuperPointConfig().to_dict()
            self.model = SuperGlueForKeypointMatching(SuperGlueConfig(keypoint_detector_config=detector, **options))
        decoder = self.model.keypoint_detector.keypoint_decoder  # detection settings are read from here
        decoder.keypoint_threshold = settings.keypoint_threshold
        decoder.max_keypoints = settings.max_keypoints
        decoder.nms_radius = settings.nms_radius
        self.settings, self.device = settings, device
        self.model = self.model.eval().to(device)

    def config(self) -> dict:
        return {"matcher": self.name, **self.settings.__dict__}

    @torch.inference_mode()
    def _detect(self, image: np.ndarray):
        return superpoint_keypoints(self.model.keypoint_detector(pixel_values=grey(image, self.device)), image, self.device)

    @torch.inference_mode()
    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        (k0, s0, d0), (k1, s1, d1) = self._detect(image0), self._detect(image1)
        info = {"n_keypoints0": len(k0), "n_keypoints1": len(k1)}
        if len(k0) == 0 or len(k1) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info)
        size0, size1 = (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0])
        n = max(len(k0), len(k1))

        def padded(t, rows):
            return torch.cat([t, t.new_zeros((rows - len(t), *t.shape[1:]))])

        keypoints = torch.stack([padded(k0, n), padded(_normalised_as(k1, size1, size0), n)])[None]
        mask = torch.stack([torch.arange(n) < len(k0), torch.arange(n) < len(k1)]).to(keypoints.device)[None]
        # transformers' matching step (a private method: its forward detects on one stacked pair
        # of equal-size images, which our pairs are not)
        matches, scores, _, _ = self.model._match_image_pair(
            keypoints, torch.stack([padded(d0, n), padded(d1, n)])[None], torch.stack([padded(s0, n), padded(s1, n)])[None],
            size0[1], size0[0], mask=mask)
        index0 = matches[0, 0, :len(k0)]
        valid = torch.nonzero(index0 > -1)[:, 0]
        return Matches(numpy(k0[valid]), numpy(k1[index0[valid]]), numpy(scores[0, 0, valid]), info)
