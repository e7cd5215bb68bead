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

from .benchmarks import BENCHMARKS, Benchmark, EvalSettings, get_benchmark, register
from .matchers import Matcher, MatcherEntry, build_matcher, get_matcher, matcher_names
from .matchers import register as register_matcher
from .matches import Matches
from .method import MethodSpec
from .runner import match_pair, run_benchmark

__version__ = "0.1.0"

__all__ = [
    "BENCHMARKS", "Benchmark", "EvalSettings", "Matcher", "MatcherEntry", "Matches", "MethodSpec",
    "build_matcher", "get_benchmark", "get_matcher", "match_pair", "matcher_names", "register", "register_matcher",
    "run_benchmark",
]
