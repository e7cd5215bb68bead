"""`dfm`: DFM (Efe et al. 2021), the two-stage baseline.

variant "release" (default) reproduces the DFM release (matching/release.py, proven by
tests/matching/test_parity.py); "corrected" is the release with its two evident slips fixed (the
refinement's B->A ratio index, the final filter's height test); "bench" is this project's
earlier reading of the DFM paper (matching/dfm.py: valid cells only, warp-border mask, a
minimum of stage-0 inliers).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import cv2
import numpy as np

from e3cm_bench.backbones.pyramid import Backbone
from e3cm_bench.matching.dfm import DFMSettings, match_two_stage
from e3cm_bench.matching.release import (
    DFM_FIXES, DFMRelease, dfm_release_final, dfm_release_stage0, dfm_release_stage1,
)
from e3cm_bench.matchers.base import Matches
from e3cm_bench.matchers.deep import DeepMatcher, level0_cosine

DFM_VARIANTS = ("release", "corrected", "bench")


def check_dfm_settings(settings: dict) -> None:
    """A ValueError where `settings` do not fit `dfm` (its variant and that variant's fields)."""
    settings = dict(settings)
    variant = settings.pop("variant", "release")
    if variant not in DFM_VARIANTS:
        raise ValueError(f"dfm variant must be one of {', '.join(DFM_VARIANTS)}, got {variant!r}")
    if variant == "bench":
        DFMSettings(**settings)
    elif set(settings) - {"ratio"}:
        raise ValueError(f"dfm variant {variant!r} takes only 'ratio', got {', '.join(sorted(settings))}")
    elif len(settings.get("ratio", DFMRelease.ratio)) < 5:
        raise ValueError("dfm ratio needs 5 values: refinement into levels 0..3, then stage 1's dense matching")


@dataclass(frozen=True)
class DFMMatcherSettings:
    """dfm's settings. variant: release (the DFM release), corrected (its two slips fixed) or
    bench (this project's reading of the paper). ratio: levels 0..3 refinement, then stage 1's
    dense matching (None: the variant's, 0.9,0.9,0.9,0.9,0.95). bench only:
    homography_threshold_px (None: 1.5 x the deepest stride) and min_inliers of stage 0."""

    variant: str = "release"
    ratio: tuple[float, ...] | None = None
    homography_threshold_px: float | None = None
    min_inliers: int | None = None

    def __post_init__(self) -> None:
        check_dfm_settings(self.given())

    def given(self) -> dict:
        """The fields set (not None): DFMMatcher's keyword arguments."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


class DFMMatcher(DeepMatcher):
    """Two-stage DFM: a coarse homography warp, then hierarchical matching on the warped pair.

    Keyword arguments: variant, ratio, and for "bench" the other DFMSettings fields. The
    stage-0 RANSAC draws from OpenCV's global RNG: the caller seeds it per pair
    (cv2.setRNGSeed; the runner does).
    """

    def __init__(self, backbone: Backbone, name: str = "dfm", channel_order: str = "rgb", variant: str = "release",
                 **settings):
        super().__init__(backbone, name, channel_order)
        check_dfm_settings({"variant": variant, **settings})
        self.variant = variant
        # The release's final filter tests y against the padded width (a slip kept): its points
        # may lie below the image.
        self.keypoints_in_image = variant == "bench"
        if variant == "bench":
            self.settings = DFMSettings(**settings)
        else:
            ratio = tuple(float(r) for r in settings.get("ratio", DFMRelease.ratio))
            self.settings = DFMRelease(ratio=ratio, fixes=DFM_FIXES if variant == "corrected" else ())

    @property
    def uses_feature_cache(self) -> bool:  # the release path runs the network with DFM's extra tap itself
        return self.variant == "bench"

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        """Timings: backbone (all passes, warped B included), stage0, warp, stage1 (seconds)."""
        if self.variant == "bench":
            feats0, feats1, t_backbone = self.pyramids(image0, image1)
            out = match_two_stage(image0, image1, feats0, feats1, self.pyramid, self.settings)
            timings = out.pop("timings")
            timings = {"backbone": t_backbone + timings.pop("backbone_warped"), **timings}
            info = {k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")}
            info["timings"] = timings
            return Matches(out["keypoints0"], out["keypoints1"], out["scores"], info)
        return self._match_release(image0, image1)

    def _match_release(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        s = self.settings
        t = time.perf_counter()
        feats0, top0 = self.backbone.pyramid(self.network_input(image0), stage1_tap=True)
        feats1, _ = self.backbone.pyramid(self.network_input(image1), stage1_tap=True)
        timings = {"backbone": time.perf_counter() - t}
        # Backbones without DFM's extra tap start stage 1 from the deepest map.
        t = time.perf_counter()
        H_init, n_stage0 = dfm_release_stage0(feats0[-1], feats1[-1], len(feats0) - 1, s)
        timings["stage0"] = time.perf_counter() - t
        t = time.perf_counter()
        warped = cv2.warpPerspective(image1, H_init, (image0.shape[1], image0.shape[0]))
        timings["warp"] = time.perf_counter() - t
        t = time.perf_counter()
        feats_w, top_w = self.backbone.pyramid(self.network_input(warped), stage1_tap=True)
        timings["backbone"] += time.perf_counter() - t
        t = time.perf_counter()
        top0 = feats0[-1] if top0 is None else top0
        top_w = feats_w[-1] if top_w is None else top_w
        cells0, cells_w = dfm_release_stage1(feats0, feats_w, top0, top_w, s)
        size0, size1 = (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0])
        scores = level0_cosine(feats0[0], feats_w[0], cells0.cpu().numpy(), cells_w.cpu().numpy())
        x0, x1, keep = dfm_release_final(cells0, cells_w, H_init, size0, size1, s)
        timings["stage1"] = time.perf_counter() - t
        info = {"stage0_matches": n_stage0, "H_BA": H_init, "stage1_matches": len(cells0), "timings": timings}
        return Matches(x0, x1, scores[keep], info)

    def settings_dict(self) -> dict:
        if self.variant == "bench":
            return {"variant": "bench", **self.settings.to_dict(self.backbone.deepest_stride)}
        s = self.settings
        return {
            "variant": self.variant, "ratio": list(s.ratio), "stage0_ratio": s.stage0_ratio,
            "homography_threshold_px": s.homography_threshold_px, "fixes": list(s.fixes),
            "stage1_start": "conv5_2" if self.backbone.spec.stage1_tap is not None and self.backbone.num_levels == 5
            else "deepest tap",
        }
