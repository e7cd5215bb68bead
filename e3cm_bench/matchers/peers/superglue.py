"""`superpoint+superglue`: SuperPoint + SuperGlue (Sarlin et al. 2020), transformers'
implementation of Magic Leap's models and weights (licensed for non-commercial use only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.peers.common import SUPERPOINT_REPO, grey, numpy, superpoint_keypoints

SUPERGLUE_REPOS = {"outdoor": "magic-leap-community/superglue_outdoor",
                   "indoor": "magic-leap-community/superglue_indoor"}


def _normalised_as(points: torch.Tensor, size: tuple[int, int], canvas: tuple[int, int]) -> torch.Tensor:
    """Points of an image of `size` (w, h) moved so that SuperGlue's keypoint normalisation
    for an image of `canvas` gives what it gives them in their own image: SuperGlue
    normalises each image's keypoints by that image's size, transformers' pair by one size."""
    own, other = torch.tensor(size, dtype=points.dtype), torch.tensor(canvas, dtype=points.dtype)
    return other / 2 + (points - own / 2) * (other.max() / own.max())


def release_state_dict(release: dict, heads: int) -> dict:
    """Magic Leap's release checkpoint (``superglue_outdoor.pth``, ``superglue_indoor.pth``: 1x1
    Conv1d layers under ``kenc``, ``gnn.layers.N.attn`` / ``.mlp``, ``final_proj``, ``bin_score``)
    as the state dict of transformers' SuperGlue (Linear layers, its own names).

    The release cuts each projection's channels into heads as channel = d * heads + h,
    transformers as channel = h * head_dim + d; the rows of query, key and value and the
    columns of the merge are reordered so that the two compute the same attention.
    An unknown key or a missing layer is a ValueError."""
    def linear(value: torch.Tensor) -> torch.Tensor:
        return value[..., 0] if value.dim() == 3 else value

    encoder = sorted({int(k.split(".")[2]) for k in release if k.startswith("kenc.encoder.") and k.endswith(".weight")
                      and release[k].dim() == 3})
    if not encoder or "bin_score" not in release or "final_proj.weight" not in release:
        raise ValueError("not a SuperGlue release checkpoint (it lacks kenc.encoder.*, final_proj or bin_score)")
    dim = release["final_proj.weight"].shape[0]
    order = torch.arange(dim).view(dim // heads, heads).t().reshape(-1)  # transformers' channel -> the release's
    out = {}
    for key, value in release.items():
        parts, value = key.split("."), linear(value)
        if key == "bin_score":
            new = key
        elif parts[0] == "final_proj":
            new = f"final_projection.final_proj.{parts[-1]}"
        elif parts[:2] == ["kenc", "encoder"] and len(parts) == 4:
            index = int(parts[2])
            layer, kind = divmod(index, 3)
            if kind == 0:
                new = f"keypoint_encoder.encoder.{layer}.{'' if index == encoder[-1] else 'linear.'}{parts[3]}"
            elif kind == 1:
                new = f"keypoint_encoder.encoder.{layer}.batch_norm.{parts[3]}"
            else:
                raise ValueError(f"not a SuperGlue release checkpoint (unexpected key {key})")
        elif parts[:2] == ["gnn", "layers"] and parts[3] == "attn":
            prefix = f"gnn.layers.{parts[2]}.attention"
            if parts[4] == "proj" and len(parts) == 7:
                new = f"{prefix}.self.{('query', 'key', 'value')[int(parts[5])]}.{parts[6]}"
                value = value[order]
            elif parts[4] == "merge" and len(parts) == 6:
                new = f"{prefix}.output.dense.{parts[5]}"
                value = value[:, order] if parts[5] == "weight" else value
            else:
                raise ValueError(f"not a SuperGlue release checkpoint (unexpected key {key})")
        elif parts[:2] == ["gnn", "layers"] and parts[3] == "mlp" and len(parts) == 6:
            place = {"0": "0.linear", "1": "0.batch_norm", "3": "1"}.get(parts[4])
            if place is None:
                raise ValueError(f"not a SuperGlue release checkpoint (unexpected key {key})")
            new = f"gnn.layers.{parts[2]}.mlp.{place}.{parts[5]}"
        else:
            raise ValueError(f"not a SuperGlue release checkpoint (unexpected key {key})")
        out[new] = value.contiguous()
    return out


def load_release(model, path: Path) -> None:
    """SuperGlue's layers of `model` from the release checkpoint at `path` (SuperPoint's are
    left as they are); a file that is not one is a one-line ValueError naming it."""
    try:
        release = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(release, dict):
            raise ValueError("not a state dict")
        state = release_state_dict(release, model.config.num_attention_heads)
        missing, unexpected = model.load_state_dict(state, strict=False)
    except (RuntimeError, ValueError, KeyError, IndexError, AttributeError, OSError) as error:
        reason = " ".join(str(error).split())[:300]
        raise ValueError(f"{path}: cannot load as SuperGlue's release weights ({reason})") from None
    missing = [k for k in missing if not k.startswith("keypoint_detector.")]
    if missing or unexpected:
        raise ValueError(
            f"{path}: cannot load as SuperGlue's release weights (missing {missing[:3]}, unexpected {unexpected[:3]})"
        )


class SuperGlueMatcher(Matcher):
    """SuperPoint on each grey image (its own size), then SuperGlue's graph network and
    Sinkhorn; mutual matches above match_threshold. Scores: SuperGlue's matching scores.
    weights: Magic Leap's release ``superglue_*.pth`` (SuperPoint then comes from transformers'
    cache); without it, transformers' converted models from the Hugging Face cache."""

    name = "superpoint+superglue"

    def __init__(self, settings, device: str = "cpu", weights: str | Path | None = None, pretrained: bool = True):
        from transformers import (
            SuperGlueConfig,
            SuperGlueForKeypointMatching,
            SuperPointConfig,
            SuperPointForKeypointDetection,
        )

        options = {"sinkhorn_iterations": settings.sinkhorn_iterations, "matching_threshold": settings.match_threshold}
        if weights is not None:  # the release's .pth; SuperPoint from transformers' cache
            self.model = SuperGlueForKeypointMatching(
                SuperGlueConfig(keypoint_detector_config=SuperPointConfig().to_dict(), **options)
            )
            load_release(self.model, Path(weights))
            if pretrained:
                self.model.keypoint_detector = SuperPointForKeypointDetection.from_pretrained(SUPERPOINT_REPO)
        elif pretrained:
            self.model = SuperGlueForKeypointMatching.from_pretrained(SUPERGLUE_REPOS[settings.weights], **options)
        else:
            self.model = SuperGlueForKeypointMatching(
                SuperGlueConfig(keypoint_detector_config=SuperPointConfig().to_dict(), **options)
            )
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
        return superpoint_keypoints(
            self.model.keypoint_detector(pixel_values=grey(image, self.device)), image, self.device
        )

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
            keypoints,
            torch.stack([padded(d0, n), padded(d1, n)])[None],
            torch.stack([padded(s0, n), padded(s1, n)])[None],
            size0[1],
            size0[0],
            mask=mask,
        )
        index0 = matches[0, 0, :len(k0)]
        valid = torch.nonzero(index0 > -1)[:, 0]
        return Matches(numpy(k0[valid]), numpy(k1[index0[valid]]), numpy(scores[0, 0, valid]), info)
