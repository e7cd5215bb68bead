"""Matchers, one small class per file; `build_matcher` turns a name and settings into one.

Adding a matcher: write `matchers/mine.py` with a `Matcher` subclass implementing
`match(image0, image1) -> Matches`, then add its name to MATCHERS and a branch to
`build_matcher` below. Models are imported only when a matcher is built, so that
listing matchers (the CLI's help, config validation) does not load torch.
"""

from __future__ import annotations

from ..matching import RANDOM_ESTIMATORS
from .base import Matcher

MATCHERS = ("e3cm", "e3cm-release", "e3cm-plus", "direct", "dfm", "sift")
NEEDS_BACKBONE = ("e3cm", "e3cm-release", "e3cm-plus", "direct", "dfm")
# Settings every deep matcher takes, besides its own (E3CMSettings, E3CMReleaseSettings, dfm's):
# how many levels of the backbone it uses (the E3CM release's match_small_img uses 4), the
# channel order fed to the network, and the backbone's precision (fp32 exact; bf16, fp16).
BACKBONE_SETTINGS = ("num_levels", "channel_order", "precision")
CHANNEL_ORDERS = ("rgb", "bgr")
# fp32: exact; bf16 (CPUs with AVX-512 BF16 / AMX, recent GPUs) and fp16 (GPUs): autocast.
PRECISIONS = ("fp32", "bf16", "fp16")


def is_random(name: str, settings: dict) -> bool:
    """Whether the matcher draws from OpenCV's RNG (a RANSAC inside): then its seed is part of
    the identity of its matches. dfm and e3cm-plus always (stage 0, MAGSAC++); e3cm with a robust cascade estimator;
    e3cm-release with its cascade."""
    return (name in ("dfm", "e3cm-plus")
            or (name == "e3cm" and settings.get("estimator", "top8") in RANDOM_ESTIMATORS)
            or (name == "e3cm-release" and settings.get("cascade", True)))


def check_device(device: str) -> str:
    """The device if torch has it here; else a one-line ValueError naming what is available."""
    import torch

    available = ["cpu"] + [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        available.append("mps")
    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise ValueError(f"--device {device}: not a device; use cpu, cuda, cuda:N or mps "
                         f"(available here: {', '.join(available)})") from None
    index = torch.device(device).index
    if kind == "cuda" and (not torch.cuda.is_available() or (index or 0) >= torch.cuda.device_count()):
        raise ValueError(f"--device {device}: no such CUDA GPU here (available: {', '.join(available)})")
    if kind == "mps" and "mps" not in available:
        raise ValueError(f"--device {device}: Apple's MPS is not available here (available: {', '.join(available)})")
    return device


def is_out_of_memory(error: BaseException) -> bool:
    """torch's allocator failures: CUDA's OutOfMemoryError, or the CPU allocator's RuntimeError."""
    text = str(error).lower()
    return type(error).__name__ == "OutOfMemoryError" or (
        isinstance(error, RuntimeError) and ("out of memory" in text or "can't allocate memory" in text
                                             or "not enough memory" in text))


def build_matcher(
    name: str = "e3cm",
    backbone: str = "vgg19",
    weights: str | None = None,
    device: str = "cpu",
    pretrained: bool = True,
    settings: dict | None = None,
    loaded: dict | None = None,
) -> Matcher:
    """A matcher by name. `settings` holds the matcher's own fields (E3CMSettings for e3cm and
    direct, E3CMReleaseSettings for e3cm-release, E3CMPlusSettings for e3cm-plus,
    variant/ratio/DFMSettings for dfm) and the
    BACKBONE_SETTINGS. loaded: backbones built before, by what they were built from; a
    matcher asking for the same one reuses it instead of loading the weights again."""
    settings = dict(settings or {})
    if name not in MATCHERS:
        raise ValueError(f"unknown matcher {name!r}; choose one of: {', '.join(MATCHERS)}")
    if name == "sift":
        from .sift import SiftMatcher

        return SiftMatcher()
    from ..backbones import MAX_LEVELS, load_backbone

    check_device(device)
    num_levels = int(settings.pop("num_levels", MAX_LEVELS))
    channel_order = settings.pop("channel_order", "rgb")
    precision = settings.pop("precision", "fp32")
    key = (backbone, str(weights), pretrained, device, num_levels, precision)
    net = None if loaded is None else loaded.get(key)
    if net is None:
        net = load_backbone(backbone, weights=weights, pretrained=pretrained, device=device, num_levels=num_levels,
                            precision=precision)
        if loaded is not None:
            loaded[key] = net
    return _deep_matcher(name, net, settings, channel_order)


def _deep_matcher(name: str, net, settings: dict, channel_order: str) -> Matcher:
    if name == "dfm":
        from .dfm import DFMMatcher

        return DFMMatcher(net, channel_order=channel_order, **settings)
    if name == "e3cm-release":
        from .e3cm_release import E3CMReleaseMatcher, E3CMReleaseSettings

        return E3CMReleaseMatcher(net, E3CMReleaseSettings(**settings), channel_order=channel_order)
    if name == "e3cm-plus":
        from .e3cm_plus import E3CMPlusMatcher, E3CMPlusSettings

        return E3CMPlusMatcher(net, E3CMPlusSettings(**settings), channel_order=channel_order)
    from ..matching.pipeline import E3CMSettings
    from .e3cm import E3CMMatcher

    if name == "direct":
        settings["cascade"] = False
    return E3CMMatcher(net, E3CMSettings(**settings), name=name, channel_order=channel_order)


def check_settings(name: str, settings: dict) -> None:
    """A one-line ValueError where `settings` do not fit matcher `name` (builds no backbone)."""
    settings = dict(settings)
    if name == "sift" and settings:
        raise ValueError(f"sift takes no settings, got {', '.join(sorted(settings))}")
    if name not in NEEDS_BACKBONE:
        return
    levels = settings.pop("num_levels", 5)
    if not isinstance(levels, int) or isinstance(levels, bool) or not 2 <= levels <= 5:
        raise ValueError(f"num_levels must be a whole number 2..5, got {levels!r}")
    order = settings.pop("channel_order", "rgb")
    if order not in CHANNEL_ORDERS:
        raise ValueError(f"channel_order must be rgb or bgr, got {order!r}")
    precision = settings.pop("precision", "fp32")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be fp32, bf16 or fp16, got {precision!r}")
    try:
        if name == "dfm":
            from .dfm import check_dfm_settings

            check_dfm_settings(settings)
        elif name == "e3cm-release":
            from .e3cm_release import E3CMReleaseSettings

            E3CMReleaseSettings(**settings)
        elif name == "e3cm-plus":
            from .e3cm_plus import E3CMPlusSettings

            E3CMPlusSettings(**settings)
        else:
            from ..matching.pipeline import E3CMSettings

            E3CMSettings(**settings)
    except TypeError as exc:  # an unknown field name
        raise ValueError(f"{name}: {str(exc).split('() ')[-1]}") from None


__all__ = ["BACKBONE_SETTINGS", "CHANNEL_ORDERS", "PRECISIONS", "MATCHERS", "NEEDS_BACKBONE", "Matcher", "build_matcher", "check_device", "check_settings",
           "is_out_of_memory", "is_random"]
