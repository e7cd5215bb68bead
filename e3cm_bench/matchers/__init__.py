"""Matchers, one small class per file; `build_matcher` turns a name and settings into one.

Adding a matcher: write `matchers/mine.py` with a `Matcher` subclass implementing
`match(image0, image1) -> Matches`, then add its name to MATCHERS and a branch to
`build_matcher` below. Models are imported only when a matcher is built, so that
listing matchers (the CLI's help, config validation) does not load torch.
"""

from __future__ import annotations

from ..matching import RANDOM_ESTIMATORS
from .base import Matcher

MATCHERS = ("e3cm", "direct", "dfm", "sift")
NEEDS_BACKBONE = ("e3cm", "direct", "dfm")


def is_random(name: str, settings: dict) -> bool:
    """Whether the matcher draws from OpenCV's RNG (a RANSAC inside): then its seed is part of
    the identity of its matches. dfm always (stage 0); e3cm with a robust cascade estimator."""
    return name == "dfm" or (name == "e3cm" and settings.get("estimator", "top8") in RANDOM_ESTIMATORS)


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
) -> Matcher:
    """A matcher by name. `settings` holds E3CMSettings fields (e3cm, direct) or DFMSettings fields (dfm)."""
    settings = dict(settings or {})
    if name not in MATCHERS:
        raise ValueError(f"unknown matcher {name!r}; choose one of: {', '.join(MATCHERS)}")
    if name == "sift":
        from .sift import SiftMatcher

        return SiftMatcher()
    from ..backbones import load_backbone

    check_device(device)
    net = load_backbone(backbone, weights=weights, pretrained=pretrained, device=device)
    if name == "dfm":
        from .dfm import DFMMatcher

        return DFMMatcher(net, **settings)
    from ..matching.pipeline import E3CMSettings
    from .e3cm import E3CMMatcher

    if name == "direct":
        settings["cascade"] = False
    return E3CMMatcher(net, E3CMSettings(**settings), name=name)


__all__ = ["MATCHERS", "NEEDS_BACKBONE", "Matcher", "build_matcher", "check_device", "is_out_of_memory", "is_random"]
