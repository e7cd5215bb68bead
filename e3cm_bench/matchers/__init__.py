"""Matchers: one small module per model, each registered as a `MatcherEntry`.

The registry (registry.py) finds a matcher by name: the built-ins (builtin.py), plugins in
the entry-point group ``e3cm_bench.matchers``, or ``package.module:factory``. Adding one
needs no edit here: docs/own-matcher.md "Benchmark your own matcher". Models are imported when a
matcher is built, so listing names does not load a network.
"""

from __future__ import annotations

from e3cm_bench.matchers.base import (
    BACKBONE_SETTINGS,
    CHANNEL_ORDERS,
    PRECISIONS,
    BackboneSettings,
    Features,
    Matcher,
    MatcherEntry,
)
from e3cm_bench.matchers.registry import (
    ENTRY_POINT_GROUP,
    broken_plugins,
    build_matcher,
    built_settings,
    check_settings,
    entries,
    get_matcher,
    matcher_names,
    register,
    resolve,
    unregister,
)

__all__ = [
    "BACKBONE_SETTINGS", "CHANNEL_ORDERS", "ENTRY_POINT_GROUP", "PRECISIONS", "BackboneSettings", "Features", "Matcher",
    "MatcherEntry", "broken_plugins", "build_matcher", "built_settings", "check_settings", "entries", "get_matcher",
    "matcher_names", "register", "resolve", "unregister",
]
