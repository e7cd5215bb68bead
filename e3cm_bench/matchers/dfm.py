"""DFM (Efe et al. 2021), the two-stage baseline, as PROTOCOLS §1 pins it.

stage 0: mutual NN + ratio at the deepest level, RANSAC homography H_BA (B -> A pixels);
warp:    image B onto A's frame with H_BA;
stage 1: the E3CM pipeline without the cascade (dense matching at the deepest level, DFM
         2x2 refinement down to level 0) between A and the warped B;
back:    warped-B keypoints -> B pixels with inv(H_BA); matches outside B or on the black
         border of the warp are dropped.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..backbones import Backbone
from ..geometry import estimate_homography, warp_points
from ..matching.dense import match_dense_level
from ..matching.levels import cell_centres, valid_extent
from ..matching.pipeline import E3CMSettings, match_pyramids
from .base import Matcher, Matches
from .e3cm import image_to_tensor

# Stage-0 RANSAC threshold, in cells of the deepest level (x its stride = pixels).
# Stage-0 points are cell centres, so each side is quantised by up to half a stride and a
# correct match can sit ~0.7 stride off the true H. Measured on v_graffiti 1-2 and
# v_boat 1-3 (640 px, EfficientNet-Lite0, stride 16): see HOMOGRAPHY_THRESHOLD_NOTE.
HOMOGRAPHY_THRESHOLD_CELLS = 0.5
HOMOGRAPHY_MAX_ITERS = 5000
HOMOGRAPHY_CONFIDENCE = 0.9999


class DFMMatcher(Matcher):
    """Two-stage DFM: a coarse homography warp, then hierarchical matching on the warped pair."""

    def __init__(
        self,
        backbone: Backbone,
        ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.95),
        homography_threshold_px: float | None = None,
        name: str = "dfm",
        seed: int = 0,
    ):
        self.backbone = backbone
        self.name = name
        # The pipeline validates the ratios (5 values, levels 0..4); the cascade is DFM-less.
        self.settings = E3CMSettings(cascade=False, ratio=ratio)
        self.ratio = self.settings.ratio
        if homography_threshold_px is None:
            homography_threshold_px = HOMOGRAPHY_THRESHOLD_CELLS * backbone.deepest_stride
        self.homography_threshold_px = float(homography_threshold_px)
        self.seed = int(seed)

    @property
    def device(self) -> torch.device:
        return self.backbone.mean.device

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        timings: dict[str, float] = {}
        size0 = (image0.shape[1], image0.shape[0])
        size1 = (image1.shape[1], image1.shape[0])

        t = time.perf_counter()
        feats0 = self.backbone(image_to_tensor(image0, self.device))
        feats1 = self.backbone(image_to_tensor(image1, self.device))
        timings["backbone"] = time.perf_counter() - t

        t = time.perf_counter()
        n_stage0, H_BA = self._stage0(feats0[-1], feats1[-1], size0, size1)
        timings["stage0"] = time.perf_counter() - t
        found = H_BA is not None

        t = time.perf_counter()
        if found:
            warped = cv2.warpPerspective(image1, H_BA, size0, flags=cv2.INTER_LINEAR, borderValue=0)
            # Bilinear on a 255 mask: any pixel that blends in the black border drops below 255.
            valid = cv2.warpPerspective(np.full(image1.shape[:2], 255, np.uint8), H_BA, size0, flags=cv2.INTER_LINEAR) == 255
        else:
            # Identity fallback: "warping" by I is image B itself; using it unwarped keeps all
            # of B even when the two sizes differ, and saves a backbone pass.
            H_BA = np.eye(3)
            warped, valid = image1, np.ones(image1.shape[:2], bool)
        timings["warp"] = time.perf_counter() - t

        if found:
            t = time.perf_counter()
            feats_w = self.backbone(image_to_tensor(warped, self.device))
            timings["backbone"] += time.perf_counter() - t
        else:
            feats_w = feats1

        t = time.perf_counter()
        size_w = (warped.shape[1], warped.shape[0])
        out = match_pyramids(feats0, feats_w, size0, size_w, self.settings)
        kpts0, kpts_w, scores = out["keypoints0"], out["keypoints1"], out["scores"]
        kpts1 = warp_points(np.linalg.inv(H_BA), kpts_w)
        # Level-0 keypoints are integer pixel centres, so they index the mask directly.
        col = np.rint(kpts_w[:, 0]).astype(int)
        row = np.rint(kpts_w[:, 1]).astype(int)
        keep = valid[row, col] & _inside(kpts1, size1)
        timings["stage1"] = time.perf_counter() - t

        stage1 = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
        stage1["matches_before_mapping"] = len(kpts0)
        info = {
            "stage0_matches": n_stage0,
            "homography_found": found,
            "homography_fallback": None if found else "identity: stage 0 gave no usable homography",
            "H_BA": H_BA,
            "stage1": stage1,
            "timings": timings,
        }
        return Matches(kpts0[keep], kpts1[keep], scores[keep], info)

    def _stage0(
        self, top0: torch.Tensor, top1: torch.Tensor, size0: tuple[int, int], size1: tuple[int, int]
    ) -> tuple[int, np.ndarray | None]:
        """Deepest-level matches and the homography B -> A from their cell centres (or None)."""
        level = self.backbone.num_levels - 1
        cells0, cells1, _ = match_dense_level(
            F.normalize(top0, dim=0), F.normalize(top1, dim=0),
            valid_extent(size0, level), valid_extent(size1, level),
            self.ratio[level], self.settings.drop_border, self.settings.dense_chunk,
        )
        x0 = cell_centres(cells0, level).cpu().numpy()
        x1 = cell_centres(cells1, level).cpu().numpy()
        # OpenCV's RANSAC draws from a global RNG; seeding it here makes a pair's H independent
        # of whatever ran before it.
        cv2.setRNGSeed(self.seed)
        H = estimate_homography(
            x1, x0, self.homography_threshold_px, HOMOGRAPHY_MAX_ITERS, HOMOGRAPHY_CONFIDENCE
        )
        # A singular H cannot be inverted to map the stage-1 matches back to B.
        if H is not None and abs(np.linalg.det(H)) < 1e-12:
            H = None
        return len(cells0), H

    def config(self) -> dict:
        return {
            "matcher": self.name,
            "backbone": self.backbone.name,
            "backbone_taps": self.backbone.spec.taps,
            "num_levels": self.backbone.num_levels,
            "upsample": self.backbone.upsample,
            "weights": self.backbone.weights_id,
            "ratio": list(self.ratio),
            "max_per_parent": self.settings.max_per_parent,
            "drop_border": self.settings.drop_border,
            "homography_ransac": {
                "threshold_px": self.homography_threshold_px,
                "max_iters": HOMOGRAPHY_MAX_ITERS,
                "confidence": HOMOGRAPHY_CONFIDENCE,
                "seed": self.seed,
            },
        }


def _inside(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Points within the image area, pixel-centre convention: [-0.5, w - 0.5] x [-0.5, h - 0.5]."""
    w, h = size
    with np.errstate(invalid="ignore"):
        return (
            (points[:, 0] >= -0.5) & (points[:, 0] <= w - 0.5)
            & (points[:, 1] >= -0.5) & (points[:, 1] <= h - 0.5)
        )
