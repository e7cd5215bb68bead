"""e3cm-plus: this project's best training-free variant of E3CM (docs/methods.md "e3cm-plus").

The paper's idea is kept: deep matches refined level by level, each level's epipolar geometry
rejecting the next level's outliers. What changed, where measurements on the choosing split
(the HPatches and KITTI samples; ScanNet never) pointed:
- prewarp: DFM's stage 0 first (a homography from the deepest level's matches), and B warped
  onto A where that homography turns or stretches the image centre's neighbourhood beyond
  what the features tolerate ("auto", PREWARP_*): rotation, zoom and strong perspective no
  longer defeat features that are not invariant to them. The cascade then runs between A
  and the warped B (their epipolar geometry is B's composed with the homography) and the
  points are mapped back. On KITTI's forward motion the homography is a poor stand-in for a
  non-planar scene and warping cost pose accuracy; the auto test leaves those pairs as they are.
- realign: where B was warped, the homography is fitted again to the final matches and B
  matched once more through it; nearly aligned, the fine levels' features agree and
  localise better (one more backbone pass on those pairs).
- estimator: F of each level from all its matches, by OpenCV's MAGSAC++ where B was warped
  (such pairs are near-planar, where plain RANSAC's F degenerates and USAC's checks it) and
  by RANSAC elsewhere ("auto"), instead of an exact 8-point fit to 8 cell centres.
- subpixel (off by default; it cost KITTI 8 points of AUC@5): each B keypoint moved to the
  peak of a parabola fitted to the level-0 similarity.
- refine (lk-auto by default): the final matches refined on the images (matching/subpixel.py,
  `refine_lk_auto`): Lucas-Kanade from each match, the matches that fail its checks dropped
  where LK fits the pair (on the grey levels, or on the local contrast across an illumination
  change), kept where it does not (a large turn or zoom). On the choosing sets it lifted
  HPatches h_acc@1 from 0.40 to 0.53 (3 and 5 px unchanged) and KITTI AUC@5 from 61.2 to 69.7.
Each is a setting (`--set prewarp=false`, ...), so the ablation runs from the CLI.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from e3cm_bench.backbones.pyramid import Backbone
from e3cm_bench.geometry.two_view import estimate_homography, local_distortion
from e3cm_bench.matching import ESTIMATORS
from e3cm_bench.matching.dfm import MIN_INLIERS, DFMSettings, match_through_warp, stage0_homography
from e3cm_bench.matching.pipeline import E3CMSettings
from e3cm_bench.matching.subpixel import check_refine, refine_matches
from e3cm_bench.matchers.base import Matches
from e3cm_bench.matchers.deep import DeepMatcher

# "auto" prewarp: warp when the stage-0 homography's local map at B's centre turns by more
# than this, or scales (either axis, or one against the other) by more than this factor.
# The warp rescues pairs with large turns or zooms, which the unwarped cascade fails, and
# costs a little accuracy on pairs the unwarped cascade already matches; the bounds sit
# between those two kinds of pair on the shared sets (scripts/results/prewarp_report.py; the
# evidence: docs/methods.md, "Where e3cm-plus's automatic prewarp fires").
PREWARP_MIN_ROTATION_DEG = 16.0
PREWARP_MAX_SCALE = 1.5
# realign: the RANSAC threshold of the homography refitted to the final (level-0) matches.
REALIGN_PX = 3.0
# estimator "auto": the cascade's estimator for pairs matched through a warp, and for the rest.
AUTO_ESTIMATORS = {"warped": "magsac", "direct": "ransac"}


def prewarp_refusal(H_BA: np.ndarray, size_b: tuple[int, int]) -> str | None:
    """None when H_BA distorts B's centre enough to be worth warping, else why not."""
    rotation, big, small = local_distortion(H_BA, (size_b[0] / 2, size_b[1] / 2))
    if abs(rotation) > PREWARP_MIN_ROTATION_DEG or big > PREWARP_MAX_SCALE or small < 1 / PREWARP_MAX_SCALE \
            or big / small > PREWARP_MAX_SCALE:
        return None
    return f"close to the identity (rotation {rotation:.1f} deg, scales {big:.2f} / {small:.2f})"


def prewarp_decision(feats0: list, feats1: list, size0: tuple[int, int], size1: tuple[int, int],
                     settings: E3CMPlusSettings) -> tuple[np.ndarray | None, dict]:
    """(H_BA or None, info): DFM's stage 0 on the deepest maps, and whether B is warped by it
    (settings.prewarp true: whenever stage 0 finds H; "auto": where prewarp_refusal says it
    is worth it). info: the decision ("warped" / "not warped: why"), the stage-0 match and
    inlier counts, and H's rotation and scales at B's centre (degrees; larger, smaller)."""
    top = len(feats0) - 1
    stage0 = stage0_homography(feats0[-1], feats1[-1], top, size0, size1, settings.stage0,
                               settings.stage0.threshold_px(2**top))
    H_BA, why = stage0["H_BA"], stage0["failure"]
    info = {"stage0_matches": stage0["matches"], "stage0_inliers": stage0["inliers"]}
    if H_BA is not None:
        rotation, big, small = local_distortion(H_BA, (size1[0] / 2, size1[1] / 2))
        info.update(rotation_deg=float(rotation), scale_big=float(big), scale_small=float(small))
        if settings.prewarp == "auto":
            why = prewarp_refusal(H_BA, size1)
            H_BA = None if why else H_BA
    info = {"prewarp": "warped" if H_BA is not None else f"not warped: {why}", **info}
    return H_BA, info


@dataclass
class E3CMPlusSettings:
    """prewarp (true, false, auto), realign, estimator (one of the cascade's, or auto),
    subpixel: the changes (module docstring). refine, refine_window: sub-pixel refinement of
    the final matches on the images, as e3cm's (E3CMSettings), lk-auto by default (none in e3cm). ratio: per
    level 0..4. sampson_px: rejection thresholds of levels 0..3 (None: the estimator's
    default). max_per_parent: children kept per refined match. min_inliers: fewest stage-0
    RANSAC inliers for its homography."""

    prewarp: bool | str = "auto"
    realign: bool = True
    estimator: str = "auto"
    subpixel: bool = False
    ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.9)
    sampson_px: tuple[float, ...] | None = None
    max_per_parent: int = 2
    min_inliers: int = MIN_INLIERS
    refine: str = "lk-auto"
    refine_window: int = 9

    def __post_init__(self) -> None:
        if self.prewarp not in (True, False, "auto"):
            raise ValueError(f"prewarp must be true, false or auto, got {self.prewarp!r}")
        for name in ("subpixel", "realign"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.estimator != "auto" and self.estimator not in ESTIMATORS:
            raise ValueError(
                f"unknown cascade estimator {self.estimator!r}; choose auto or one of {', '.join(ESTIMATORS)}"
            )
        self.pipelines = {
            kind: E3CMSettings(estimator=AUTO_ESTIMATORS[kind] if self.estimator == "auto" else self.estimator,
                               ratio=self.ratio, sampson_px=self.sampson_px, subpixel=self.subpixel,
                               max_per_parent=self.max_per_parent)
            for kind in ("warped", "direct")
        }
        self.ratio = self.pipelines["direct"].ratio
        check_refine(self.refine, self.refine_window)
        self.stage0 = DFMSettings(ratio=self.ratio, min_inliers=self.min_inliers)

    def to_dict(self, deepest_stride: int) -> dict:
        fields = {k: v for k, v in asdict(self).items() if k not in ("pipelines", "stage0")}
        fields["ratio"] = list(self.ratio)
        fields["pipeline"] = {kind: p.to_dict() for kind, p in self.pipelines.items()}
        if self.prewarp:
            fields["stage0"] = self.stage0.to_dict(deepest_stride)["homography_ransac"]
            fields["prewarp_auto"] = {"min_rotation_deg": PREWARP_MIN_ROTATION_DEG, "max_scale": PREWARP_MAX_SCALE}
            fields["realign_px"] = REALIGN_PX
        return fields


class E3CMPlusMatcher(DeepMatcher):
    """[stage 0 -> warp B [-> realign]] -> E3CM with a robust cascade -> [sub-pixel level 0]."""

    def __init__(self, backbone: Backbone, settings: E3CMPlusSettings | None = None, channel_order: str = "rgb"):
        super().__init__(backbone, "e3cm-plus", channel_order)
        self.settings = settings or E3CMPlusSettings()

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        s = self.settings
        feats0, feats1, t_backbone = self.pyramids(image0, image1)
        timings = {"backbone": t_backbone}
        size0, size1 = (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0])
        H_BA, info = None, {"prewarp": "off"}
        if s.prewarp:
            t = time.perf_counter()
            H_BA, info = prewarp_decision(feats0, feats1, size0, size1, s)
            timings["stage0"] = time.perf_counter() - t
        pipeline = s.pipelines["warped" if H_BA is not None else "direct"]
        out = match_through_warp(image0, image1, feats0, feats1, H_BA, self.pyramid, pipeline)
        if H_BA is not None and s.realign:
            H = estimate_homography(out["keypoints1"], out["keypoints0"], REALIGN_PX)
            if H is not None and abs(np.linalg.det(H)) > 1e-12:
                first = out["timings"]
                out = match_through_warp(image0, image1, feats0, feats1, H, self.pyramid, pipeline)
                out["timings"] = {k: first.get(k, 0.0) + v for k, v in out["timings"].items()}
                info["realigned"] = True
        steps = out.pop("timings")
        timings["backbone"] += steps.pop("backbone_warped")
        timings.update(steps)
        if s.refine != "none":  # on the final matches, in the original images
            t = time.perf_counter()
            k1, keep = refine_matches(image0, image1, out["keypoints0"], out["keypoints1"], s.refine, s.refine_window)
            out.update(keypoints0=out["keypoints0"][keep], keypoints1=k1[keep], scores=out["scores"][keep])
            timings["refine"] = time.perf_counter() - t
        info.update({k: v for k, v in out.items() if k not in ("keypoints0", "keypoints1", "scores")},
                    estimator=pipeline.estimator, timings=timings)
        return Matches(out["keypoints0"], out["keypoints1"], out["scores"], info)

    def settings_dict(self) -> dict:
        return self.settings.to_dict(self.backbone.deepest_stride)
