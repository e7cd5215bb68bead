"""DFM (Efe et al. 2021), the two-stage baseline, as PROTOCOLS §1 pins it: arrays in, a dict out.

stage 0: mutual NN + ratio at the deepest level, RANSAC homography H_BA (B -> A pixels);
warp:    image B onto A's frame with H_BA;
stage 1: the E3CM pipeline without the cascade (dense matching at the deepest level, DFM
         2x2 refinement down to level 0) between A and the warped B;
back:    warped-B keypoints -> B pixels with inv(H_BA); matches outside B or on the black
         border of the warp are dropped.
When stage 0 gives no usable homography, H_BA falls back to the identity (B is matched as is)
and the result says so. The warped image needs its own features: the caller passes the
feature extractor, so this module stays free of models and files.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from e3cm_bench.geometry.two_view import estimate_homography, warp_points
from e3cm_bench.matching.dense import match_dense_level
from e3cm_bench.matching.levels import cell_centres, valid_extent
from e3cm_bench.matching.pipeline import E3CMSettings, match_pyramids

# Stage-0 RANSAC threshold, in cells of the deepest level (x its stride = pixels). Stage-0
# points are cell centres on the stride grid of both images, so a correct match can be off
# by up to a stride from the true H before the coarse features' own localisation error.
# Measured with EfficientNet-Lite0 at 640 px (stride 16) on v_graffiti and v_boat 1-2..1-6
# (10 pairs): threshold 8 / 16 / 24 px gave mean stage-1 MMA@3 0.67 / 0.68 / 0.73 and MMA@5
# 0.78 / 0.79 / 0.85 (v_graffiti 1-2 alone: 0.62 / 0.76 / 0.88); the stage-0 H alone, on those
# pairs plus i_leuven, was as good at 24-48 px as at 16-24 and worse below 16. Hence 1.5 cells.
HOMOGRAPHY_THRESHOLD_CELLS = 1.5
HOMOGRAPHY_MAX_ITERS = 5000
HOMOGRAPHY_CONFIDENCE = 0.9999

# Fewest RANSAC inliers for the stage-0 H to be trusted. Four points always fit some H, so
# unrelated images "find" one: at 640 px, pairs of unrelated HPatches images and of random
# noise gave 5-10 inliers, the 15 v_graffiti / v_boat / i_leuven pairs 22-910 (except v_boat
# 1-5, 7 inliers and a wrong H either way). DFM itself has no such check; min_inliers=4
# restores its behaviour.
MIN_INLIERS = 15

FeatureExtractor = Callable[[np.ndarray], list[torch.Tensor]]


@dataclass
class DFMSettings:
    """ratio: ratio-test threshold per level 0..4; the deepest level's entry also serves stage 0.
    homography_threshold_px: stage-0 RANSAC threshold (None: 1.5 x the deepest stride).
    min_inliers: fewest stage-0 RANSAC inliers to accept H_BA; below it, the identity is used.
    """

    ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.95)
    homography_threshold_px: float | None = None
    min_inliers: int = MIN_INLIERS

    def __post_init__(self) -> None:
        # DFM's stage 1 is the E3CM pipeline with the cascade off; it also validates `ratio`.
        self.stage1 = E3CMSettings(cascade=False, ratio=self.ratio)
        self.ratio = self.stage1.ratio
        self.min_inliers = max(4, int(self.min_inliers))

    def threshold_px(self, deepest_stride: int) -> float:
        if self.homography_threshold_px is None:
            return HOMOGRAPHY_THRESHOLD_CELLS * deepest_stride
        return float(self.homography_threshold_px)

    def to_dict(self, deepest_stride: int) -> dict:
        return {
            "ratio": list(self.ratio),
            "max_per_parent": self.stage1.max_per_parent,
            "drop_border": self.stage1.drop_border,
            "homography_ransac": {
                "threshold_px": self.threshold_px(deepest_stride),
                "max_iters": HOMOGRAPHY_MAX_ITERS,
                "confidence": HOMOGRAPHY_CONFIDENCE,
                "min_inliers": self.min_inliers,
            },
            "fallback": "identity H_BA (B matched unwarped) when stage 0 gives no usable homography",
        }


def match_two_stage(
    image0: np.ndarray,
    image1: np.ndarray,
    feats0: list[torch.Tensor],
    feats1: list[torch.Tensor],
    extract: FeatureExtractor,
    settings: DFMSettings,
    stage1: E3CMSettings | None = None,
) -> dict:
    """DFM on two RGB images whose feature pyramids are given; `extract` computes the warped B's.

    stage1: the pipeline between A and the warped B (default DFM's, settings.stage1: no
    cascade).

    The stage-0 RANSAC draws from OpenCV's global RNG: the caller seeds it per pair
    (cv2.setRNGSeed), as for the cascade's RANSAC. Returns keypoints0/1 (pixels of the
    images), scores and diagnostics; timings: stage0, warp, backbone_warped, stage1 (s).
    """
    timings: dict[str, float] = {}
    size0 = (image0.shape[1], image0.shape[0])
    size1 = (image1.shape[1], image1.shape[0])
    deepest_stride = 2 ** (len(feats0) - 1)
    threshold = settings.threshold_px(deepest_stride)

    t = time.perf_counter()
    stage0 = stage0_homography(feats0[-1], feats1[-1], len(feats0) - 1, size0, size1, settings, threshold)
    timings["stage0"] = time.perf_counter() - t
    H_BA = stage0["H_BA"]
    found = H_BA is not None

    out = match_through_warp(image0, image1, feats0, feats1 if not found else None, H_BA, extract,
                             stage1 or settings.stage1)
    timings.update(out.pop("timings"))
    return {
        **out,
        "stage0_matches": stage0["matches"],
        "stage0_inliers": stage0["inliers"],
        "homography_found": found,
        "homography_fallback": None if found else f"identity ({stage0['failure']})",
        "timings": timings,
    }


def match_through_warp(
    image0: np.ndarray,
    image1: np.ndarray,
    feats0: list[torch.Tensor],
    feats1: list[torch.Tensor] | None,
    H_BA: np.ndarray | None,
    extract: FeatureExtractor,
    stage1: E3CMSettings,
) -> dict:
    """Stage 1: B warped onto A by H_BA (None: B as is, with its pyramid feats1), matched to A
    with the `stage1` pipeline, and the keypoints mapped back to B. Matches outside B or on
    the warp's black border are dropped. Returns keypoints0/1, scores, H_BA, stage1 (the
    pipeline's diagnostics) and timings: warp, backbone_warped, stage1 (s)."""
    timings: dict[str, float] = {}
    size0 = (image0.shape[1], image0.shape[0])
    size1 = (image1.shape[1], image1.shape[0])
    found = H_BA is not None
    t = time.perf_counter()
    warped, valid, H_BA = _warped(image1, H_BA, size0)
    timings["warp"] = time.perf_counter() - t

    t = time.perf_counter()
    feats_w = extract(warped) if found else feats1
    timings["backbone_warped"] = time.perf_counter() - t

    t = time.perf_counter()
    size_w = (warped.shape[1], warped.shape[0])
    out = match_pyramids(feats0, feats_w, size0, size_w, stage1)
    kpts0, kpts_w, scores = out["keypoints0"], out["keypoints1"], out["scores"]
    kpts1 = warp_points(np.linalg.inv(H_BA), kpts_w)
    # Level-0 keypoints lie inside the warped image (sub-pixel ones within half a pixel of
    # a pixel centre): rounded, they index the mask.
    rows = np.clip(np.rint(kpts_w[:, 1]).astype(int), 0, valid.shape[0] - 1)
    cols = np.clip(np.rint(kpts_w[:, 0]).astype(int), 0, valid.shape[1] - 1)
    on_image = valid[rows, cols]
    in_b = _inside(kpts1, size1)
    keep = on_image & in_b
    timings["stage1"] = time.perf_counter() - t

    diagnostics = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
    diagnostics["matches_before_mapping"] = len(kpts0)
    diagnostics["dropped_on_warp_border"] = int((~on_image).sum())
    diagnostics["dropped_outside_b"] = int((on_image & ~in_b).sum())
    return {
        "keypoints0": kpts0[keep],
        "keypoints1": kpts1[keep],
        "scores": scores[keep],
        "H_BA": H_BA,
        "stage1": diagnostics,
        "timings": timings,
    }


def _warped(image1: np.ndarray, H_BA: np.ndarray | None, size0: tuple[int, int]) -> tuple:
    """(B warped onto A by H_BA, the mask of its pixels that are all B's, the H_BA used): B as
    it is, whole, with the identity where H_BA is None."""
    if H_BA is not None:
        warped = cv2.warpPerspective(image1, H_BA, size0, flags=cv2.INTER_LINEAR, borderValue=0)
        # A full-white mask warped the same (bilinear) way drops below 255 on every pixel
        # that blends in the black outside of B.
        ones = np.full(image1.shape[:2], 255, np.uint8)
        valid = cv2.warpPerspective(ones, H_BA, size0, flags=cv2.INTER_LINEAR, borderValue=0) == 255
        return warped, valid, H_BA
    # Warping by the identity is image B itself; taking B unwarped also keeps all of it
    # when the two sizes differ, and its features are already computed.
    return image1, np.ones(image1.shape[:2], bool), np.eye(3)


def stage0_homography(
    top0: torch.Tensor, top1: torch.Tensor, level: int, size0: tuple[int, int], size1: tuple[int, int],
    settings: DFMSettings, threshold: float,
) -> dict:
    """Deepest-level matches and the homography B -> A fitted to their cell centres.

    Returns matches, inliers, H_BA (None when unusable) and failure (why, or None).
    """
    cells0, cells1, _ = match_dense_level(
        F.normalize(top0, dim=0), F.normalize(top1, dim=0),
        valid_extent(size0, level), valid_extent(size1, level),
        settings.ratio[level], settings.stage1.drop_border, settings.stage1.dense_chunk,
    )
    result = {"matches": len(cells0), "inliers": 0, "H_BA": None, "failure": None}
    if len(cells0) < 4:
        result["failure"] = f"{len(cells0)} stage-0 matches, fewer than 4"
        return result
    x0 = cell_centres(cells0, level).cpu().numpy()
    x1 = cell_centres(cells1, level).cpu().numpy()
    H = estimate_homography(x1, x0, threshold, HOMOGRAPHY_MAX_ITERS, HOMOGRAPHY_CONFIDENCE)
    if H is None or abs(np.linalg.det(H)) < 1e-12:  # a singular H cannot map matches back to B
        result["failure"] = "RANSAC found no invertible homography"
        return result
    # The same reprojection error OpenCV's RANSAC scores inliers with (B mapped into A).
    with np.errstate(invalid="ignore"):
        residuals = np.linalg.norm(warp_points(H, x1) - x0, axis=1)
    result["inliers"] = int(np.sum(residuals <= threshold))
    if result["inliers"] < settings.min_inliers:
        result["failure"] = f"{result['inliers']} RANSAC inliers, fewer than {settings.min_inliers}"
        return result
    result["H_BA"] = H
    return result


def _inside(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Points within the image area, pixel-centre convention: [-0.5, w - 0.5] x [-0.5, h - 0.5]."""
    w, h = size
    x, y = points[:, 0], points[:, 1]
    with np.errstate(invalid="ignore"):  # points sent to infinity by H are NaN/inf: outside
        return (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
