"""The built-in matchers' names, without torch: what a mistyped --matcher is checked against
before anything is loaded (registry.check_name). builtin.py and peers/ build one entry per
name here; tests/matching/test_matcher_registry.py checks that the two agree."""

BUILTIN_MATCHERS = ("e3cm", "e3cm-ransac", "e3cm-release", "e3cm-plus", "direct", "dfm", "sift", "colmap-sift", "loftr",
                    "superpoint+superglue", "superpoint+lightglue", "disk+lightglue", "aliked+lightglue",
                    "xfeat", "xfeat-star", "xfeat+lighterglue")
