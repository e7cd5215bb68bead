"""DFM (Efe et al. 2021): the two-stage baseline; the algorithm is matching/dfm.py."""

from __future__ import annotations

import numpy as np

from ..backbones import Backbone
from ..matching.dfm import DFMSettings, match_two_stage
from .base import Matches
from .deep import DeepMatcher


class DFMMatcher(DeepMatcher):
    """Two-stage DFM: a coarse homography warp, then hierarchical matching on the warped pair.

    Keyword arguments are DFMSettings fields. The stage-0 RANSAC draws from OpenCV's global
    RNG: the caller seeds it per pair (cv2.setRNGSeed; the runner does).
    """

    def __init__(self, backbone: Backbone, name: str = "dfm", **settings):
        super().__init__(backbone, name)
        self.settings = DFMSettings(**settings)

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        """Timings: backbone (all passes, warped B included), stage0, warp, stage1 (seconds)."""
        feats0, feats1, t_backbone = self.pyramids(image0, image1)
        out = match_two_stage(image0, image1, feats0, feats1, self.features, self.settings)
        timings = out.pop("timings")
        timings = {"backbone": t_backbone + timings.pop("backbone_warped"), **timings}
        info = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
        info["timings"] = timings
        return Matches(out["keypoints0"], out["keypoints1"], out["scores"], info)

    def settings_dict(self) -> dict:
        return self.settings.to_dict(self.backbone.deepest_stride)
