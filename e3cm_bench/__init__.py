"""e3cm-bench: training-free deep feature matching (E3CM, DFM, SIFT+NN) and its benchmarks.

The public Python API (the CLI is built on the same functions)::

    import e3cm_bench as eb
    matcher = eb.build_matcher("e3cm", backbone="efficientnet_lite0")
    m = eb.match_pair(matcher, "a.jpg", "b.jpg", max_side=1200)      # Matches, original pixels
    method = eb.MethodSpec.create("e3cm", backbone="efficientnet_lite0")
    summary = eb.run_benchmark("hpatches", root=..., out=..., method=method)  # a one-row DataFrame
    eb.register_matcher(eb.MatcherEntry("mine", "my matcher", build=lambda settings: MyMatcher()))

Models and torch are imported when a matcher is built, not when this package is imported.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# Old module paths (the earlier plugin guide's `e3cm_bench.matches`, ...) kept importable for one
# release, with a DeprecationWarning naming the new import (ground/moved.py); last, so nothing that
# exists is ever found there.
import sys as _sys  # noqa: E402

from e3cm_bench.ground.moved import FINDER as _FINDER  # noqa: E402

if _FINDER not in _sys.meta_path:
    _sys.meta_path.append(_FINDER)

# The public names, imported on first use (PEP 562) rather than here: `import e3cm_bench`
# then loads nothing heavy, so the command line's entry point (e3cm_bench.__main__.main) is
# running, and can turn a Ctrl-C during the slow imports into one line, from the first moment.
_EXPORTS = {
    "BENCHMARKS": ".benchmarks", "Benchmark": ".benchmarks", "EvalSettings": ".benchmarks",
    "get_benchmark": ".benchmarks", "register": ".benchmarks",
    "Features": ".matchers", "Matcher": ".matchers", "MatcherEntry": ".matchers", "build_matcher": ".matchers",
    "get_matcher": ".matchers",
    "matcher_names": ".matchers", "register_matcher": ".matchers",
    "Matches": ".ground.matches", "MethodSpec": ".method.spec", "match_pair": ".pipeline.runner",
    "run_benchmark": ".pipeline.runner",
}
_RENAMED = {"register_matcher": "register"}

__all__ = [
    "BENCHMARKS", "Benchmark", "EvalSettings", "Features", "Matcher", "MatcherEntry", "Matches", "MethodSpec",
    "build_matcher", "get_benchmark", "get_matcher", "match_pair", "matcher_names", "register", "register_matcher",
    "run_benchmark",
]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), _RENAMED.get(name, name))
    globals()[name] = value  # found directly from now on
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what type checkers and the documentation's static reader see
    from e3cm_bench.benchmarks import BENCHMARKS, Benchmark, EvalSettings, get_benchmark, register
    from e3cm_bench.matchers import Features, Matcher, MatcherEntry, build_matcher, get_matcher, matcher_names
    from e3cm_bench.matchers import register as register_matcher
    from e3cm_bench.ground.matches import Matches
    from e3cm_bench.method.spec import MethodSpec
    from e3cm_bench.pipeline.runner import match_pair, run_benchmark
