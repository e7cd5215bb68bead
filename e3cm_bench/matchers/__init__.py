"""Matchers, one small class per file; `build_matcher` turns CLI/config options into one.

Adding a matcher: write `matchers/mine.py` with a `Matcher` subclass implementing
`match(image0, image1) -> Matches`, then add a line to `build_matcher` below.
"""

from __future__ import annotations

from ..backbones import load_backbone
from ..matching.pipeline import E3CMSettings
from .base import Matcher, Matches

MATCHERS = ("e3cm", "direct", "dfm", "sift")
NEEDS_BACKBONE = ("e3cm", "direct", "dfm")


def build_matcher(
    name: str = "e3cm",
    backbone: str = "vgg19",
    weights: str | None = None,
    device: str = "cpu",
    pretrained: bool = True,
    settings: dict | None = None,
) -> Matcher:
    """A matcher by name. `settings` holds E3CMSettings fields (e3cm, direct) or DFM ratios."""
    settings = dict(settings or {})
    if name not in MATCHERS:
        raise ValueError(f"unknown matcher {name!r}; choose one of: {', '.join(MATCHERS)}")
    if name == "sift":
        from .sift import SiftMatcher

        return SiftMatcher()
    net = load_backbone(backbone, weights=weights, pretrained=pretrained, device=device)
    if name == "dfm":
        from .dfm import DFMMatcher

        return DFMMatcher(net, **settings)
    from .e3cm import E3CMMatcher

    if name == "direct":
        settings["cascade"] = False
    return E3CMMatcher(net, E3CMSettings(**settings), name=name)


__all__ = ["MATCHERS", "Matcher", "Matches", "build_matcher"]
