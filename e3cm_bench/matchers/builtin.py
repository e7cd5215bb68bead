"""The built-in matchers' registry entries: registered by the registry's first lookup through
the same `MatcherEntry` every plugin gives. What each name means is fixed (docs/methods.md
"Matchers"): a row's meaning never drifts with a setting's default."""

from __future__ import annotations

from e3cm_bench.matching import RANDOM_ESTIMATORS
from e3cm_bench.matching.pipeline import E3CMSettings
from e3cm_bench.matchers.base import MatcherEntry, always
from e3cm_bench.matchers.dfm import DFMMatcher, DFMMatcherSettings
from e3cm_bench.matchers.e3cm import DirectSettings, E3CMMatcher
from e3cm_bench.matchers.e3cm_plus import E3CMPlusMatcher, E3CMPlusSettings
from e3cm_bench.matchers.e3cm_release import E3CMReleaseMatcher, E3CMReleaseSettings
from e3cm_bench.matchers.colmap_sift import ColmapSiftSettings
from e3cm_bench.matchers.sift import SiftMatcher, SiftSettings


def _e3cm(settings: E3CMSettings, net, channel_order: str) -> E3CMMatcher:
    return E3CMMatcher(net, settings, name="e3cm", channel_order=channel_order)


def _direct(settings: DirectSettings, net, channel_order: str) -> E3CMMatcher:
    return E3CMMatcher(net, settings, name="direct", channel_order=channel_order)


def _colmap_sift(settings):
    from e3cm_bench.matchers.colmap_sift import ColmapSiftMatcher

    return ColmapSiftMatcher(settings)


def _release_as_published(settings: dict) -> bool:
    return not set(settings) - {"channel_order", "num_levels"}


BUILTIN = (
    MatcherEntry(
        "e3cm", "E3CM as the paper writes it: cascade of fundamental matrices, top-8 8-point fits per level",
        _e3cm, E3CMSettings, needs_backbone=True,
        is_random=lambda s: s.estimator in RANDOM_ESTIMATORS,
        shorthands=("ratio", "estimator", "sampson_px"), recorded={"estimator": "top8"}),
    MatcherEntry(
        "e3cm-ransac", "e3cm with a RANSAC cascade (our variant): e3cm with estimator=ransac",
        _e3cm, preset_of="e3cm", preset={"estimator": "ransac"}, needs_backbone=True),
    MatcherEntry(
        "e3cm-release", "the E3CM authors' released code (match_large_img + refinement_pose_ransac)",
        lambda s, net, channel_order: E3CMReleaseMatcher(net, s, channel_order=channel_order),
        E3CMReleaseSettings, needs_backbone=True, is_random=lambda s: s.cascade, shorthands=("ratio",),
        paper_row="E3CM", paper_setting=_release_as_published),
    MatcherEntry(
        "e3cm-plus", "our variant: stage-0 prewarp, robust cascade, realignment, sub-pixel refinement (lk-auto)",
        lambda s, net, channel_order: E3CMPlusMatcher(net, s, channel_order=channel_order),
        E3CMPlusSettings, needs_backbone=True, is_random=always, shorthands=("ratio",),
        # recorded: its runs from before refinement was on (settings {}) are not resumed as these
        recorded={"refine": "lk-auto"}),
    MatcherEntry(
        "direct", "ablation: E3CM without the cascade (mutual NN + ratio + refinement)",
        _direct, DirectSettings, needs_backbone=True, shorthands=("ratio",)),
    MatcherEntry(
        "dfm", "DFM (Efe et al. 2021) as released: homography prewarp, then hierarchical refinement",
        lambda s, net, channel_order: DFMMatcher(net, channel_order=channel_order, **s.given()),
        DFMMatcherSettings, needs_backbone=True, is_random=always, shorthands=("ratio",),
        paper_row="DFM", paper_setting=lambda settings: settings.get("variant", "release") == "release"),
    MatcherEntry(
        "sift", "SIFT + nearest neighbour with Lowe's ratio test (OpenCV)",
        lambda s: SiftMatcher(s.max_keypoints, s.ratio, s.cross_check), SiftSettings, paper_row="SIFT+NN",
        keypoints_are_detections=True),
    MatcherEntry(
        "colmap-sift", "COLMAP's own SIFT and matcher (pycolmap; the multi-view tables' reference row)",
        _colmap_sift, ColmapSiftSettings, requires=("pycolmap",), keypoints_are_detections=True),
)
