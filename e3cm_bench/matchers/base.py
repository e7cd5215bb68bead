"""What a matcher is: the `Matcher` interface, and the `MatcherEntry` that registers one.

numpy only: the registry, the CLI's listing and the backbones read these names without
loading a model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from e3cm_bench.ground.matches import Matches

from e3cm_bench.backbones.names import CHANNEL_ORDERS, MEMORY_FORMATS, PRECISIONS


class Features(dict):
    """One image's features, as a two-stage matcher's ``features`` returns them: named values
    (numpy arrays or torch tensors, and plain numbers or strings) that its ``match_features``
    reads. The match stage keeps them for the image's later pairs (matchers/feature_cache.py),
    so match_features must not change them in place. Only arrays and plain values can wait on
    disk: features holding another kind of object stay in memory or are computed again."""


class Matcher:
    """Base class. A matcher is one class with one method, ``match``, or two: ``features``
    per image and ``match_features`` per pair (a two-stage matcher, `splits`).

    ``image0``/``image1`` are H x W x 3 uint8 RGB arrays. A matcher never reads files.
    ``config()`` returns every setting its result depends on (written to config.yaml).
    ``keypoints_in_image``: whether every keypoint it returns lies in its image (the runner
    checks it: a point outside is a broken matcher). The two releases are reproduced with
    their slips, and the DFM release's final filter tests y against the padded width, so
    their points may lie in the padding: they set it False.

    A two-stage matcher's ``features(image)`` may depend on that image alone (and on the
    matcher's settings): the match stage computes it once per image of a run and matches
    each pair from what it keeps (``--no-feature-reuse``: from two fresh extractions, as
    ``match`` does), so ``match_features(features(a), features(b))`` must be ``match(a, b)``.
    """

    name = "base"
    keypoints_in_image = True

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        if not splits(self):  # pragma: no cover - a matcher defines match or both stages
            raise NotImplementedError(f"{self.name} defines neither match() nor features() and match_features()")
        return self.match_features(self.features(image0), self.features(image1))

    def features(self, image: np.ndarray) -> Features:  # pragma: no cover - optional
        raise NotImplementedError

    def match_features(self, features0: Features, features1: Features) -> Matches:  # pragma: no cover - optional
        raise NotImplementedError

    def config(self) -> dict:
        return {"matcher": self.name}


def splits(matcher: object) -> bool:
    """Whether a matcher (a Matcher or any object with ``match``) is two-stage: its class
    defines both ``features`` and ``match_features``."""
    cls = type(matcher)
    return (callable(getattr(cls, "features", None)) and callable(getattr(cls, "match_features", None))
            and getattr(cls, "features") is not Matcher.features
            and getattr(cls, "match_features") is not Matcher.match_features)


@dataclass(frozen=True)
class BackboneSettings:
    """The settings every matcher on a backbone takes besides its own: how many levels of the
    pyramid it uses (the E3CM release's match_small_img uses 4), the channel order fed to the
    network, and the network's precision."""

    num_levels: int = 5
    channel_order: str = "rgb"
    precision: str = "fp32"
    # The convolutions' memory layout: auto = channels_last where measured faster (every
    # backbone in bf16 / fp16; VGG19 and Lite0 in fp32), else nchw. nchw gives VGG19 the
    # releases' maps bit for bit; channels_last rounds differently (maps up to 6e-6 apart).
    memory_format: str = "auto"

    def __post_init__(self) -> None:
        levels = self.num_levels
        if not isinstance(levels, int) or isinstance(levels, bool) or not 2 <= levels <= 5:
            raise ValueError(f"num_levels must be a whole number 2..5, got {levels!r}")
        if self.channel_order not in CHANNEL_ORDERS:
            raise ValueError(f"channel_order must be rgb or bgr, got {self.channel_order!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be fp32, bf16 or fp16, got {self.precision!r}")
        if self.memory_format not in MEMORY_FORMATS:
            raise ValueError(f"memory_format must be auto, nchw or channels_last, got {self.memory_format!r}")


BACKBONE_SETTINGS = tuple(f.name for f in dataclasses.fields(BackboneSettings))


def never(settings: Any) -> bool:
    return False


def always(settings: Any) -> bool:
    return True


# The optional extra (pyproject.toml) that installs a module a matcher requires; any other: peers.
EXTRA_OF = {"pycolmap": "colmap"}


@dataclass(frozen=True)
class MatcherEntry:
    """One matcher in the registry (matchers/registry.py), built-in or a plugin's.

    name: what --matcher, configs and the API call it. description: one line.
    settings: a dataclass of its own settings (defaults; __post_init__ raises a one-line
        ValueError for a bad value), or None for a matcher that takes none.
    build: settings instance -> Matcher; a matcher on a backbone is built as
        ``build(settings, net=..., channel_order=...)`` with the loaded `backbones.Backbone`.
    needs_backbone: it runs on a backbone (--backbone, --weights and BackboneSettings apply).
    is_random: settings instance -> whether the matcher draws from OpenCV's RNG (a RANSAC
        inside); then the seed is part of the identity of its matches.
    shorthands: which of the option shorthands --ratio, --estimator, --sampson-px it takes
        (each is a setting of the same name).
    recorded: settings written into the identity even when not given (e3cm's estimator, so
        that the identity of every e3cm run names it).
    preset_of, preset: a name for another matcher with fixed settings (e3cm-ransac = e3cm with
        estimator ransac): it builds, and is identified as, that matcher with those settings.
    paper_row: the paper's table row its runs compare with, when paper_setting(settings dict)
        says they were made as the paper's were.
    model: it loads a network of its own (a peer): built as ``build(settings, device=...,
        weights=FILE or None, pretrained=...)``; --device and --weights FILE apply to it.
    requires: modules it needs beyond the base install (checked before anything runs).
    weights: settings -> the files it loads the libraries' way (peers/weights.py); their
        names and sha256 enter the identity.
    weights_beside: settings -> the library files it still loads when --weights FILE replaces
        its own (e.g. the keypoint extractor); they enter the identity after the file's hash.
    keypoints_are_detections: its keypoints are an image's detections, the same in every pair of
        the image (SIFT, SuperPoint, DISK, ALIKED), so that exact repeats chain into tracks; False
        for dense and semi-dense matchers, which place each point afresh per pair (the sfm
        benchmark then merges near keypoints by default: sfm/protocol.py).
    origin: "built-in", "plugin DIST VERSION" or "module NAME" (set by the registry).
    source: what the plugin's code is, for the identity: {"package", "version", "sha256"} or
        {"module", "sha256"}, the sha256 of its code (plugin_code.code_sha256); None for
        built-ins (the package's own version is in config.yaml).
    """

    name: str
    description: str
    build: Callable[..., Matcher]
    settings: type | None = None
    needs_backbone: bool = False
    is_random: Callable[[Any], bool] = never
    shorthands: tuple[str, ...] = ()
    recorded: dict = field(default_factory=dict)
    preset_of: str | None = None
    preset: dict = field(default_factory=dict)
    paper_row: str | None = None
    paper_setting: Callable[[dict], bool] = always
    model: bool = False
    requires: tuple[str, ...] = ()
    weights: Callable[[Any], list] | None = None
    weights_beside: Callable[[Any], list] | None = None
    keypoints_are_detections: bool = False
    origin: str = "built-in"
    source: dict | None = None

    def check_requirements(self) -> None:
        """A one-line ValueError naming what to install when a module it needs is missing."""
        import importlib.util

        missing = [name for name in self.requires if importlib.util.find_spec(name) is None]
        if missing:
            extras = sorted({EXTRA_OF.get(name, "peers") for name in self.requires})
            raise ValueError(
                f"{self.name} needs {', '.join(missing)}, which the {' and '.join(extras)} extra installs: "
                f"{self.install_hint()}"
            )

    def install_hint(self) -> str:
        """The extra that installs what it requires (EXTRA_OF: pycolmap's is colmap)."""
        extras = sorted({EXTRA_OF.get(name, "peers") for name in self.requires})
        return f"pip install 'e3cm-bench[{','.join(extras)}]'"

    def setting_fields(self) -> list[dataclasses.Field]:
        return list(dataclasses.fields(self.settings)) if self.settings is not None else []

    def make_settings(self, given: dict) -> Any:
        """Its settings dataclass from the settings given by name (backbone settings taken out
        first); a one-line ValueError for an unknown name or a bad value."""
        if self.settings is None:
            if given:
                raise ValueError(f"{self.name} takes no settings, got {', '.join(sorted(given))}")
            return None
        known = {f.name for f in self.setting_fields() if f.init}
        unknown = sorted(set(given) - known)
        if unknown:
            extra = f", {', '.join(BACKBONE_SETTINGS)}" if self.needs_backbone else ""
            raise ValueError(f"{self.name}: unknown setting(s) {', '.join(unknown)}; it takes: "
                             f"{', '.join(sorted(known)) or 'none'}{extra}")
        for name, value in given.items():  # by the dataclass's annotations, before any pair
            wanted = setting_kind(self.settings, name, value)
            if wanted:
                raise ValueError(f"{self.name}: setting {name} must be {wanted}, got {value!r}")
        try:
            return self.settings(**given)
        except TypeError as exc:  # a value of the wrong kind inside the dataclass
            raise ValueError(f"{self.name}: {exc}") from None


# What an annotation of a settings dataclass allows, in an error's words: a plugin's settings are
# checked by their annotations when given (``--set ratio=abc`` for ``ratio: float``), not at the
# first pair. Annotations this does not know (a Literal, a class of the plugin's) are the
# dataclass's own to check.
_ANNOTATED = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}


def _fits(value, annotation) -> bool | None:
    """Whether `value` is of `annotation` (None: an annotation this cannot judge)."""
    import types
    import typing

    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        verdicts = [_fits(value, a) for a in args]
        return True if any(verdicts) else None if None in verdicts else False
    if annotation is type(None):
        return value is None
    if origin in (tuple, list):
        if not isinstance(value, (tuple, list)):
            return False
        inner = [a for a in args if a is not Ellipsis]
        verdicts = [_fits(v, inner[0]) for v in value] if len(inner) == 1 else [None]
        return None if None in verdicts else all(verdicts)
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    return None


def setting_kind(settings: type, name: str, value) -> str:
    """'' where `value` may be the settings dataclass's field `name` by its annotation (or the
    annotation is one this cannot judge), else what the annotation allows, in words."""
    import typing

    try:
        annotation = typing.get_type_hints(settings).get(name)
    except Exception:  # noqa: BLE001 - an annotation that does not resolve: the dataclass's own check
        return ""
    if annotation is None or _fits(value, annotation) is not False:
        return ""
    if typing.get_origin(annotation) in (tuple, list):
        return "a list"
    args = [a for a in typing.get_args(annotation) if a is not type(None)] or [annotation]
    words = ["a list" if typing.get_origin(a) in (tuple, list) else _ANNOTATED.get(a) or getattr(a, "__name__", str(a))
             for a in args]
    return " or ".join(dict.fromkeys(words)) + (" (or null)" if type(None) in typing.get_args(annotation) else "")
