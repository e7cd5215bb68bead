"""`loftr`: LoFTR (Sun et al. 2021), kornia's implementation and weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.peers.common import grey, numpy
from e3cm_bench.matchers.peers.weights import HubFile, checked_cache_file, load_into, load_weights

# kornia puts the pretrained models' output in the reference frame, where the centre of pixel
# (x, y) is (x + 0.5, y + 0.5) (kornia.feature.LoFTR's docstring); ours has it at (x, y).
REFERENCE_FRAME_OFFSET = 0.5


class LoFTRMatcher(Matcher):
    """Grey images in [0, 1] (any size; kornia pads the coarse grid), dual-softmax coarse
    matches above match_threshold, refined at the fine level. Scores: the coarse confidence."""

    name = "loftr"

    def __init__(self, settings, device: str = "cpu", weights: str | Path | None = None, pretrained: bool = True):
        import kornia.feature as KF

        config = {**KF.loftr.loftr.default_cfg}
        config["match_coarse"] = {**config["match_coarse"], "thr": float(settings.match_threshold)}
        if settings.weights == "indoor_new":
            config["coarse"] = {**config["coarse"], "temp_bug_fix": True}  # what kornia sets for these weights
        self.settings = settings
        self.device = device
        source = settings.weights if pretrained and weights is None else None
        if source in KF.loftr.loftr.urls:  # kornia's cache file checked first: a broken one is one line
            cached = HubFile.of(KF.loftr.loftr.urls[source]).path()
            if cached.is_file():
                checked_cache_file(cached)
        self.model = KF.LoFTR(pretrained=source, config=config)
        if weights is not None:  # the release's .ckpt: a Lightning checkpoint holding state_dict (keys 'matcher.*')
            state = load_weights(weights, "LoFTR weights")
            state = state.get("state_dict", state) if isinstance(state.get("state_dict"), dict) else state
            load_into(self.model, weights, "LoFTR weights", {k.removeprefix("matcher."): v for k, v in state.items()})
        self.model = self.model.eval().to(device)

    def config(self) -> dict:
        return {"matcher": self.name, **self.settings.__dict__}

    @torch.inference_mode()
    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        out = self.model({"image0": grey(image0, self.device), "image1": grey(image1, self.device)})
        k0 = numpy(out["keypoints0"]) - REFERENCE_FRAME_OFFSET
        k1 = numpy(out["keypoints1"]) - REFERENCE_FRAME_OFFSET
        return Matches(k0, k1, numpy(out["confidence"]), {"n_matches_raw": len(k0)})
