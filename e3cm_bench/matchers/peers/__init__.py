"""The paper's supervised rows as registered matchers, on the well-kept libraries that ship
them (the optional extra ``e3cm-bench[peers]``: kornia, transformers). Nothing here imports
them until a peer is built; without the extra, asking for one says what to install.

Settings default to each model's reference evaluation settings (docs/peers.md "Peers" names the
source of each); weights come the libraries' way (weights.py) or from --weights FILE.
"""

from __future__ import annotations

from dataclasses import dataclass

from e3cm_bench.matchers.base import MatcherEntry
from e3cm_bench.matchers.peers.weights import HubFile, HubModel

LOFTR_WEIGHTS = ("outdoor", "indoor", "indoor_new")


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _whole(value, low: int, name: str) -> None:
    _check(isinstance(value, int) and not isinstance(value, bool) and value >= low,
           f"{name} must be a whole number >= {low}, got {value!r}")


@dataclass(frozen=True)
class LoFTRSettings:
    """weights: kornia's outdoor (MegaDepth), indoor or indoor_new (ScanNet);
    match_threshold: the coarse dual-softmax threshold (LoFTR's configs: 0.2)."""

    weights: str = "outdoor"
    match_threshold: float = 0.2

    def __post_init__(self) -> None:
        _check(self.weights in LOFTR_WEIGHTS, f"weights must be one of {', '.join(LOFTR_WEIGHTS)}, got {self.weights!r}")
        _check(isinstance(self.match_threshold, (int, float)) and 0 <= self.match_threshold < 1,
               f"match_threshold must be in [0, 1), got {self.match_threshold!r}")


@dataclass(frozen=True)
class SuperGlueSettings:
    """SuperGlue's match_pairs.py defaults (its ScanNet evaluation), outdoor weights; its YFCC
    evaluation sets max_keypoints 2048 and nms_radius 3."""

    weights: str = "outdoor"
    max_keypoints: int = 1024
    keypoint_threshold: float = 0.005
    nms_radius: int = 4
    sinkhorn_iterations: int = 20
    match_threshold: float = 0.2

    def __post_init__(self) -> None:
        _check(self.weights in ("outdoor", "indoor"), f"weights must be outdoor or indoor, got {self.weights!r}")
        _whole(self.max_keypoints, 1, "max_keypoints")
        _whole(self.nms_radius, 1, "nms_radius")
        _whole(self.sinkhorn_iterations, 1, "sinkhorn_iterations")
        for name in ("keypoint_threshold", "match_threshold"):
            value = getattr(self, name)
            _check(isinstance(value, (int, float)) and 0 <= value < 1, f"{name} must be in [0, 1), got {value!r}")


@dataclass(frozen=True)
class LightGlueSettings:
    """glue-factory's official LightGlue evaluation: 2048 keypoints, detection threshold 0,
    no early stopping or pruning (depth and width confidence -1), filter_threshold 0.1.
    nms_radius: SuperPoint's NMS radius (3), DISK's window (5), ALIKED's radius (2)."""

    max_keypoints: int = 2048
    detection_threshold: float = 0.0
    nms_radius: int = 3
    depth_confidence: float = -1.0
    width_confidence: float = -1.0
    filter_threshold: float = 0.1

    def __post_init__(self) -> None:
        _whole(self.max_keypoints, 1, "max_keypoints")
        _whole(self.nms_radius, 1, "nms_radius")
        _check(isinstance(self.filter_threshold, (int, float)) and 0 <= self.filter_threshold < 1,
               f"filter_threshold must be in [0, 1), got {self.filter_threshold!r}")


@dataclass(frozen=True)
class DiskLightGlueSettings(LightGlueSettings):
    nms_radius: int = 5


@dataclass(frozen=True)
class AlikedLightGlueSettings(LightGlueSettings):
    nms_radius: int = 2


def _loftr(settings, **model):
    from e3cm_bench.matchers.peers.loftr import LoFTRMatcher

    return LoFTRMatcher(settings, **model)


def _superglue(settings, **model):
    from e3cm_bench.matchers.peers.superglue import SuperGlueMatcher

    return SuperGlueMatcher(settings, **model)


def _lightglue(kind: str):
    def build(settings, **model):
        from e3cm_bench.matchers.peers.lightglue import LightGlueMatcher

        return LightGlueMatcher(kind, settings, **model)

    return build


# The weights files, named and located by kornia's own tables (read when a run is set up,
# after the extra is known to be installed), so that the file hashed is the file kornia loads.
def _loftr_weights(settings: LoFTRSettings) -> list:
    from kornia.feature.loftr.loftr import urls

    return [HubFile.of(urls[settings.weights])]


def _lightglue_weights(kind: str):
    def files(settings) -> list:
        import kornia.feature as KF
        from kornia.core.download import hf_url

        from e3cm_bench.matchers.peers.common import SUPERPOINT_REPO
        from e3cm_bench.matchers.peers.lightglue import lightglue_file_name

        if kind == "superpoint":
            extractor = HubModel(SUPERPOINT_REPO)
        elif kind == "disk":
            from kornia.feature.disk.disk import urls

            extractor = HubFile.of(urls["depth"])
        else:
            from kornia.feature.aliked.aliked import _CHECKPOINT_URLS

            extractor = HubFile.of([url.format("aliked-n16") for url in _CHECKPOINT_URLS])
        lightglue = HubFile.of([hf_url("lightglue", f"{kind}_lightglue.pth"), KF.LightGlue.url.format(KF.LightGlue.version, kind)],
                               lightglue_file_name(kind))
        return [extractor, lightglue]

    return files


def _lightglue_extractor(kind: str):
    """With --weights FILE (LightGlue's), the extractor's weights still come from the cache."""
    files = _lightglue_weights(kind)
    return lambda settings: files(settings)[:1]


def _superglue_weights(settings: SuperGlueSettings) -> list:
    from e3cm_bench.matchers.peers.superglue import SUPERGLUE_REPOS

    return [HubModel(SUPERGLUE_REPOS[settings.weights])]


def _superpoint_weights(settings) -> list:
    """With --weights FILE (SuperGlue's release .pth), SuperPoint comes from transformers' cache."""
    from e3cm_bench.matchers.peers.common import SUPERPOINT_REPO

    return [HubModel(SUPERPOINT_REPO)]


def _as_published(settings: dict) -> bool:
    """The paper's rows are the released models at their own settings."""
    return not settings


PEERS = (
    MatcherEntry("loftr", "LoFTR, detector-free transformer matching (kornia; weights outdoor / indoor)",
                 _loftr, LoFTRSettings, model=True, requires=("kornia",), weights=_loftr_weights, paper_row="LoFTR",
                 paper_setting=_as_published),
    MatcherEntry("superpoint+superglue", "SuperPoint + SuperGlue (transformers; Magic Leap's weights, non-commercial licence)",
                 _superglue, SuperGlueSettings, model=True, requires=("transformers",), weights=_superglue_weights,
                 weights_beside=_superpoint_weights, keypoints_are_detections=True,
                 paper_row="SuperPoint+SuperGlue", paper_setting=_as_published),
    MatcherEntry("superpoint+lightglue", "SuperPoint (transformers) + LightGlue (kornia)",
                 _lightglue("superpoint"), LightGlueSettings, model=True, requires=("kornia", "transformers"),
                 weights=_lightglue_weights("superpoint"),
                 weights_beside=_lightglue_extractor("superpoint"), keypoints_are_detections=True),
    MatcherEntry("disk+lightglue", "DISK + LightGlue (kornia)", _lightglue("disk"), DiskLightGlueSettings, model=True,
                 requires=("kornia",), weights=_lightglue_weights("disk"),
                 weights_beside=_lightglue_extractor("disk"), keypoints_are_detections=True),
    MatcherEntry("aliked+lightglue", "ALIKED-n16 + LightGlue (kornia)", _lightglue("aliked"), AlikedLightGlueSettings,
                 model=True, requires=("kornia",), weights=_lightglue_weights("aliked"),
                 weights_beside=_lightglue_extractor("aliked"), keypoints_are_detections=True),
)
